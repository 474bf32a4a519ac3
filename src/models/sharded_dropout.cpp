// Sharded dropout (models/sharded_dropout.h): the mask of the whole batch, cut to
// this rank's rows; and LibTorch's encoder layer forward written out around it.
#include "models/sharded_dropout.h"

#include <limits>

#include "core/error.h"

namespace mc {
namespace nn = torch::nn;
namespace F = torch::nn::functional;

namespace {
thread_local const BatchRows* g_rows = nullptr;
}

BatchRowsScope::BatchRowsScope(const BatchRows& rows) : rows_(rows), previous_(g_rows) { g_rows = &rows_; }
BatchRowsScope::~BatchRowsScope() { g_rows = previous_; }
const BatchRows* BatchRowsScope::current() { return g_rows; }

torch::Tensor sharded_dropout(const torch::Tensor& x, double p, bool training, int64_t batch_dim) {
  const BatchRows* rows = g_rows;
  // p = 1 draws nothing (torch multiplies by zero), so it needs no whole-batch mask.
  if (!rows || rows->whole() || !training || p <= 0 || p >= 1 || x.numel() == 0) return torch::dropout(x, p, training);
  const int64_t dim = batch_dim < 0 ? batch_dim + x.dim() : batch_dim;
  const int64_t here = x.size(dim), n = rows->size();
  if (n <= 0 || here % n != 0)
    throw std::logic_error(fmt::format("sharded dropout: dimension {} of a {}-d tensor has {} entries, not a multiple "
                                       "of the {} rows this rank computes",
                                       dim, x.dim(), here, n));
  const int64_t per_row = here / n;
  // torch::dropout draws its mask into a contiguous tensor of x's sizes (row-major,
  // whatever x's strides): the whole batch's mask is drawn the same way, then cut.
  auto sizes = x.sizes().vec();
  sizes[dim] = per_row * rows->total;
  auto noise = torch::empty(sizes, x.options()).bernoulli_(1 - p);
  noise = noise.narrow(dim, per_row * rows->begin, here).div(1 - p);
  return x * noise;
}

torch::Tensor transformer_encoder_forward(nn::TransformerEncoderImpl& encoder, const torch::Tensor& src,
                                          const torch::Tensor& key_padding_mask) {
  torch::Tensor h = src;
  for (size_t l = 0; l < encoder.layers->size(); ++l) {
    auto& layer = encoder.layers->at<nn::TransformerEncoderLayerImpl>(l);
    auto& attn = *layer.self_attn;
    if (!attn._qkv_same_embed_dim || attn.bias_k.defined() || attn.options.add_zero_attn())
      throw std::logic_error("transformer_encoder_forward: only plain self-attention layers are written out");
    // F::multi_head_attention_forward, self-attention branch, no attention mask.
    const int64_t L = h.size(0), B = h.size(1), E = h.size(2), H = attn.options.num_heads(), Dh = E / H;
    const auto scaling = 1 / std::sqrt(Dh);
    auto qkv = F::linear(h, attn.in_proj_weight, attn.in_proj_bias).chunk(3, -1);
    auto q = qkv[0] * scaling;
    q = q.contiguous().view({L, B * H, Dh}).transpose(0, 1);
    auto k = qkv[1].contiguous().view({-1, B * H, Dh}).transpose(0, 1);
    auto v = qkv[2].contiguous().view({-1, B * H, Dh}).transpose(0, 1);
    const int64_t S = k.size(1);
    auto w = torch::bmm(q, k.transpose(1, 2));
    if (key_padding_mask.defined()) {
      w = w.view({B, H, L, S});
      w = w.masked_fill(key_padding_mask.unsqueeze(1).unsqueeze(2), -std::numeric_limits<float>::infinity());
      w = w.view({B * H, L, S});
    }
    w = F::softmax(w, -1);
    w = sharded_dropout(w, attn.options.dropout(), attn.is_training(), 0);  // rows: B * H, sample-major
    auto a = torch::bmm(w, v).transpose(0, 1).contiguous().view({L, B, E});
    a = F::linear(a, attn.out_proj->weight, attn.out_proj->bias);
    // TransformerEncoderLayerImpl::forward (post-norm), batch on dimension 1.
    const double p = layer.options.dropout();
    auto ret = layer.norm1(h + sharded_dropout(a, p, layer.dropout1->is_training(), 1));
    torch::Tensor act;
    if (c10::get_if<torch::enumtype::kGELU>(&layer.options.activation()))
      act = F::gelu(layer.linear1(ret));
    else if (c10::get_if<torch::enumtype::kReLU>(&layer.options.activation()))
      act = F::relu(layer.linear1(ret));
    else
      throw std::logic_error("transformer_encoder_forward: activation must be GELU or ReLU");
    auto ff = layer.linear2(sharded_dropout(act, p, layer.dropout->is_training(), 1));
    h = layer.norm2(ret + sharded_dropout(ff, p, layer.dropout2->is_training(), 1));
  }
  if (!encoder.norm.is_empty()) h = encoder.norm.forward<torch::Tensor>(h);
  return h;
}

}  // namespace mc
