// The caption encoder module shared by the flow prior and `text_clip`, the text
// fields of their configs, and caption batching.
#include "models/text_encoder.h"

#include "models/sharded_dropout.h"

namespace mc {
namespace nn = torch::nn;

void TextEncoderFields::visit_text_fields(FieldVisitor& v, const char* width_help) {
  v("text_width", text_width, width_help, at_least(8));
  v("text_layers", text_layers, "text transformer encoder layers", in_range(1, 12));
  v("text_heads", text_heads, "text encoder attention heads", at_least(1));
  v("text_ff", text_ff, "text encoder feed-forward size", at_least(8));
  v("text_dropout", text_dropout, "text encoder dropout", in_range(0.0, 0.9));
  v("max_words", max_words, "caption length cap in tokens (incl. <sos>/<eos>)", in_range(4, 256));
}

std::string TextEncoderFields::text_fields_error() const {
  if (text_width % text_heads != 0)
    return fmt::format("text_width {} is not a multiple of text_heads {}", text_width, text_heads);
  return "";
}

TextEncoderOptions TextEncoderFields::text_encoder_options(int vocab_size) const {
  TextEncoderOptions o;
  o.vocab_size = vocab_size;
  o.width = text_width;
  o.layers = text_layers;
  o.heads = text_heads;
  o.ff = text_ff;
  o.dropout = text_dropout;
  o.max_words = max_words;
  return o;
}

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
