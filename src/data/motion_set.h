// The one in-memory motion container and its HDF5 file (docs/formats.md): used
// for datasets, generated samples and results alike.
#pragma once
#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "data/skeleton.h"

namespace mc {

struct Provenance {
  std::string generator;  // e.g. "motionctl fixture", "motionctl sample", "humanml3d_to_h5.py"
  std::string version;    // generator version
  int64_t seed = 0;
  std::string config;     // resolved config YAML text
  std::string created;    // ISO-8601 UTC; the only time in the file: callers wanting byte-identical files fix it
};

// Normalisation statistics from the train split.
struct NormStats {
  std::vector<float> joint_mean, joint_std;      // (3,): per-axis, shared by all joints (ACMDM)
  std::vector<float> feature_mean, feature_std;  // (F,): per feature dim of the joint-derived features
  std::string feature_layout;                    // name of the feature layout, e.g. "mc67"
};

struct MotionSet {
  Skeleton skeleton;
  double fps = 20.0;
  int t_max = 0;                                  // padded length
  std::vector<float> joints;                      // [N, t_max, J, 3] world metres, Y up, zero-padded
  std::vector<int> lengths;                       // [N] valid frames
  std::vector<std::string> ids;                   // [N]
  std::vector<std::string> splits;                // [N] "train" | "val" | "test" (or "sample")
  std::vector<std::vector<std::string>> captions; // [N][>=1]
  std::vector<std::string> labels;                // [N] optional free-form tag (fixture: motion program), may be empty
  Provenance provenance;
  std::optional<NormStats> stats;
  std::vector<std::string> vocab;                 // word-level vocabulary (may be empty)

  size_t size() const { return lengths.size(); }
  int num_joints() const { return skeleton.num_joints(); }
  size_t clip_stride() const { return static_cast<size_t>(t_max) * num_joints() * 3; }
  float* clip(size_t i) { return joints.data() + i * clip_stride(); }
  const float* clip(size_t i) const { return joints.data() + i * clip_stride(); }
  // Position of joint j at frame t of clip i (x, y, z).
  float* at(size_t i, int t, int j) { return clip(i) + (static_cast<size_t>(t) * num_joints() + j) * 3; }
  const float* at(size_t i, int t, int j) const { return clip(i) + (static_cast<size_t>(t) * num_joints() + j) * 3; }
  std::vector<size_t> indices_of_split(const std::string& split) const;
  MotionSet subset(const std::vector<size_t>& idx) const;  // same skeleton/fps/t_max/stats/vocab
  // Shapes, finiteness, lengths in range, zero padding, unique ids, one caption or
  // more per clip, valid splits and stats; UserError naming `source` and the field.
  void check(const std::string& source) const;
  void clear_padding();  // zero the frames >= lengths[i] (the file format requires it)
};

void write_motion_file(const std::string& path, const MotionSet& m);  // atomic
MotionSet read_motion_file(const std::string& path);                  // UserError on missing/corrupt/mis-shaped

}  // namespace mc
