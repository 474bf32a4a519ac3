// T2M embedding metrics: FID, KID, R-precision, matching score, diversity and
// multimodality (reference-facts §5, §6b), plus the portable index draws they use.
#include <Eigen/Eigenvalues>
#include <algorithm>
#include <cmath>
#include <numeric>

#include "core/error.h"
#include "eval/metrics.h"

namespace mc {

// ---------------------------------------------------------------- randomness

uint64_t uniform_index(std::mt19937_64& rng, uint64_t n) {
  if (n == 0) fail("uniform_index: empty range");
  // Reject the lowest (2^64 mod n) outputs so that r % n is exactly uniform.
  const uint64_t threshold = (0 - n) % n;
  for (;;) {
    const uint64_t r = rng();
    if (r >= threshold) return r % n;
  }
}

std::vector<int> sample_without_replacement(std::mt19937_64& rng, int n, int k) {
  if (k < 0 || k > n) fail("cannot draw {} distinct indices from {}", k, n);
  std::vector<int> idx(n);
  std::iota(idx.begin(), idx.end(), 0);
  for (int i = 0; i < k; ++i) {
    const int j = i + static_cast<int>(uniform_index(rng, static_cast<uint64_t>(n - i)));
    std::swap(idx[i], idx[j]);
  }
  idx.resize(k);
  return idx;
}

// ---------------------------------------------------------------- FID

namespace {

void check_finite(const Eigen::MatrixXd& m, const char* what) {
  if (!m.allFinite()) fail("{}: embeddings contain NaN or Inf", what);
}

void check_pairs(const Embeddings& text, const Embeddings& motion, const char* what) {
  if (text.rows() == 0) fail("{}: no (text, motion) pairs", what);
  if (text.rows() != motion.rows() || text.cols() != motion.cols())
    fail("{}: text embeddings are {}x{} but motion embeddings are {}x{} (need one motion row per text row)",
         what, text.rows(), text.cols(), motion.rows(), motion.cols());
  check_finite(text, what);
  check_finite(motion, what);
}

}  // namespace

GaussianStats gaussian_stats(const Embeddings& x) {
  if (x.rows() < 2) fail("gaussian_stats: need at least 2 embeddings to fit a covariance, got {}", x.rows());
  if (x.cols() == 0) fail("gaussian_stats: embeddings have no dimensions");
  check_finite(x, "gaussian_stats");
  GaussianStats g;
  g.mean = x.colwise().mean().transpose();
  const Eigen::MatrixXd centred = x.rowwise() - g.mean.transpose();
  // Unbiased estimate (N - 1), as numpy.cov(x, rowvar=False) in the T2M scripts.
  g.cov = centred.transpose() * centred / static_cast<double>(x.rows() - 1);
  return g;
}

Eigen::MatrixXd sqrtm_psd(const Eigen::MatrixXd& a) {
  if (a.rows() != a.cols()) fail("sqrtm_psd: matrix is {}x{}, not square", a.rows(), a.cols());
  const Eigen::MatrixXd sym = 0.5 * (a + a.transpose());  // remove rounding asymmetry
  Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> es(sym);
  if (es.info() != Eigen::Success) fail("sqrtm_psd: eigendecomposition did not converge");
  const Eigen::VectorXd root = es.eigenvalues().cwiseMax(0.0).cwiseSqrt();  // clamp tiny negatives
  return es.eigenvectors() * root.asDiagonal() * es.eigenvectors().transpose();
}

// Fréchet distance between N(mu1, C1) and N(mu2, C2) (T2M / FID):
//   ||mu1 - mu2||^2 + Tr(C1) + Tr(C2) - 2 Tr((C1 C2)^{1/2}).
// Tr((C1 C2)^{1/2}) without a general (non-symmetric) matrix square root: let
// S = C1^{1/2} (symmetric PSD) and M = S C2 S (symmetric PSD). Then C1 C2 = S (S C2)
// and M = (S C2) S; AB and BA have the same non-zero eigenvalues with multiplicity,
// so the eigenvalues of C1 C2 are those of M: real and >= 0. The principal square
// root of C1 C2 has eigenvalues sqrt(lambda_i), hence
//   Tr((C1 C2)^{1/2}) = sum_i sqrt(lambda_i(M)) = Tr(M^{1/2}).
// M goes through a symmetric eigensolver (backward stable, real output) and rounding
// negatives are clamped to 0, where scipy's sqrtm of the non-symmetric product C1 C2
// (the T2M script) can return spurious imaginary parts that it then discards.
double frechet_distance(const Eigen::VectorXd& mu1, const Eigen::MatrixXd& cov1, const Eigen::VectorXd& mu2,
                        const Eigen::MatrixXd& cov2) {
  const Eigen::Index d = mu1.size();
  if (d == 0) fail("frechet_distance: empty mean vector");
  if (mu2.size() != d || cov1.rows() != d || cov1.cols() != d || cov2.rows() != d || cov2.cols() != d)
    fail("frechet_distance: shapes disagree (mu1 {}, cov1 {}x{}, mu2 {}, cov2 {}x{})", mu1.size(), cov1.rows(),
         cov1.cols(), mu2.size(), cov2.rows(), cov2.cols());
  if (!mu1.allFinite() || !mu2.allFinite() || !cov1.allFinite() || !cov2.allFinite())
    fail("frechet_distance: NaN or Inf in the statistics");
  const Eigen::MatrixXd s1 = sqrtm_psd(cov1);
  const Eigen::MatrixXd m = s1 * cov2 * s1;
  Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> es(0.5 * (m + m.transpose()), Eigen::EigenvaluesOnly);
  if (es.info() != Eigen::Success) fail("frechet_distance: eigendecomposition did not converge");
  const double tr_covmean = es.eigenvalues().cwiseMax(0.0).cwiseSqrt().sum();
  return (mu1 - mu2).squaredNorm() + cov1.trace() + cov2.trace() - 2.0 * tr_covmean;
}

double fid(const Embeddings& a, const Embeddings& b) {
  if (a.cols() != b.cols()) fail("fid: embedding dimensions differ ({} vs {})", a.cols(), b.cols());
  const GaussianStats ga = gaussian_stats(a), gb = gaussian_stats(b);
  return frechet_distance(ga.mean, ga.cov, gb.mean, gb.cov);
}

// ---------------------------------------------------------------- KID

// Unbiased MMD^2 (Gretton et al. 2012, eq. 3) with KID's cubic polynomial kernel:
//   sum_{i != j} k(a_i, a_j) / (m (m - 1)) + sum_{i != j} k(b_i, b_j) / (n (n - 1))
//   - 2 sum_{i, j} k(a_i, b_j) / (m n).
// Dropping the diagonal terms k(x_i, x_i) is what removes the bias a plug-in
// (V-statistic) estimate has at small N.
double kid(const Embeddings& a, const Embeddings& b) {
  if (a.rows() < 2 || b.rows() < 2) fail("kid: need at least 2 embeddings per set, got {} and {}", a.rows(), b.rows());
  if (a.cols() != b.cols()) fail("kid: embedding dimensions differ ({} vs {})", a.cols(), b.cols());
  if (a.cols() == 0) fail("kid: embeddings have no dimensions");
  check_finite(a, "kid");
  check_finite(b, "kid");
  const double d = static_cast<double>(a.cols());
  auto kernel = [d](const Embeddings& x, const Embeddings& y) -> Eigen::MatrixXd {
    return ((x * y.transpose()).array() / d + 1.0).cube().matrix();
  };
  const double m = static_cast<double>(a.rows()), n = static_cast<double>(b.rows());
  const Eigen::MatrixXd kaa = kernel(a, a), kbb = kernel(b, b), kab = kernel(a, b);
  const double saa = kaa.sum() - kaa.diagonal().sum(), sbb = kbb.sum() - kbb.diagonal().sum();
  return saa / (m * (m - 1)) + sbb / (n * (n - 1)) - 2.0 * kab.sum() / (m * n);
}

// ---------------------------------------------------------------- retrieval

std::vector<double> r_precision(const Embeddings& text, const Embeddings& motion, int pool, int top_k) {
  check_pairs(text, motion, "r_precision");
  if (pool < 1) fail("r_precision: pool size must be >= 1, got {}", pool);
  if (top_k < 1 || top_k > pool) fail("r_precision: top_k must be in [1, pool = {}], got {}", pool, top_k);
  const Eigen::Index pools = text.rows() / pool;  // the last partial pool is dropped (T2M drop_last)
  if (pools == 0)
    fail("r_precision: {} pairs do not fill one pool of {} (the partial pool is dropped)", text.rows(), pool);
  std::vector<double> hits(top_k, 0.0);
  for (Eigen::Index p = 0; p < pools; ++p) {
    const Eigen::Index base = p * pool;
    for (int i = 0; i < pool; ++i) {
      const auto t = text.row(base + i);
      const double own = (t - motion.row(base + i)).norm();
      // Rank of the paired motion in a stable ascending sort of the distances.
      int rank = 0;
      for (int j = 0; j < pool && rank < top_k; ++j) {
        if (j == i) continue;
        const double d = (t - motion.row(base + j)).norm();
        if (d < own || (d == own && j < i)) ++rank;
      }
      for (int k = rank; k < top_k; ++k) hits[k] += 1.0;  // cumulative: a hit at k counts for k' >= k
    }
  }
  const double n = static_cast<double>(pools * pool);
  for (double& h : hits) h /= n;
  return hits;
}

double matching_score(const Embeddings& text, const Embeddings& motion) {
  check_pairs(text, motion, "matching_score");
  return (text - motion).rowwise().norm().mean();
}

// ---------------------------------------------------------------- diversity

double diversity(const Embeddings& emb, int pairs, std::mt19937_64& rng) {
  if (pairs < 1) fail("diversity: pairs must be >= 1, got {}", pairs);
  if (emb.rows() < pairs)
    fail("diversity: need at least {} samples for {} pairs, got {}", pairs, pairs, emb.rows());
  check_finite(emb, "diversity");
  const int n = static_cast<int>(emb.rows());
  const std::vector<int> first = sample_without_replacement(rng, n, pairs);
  const std::vector<int> second = sample_without_replacement(rng, n, pairs);
  double sum = 0.0;
  for (int i = 0; i < pairs; ++i) sum += (emb.row(first[i]) - emb.row(second[i])).norm();
  return sum / pairs;
}

double multimodality(const std::vector<Embeddings>& groups, int pairs, std::mt19937_64& rng) {
  if (pairs < 1) fail("multimodality: pairs must be >= 1, got {}", pairs);
  if (groups.empty()) fail("multimodality: no texts");
  const Eigen::Index g = groups[0].rows(), d = groups[0].cols();
  for (size_t i = 0; i < groups.size(); ++i) {
    if (groups[i].rows() != g || groups[i].cols() != d)
      fail("multimodality: text {} has {}x{} embeddings but text 0 has {}x{} (need the same number of "
           "generations per text)",
           i, groups[i].rows(), groups[i].cols(), g, d);
    check_finite(groups[i], "multimodality");
  }
  if (g < pairs) fail("multimodality: need at least {} generations per text for {} pairs, got {}", pairs, pairs, g);
  // One draw of indices shared by every text, as calculate_multimodality in T2M.
  const std::vector<int> first = sample_without_replacement(rng, static_cast<int>(g), pairs);
  const std::vector<int> second = sample_without_replacement(rng, static_cast<int>(g), pairs);
  double sum = 0.0;
  for (const Embeddings& e : groups)
    for (int i = 0; i < pairs; ++i) sum += (e.row(first[i]) - e.row(second[i])).norm();
  return sum / (static_cast<double>(groups.size()) * pairs);
}

}  // namespace mc
