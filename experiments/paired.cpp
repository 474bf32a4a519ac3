// Paired decisions: per-sample row records (samples.h5, sealed; a row's cached
// records read back or found damaged), the papers' headline
// averaging over task groups, FID/KID on resampled indices without refitting the
// reference, and the stratified paired bootstrap behind the claim verdicts.
#include "experiments/paired.h"

#include <H5Cpp.h>

#include <algorithm>
#include <cmath>
#include <numeric>
#include <set>

#include "core/atomic_file.h"
#include "core/error.h"
#include "core/h5_seal.h"
#include "eval/h5_arrays.h"

namespace mc {
namespace fs = std::filesystem;

// ------------------------------------------------------------------ metric kinds

bool group_averaged_metric(const std::string& m) {
  static const std::set<std::string> g = {"avg_err",  "traj_err",  "loc_err",   "control_error", "foot_skating",
                                          "foot_skating_padded", "foot_skating_valid", "mpjpe_2d", "mpjpe_3d",
                                          "avg_err_2d", "avg_err_3d",
                                          // issue 20: angle error of direction items, floor contact, worst inequality
                                          "direction_error", "floor_penetration", "floor_frames",
                                          "inequality_violation"};
  return g.count(m) > 0 || m.rfind("traj_err_", 0) == 0 || m.rfind("loc_err_", 0) == 0;
}

bool set_level_metric(const std::string& m) { return m == "fid" || m == "kid" || m == "diversity"; }

// ------------------------------------------------------------------ per-sample T2M

std::map<std::string, std::vector<double>> per_sample_t2m(const Embeddings& text, const Embeddings& motion, int pool,
                                                         uint64_t seed) {
  const int n = static_cast<int>(motion.rows());
  std::map<std::string, std::vector<double>> out;
  auto& match = out["matching"];
  for (int i = 0; i < n; ++i) match.push_back((text.row(i) - motion.row(i)).norm());
  for (int k = 1; k <= 3; ++k) out[fmt::format("r_precision_top{}", k)].assign(n, std::nan(""));
  if (n < pool) return out;
  // The permutation t2m_metrics draws first from the same seed: the same pools.
  std::mt19937_64 rng(seed);
  std::vector<int> perm(n);
  std::iota(perm.begin(), perm.end(), 0);
  for (int i = n - 1; i > 0; --i) std::swap(perm[i], perm[uniform_index(rng, i + 1)]);
  for (int p = 0; p + pool <= n; p += pool) {
    for (int a = 0; a < pool; ++a) {
      const int i = perm[p + a];
      const double own = (text.row(i) - motion.row(i)).norm();
      int rank = 0;  // motions of the pool closer than its own (ties broken by pool position, as r_precision)
      for (int b = 0; b < pool; ++b) {
        if (b == a) continue;
        const double d = (text.row(i) - motion.row(perm[p + b])).norm();
        rank += d < own || (d == own && b < a);
      }
      for (int k = 1; k <= 3; ++k) out[fmt::format("r_precision_top{}", k)][i] = rank < k ? 1.0 : 0.0;
    }
  }
  // T2M's matching score covers the full pools only: the samples outside them are not applicable.
  for (int q = n / pool * pool; q < n; ++q) match[perm[q]] = std::nan("");
  return out;
}

// ------------------------------------------------------------------ realism reference

namespace {

Eigen::MatrixXd cubic_kernel(const Embeddings& x, const Embeddings& y) {
  const double d = static_cast<double>(x.cols());
  return ((x * y.transpose()).array() / d + 1.0).cube().matrix();
}

// FID of the rows `idx` of X against the reference, with Y = X sqrt(C_ref):
// Tr sqrt(C_x C_ref) = Tr sqrt(S C_x S) = sum sqrt(eig(Yc Yc^T / (n - 1))), an n x n problem.
double fid_rows(const Embeddings& x, const Embeddings& y, const std::vector<int>& idx, const RealismReference& ref) {
  const Eigen::Index n = static_cast<Eigen::Index>(idx.size());
  if (n < 2) return std::nan("");
  Embeddings xs(n, x.cols()), ys(n, y.cols());
  for (Eigen::Index i = 0; i < n; ++i) {
    xs.row(i) = x.row(idx[i]);
    ys.row(i) = y.row(idx[i]);
  }
  const Eigen::RowVectorXd mx = xs.colwise().mean(), my = ys.colwise().mean();
  xs.rowwise() -= mx;
  ys.rowwise() -= my;
  const double trace_x = xs.squaredNorm() / static_cast<double>(n - 1);
  Eigen::MatrixXd g = ys * ys.transpose() / static_cast<double>(n - 1);
  Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> es(0.5 * (g + g.transpose()), Eigen::EigenvaluesOnly);
  const double tr_covmean = es.eigenvalues().cwiseMax(0.0).cwiseSqrt().sum();
  return (mx.transpose() - ref.mean).squaredNorm() + trace_x + ref.trace_cov - 2.0 * tr_covmean;
}

// KID of the rows `idx` from the kernel matrix K_xx and the row sums of K_x,ref.
double kid_rows(const Eigen::MatrixXd& kxx, const Eigen::VectorXd& kxy_rows, const RealismReference& ref,
                const std::vector<int>& idx) {
  const size_t n = idx.size();
  if (n < 2) return std::nan("");
  double sxx = 0, sxy = 0;
  for (size_t a = 0; a < n; ++a) {
    sxy += kxy_rows[idx[a]];
    for (size_t b = 0; b < n; ++b)
      if (a != b) sxx += kxx(idx[a], idx[b]);
  }
  const double m = static_cast<double>(ref.embeddings.rows());
  return sxx / (static_cast<double>(n) * (n - 1)) + ref.kyy - 2.0 * sxy / (static_cast<double>(n) * m);
}

std::vector<int> all_indices(size_t n) {
  std::vector<int> idx(n);
  std::iota(idx.begin(), idx.end(), 0);
  return idx;
}

}  // namespace

RealismReference::RealismReference(const Embeddings& reference) : embeddings(reference) {
  const double m = static_cast<double>(reference.rows());
  if (m < 2) fail("realism reference: need at least 2 embeddings, got {}", reference.rows());
  GaussianStats g = gaussian_stats(reference);
  mean = g.mean;
  sqrt_cov = sqrtm_psd(g.cov);
  trace_cov = g.cov.trace();
  Eigen::MatrixXd k = cubic_kernel(reference, reference);
  kyy = (k.sum() - k.diagonal().sum()) / (m * (m - 1));
}

double RealismReference::fid(const Embeddings& x) const { return fid_rows(x, x * sqrt_cov, all_indices(x.rows()), *this); }

double RealismReference::kid(const Embeddings& x) const {
  return kid_rows(cubic_kernel(x, x), cubic_kernel(x, embeddings).rowwise().sum(), *this, all_indices(x.rows()));
}

// ------------------------------------------------------------------ statistics on indices

namespace {

// "metric@filter" -> (metric, filter); a filter matches a whole group or one of its
// '/'-separated parts ("K=2" matches "family=root3d/K=2", not "K=32").
std::pair<std::string, std::string> split_metric(const std::string& key) {
  size_t at = key.find('@');
  if (at == std::string::npos) return {key, ""};
  return {key.substr(0, at), key.substr(at + 1)};
}

bool group_matches(const std::string& group, const std::string& filter) {
  if (filter.empty() || group == filter) return true;
  size_t start = 0;
  while (true) {
    size_t slash = group.find('/', start);
    if (group.substr(start, slash == std::string::npos ? std::string::npos : slash - start) == filter) return true;
    if (slash == std::string::npos) return false;
    start = slash + 1;
  }
}

// One (row, replicate, metric) prepared for many index draws: per-draw cost O(n) for
// per-sample metrics, O(n^2 D + n^3) for FID, O(n^2) for KID.
struct Prepared {
  enum class Kind { per_sample, fid, kid, diversity } kind = Kind::per_sample;
  bool group_mean = false;
  const std::vector<double>* values = nullptr;
  const std::vector<double>* weights = nullptr;  // control_entries for control_error
  std::vector<int> group_of;                     // sample -> group index
  int groups = 0;
  const Embeddings* x = nullptr;
  Embeddings y;        // x sqrt(C_ref) (FID)
  Eigen::MatrixXd kxx; // (KID)
  Eigen::VectorXd kxy; // (KID)
  const RealismReference* ref = nullptr;
  uint64_t seed = 0;
  int pairs = 0;

