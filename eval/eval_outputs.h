// What outside tools need from an evaluation (defined in eval/evaluation.cpp):
// control errors from the per-sample constraint specs a generated file carries,
// and metrics.h5 with the evaluator embeddings and per-sample metrics
// (docs/formats.md, "metrics.h5"), so FID and R-precision can be recomputed
// with the community's T2M code.
#pragma once
#include <map>
#include <string>
#include <vector>

#include "control/constraint_spec.h"
#include "eval/evaluation.h"

namespace mc {

// Per motion, the error of every constrained entry (observation_entry_errors), from
// one spec file for all motions (with `source` for from_source targets; may be null)
// or from one spec per motion compiled without a source; empty for a motion
// without constraints.
std::vector<std::vector<double>> control_entry_errors(const MotionSet& motions, const std::string& motions_source,
                                                      const std::string& constraints, const MotionSet* source);
std::vector<std::vector<double>> control_entry_errors(const MotionSet& motions, const std::string& motions_source,
                                                      const std::vector<ConstraintSpec>& specs);

// evaluator_free_metrics with one spec per motion (the /control group of a generated
// file, control/sample_constraints.h); motions whose spec is empty are left out of
// the control metrics, as `motionctl generate` leaves them out of its error line.
std::map<std::string, double> evaluator_free_metrics(const MotionSet& motions, const std::string& motions_source,
                                                     const EvalProtocol& p, const std::vector<ConstraintSpec>& specs);

// What one `motionctl eval` saw per sample.
struct EvalSampleRecord {
  const EvalEmbeddings* embeddings = nullptr;          // motion/text [N, D], gt_motion [M, D]
  std::vector<std::string> ids, reference_ids;         // [N], [M]
  std::vector<int> lengths;                            // [N]
  std::map<std::string, std::vector<double>> metrics;  // per-sample metric -> [N] (NaN = not applicable)
  std::map<std::string, std::string> attrs;            // input paths and their SHA-1, evaluator run, split
};

// write_metric_results with the given summaries (bootstrap_summary: the values are
// bootstrap resamples; metrics.h5's root attribute `interval` says "bootstrap"), and
// metrics.h5 also holds /embeddings, /samples and the record's attributes.
void write_eval_results(const std::string& dir, const std::map<std::string, std::vector<double>>& values,
                        const std::map<std::string, Replicated>& summaries, const EvalSampleRecord& record);
// The embeddings metrics.h5 stores (/embeddings); UserError naming the file when absent
// or damaged (read as read_metric_results reads: seal checked, unsealed files probed).
EvalEmbeddings read_eval_embeddings(const std::string& dir);

}  // namespace mc
