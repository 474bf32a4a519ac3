// What every row of every table is measured against: the ground-truth file and
// split (tasks and the FID reference) and the trained evaluator, loaded once.
#pragma once
#include <memory>
#include <string>
#include <vector>

#include "control/control_task.h"
#include "data/motion_set.h"
#include "eval/evaluation.h"
#include "eval/t2m_evaluator.h"
#include "experiments/experiment.h"
#include "experiments/paired.h"

namespace mc {

class RowEvaluator {
 public:
  // Builds the data from profile.data_fixture when missing; trains the evaluator on first use.
  explicit RowEvaluator(const ProfileConfig& profile);

  // The protocol's tasks on the first n clips of the split (n = 0: all). Same
  // arguments, same tasks: every row of a table sees the same tasks.
  std::vector<ControlTask> tasks(const ControlProtocol& protocol, int n, uint64_t seed) const;
  // One replication of the evaluator metrics of `generated` against the split.
  std::map<std::string, double> t2m(const MotionSet& generated, const EvalProtocol& p, uint64_t seed) const;
  // The evaluator embeddings of `generated` (motions and their first captions) against the split.
  EvalEmbeddings embed(const MotionSet& generated) const;
  std::map<std::string, double> t2m(const EvalEmbeddings& e, const EvalProtocol& p, uint64_t seed) const;
  // FID and KID of n held-out ground-truth clips (the first n of another split) against
  // the reference split: the floor a perfect generator reaches at the same N (the
  // GT-vs-GT floor `motionctl health` reports). Cached per n.
  std::pair<double, double> realism_floor(int n) const;
  // The reference split's embeddings prepared for FID/KID on resampled samples.
  const RealismReference& realism() const { return realism_; }
  // T2M's multimodality of `generated` = `texts` groups of `per_text` consecutive
  // generations of one text each (`pairs` pairs per group).
  double multimodality(const MotionSet& generated, int texts, int per_text, int pairs, uint64_t seed) const;

  const MotionSet& data() const { return data_; }
  const MotionSet& reference() const { return reference_; }
  // SHA-1 of what the ground truth holds (skeleton, fps, clips, ids, splits, captions,
  // labels, statistics, vocabulary), not of the file's bytes: a fixture rebuilt on a
  // fresh clone has the same content but not the same bytes (HDF5 layout, its provenance
  // naming the output path), and should not count as other data. Computed once.
  const std::string& data_content_sha1() const;
  const std::string& evaluator_run() const { return evaluator_run_; }

 private:
  MotionSet data_, reference_;
  std::vector<size_t> split_;
  std::string data_path_, evaluator_run_, split_name_;
  std::unique_ptr<T2MEvaluator> evaluator_;
  Embeddings reference_embeddings_;
  RealismReference realism_;
  mutable std::map<int, std::pair<double, double>> floors_;
  mutable std::string content_sha1_;
};

}  // namespace mc
