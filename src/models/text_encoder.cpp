// The caption encoder module shared by the flow prior and `text_clip`, and caption
// batching.
#include "models/text_encoder.h"

#include "models/sharded_dropout.h"

namespace mc {
namespace nn = torch::nn;

TextEncoderImpl::TextEncoderImpl(const TextEncoderOptions& o) {
  embedding =
      register_module("embedding", nn::Embedding(nn::EmbeddingOptions(o.vocab_size, o.width).padding_idx(TextVocab::kPad)));
  position = register_module("position", nn::Embedding(o.max_words, o.width));
  // LibTorch 1.13's encoder layer is post-norm; at 2 layers that trains fine.
  auto layer = nn::TransformerEncoderLayer(
      nn::TransformerEncoderLayerOptions(o.width, o.heads).dim_feedforward(o.ff).dropout(o.dropout).activation(torch::kGELU));
  encoder = register_module("encoder", nn::TransformerEncoder(nn::TransformerEncoderOptions(layer, o.layers)));
  norm = register_module("norm", nn::LayerNorm(nn::LayerNormOptions({o.width})));
  out = register_module("out", nn::Linear(o.width, o.width));
  torch::NoGradGuard ng;
  nn::init::normal_(embedding->weight, 0.0, 0.02);
  embedding->weight[TextVocab::kPad].zero_();
  nn::init::normal_(position->weight, 0.0, 0.02);
}

torch::Tensor TextEncoderImpl::forward(const torch::Tensor& ids, const torch::Tensor& lengths) {
  const int64_t L = ids.size(1);
  auto dev = ids.device();
  auto pos = torch::arange(L, torch::TensorOptions().dtype(torch::kInt64).device(dev));
  auto h = embedding(ids) + position(pos).unsqueeze(0);          // [B, L, E]
  auto valid = pos.unsqueeze(0) < lengths.to(dev).unsqueeze(1);  // [B, L]
  h = transformer_encoder_forward(*encoder, h.transpose(0, 1), valid.logical_not()).transpose(0, 1);
  // Mean over the real tokens: every word counts, unlike a last-token readout
  // which a post-norm encoder this shallow tends to wash out.
  auto m = valid.unsqueeze(-1).to(h.dtype());
  auto pooled = (h * m).sum(1) / m.sum(1).clamp_min(1.0);
  return out(norm(pooled));
}

EncodedCaptions encode_captions(const TextVocab& vocab, const std::vector<std::string>& captions, int max_words) {
  const int64_t B = captions.size();
  auto ids = torch::zeros({B, max_words}, torch::kInt64);
  auto lengths = torch::zeros({B}, torch::kInt64);
  auto ia = ids.accessor<int64_t, 2>();
  for (int64_t b = 0; b < B; ++b) {
    auto e = vocab.encode(captions[b], max_words);
    for (int k = 0; k < max_words; ++k) ia[b][k] = e.ids[k];
    lengths[b] = std::max(1, e.length);
  }
  return {ids, lengths};
}

}  // namespace mc
