// The shared ground truth and evaluator of the table replay.
#include "experiments/row_evaluator.h"

#include <c10/util/hash.h>

#include <array>
#include <filesystem>
#include <random>
#include <type_traits>

#include "core/error.h"
#include "data/fixture/fixture_build.h"
#include "data/skeleton.h"
#include "train/train_job.h"

namespace mc {
namespace fs = std::filesystem;

namespace {

// Appends values to a byte string with their sizes, so that two different sequences
// never serialise to the same bytes.
struct ContentBytes {
  std::string out;
  template <class T>
  void pod(const T& v) {
    out.append(reinterpret_cast<const char*>(&v), sizeof v);
  }
  void str(const std::string& v) {
    pod(static_cast<uint64_t>(v.size()));
    out += v;
  }
  template <class T>
  void vec(const std::vector<T>& v) {
    pod(static_cast<uint64_t>(v.size()));
    if constexpr (std::is_same_v<T, std::string>)
      for (const auto& x : v) str(x);
    else
      out.append(reinterpret_cast<const char*>(v.data()), v.size() * sizeof(T));
  }
};

}  // namespace

const std::string& RowEvaluator::data_content_sha1() const {
  if (!content_sha1_.empty()) return content_sha1_;
  const MotionSet& m = data_;
  ContentBytes b;
  b.str("motionctl ground-truth content v1");
  b.str(m.skeleton.name);
  b.vec(m.skeleton.joint_names);
  b.vec(m.skeleton.parents);
  b.vec(m.skeleton.bone_lengths);
  for (const auto& d : m.skeleton.rest_directions) b.pod(std::array<double, 3>{d.x(), d.y(), d.z()});
  b.pod(m.fps);
  b.pod(m.t_max);
  b.vec(m.lengths);
  b.vec(m.joints);
  b.vec(m.ids);
  b.vec(m.splits);
  b.pod(static_cast<uint64_t>(m.captions.size()));
  for (const auto& c : m.captions) b.vec(c);
  b.vec(m.labels);
  b.pod(m.stats.has_value());
  if (m.stats) {
    b.vec(m.stats->joint_mean);
    b.vec(m.stats->joint_std);
    b.vec(m.stats->feature_mean);
    b.vec(m.stats->feature_std);
    b.str(m.stats->feature_layout);
  }
  b.vec(m.vocab);
  content_sha1_ = c10::sha1(b.out).str();
  return content_sha1_;
}

RowEvaluator::RowEvaluator(const ProfileConfig& profile) {
  data_path_ = resolve_data_path(profile.data);
  if (!fs::exists(data_path_)) {
    if (profile.data_fixture.empty())
      fail("profile.data '{}' does not exist and profile.data_fixture is empty; build it with `motionctl fixture`",
           profile.data);
    build_fixture(resolve_data_path(profile.data_fixture), {fmt::format("output={}", profile.data)}, false);
  }
  data_ = read_motion_file(data_path_);
  split_ = data_.indices_of_split(profile.split);
  split_name_ = profile.split;
  if (split_.empty()) fail("{}: the {} split is empty; choose another profile.split", profile.data, profile.split);
  reference_ = data_.subset(split_);
  TrainResult r = run_train(resolve_data_path(profile.evaluator), {});
  evaluator_run_ = r.run_dir.string();
  evaluator_ = std::make_unique<T2MEvaluator>(T2MEvaluator::load(evaluator_run_));
  reference_embeddings_ = evaluator_->embed_motions(reference_, profile.data);
  realism_ = RealismReference(reference_embeddings_);
}

EvalEmbeddings RowEvaluator::embed(const MotionSet& generated) const {
  EvalEmbeddings e;
  e.gt_motion = reference_embeddings_;
  e.motion = evaluator_->embed_motions(generated, "generated motions");
  for (size_t i = 0; i < generated.size(); ++i) e.captions.push_back(generated.captions[i].at(0));
  e.text = evaluator_->embed_texts(e.captions);
  return e;
}

std::map<std::string, double> RowEvaluator::t2m(const EvalEmbeddings& e, const EvalProtocol& p, uint64_t seed) const {
  return t2m_metrics(e, p, seed);
}

std::pair<double, double> RowEvaluator::realism_floor(int n) const {
  auto it = floors_.find(n);
  if (it != floors_.end()) return it->second;
  // Held-out clips: the first n of the val split, else of train (never the reference split).
  std::vector<size_t> held;
  for (const char* split : {"val", "train", "test"}) {
    if (split == split_name_) continue;
    held = data_.indices_of_split(split);
    if (held.size() >= static_cast<size_t>(n)) break;
  }
  if (held.size() < static_cast<size_t>(std::max(n, 2)))
    fail("{}: the ground-truth floor at N = {} needs {} held-out clips (val or train split), found {}", data_path_, n,
         n, held.size());
  held.resize(n);
  Embeddings e = evaluator_->embed_motions(data_.subset(held), "held-out ground truth");
  auto v = std::make_pair(realism_.fid(e), realism_.kid(e));
  floors_[n] = v;
  return v;
}

std::vector<ControlTask> RowEvaluator::tasks(const ControlProtocol& protocol, int n, uint64_t seed) const {
  std::vector<size_t> clips = split_;
  if (n > 0 && static_cast<size_t>(n) < clips.size()) clips.resize(n);
  std::vector<ControlTask> t = protocol.make_tasks(data_, clips, seed);
  if (t.empty()) fail("the protocol produced no tasks from {} clips", clips.size());
  return t;
}

std::map<std::string, double> RowEvaluator::t2m(const MotionSet& generated, const EvalProtocol& p,
                                                uint64_t seed) const {
  return t2m_metrics(embed(generated), p, seed);
}

double RowEvaluator::multimodality(const MotionSet& generated, int texts, int per_text, int pairs,
                                   uint64_t seed) const {
  if (static_cast<size_t>(texts) * per_text != generated.size())
    fail("multimodality: {} motions are not {} texts x {} generations", generated.size(), texts, per_text);
  Embeddings all = evaluator_->embed_motions(generated, "multimodality generations");
  std::vector<Embeddings> groups;
  for (int i = 0; i < texts; ++i) groups.push_back(all.middleRows(static_cast<Eigen::Index>(i) * per_text, per_text));
  std::mt19937_64 rng(seed);
  return mc::multimodality(groups, std::min(pairs, per_text), rng);
}

}  // namespace mc
