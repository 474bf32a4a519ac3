// Paired decisions for the table replay: what every row keeps per sample (so a
// cached row can still be tested), the headline averaging each paper uses (mean
// over task groups of per-group means), fast set-level metrics on resampled
// indices (FID, KID), and the stratified (Rao-Wu) paired bootstrap that gives each claim a
// three-way verdict: holds, contradicted or undecided.
#pragma once
#include <map>
#include <optional>
#include <random>
#include <string>
#include <vector>

#include "eval/evaluation.h"
#include "eval/metrics.h"

namespace mc {

// What one row saw per sample, for every replicate. Replicate r of every row of a
// table draws the same tasks and the same seed, so rows are paired sample by sample.
struct RowSamples {
  std::vector<std::string> task_ids, groups;  // [N]
  std::vector<Embeddings> motion, text;       // per replicate: evaluator embeddings [N, D]
  std::vector<uint64_t> seeds;                // per replicate: the seed the pools/pairs were drawn with
  // Per replicate: per-sample metric -> [N] (NaN = not applicable to that sample).
  std::vector<std::map<std::string, std::vector<double>>> metrics;
  size_t size() const { return task_ids.size(); }
  size_t replicates() const { return metrics.size(); }
  bool empty() const { return task_ids.empty() || metrics.empty(); }
};
// <run dir>/samples.h5 (docs/formats.md, "samples.h5"). Atomic, sealed write
// (core/h5_seal.h); the read fails naming the file and the fix (delete the row's run
// directory) when it is missing, damaged or unreadable, and reads a file written
// before seals in a forked child first, so it cannot crash this process.
void write_row_samples(const std::string& path, const RowSamples& s);
RowSamples read_row_samples(const std::string& path);

// What a finished row run left for the replay's cache: its replicate values
// (metrics.h5) and per-sample records (samples.h5). A damaged cache is a cache miss,
// not a failed row: when either file is missing, damaged (seal mismatch) or
// unreadable, `damage` says which and why (naming the file) and the rest is empty,
// so the caller warns and recomputes the row (docs/choices.md, "Damaged result files").
struct CachedRowRecords {
  std::map<std::string, std::vector<double>> values;
  RowSamples samples;
  std::string damage;  // '' = both read
  bool usable() const { return damage.empty(); }
};
CachedRowRecords read_cached_row_records(const std::string& run_dir);

// How a per-sample metric becomes a table number.
//  - group-averaged (control errors, foot skating, lifting errors): the papers' mean over
//    settings of per-setting means (OmniControl/ProjFlow: densities and joints, AnchorRoute:
//    anchor counts K); a setting = a distinct task group string;
//  - pooled (T2M matching, R-precision hits): the mean over all samples, as the T2M scripts.
// control_error is entry-weighted inside a group (weights: per-sample `control_entries`).
bool group_averaged_metric(const std::string& metric);
// Metrics recomputed from the embeddings of the resampled samples (not per-sample means).
bool set_level_metric(const std::string& metric);

// The reference a row is compared with for FID/KID, precomputed once: sqrt of its
// covariance (FID through an N x N eigenproblem) and its kernel sums (KID in O(N^2)).
struct RealismReference {
  RealismReference() = default;
  explicit RealismReference(const Embeddings& reference);
  bool empty() const { return embeddings.rows() == 0; }
  // Equal to fid(x, reference) and kid(x, reference) up to rounding (tested).
  double fid(const Embeddings& x) const;
  double kid(const Embeddings& x) const;

  Embeddings embeddings;
  Eigen::VectorXd mean;
  Eigen::MatrixXd sqrt_cov;
  double trace_cov = 0, kyy = 0;  // Tr C_ref; sum_{i != j} k(y_i, y_j) / (m (m - 1))
};

// Metric `metric` (optionally "metric@filter") of replicate r of a row on the samples
// `idx` (indices into the row, repeats allowed: a bootstrap draw). nullopt when the
// row has no per-sample data for it.
std::optional<double> sample_statistic(const RowSamples& s, size_t r, const std::string& metric,
                                       const std::vector<int>& idx, const RealismReference* ref,
                                       const EvalProtocol& p);

// Per-sample T2M quantities of one replicate, with the pools t2m_metrics(seed) draws:
// r_precision_top{1,2,3} = 1 if the sample's own motion ranks < k among its pool's
// motions (NaN outside the full pools), matching = ||t_i - m_i||. Their pooled means
// are t2m_metrics' values.
std::map<std::string, std::vector<double>> per_sample_t2m(const Embeddings& text, const Embeddings& motion, int pool,
                                                         uint64_t seed);

// A table number from one replicate's per-sample values: "metric" or "metric@filter"
// averaged as group_averaged_metric says (pooled = true: the plain mean over samples,
// entry-weighted for control_error, the extra labelled column). nullopt when no sample
// has a finite value.
std::optional<double> headline_value(const std::map<std::string, std::vector<double>>& per_sample,
                                     const std::vector<std::string>& groups, const std::string& key,
                                     bool pooled = false);

// A paired (or, when the rows saw different tasks, unpaired) bootstrap test.
struct PairedTest {
  double estimate = 0;   // statistic(a) - statistic(b) on all samples (one row: statistic(a))
  double lo = 0, hi = 0; // 95% percentile interval
  double se = 0;         // bootstrap standard deviation of the estimate
  int n = 0;             // tasks per row
  int draws = 0;
  bool paired = true;    // false: the rows' tasks differ, resampled independently
  std::string method;    // "paired Rao-Wu bootstrap over tasks (30 strata of >= 2 tasks), 1000 draws", ...
};
struct BootstrapOptions {
  int draws = 1000;
  int set_level_draws = 400;  // FID/KID/diversity recomputed per half-sample
  uint64_t seed = 20240917;
  double factor = 1.0;  // the statistic is a - factor * b (claims "a <= factor x b"; 1 = the plain difference)
};
// Statistic of row a minus that of row b (b = nullptr: of a alone), averaged over the
// replicates both have; tasks resampled within strata (task groups, coarsened until each
// holds >= 2 tasks), the same for both rows when their tasks agree: per-sample metrics by
// the Rao-Wu bootstrap (n_h - 1 draws with replacement per stratum), set-level ones (FID,
// KID, diversity) by half-samples without replacement, their interval re-centred on the
// estimate. nullopt when a row lacks per-sample data for the metric.
std::optional<PairedTest> bootstrap_difference(const RowSamples& a, const RowSamples* b, const std::string& metric,
                                               const RealismReference* ref, const EvalProtocol& p,
                                               const BootstrapOptions& o);
// Paired replicate differences with a Student-t interval: the fallback for metrics
// kept per replicate only (time per sample, parameters, multimodality).
PairedTest replicate_difference(const std::vector<double>& a, const std::vector<double>* b, double factor = 1.0);

// holds / contradicted / undecided for "a better than b" (direction lower|higher) or,
// with b absent, "a <= tol" (the zero claims).
std::string better_verdict(const PairedTest& t, const std::string& direction);
std::string zero_verdict(const PairedTest& t, double tol);
// Tasks that would decide an undecided test at the observed effect (normal
// approximation from the paired SD, 80% power at 5%): n = ((1.96 + 0.84) sd / effect)^2
// with sd = se sqrt(n). `margin` is the value the interval must exclude (0, or tol).
double samples_to_decide(const PairedTest& t, double margin = 0.0);

}  // namespace mc
