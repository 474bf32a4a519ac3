// Shared helpers for the data-layer tests: scratch directories, a random
// MotionSet, and exact MotionSet comparison.
#pragma once
#include <unistd.h>

#include <atomic>
#include <cmath>
#include <filesystem>
#include <random>
#include <string>
#include <vector>

#include "data/motion_set.h"

namespace mc::test {

namespace fs = std::filesystem;

// A fresh directory under the system temp dir, removed with its contents at scope exit.
class ScratchDir {
 public:
  ScratchDir() {
    static std::atomic<int> counter{0};
    path_ = fs::temp_directory_path() / ("motionctl_data_test_" + std::to_string(::getpid()) + "_" +
                                         std::to_string(counter++));
    fs::remove_all(path_);
    fs::create_directories(path_);
  }
  ~ScratchDir() {
    std::error_code ec;
    fs::remove_all(path_, ec);
  }
  std::string file(const std::string& name) const { return (path_ / name).string(); }
  const fs::path& path() const { return path_; }
  std::vector<std::string> entries() const {
    std::vector<std::string> names;
    for (auto& e : fs::directory_iterator(path_)) names.push_back(e.path().filename().string());
    return names;
  }

 private:
  fs::path path_;
};

// Random joints (zero padded) for the given lengths on the HumanML3D skeleton.
inline MotionSet random_motion_set(const std::vector<int>& lengths, const std::vector<std::string>& splits,
                                   unsigned seed = 7) {
  MotionSet m;
  m.skeleton = humanml3d_skeleton();
  m.fps = 20.0;
  m.t_max = 0;
  for (int l : lengths) m.t_max = std::max(m.t_max, l);
  m.lengths = lengths;
  m.joints.assign(lengths.size() * m.clip_stride(), 0.0f);
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> u(-1.5f, 1.5f);
  for (size_t i = 0; i < lengths.size(); ++i) {
    for (int t = 0; t < lengths[i]; ++t)
      for (int j = 0; j < m.num_joints(); ++j)
        for (int a = 0; a < 3; ++a) m.at(i, t, j)[a] = u(rng);
    m.ids.push_back("clip" + std::to_string(i));
    m.splits.push_back(splits[i % splits.size()]);
    m.captions.push_back({"a person walks number " + std::to_string(i)});
  }
  return m;
}

inline bool same_stats(const std::optional<NormStats>& a, const std::optional<NormStats>& b) {
  if (a.has_value() != b.has_value()) return false;
  if (!a) return true;
  return a->joint_mean == b->joint_mean && a->joint_std == b->joint_std && a->feature_mean == b->feature_mean &&
         a->feature_std == b->feature_std && a->feature_layout == b->feature_layout;
}

// Exact equality of everything a motion file stores.
inline bool same_motion_set(const MotionSet& a, const MotionSet& b) {
  return a.skeleton == b.skeleton && a.fps == b.fps && a.t_max == b.t_max && a.joints == b.joints &&
         a.lengths == b.lengths && a.ids == b.ids && a.splits == b.splits && a.captions == b.captions &&
         a.labels == b.labels && a.provenance.generator == b.provenance.generator &&
         a.provenance.version == b.provenance.version && a.provenance.seed == b.provenance.seed &&
         a.provenance.config == b.provenance.config && a.provenance.created == b.provenance.created &&
         same_stats(a.stats, b.stats) && a.vocab == b.vocab;
}

}  // namespace mc::test
