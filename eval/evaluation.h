// The evaluation protocol behind `motionctl eval` and the table replay: T2M
// metrics through the trained evaluator, evaluator-free metrics (foot skating,
// control errors from a constraint spec), replications with 95% CIs.
#pragma once
#include <map>
#include <string>
#include <vector>

#include "core/config.h"
#include "data/motion_set.h"
#include "eval/metrics.h"
#include "eval/t2m_evaluator.h"

namespace mc {

struct EvalProtocol : Config {
  int r_precision_pool = 32;
  int diversity_pairs = 300;
  int multimodality_pairs = 10;
  int repeats = 20;
  bool foot_skating_padded_196 = false;
  std::vector<double> control_thresholds = {0.5, 0.2};
  void visit(FieldVisitor& v) override {
    v("r_precision_pool", r_precision_pool, "R-precision batch size (T2M: 32)", at_least(2));
    v("diversity_pairs", diversity_pairs, "diversity pairs (T2M: 300; capped at the sample count)", at_least(1));
    v("multimodality_pairs", multimodality_pairs, "pairs per text for multimodality (T2M: 10)", at_least(1));
    v("repeats", repeats, "replications (papers: 20); each reshuffles pools and pair draws", at_least(1));
    v("foot_skating_padded_196", foot_skating_padded_196,
      "foot skating over the padded 196-frame sequence (the convention some papers used)");
    v("control_thresholds", control_thresholds, "control error thresholds in metres; the first is the headline",
      each(at_least(0.0)));
  }
  std::string validate() const override {
    return control_thresholds.empty() ? "control_thresholds needs at least one threshold" : "";
  }
};

// Embeddings of one evaluation: ground-truth motions of the reference split and
// the generated motions with the texts they were generated from (first caption).
struct EvalEmbeddings {
  Embeddings gt_motion;
  Embeddings motion;
  Embeddings text;
  std::vector<std::string> captions;
};
EvalEmbeddings embed_for_eval(const T2MEvaluator& ev, const MotionSet& reference, const std::string& reference_source,
                              const MotionSet& motions, const std::string& motions_source);

// One replication of the evaluator metrics: r_precision_top{1,2,3}, matching,
// fid, diversity, multimodality (when some caption has >= 2 generations).
std::map<std::string, double> t2m_metrics(const EvalEmbeddings& e, const EvalProtocol& p, uint64_t seed);

// Evaluator-free metrics of a motion set: foot_skating; with `constraints`
// (a spec file), traj_err/loc_err at each threshold, avg_err, control_error.
// `source` provides from_source targets (clip i for sample i); may be null.
std::map<std::string, double> evaluator_free_metrics(const MotionSet& motions, const std::string& motions_source,
                                                     const EvalProtocol& p, const std::string& constraints,
                                                     const MotionSet* source);

// Evaluator-free metrics of a selection of samples whose indices may repeat (a
// bootstrap resample): foot skating over clips[idx]; with `errors` (per sample entry
// errors, control_entry_errors), the control metrics of the selected samples whose
// list is non-empty. Nothing is recompiled, so a resample costs little.
std::map<std::string, double> free_metrics_of_selection(const std::vector<JointsView>& clips,
                                                        const std::vector<std::vector<double>>* errors,
                                                        const std::vector<size_t>& idx, const Skeleton& skeleton,
                                                        double fps, const EvalProtocol& p);
// The rows idx (may repeat) of the generated motions' embeddings and captions; the
// ground-truth embeddings are kept whole (the reference is not resampled).
EvalEmbeddings select_rows(const EvalEmbeddings& e, const std::vector<size_t>& idx);

// A metric over fixed samples (`motionctl eval` of one motion file, where nothing is
// regenerated): the reported value is the full set's, and its spread comes from B
// bootstrap resamples of the samples (std: their sample SD; ci95: 1.96 SD, the normal
// bootstrap interval; n = B). With B < 2 the spread is 0.
Replicated bootstrap_summary(double full_set_value, const std::vector<double>& resamples);

// Writes {metric: replicate values} and their summaries as CSV and HDF5 (atomic;
// metrics.h5 sealed, core/h5_seal.h). Replications (fresh generations per
// replicate): mean +- 1.96 std / sqrt(n).
void write_metric_results(const std::string& dir, const std::map<std::string, std::vector<double>>& values);
// Reads what write_metric_results wrote (metrics.h5); UserError naming the file and
// the fix when it is missing, damaged (seal mismatch) or unreadable. A file written
// before seals is read in a forked child first, so it cannot crash this process.
std::map<std::string, std::vector<double>> read_metric_results(const std::string& dir);
std::string format_metric_table(const std::map<std::string, std::vector<double>>& values);
std::string format_metric_table(const std::map<std::string, Replicated>& summaries);

}  // namespace mc
