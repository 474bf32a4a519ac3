// Random motions and random constraint items of every type, for the property
// tests of the constraint compiler and the projection solver.
#pragma once
#include <Eigen/Dense>
#include <algorithm>
#include <numeric>
#include <random>
#include <string>
#include <vector>

#include "control/constraint_spec.h"
#include "control/linear_observation.h"
#include "core/error.h"
#include "data/skeleton.h"

namespace mc::test {

// A [T, J, 3] world motion: rest pose, a drifting root and per-joint noise.
inline std::vector<float> random_motion(std::mt19937_64& rng, int T, const Skeleton& sk, double noise = 0.05) {
  std::normal_distribution<double> n(0.0, 1.0);
  auto rest = sk.rest_pose();
  const int J = sk.num_joints();
  std::vector<float> m(static_cast<size_t>(T) * J * 3);
  Eigen::Vector3d root(0.3 * n(rng), 0.9, 0.3 * n(rng));
  for (int t = 0; t < T; ++t) {
    root += Eigen::Vector3d(0.05 * n(rng), 0.01 * n(rng), 0.05 * n(rng));
    for (int j = 0; j < J; ++j)
      for (int c = 0; c < 3; ++c)
        m[(static_cast<size_t>(t) * J + j) * 3 + c] = static_cast<float>(root[c] + rest[j][c] + noise * n(rng));
  }
  return m;
}

inline Eigen::VectorXd to_vector(const std::vector<float>& m) {
  Eigen::VectorXd v(static_cast<Eigen::Index>(m.size()));
  for (size_t i = 0; i < m.size(); ++i) v[static_cast<Eigen::Index>(i)] = m[i];
  return v;
}

inline int uniform_int(std::mt19937_64& rng, int lo, int hi) {  // inclusive
  return std::uniform_int_distribution<int>(lo, hi)(rng);
}
inline double uniform(std::mt19937_64& rng, double lo, double hi) {
  return std::uniform_real_distribution<double>(lo, hi)(rng);
}

// k distinct sorted values from 0..n-1.
inline std::vector<int> random_subset(std::mt19937_64& rng, int n, int k) {
  std::vector<int> all(n);
  std::iota(all.begin(), all.end(), 0);
  std::shuffle(all.begin(), all.end(), rng);
  all.resize(std::min(k, n));
  std::sort(all.begin(), all.end());
  return all;
}

inline std::vector<JointRef> joint_refs(const std::vector<int>& js, const Skeleton& sk, std::mt19937_64& rng) {
  std::vector<JointRef> out;
  bool by_name = uniform_int(rng, 0, 1) == 1;  // exercise both spellings
  for (int j : js) out.push_back(by_name ? JointRef{-1, sk.joint_names[j]} : JointRef{j, ""});
  return out;
}

inline FrameSelection frame_list(const std::vector<int>& fs) {
  FrameSelection f;
  f.kind = FrameSelection::Kind::list;
  f.list = fs;
  return f;
}

inline std::vector<int> random_axes(std::mt19937_64& rng) {
  std::vector<int> a = random_subset(rng, 3, uniform_int(rng, 1, 3));
  if (uniform_int(rng, 0, 2) == 0) return {};  // default xyz
  return a;
}

// Explicit targets: the source value plus an offset, so that hard rows of one
// item stay consistent while still differing from the source.
inline TargetArray values_of(std::vector<int> shape, const std::vector<double>& data) {
  TargetArray v;
  v.shape = std::move(shape);
  v.data = data;
  return v;
}

// One random item of `type` for a clip of T frames. Targets come from the source
// or are given explicitly (random), chosen at random.
inline ConstraintItem random_item(const std::string& type, std::mt19937_64& rng, int T, const Skeleton& sk,
                                  double variance) {
  const int J = sk.num_joints();
  std::normal_distribution<double> n(0.0, 1.0);
  ConstraintItem it;
  it.type = type;
  it.name = type + "_" + std::to_string(uniform_int(rng, 0, 999));
  it.variance = variance;
  const bool explicit_values = uniform_int(rng, 0, 1) == 1;
  auto random_data = [&](size_t count, double scale) {
    std::vector<double> d(count);
    for (auto& v : d) v = scale * n(rng);
    return d;
  };
  auto axes_count = [](const std::vector<int>& a) { return a.empty() ? 3 : static_cast<int>(a.size()); };
  if (type == "keyframe" || type == "trajectory") {
    auto js = random_subset(rng, J, uniform_int(rng, 1, 4));
    it.joints = joint_refs(js, sk, rng);
    std::vector<int> fs;
    if (type == "keyframe") {
      fs = random_subset(rng, T, uniform_int(rng, 1, std::min(3, T)));
      it.frames = frame_list(fs);
    } else if (uniform_int(rng, 0, 1)) {
      it.frames.kind = FrameSelection::Kind::all;
      fs.resize(T);
      std::iota(fs.begin(), fs.end(), 0);
    } else {
      it.frames.kind = FrameSelection::Kind::range;
      it.frames.start = uniform_int(rng, 0, T - 2);
      it.frames.stop = uniform_int(rng, it.frames.start + 1, T);
      it.frames.step = uniform_int(rng, 1, 2);
      for (int t = it.frames.start; t < it.frames.stop; t += it.frames.step) fs.push_back(t);
    }
    it.axes = random_axes(rng);
    const int F = static_cast<int>(fs.size()), Jk = static_cast<int>(js.size()), A = axes_count(it.axes);
    if (explicit_values) it.values = values_of({F, Jk, A}, random_data(static_cast<size_t>(F) * Jk * A, 0.5));
    else it.from_source = true;
  } else if (type == "planar_root") {
    auto fs = random_subset(rng, T, uniform_int(rng, 1, T));
    it.frames = frame_list(fs);
    const int F = static_cast<int>(fs.size());
    if (explicit_values) it.values = values_of({F, 2}, random_data(static_cast<size_t>(F) * 2, 1.0));
    else it.from_source = true;
  } else if (type == "camera_2d") {
    auto js = random_subset(rng, J, uniform_int(rng, 1, J));
    it.joints = joint_refs(js, sk, rng);
    auto fs = random_subset(rng, T, uniform_int(rng, 1, T));
    it.frames = frame_list(fs);
    it.has_camera = true;
    it.camera = {uniform(rng, 0.8, 1.2), uniform(rng, 0, 30), uniform(rng, -45, 45),
                 uniform_int(rng, 0, 1) ? 0.0 : uniform(rng, -20, 20)};
    const int F = static_cast<int>(fs.size()), Jk = static_cast<int>(js.size());
    if (explicit_values) it.values = values_of({F, Jk, 2}, random_data(static_cast<size_t>(F) * Jk * 2, 0.5));
    else it.from_source = true;
  } else if (type == "relative") {
    auto js = random_subset(rng, J, 2);
    std::shuffle(js.begin(), js.end(), rng);
    it.joints = joint_refs(js, sk, rng);
    auto fs = random_subset(rng, T, uniform_int(rng, 1, T));
    it.frames = frame_list(fs);
    it.axes = random_axes(rng);
    const int F = static_cast<int>(fs.size()), A = axes_count(it.axes);
    if (!explicit_values) it.from_source = true;
    else if (uniform_int(rng, 0, 1)) it.values = values_of({A}, random_data(static_cast<size_t>(A), 0.3));
    else it.values = values_of({F, A}, random_data(static_cast<size_t>(F) * A, 0.3));
  } else if (type == "loop") {
    if (uniform_int(rng, 0, 3) > 0) it.joints = joint_refs(random_subset(rng, J, uniform_int(rng, 1, J)), sk, rng);
    it.axes = random_axes(rng);
    it.up_to_root_translation = uniform_int(rng, 0, 1) == 1;
    if (uniform_int(rng, 0, 1)) {
      auto fs = random_subset(rng, T, 2);
      it.frames = frame_list(fs);
    }
  } else if (type == "upper_body_edit") {
    if (uniform_int(rng, 0, 1)) it.frames = frame_list(random_subset(rng, T, uniform_int(rng, 1, T)));
    it.axes = random_axes(rng);
  }
  return it;
}

// A compiled random spec. Items are added one by one and an item whose hard rows
// would be redundant with the ones before (compile rejects those) is redrawn, up
// to 100 times, then dropped; so every returned observation is valid, and
// `spec_out` tells which items made it.
inline LinearObservation random_observation(const std::vector<std::string>& types, std::mt19937_64& rng, int T,
                                            const Skeleton& sk, const std::vector<float>& source, bool soft,
                                            ConstraintSpec* spec_out = nullptr) {
  ConstraintSpec spec;
  spec.source = "<random>";
  for (auto& type : types)
    for (int attempt = 0; attempt < 100; ++attempt) {
      spec.items.push_back(random_item(type, rng, T, sk, soft ? std::pow(10.0, uniform(rng, -4, 0)) : 0.0));
      try {
        compile(spec, T, sk, source.data());
        break;
      } catch (const UserError&) {
        spec.items.pop_back();
      }
    }
  if (spec.items.empty()) throw std::runtime_error("could not draw a valid random constraint set");
  if (spec_out) *spec_out = spec;
  return compile(spec, T, sk, source.data());
}

}  // namespace mc::test