  double operator()(const std::vector<int>& idx) const {
    switch (kind) {
      case Kind::fid:
        return fid_rows(*x, y, idx, *ref);
      case Kind::kid:
        return kid_rows(kxx, kxy, *ref, idx);
      case Kind::diversity: {
        if (idx.size() < 2) return std::nan("");
        Embeddings e(static_cast<Eigen::Index>(idx.size()), x->cols());
        for (size_t i = 0; i < idx.size(); ++i) e.row(static_cast<Eigen::Index>(i)) = x->row(idx[i]);
        std::mt19937_64 rng(seed);
        return mc::diversity(e, std::min<int>(pairs, static_cast<int>(idx.size())), rng);
      }
      case Kind::per_sample:
        break;
    }
    const std::vector<double>& v = *values;
    if (!group_mean) {
      double s = 0;
      int n = 0;
      for (int i : idx)
        if (std::isfinite(v[i])) s += v[i], ++n;
      return n ? s / n : std::nan("");
    }
    std::vector<double> sum(groups, 0.0), w(groups, 0.0);
    for (int i : idx) {
      if (!std::isfinite(v[i])) continue;
      const double wi = weights ? (*weights)[i] : 1.0;
      sum[group_of[i]] += wi * v[i];
      w[group_of[i]] += wi;
    }
    double s = 0;
    int n = 0;
    for (int g = 0; g < groups; ++g)
      if (w[g] > 0) s += sum[g] / w[g], ++n;
    return n ? s / n : std::nan("");
  }
};

// nullopt: the row has no per-sample data for the metric.
std::optional<Prepared> prepare(const RowSamples& s, size_t r, const std::string& metric,
                                const RealismReference* ref, const EvalProtocol& p) {
  if (s.empty() || r >= s.replicates()) return std::nullopt;
  Prepared pr;
  std::map<std::string, int> gi;
  for (const auto& g : s.groups) {
    auto it = gi.find(g);
    if (it == gi.end()) it = gi.emplace(g, static_cast<int>(gi.size())).first;
    pr.group_of.push_back(it->second);
  }
  pr.groups = static_cast<int>(gi.size());
  if (set_level_metric(metric)) {
    if (r >= s.motion.size() || s.motion[r].rows() != static_cast<Eigen::Index>(s.size())) return std::nullopt;
    pr.x = &s.motion[r];
    if (metric == "diversity") {
      pr.kind = Prepared::Kind::diversity;
      pr.seed = r < s.seeds.size() ? s.seeds[r] : 0;
      pr.pairs = p.diversity_pairs;
      return pr;
    }
    if (!ref || ref->empty()) return std::nullopt;
    pr.ref = ref;
    if (metric == "fid") {
      pr.kind = Prepared::Kind::fid;
      pr.y = *pr.x * ref->sqrt_cov;
    } else {
      pr.kind = Prepared::Kind::kid;
      pr.kxx = cubic_kernel(*pr.x, *pr.x);
      pr.kxy = cubic_kernel(*pr.x, ref->embeddings).rowwise().sum();
    }
    return pr;
  }
  const auto& m = s.metrics[r];
  auto it = m.find(metric);
  if (it == m.end() || it->second.size() != s.size()) return std::nullopt;
  pr.values = &it->second;
  pr.group_mean = group_averaged_metric(metric);
  if (metric == "control_error") {
    auto w = m.find("control_entries");
    if (w != m.end() && w->second.size() == s.size()) pr.weights = &w->second;
  }
  return pr;
}

// The samples a "metric@filter" covers.
std::vector<int> covered(const RowSamples& s, const std::string& filter) {
  std::vector<int> out;
  for (size_t i = 0; i < s.size(); ++i)
    if (group_matches(s.groups[i], filter)) out.push_back(static_cast<int>(i));
  return out;
}

// Mean over replicates of a prepared statistic on idx (replicates with NaN skipped).
double mean_over(const std::vector<Prepared>& reps, const std::vector<int>& idx) {
  double s = 0;
  int n = 0;
  for (const auto& p : reps) {
    double v = p(idx);
    if (std::isfinite(v)) s += v, ++n;
  }
  return n ? s / n : std::nan("");
}

std::optional<std::vector<Prepared>> prepare_all(const RowSamples& s, const std::string& metric,
                                                 const RealismReference* ref, const EvalProtocol& p) {
  std::vector<Prepared> out;
  for (size_t r = 0; r < s.replicates(); ++r) {
    auto pr = prepare(s, r, metric, ref, p);
    if (!pr) return std::nullopt;
    out.push_back(std::move(*pr));
  }
  if (out.empty()) return std::nullopt;
  return out;
}

// One bootstrap draw (Rao & Wu 1988, rescaling bootstrap with m_h = n_h - 1): from each
// stratum of n_h >= 2 tasks, n_h - 1 indices with replacement. Drawing n_h would make the
// bootstrap variance of a stratum mean (n_h - 1) / n_h of the unbiased s_h^2 / n_h: half
// of it with two tasks per group, none with one, which is what made claims on 30 task
// groups of ~1 task each look decided (docs/choices.md, "Bootstrap strata").
std::vector<int> stratified_draw(const std::vector<std::vector<int>>& strata, std::mt19937_64& rng) {
  std::vector<int> idx;
  for (const auto& st : strata) {
    const size_t m = st.size() > 1 ? st.size() - 1 : st.size();
    for (size_t k = 0; k < m; ++k) idx.push_back(st[uniform_index(rng, st.size())]);
  }
  return idx;
}

// One half-sample for set-level metrics (FID, KID, diversity): from each stratum about
// half of its tasks without replacement, round(n / 2) in all (strata with an odd count
// share the extra tasks at random). A mean over m of n tasks drawn without replacement
// varies as (1/m - 1/n) s^2, which is the full sample's s^2 / n at m = n / 2; the
// statistic of a smooth functional does to first order. Unlike draws with replacement,
// no row is duplicated and every draw has the same number of distinct tasks, which
// FID's small-set bias (~ c / n, c differing between rows) depends on; measured, both
// draws are calibrated off the reference (docs/choices.md, "Bootstrap strata").
std::vector<int> half_sample_draw(const std::vector<std::vector<int>>& strata, std::mt19937_64& rng) {
  size_t total = 0, base = 0;
  std::vector<size_t> odd;
  for (size_t h = 0; h < strata.size(); ++h) {
    total += strata[h].size();
    base += strata[h].size() / 2;
    if (strata[h].size() % 2) odd.push_back(h);
  }
  const size_t target = (total + 1) / 2;
  for (size_t i = 0; i < odd.size(); ++i) std::swap(odd[i], odd[i + uniform_index(rng, odd.size() - i)]);
  std::vector<char> extra(strata.size(), 0);
  for (size_t i = 0; i < odd.size() && base + i < target; ++i) extra[odd[i]] = 1;
  std::vector<int> idx;
  for (size_t h = 0; h < strata.size(); ++h) {
    std::vector<int> st = strata[h];
    const size_t m = st.size() / 2 + extra[h];
    for (size_t k = 0; k < m; ++k) {  // partial Fisher-Yates: m distinct tasks
      std::swap(st[k], st[k + uniform_index(rng, st.size() - k)]);
      idx.push_back(st[k]);
    }
  }
  return idx;
}

// Resampling strata: the task groups, coarsened while any stratum holds fewer than 2 tasks
// (a single task carries no within-stratum variance) by dropping the group key's leading
// '/'-part ("joint=head/density=1" -> "density=1" -> one stratum). A coarsened stratum mixes
// settings, so its draws can leave a setting out of a group-mean statistic; that adds the
// between-setting spread to the interval (conservative), never removes variance.
std::vector<std::vector<int>> strata_of(const RowSamples& s, const std::vector<int>& members) {
  std::vector<std::string> keys;
  for (int i : members) keys.push_back(s.groups[i]);
  while (true) {
    std::map<std::string, int> count;
    for (const auto& k : keys) ++count[k];
    bool small = false, coarsenable = false;
    for (const auto& [k, c] : count) small = small || c < 2, coarsenable = coarsenable || !k.empty();
    if (!small || !coarsenable) break;
    for (auto& k : keys) {
      const size_t slash = k.find('/');
      k = slash == std::string::npos ? std::string() : k.substr(slash + 1);
    }
  }
  std::map<std::string, std::vector<int>> by;
  for (size_t j = 0; j < members.size(); ++j) by[keys[j]].push_back(members[j]);
  std::vector<std::vector<int>> out;
  for (auto& [_, v] : by) out.push_back(v);
  return out;
}

double percentile(std::vector<double> v, double q) {
  std::sort(v.begin(), v.end());
  const double pos = q * (v.size() - 1);
  const size_t lo = static_cast<size_t>(std::floor(pos)), hi = std::min(lo + 1, v.size() - 1);
  return v[lo] + (pos - lo) * (v[hi] - v[lo]);
}

}  // namespace

std::optional<double> sample_statistic(const RowSamples& s, size_t r, const std::string& key,
                                       const std::vector<int>& idx, const RealismReference* ref,
                                       const EvalProtocol& p) {
  auto [metric, filter] = split_metric(key);
  auto pr = prepare(s, r, metric, ref, p);
  if (!pr) return std::nullopt;
  std::vector<int> kept;
  for (int i : idx)
    if (group_matches(s.groups.at(i), filter)) kept.push_back(i);
  double v = (*pr)(kept);
  if (!std::isfinite(v)) return std::nullopt;
  return v;
}

std::optional<double> headline_value(const std::map<std::string, std::vector<double>>& per_sample,
                                     const std::vector<std::string>& groups, const std::string& key, bool pooled) {
  auto [metric, filter] = split_metric(key);
  auto it = per_sample.find(metric);
  if (it == per_sample.end() || it->second.size() != groups.size()) return std::nullopt;
  Prepared pr;
  pr.values = &it->second;
  pr.group_mean = !pooled && group_averaged_metric(metric);
  if (metric == "control_error") {
    auto w = per_sample.find("control_entries");
    if (w != per_sample.end() && w->second.size() == groups.size()) pr.weights = &w->second;
  }
  std::map<std::string, int> gi;
  for (const auto& g : groups) pr.group_of.push_back(gi.emplace(g, static_cast<int>(gi.size())).first->second);
  pr.groups = static_cast<int>(gi.size());
  std::vector<int> idx;
  for (size_t i = 0; i < groups.size(); ++i)
    if (group_matches(groups[i], filter)) idx.push_back(static_cast<int>(i));
  if (pooled && pr.weights) {  // entry-pooled: one group
    pr.group_mean = true;
    pr.group_of.assign(groups.size(), 0);
    pr.groups = 1;
  }
  const double v = pr(idx);
  if (!std::isfinite(v)) return std::nullopt;
  return v;
}

std::optional<PairedTest> bootstrap_difference(const RowSamples& a, const RowSamples* b, const std::string& key,
                                               const RealismReference* ref, const EvalProtocol& p,
                                               const BootstrapOptions& o) {
  auto [metric, filter] = split_metric(key);
  auto pa = prepare_all(a, metric, ref, p);
  if (!pa) return std::nullopt;
  std::optional<std::vector<Prepared>> pb;
  if (b) {
    pb = prepare_all(*b, metric, ref, p);
    if (!pb) return std::nullopt;
  }
  const std::vector<int> ma = covered(a, filter);
  const std::vector<int> mb = b ? covered(*b, filter) : std::vector<int>{};
  if (ma.empty() || (b && mb.empty())) return std::nullopt;
  PairedTest t;
  t.paired = !b || (a.task_ids == b->task_ids && a.groups == b->groups);
  t.n = static_cast<int>(ma.size());
  const double va = mean_over(*pa, ma), vb = b ? mean_over(*pb, mb) : 0.0;
  if (!std::isfinite(va) || !std::isfinite(vb)) return std::nullopt;
  t.estimate = va - o.factor * vb;
  t.draws = set_level_metric(metric) ? o.set_level_draws : o.draws;
  const auto sa = strata_of(a, ma);
  const auto sb = b ? strata_of(*b, mb) : std::vector<std::vector<int>>{};
  std::mt19937_64 rng(o.seed);
  std::vector<double> diffs;
  diffs.reserve(t.draws);
  const bool half = set_level_metric(metric);
  auto draw = [&](const std::vector<std::vector<int>>& st) {
    return half ? half_sample_draw(st, rng) : stratified_draw(st, rng);
  };
  for (int k = 0; k < t.draws; ++k) {
    std::vector<int> ia = draw(sa);
    // Paired: the same resampled tasks for both rows (common random numbers).
    std::vector<int> ib = b ? (t.paired ? ia : draw(sb)) : std::vector<int>{};
    const double da = mean_over(*pa, ia), db = b ? mean_over(*pb, ib) : 0.0;
    if (std::isfinite(da) && std::isfinite(db)) diffs.push_back(da - o.factor * db);
  }
  if (diffs.size() < 10) return std::nullopt;
  t.draws = static_cast<int>(diffs.size());
  double mean = std::accumulate(diffs.begin(), diffs.end(), 0.0) / diffs.size(), ss = 0;
  for (double d : diffs) ss += (d - mean) * (d - mean);
  t.se = std::sqrt(ss / std::max<size_t>(1, diffs.size() - 1));
  // FID/KID/diversity of a half-sample carry another small-set bias than the estimate on
  // all n (FID ~ FID_inf + c / n): the spread of the draws is the sampling spread, their
  // location is not, so the interval is re-centred on the estimate.
  const double shift = half ? t.estimate - mean : 0.0;
  t.lo = percentile(diffs, 0.025) + shift;
  t.hi = percentile(diffs, 0.975) + shift;
  t.method = fmt::format("{} {} over tasks ({} of >= 2 tasks), {} draws",
                         t.paired ? "paired" : "unpaired (the rows saw different tasks)",
                         half ? "half-samples without replacement, re-centred," : "Rao-Wu bootstrap",
                         sa.size() == 1 ? std::string("1 stratum") : fmt::format("{} strata", sa.size()), t.draws);
  return t;
}

// Two-sided 97.5% Student-t quantiles for 1..30 degrees of freedom; 1.96 beyond.
static double t975(int df) {
  static const double q[] = {12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228,
                             2.201,  2.179, 2.160, 2.145, 2.131, 2.120, 2.110, 2.101, 2.093, 2.086,
                             2.080,  2.074, 2.069, 2.064, 2.060, 2.056, 2.052, 2.048, 2.045, 2.042};
  return df >= 1 && df <= 30 ? q[df - 1] : 1.96;
}

PairedTest replicate_difference(const std::vector<double>& a, const std::vector<double>* b, double factor) {
  PairedTest t;
  const size_t n = b ? std::min(a.size(), b->size()) : a.size();
  if (n == 0) fail("replicate_difference: no replicates");
  std::vector<double> d(n);
  for (size_t i = 0; i < n; ++i) d[i] = a[i] - (b ? factor * (*b)[i] : 0.0);
  const double mean = std::accumulate(d.begin(), d.end(), 0.0) / n;
  double ss = 0;
  for (double x : d) ss += (x - mean) * (x - mean);
  const double sd = n > 1 ? std::sqrt(ss / (n - 1)) : 0.0;
  t.estimate = mean;
  t.n = static_cast<int>(n);
  t.se = sd / std::sqrt(static_cast<double>(n));
  // One replicate of a varying quantity cannot bound anything: an infinite interval.
  const double half = n > 1 ? t975(static_cast<int>(n) - 1) * t.se : (sd == 0 && b ? 0.0 : INFINITY);
  t.lo = mean - half;
  t.hi = mean + half;
  t.paired = true;
  t.method = fmt::format("paired differences of {} replicates, Student-t interval", n);
  if (n == 1) {  // constant quantities (parameter counts) are exact; anything else is undecided
    t.lo = t.hi = mean;
    t.method = "one replicate (exact only for deterministic quantities)";
  }
  return t;
}

std::string better_verdict(const PairedTest& t, const std::string& direction) {
  // d = a - b; "a better" means d < 0 for lower, d > 0 for higher.
  const bool lower = direction != "higher";
  if (lower ? t.hi < 0 : t.lo > 0) return "holds";
  if (lower ? t.lo > 0 : t.hi < 0) return "contradicted";
  return "undecided";
}

std::string zero_verdict(const PairedTest& t, double tol) {
  if (t.hi <= tol) return "holds";
  if (t.lo > tol) return "contradicted";
  return "undecided";
}

double samples_to_decide(const PairedTest& t, double margin) {
  const double effect = std::fabs(t.estimate - margin);
  if (!(effect > 0) || !std::isfinite(t.se)) return INFINITY;
  const double sd = t.se * std::sqrt(static_cast<double>(std::max(1, t.n)));
  const double z = 1.96 + 0.84;  // 5% two-sided, 80% power
  return std::ceil(std::pow(z * sd / effect, 2));
}

// ------------------------------------------------------------------ samples.h5

namespace {

std::string h5_key(std::string k) {
  std::replace(k.begin(), k.end(), '/', '|');
  return k;
}

// A damaged record is the row's cache: deleting its run directory recomputes it.
std::string row_samples_fix(const std::string& path) {
  return fmt::format("delete the row's run directory '{}' and re-run reproduce to recompute the row",
                     fs::path(path).parent_path().string());
}

RowSamples read_row_samples_unchecked(const std::string& path) {
  RowSamples s;
  try {
    H5::Exception::dontPrint();
    H5::H5File f(path, H5F_ACC_RDONLY);
    H5::Group t = f.openGroup("tasks");
    s.task_ids = read_strings(t, "ids");
    s.groups = read_strings(t, "groups");
    for (size_t r = 0; f.nameExists(fmt::format("r{}", r)); ++r) {
      H5::Group g = f.openGroup(fmt::format("r{}", r));
      uint64_t seed = 0;
      g.openAttribute("seed").read(H5::PredType::NATIVE_UINT64, &seed);
      s.seeds.push_back(seed);
      if (g.nameExists("motion")) s.motion.push_back(read_matrix(g, "motion"));
      if (g.nameExists("text")) s.text.push_back(read_matrix(g, "text"));
      H5::Group m = g.openGroup("samples");
      std::map<std::string, std::vector<double>> mm;
      for (hsize_t i = 0; i < m.getNumObjs(); ++i) {
        std::string name = m.getObjnameByIdx(i);
        H5::DataSet ds = m.openDataSet(name);
        H5::DataSpace space = ds.getSpace();
        if (space.getSimpleExtentNdims() != 1)  // one value per task (getSimpleExtentDims would overrun n)
          fail("{}: dataset 'r{}/samples/{}' is not one-dimensional; {}", path, r, name, row_samples_fix(path));
        hsize_t n = 0;
        space.getSimpleExtentDims(&n);
        std::vector<double> v(n);
        if (n) ds.read(v.data(), H5::PredType::NATIVE_DOUBLE);
        std::replace(name.begin(), name.end(), '|', '/');
        mm[name] = std::move(v);
      }
      s.metrics.push_back(std::move(mm));
    }
  } catch (const H5::Exception& e) {
    fail("{}: cannot read the row's per-sample record ({}); {}", path, e.getDetailMsg(), row_samples_fix(path));
  }
  return s;
}

}  // namespace

void write_row_samples(const std::string& path, const RowSamples& s) {
  AtomicOutput out(path);
  {
    H5::Exception::dontPrint();
    // The user block holds the checksum seal (core/h5_seal.h), written once the file is closed.
    H5::FileCreatPropList fcpl;
    fcpl.setUserblock(kH5SealBlock);
    H5::H5File f(out.tmp_path().string(), H5F_ACC_TRUNC, fcpl);
    H5::Group root = f.openGroup("/");
    {
      H5::StrType type(H5::PredType::C_S1, H5T_VARIABLE);
      const char* fmt_name = "motionctl.row_samples";
      root.createAttribute("format", type, H5::DataSpace(H5S_SCALAR)).write(type, &fmt_name);
      const int64_t version = 1;
      root.createAttribute("format_version", H5::PredType::STD_I64LE, H5::DataSpace(H5S_SCALAR))
          .write(H5::PredType::NATIVE_INT64, &version);
    }
    H5::Group t = f.createGroup("tasks");
    write_strings(t, "ids", s.task_ids);
    write_strings(t, "groups", s.groups);
    for (size_t r = 0; r < s.replicates(); ++r) {
      H5::Group g = f.createGroup(fmt::format("r{}", r));
      const uint64_t seed = r < s.seeds.size() ? s.seeds[r] : 0;
      g.createAttribute("seed", H5::PredType::STD_U64LE, H5::DataSpace(H5S_SCALAR))
          .write(H5::PredType::NATIVE_UINT64, &seed);
      if (r < s.motion.size()) write_matrix(g, "motion", s.motion[r]);
      if (r < s.text.size()) write_matrix(g, "text", s.text[r]);
      H5::Group m = g.createGroup("samples");
      for (auto& [k, v] : s.metrics[r]) {
        hsize_t n = v.size();
        H5::DataSpace space(1, &n);
        m.createDataSet(h5_key(k), H5::PredType::IEEE_F64LE, space).write(v.data(), H5::PredType::NATIVE_DOUBLE);
      }
    }
  }  // closed (flushed) here, before the seal covers its bytes
  seal_h5_file(out.tmp_path().string(), fmt::format("per-sample record '{}'", path));
  out.commit();
}

RowSamples read_row_samples(const std::string& path) {
  std::error_code ec;
  if (!fs::is_regular_file(path, ec)) fail("per-sample record '{}' does not exist; {}", path, row_samples_fix(path));
  guard_h5_read(path, "per-sample record", row_samples_fix(path), [&] { read_row_samples_unchecked(path); });
  return read_row_samples_unchecked(path);
}

CachedRowRecords read_cached_row_records(const std::string& run_dir) {
  CachedRowRecords c;
  try {
    c.values = read_metric_results(run_dir);
    c.samples = read_row_samples((fs::path(run_dir) / "samples.h5").string());
  } catch (const UserError& e) {
    // Damaged, truncated, unreadable or missing: all mean "not cached". Nothing half-read is kept.
    c = CachedRowRecords{};
    c.damage = e.what();
  }
  return c;
}

}  // namespace mc
