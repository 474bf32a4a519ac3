// Per-task compilation into model units and the index-tensor form of stacked
// observations used by DNO (and reusable by any batched residual).
#include "samplers/task_observation.h"

#include "core/error.h"
#include "data/skeleton.h"
#include "samplers/flow_sampler.h"

namespace mc {

std::vector<LinearObservation> model_observations(const std::vector<ControlTask>& tasks, const Skeleton& skeleton,
                                                  const std::array<double, 3>& axis_scale,
                                                  const std::array<double, 3>& axis_offset) {
  std::vector<LinearObservation> out;
  out.reserve(tasks.size());
  const size_t J = skeleton.num_joints();
  for (const auto& t : tasks) {
    if (t.length < 1) fail("task '{}' asks for {} frames; it needs at least one", t.id, t.length);
    if (!t.source.empty() && t.source.size() != static_cast<size_t>(t.length) * J * 3)
      fail("task '{}' carries a source clip of {} values; {} frames x {} joints x 3 = {} expected", t.id,
           t.source.size(), t.length, J, static_cast<size_t>(t.length) * J * 3);
    LinearObservation world;
    try {
      world = compile(t.spec, t.length, skeleton, t.source.empty() ? nullptr : t.source.data());
    } catch (const UserError& e) {
      fail("task '{}': {}", t.id, e.what());
    }
    out.push_back(affine_to_model(world, axis_scale, axis_offset));
  }
  return out;
}

std::vector<LinearObservation> model_observations(const FlowPrior& prior, const std::vector<ControlTask>& tasks) {
  auto sd = prior.net()->joint_std.to(torch::kCPU, torch::kFloat64).contiguous();
  auto mu = prior.net()->joint_mean.to(torch::kCPU, torch::kFloat64).contiguous();
  std::array<double, 3> scale{}, offset{};
  for (int c = 0; c < 3; ++c) {
    scale[c] = sd[c].item<double>();
    offset[c] = mu[c].item<double>();
  }
  return model_observations(tasks, prior.skeleton(), scale, offset);
}

BatchedObservation batch_observations(const std::vector<const LinearObservation*>& obs, int64_t frames,
                                      int64_t joints, torch::Device device) {
  BatchedObservation b;
  b.batch = obs.size();
  b.frames = frames;
  b.joints = joints;
  const int64_t stride = frames * joints * 3;
  std::vector<int64_t> row, col, sample;
  std::vector<float> val, y, count(obs.size(), 0.0f);
  std::vector<uint8_t> hard;
  int64_t base_row = 0;
  for (size_t s = 0; s < obs.size(); ++s) {
    const LinearObservation& o = *obs[s];
    if (o.joints != joints || o.frames > frames)
      fail("observation '{}' of batch row {} covers {} frames x {} joints; the batch holds {} frames x {} joints",
           o.source, s, o.frames, o.joints, frames, joints);
    for (int r = 0; r < o.A.outerSize(); ++r)
      for (Eigen::SparseMatrix<double, Eigen::RowMajor>::InnerIterator it(o.A, r); it; ++it) {
        row.push_back(base_row + r);
        col.push_back(static_cast<int64_t>(s) * stride + it.col());
        val.push_back(static_cast<float>(it.value()));
      }
    for (int r = 0; r < o.rows(); ++r) {
      y.push_back(static_cast<float>(o.y[r]));
      sample.push_back(s);
      hard.push_back(o.is_hard(r));
    }
    count[s] = static_cast<float>(o.rows());
    base_row += o.rows();
  }
  auto i64 = torch::TensorOptions().dtype(torch::kInt64);
  auto f32 = torch::TensorOptions().dtype(torch::kFloat32);
  b.row = torch::tensor(row, i64).to(device);
  b.col = torch::tensor(col, i64).to(device);
  b.val = torch::tensor(val, f32).to(device);
  b.y = torch::tensor(y, f32).to(device);
  b.sample = torch::tensor(sample, i64).to(device);
  b.hard = torch::tensor(std::vector<int64_t>(hard.begin(), hard.end()), i64).to(torch::kBool).to(device);
  b.row_count = torch::tensor(count, f32).to(device);
  return b;
}

torch::Tensor BatchedObservation::apply(const torch::Tensor& x) const {
  TORCH_CHECK(x.dim() == 4 && x.size(0) == batch && x.size(1) == frames && x.size(2) == joints && x.size(3) == 3,
              "BatchedObservation::apply expects [", batch, ", ", frames, ", ", joints, ", 3], got ", x.sizes());
  auto flat = x.reshape({-1});
  auto prod = flat.index_select(0, col) * val.to(x.dtype());
  return torch::zeros({rows()}, x.options()).index_add(0, row, prod);
}

torch::Tensor BatchedObservation::mean_abs_residual(const torch::Tensor& x) const {
  auto r = residual(x).abs();
  auto per = torch::zeros({batch}, x.options()).index_add(0, sample, r);
  return per / row_count.to(x.dtype()).clamp_min(1.0);
}

}  // namespace mc
