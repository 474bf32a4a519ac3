// Dropout whose masks do not depend on how a training batch is split over
// data-parallel ranks (issue 19). While a BatchRowsScope says "this forward
// computes rows [begin, end) of a batch of `total`", a mask is drawn for the whole
// batch, exactly the draws one process makes, and this rank's rows are cut out of
// it: a 2-process step then equals the 1-process step, and every rank's random
// stream stays the same (a rank-0 checkpoint resumes any rank count). With no
// scope (one process, sampling, evaluation) it is torch::dropout, bit for bit.
// Also LibTorch's TransformerEncoder forward with this dropout.
#pragma once
#include <torch/torch.h>

namespace mc {

// Rows [begin, end) of a batch of `total` rows.
struct BatchRows {
  int64_t begin = 0, end = 0, total = 0;
  int64_t size() const { return end - begin; }
  bool whole() const { return begin == 0 && end == total; }
};

// Sets the rows the forwards of this thread compute while it lives (nests).
class BatchRowsScope {
 public:
  explicit BatchRowsScope(const BatchRows& rows);
  ~BatchRowsScope();
  BatchRowsScope(const BatchRowsScope&) = delete;
  BatchRowsScope& operator=(const BatchRowsScope&) = delete;
  // The innermost scope's rows; null outside every scope.
  static const BatchRows* current();

 private:
  BatchRows rows_;
  const BatchRows* previous_;
};

// torch::dropout(x, p, training), except inside a BatchRowsScope that is not the
// whole batch: there the mask is drawn for the whole batch and cut. `batch_dim` is
// the dimension that holds the rows; it may hold k consecutive entries per row
// ([B * heads, ...]), then the whole batch has k * total.
torch::Tensor sharded_dropout(const torch::Tensor& x, double p, bool training, int64_t batch_dim = 0);

// nn::Dropout's module form of sharded_dropout (no parameters or buffers, so it
// replaces an nn::Dropout without changing a checkpoint).
struct ShardedDropoutImpl : torch::nn::Cloneable<ShardedDropoutImpl> {
  explicit ShardedDropoutImpl(double p = 0.5, int64_t batch_dim = 0) : p(p), batch_dim(batch_dim) {}
  void reset() override {}
  torch::Tensor forward(const torch::Tensor& x) { return sharded_dropout(x, p, is_training(), batch_dim); }
  double p;
  int64_t batch_dim;
};
TORCH_MODULE(ShardedDropout);

// nn::TransformerEncoder's forward over src [L, B, E] (sequence first) with a key
// padding mask [B, L] (true = padding) and no attention mask: the same parameters
// and the same operations in the same order as LibTorch 1.13's post-norm layers
// (bit-identical outside a BatchRowsScope; tests/models/test_sharded_dropout.cpp),
// with their four dropouts sharded.
torch::Tensor transformer_encoder_forward(torch::nn::TransformerEncoderImpl& encoder, const torch::Tensor& src,
                                          const torch::Tensor& key_padding_mask);

}  // namespace mc
