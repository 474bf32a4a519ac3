// What a Trainable needs to compute its part of a data-parallel batch (issue 19):
// which rows of the global batch are this rank's, and the few collectives that
// combine the ranks' work inside a loss (sums of statistics, gathered embeddings).
// In one process the shard is the whole batch and every operation is the identity,
// so a trainable written against it computes exactly what it computed before.
//
// The contract (Trainable::loss): every rank is given the same global batch and
// draws all per-sample randomness (crops, captions, noise, t, condition drops,
// dropout masks via models/sharded_dropout.h) for the whole batch, from the same
// generator state, then computes its own rows. The loss and every logged part it
// returns is this rank's *share*: the trainer sums shares over ranks, and the sum
// is the whole batch's value, so a mean over the batch divides by the whole batch's
// count (of clips, valid frames, tokens, anchors), never by the shard's.
#pragma once
#include <torch/torch.h>

#include <vector>

#include "models/sharded_dropout.h"

namespace mc {

// Sums over the ranks of a data-parallel job (train/distributed.h implements it
// over c10d/Gloo). Every rank calls the same operations in the same order.
class Collective {
 public:
  virtual ~Collective() = default;
  virtual int rank() const = 0;
  virtual int world() const = 0;
  // In place: `t` becomes the sum of every rank's `t` (same shape and dtype
  // everywhere), identical bits on every rank.
  virtual void sum_(torch::Tensor& t) = 0;
};

class BatchShard {
 public:
  BatchShard() = default;  // one process: the whole batch
  explicit BatchShard(Collective* c) : c_(c && c->world() > 1 ? c : nullptr) {}

  int rank() const { return c_ ? c_->rank() : 0; }
  int world() const { return c_ ? c_->world() : 1; }
  bool whole() const { return c_ == nullptr; }

  // This rank's rows of a batch of n: [n r / W, n (r + 1) / W) (contiguous, in rank
  // order, so the ranks' rows concatenated are the batch).
  BatchRows rows(int64_t n) const {
    return {n * rank() / world(), n * (rank() + 1) / world(), n};
  }
  // This rank's rows (dimension 0) of a tensor built for the whole batch.
  torch::Tensor local(const torch::Tensor& whole_batch) const {
    if (whole()) return whole_batch;
    const BatchRows r = rows(whole_batch.size(0));
    return whole_batch.narrow(0, r.begin, r.size());
  }
  template <class T>
  std::vector<T> local(const std::vector<T>& whole_batch) const {
    if (whole()) return whole_batch;
    const BatchRows r = rows(static_cast<int64_t>(whole_batch.size()));
    return std::vector<T>(whole_batch.begin() + r.begin, whole_batch.begin() + r.end);
  }

  // The whole batch's rows [n, ...] from every rank's `mine` (rows(n) of it). The
  // gradient flows into this rank's rows only; the others are constants here and
  // get theirs on their own rank, so a loss every rank computes in full from
  // gathered rows (a contrastive loss over the whole batch) goes through
  // replicated() to count once.
  torch::Tensor gather(const torch::Tensor& mine, int64_t n) const {
    if (whole()) return mine;
    const BatchRows r = rows(n);
    auto sizes = mine.sizes().vec();
    sizes[0] = n;
    auto all = torch::zeros(sizes, mine.options().requires_grad(false));
    all.narrow(0, r.begin, r.size()).copy_(mine.detach());
    c_->sum_(all);  // x + 0 = x: the other ranks' rows arrive exactly
    return torch::cat({all.narrow(0, 0, r.begin), mine, all.narrow(0, r.end, n - r.end)});
  }
  // A value every rank computes in full (a loss over gathered rows, a statistic of
  // summed counts): its share is value / world, its gradient unchanged (each rank's
  // gradient reaches only its own rows' parameters through gather()).
  torch::Tensor replicated(const torch::Tensor& x) const {
    if (whole()) return x;
    return x + (x / world() - x).detach();
  }
  // A tensor a replicated loss uses directly on every rank (a learned temperature):
  // the value is unchanged, its gradient is divided by the rank count so the sum
  // over ranks is the gradient once.
  torch::Tensor shared(const torch::Tensor& x) const {
    if (whole()) return x;
    return x / world() + (x - x / world()).detach();
  }
  // In-place sum over ranks of a tensor outside the graph (counts, code statistics).
  void sum_(torch::Tensor& t) const {
    if (!whole()) c_->sum_(t);
  }
  double sum(double v) const {
    if (whole()) return v;
    auto t = torch::tensor({v}, torch::kFloat64);
    c_->sum_(t);
    return t.item<double>();
  }

 private:
  Collective* c_ = nullptr;
};

}  // namespace mc
