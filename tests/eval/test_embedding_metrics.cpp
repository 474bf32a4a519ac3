// T2M embedding metrics on hand-computed cases and statistical properties: FID
// against closed forms, KID by hand and its unbiasedness, R-precision, matching
// score, diversity, multimodality.
#include <Eigen/Eigenvalues>
#include <complex>

#include "eval_test_util.h"

using namespace mc;
using mc::test::gaussian_matrix;

namespace {

// Tr((C1 C2)^{1/2}) by an independent route: the general (non-symmetric)
// eigensolver on the product itself, summing principal square roots.
double trace_sqrt_product_general(const Eigen::MatrixXd& c1, const Eigen::MatrixXd& c2) {
  Eigen::EigenSolver<Eigen::MatrixXd> es(c1 * c2, false);
  std::complex<double> s = 0.0;
  for (Eigen::Index i = 0; i < es.eigenvalues().size(); ++i) s += std::sqrt(es.eigenvalues()(i));
  return s.real();
}

Eigen::MatrixXd random_spd(int d, uint64_t seed) {
  const Eigen::MatrixXd a = gaussian_matrix(d, d, seed);
  return a * a.transpose() + 0.1 * Eigen::MatrixXd::Identity(d, d);
}

}  // namespace

TEST_CASE("uniform_index and sample_without_replacement are in range, distinct and reproducible", "[eval]") {
  std::mt19937_64 a(7), b(7);
  for (int i = 0; i < 1000; ++i) {
    const uint64_t x = uniform_index(a, 13);
    REQUIRE(x < 13);
    REQUIRE(x == uniform_index(b, 13));
  }
  std::mt19937_64 r(1);
  const std::vector<int> s = sample_without_replacement(r, 50, 50);
  std::vector<int> sorted = s;
  std::sort(sorted.begin(), sorted.end());
  for (int i = 0; i < 50; ++i) REQUIRE(sorted[i] == i);  // a permutation
  // Golden draw: pins the index algorithm (rejection sampling + partial Fisher-Yates
  // on std::mt19937_64, whose output the standard fixes), so evaluation subsets are
  // identical on every platform and across refactors.
  std::mt19937_64 g(42);
  REQUIRE(sample_without_replacement(g, 10, 4) == std::vector<int>{6, 0, 4, 7});
  REQUIRE_USER_ERROR(sample_without_replacement(g, 3, 4), "cannot draw 4 distinct indices from 3");
}

TEST_CASE("gaussian_stats uses the unbiased covariance (numpy.cov)", "[eval]") {
  Eigen::MatrixXd x(3, 2);
  x << 0, 1,
       2, 1,
       4, 4;
  const GaussianStats g = gaussian_stats(x);
  REQUIRE(g.mean(0) == Approx(2.0));
  REQUIRE(g.mean(1) == Approx(2.0));
  // centred: (-2,-1), (0,-1), (2,2); sums of products / (N - 1 = 2)
  REQUIRE(g.cov(0, 0) == Approx(8.0 / 2));
  REQUIRE(g.cov(1, 1) == Approx(6.0 / 2));
  REQUIRE(g.cov(0, 1) == Approx(6.0 / 2));
  REQUIRE(g.cov(1, 0) == Approx(6.0 / 2));
}

TEST_CASE("sqrtm_psd squares back and clamps tiny negative eigenvalues", "[eval]") {
  const Eigen::MatrixXd c = random_spd(5, 3);
  const Eigen::MatrixXd s = sqrtm_psd(c);
  REQUIRE((s * s - c).norm() < 1e-10);
  REQUIRE((s - s.transpose()).norm() < 1e-12);
  Eigen::MatrixXd near_singular = Eigen::MatrixXd::Zero(2, 2);
  near_singular(0, 0) = 4.0;
  near_singular(1, 1) = -1e-15;  // rounding noise
  const Eigen::MatrixXd r = sqrtm_psd(near_singular);
  REQUIRE(r.allFinite());
  REQUIRE(r(0, 0) == Approx(2.0));
  REQUIRE(r(1, 1) == 0.0);
}

TEST_CASE("FID of identical sets is zero", "[eval]") {
  const Eigen::MatrixXd a = gaussian_matrix(200, 16, 11);
  REQUIRE(std::abs(fid(a, a)) < 1e-6);
  const GaussianStats g = gaussian_stats(a);
  REQUIRE(std::abs(frechet_distance(g.mean, g.cov, g.mean, g.cov)) < 1e-6);
}

TEST_CASE("Frechet distance of diagonal Gaussians equals sum (sqrt a - sqrt b)^2 + mean term", "[eval]") {
  Eigen::VectorXd mu1(3), mu2(3), a(3), b(3);
  mu1 << 0, 1, 2;
  mu2 << 1, 1, 0;
  a << 1, 4, 9;
  b << 4, 1, 0.25;
  const double expected = (1 + 0 + 4) + std::pow(1 - 2, 2) + std::pow(2 - 1, 2) + std::pow(3 - 0.5, 2);
  REQUIRE(frechet_distance(mu1, a.asDiagonal().toDenseMatrix(), mu2, b.asDiagonal().toDenseMatrix()) ==
          Approx(expected).epsilon(1e-12));
}

TEST_CASE("Frechet distance with non-commuting full covariances matches independent computations", "[eval]") {
  // 2x2 by hand: for A with eigenvalues l1, l2 >= 0, (Tr A^{1/2})^2 = Tr A + 2 sqrt(det A).
  Eigen::MatrixXd c1(2, 2), c2(2, 2);
  c1 << 2, 1,
        1, 2;
  c2 << 1, 0,
        0, 3;
  REQUIRE(((c1 * c2) - (c2 * c1)).norm() > 1.0);  // they really do not commute
  // C1 C2 = [[2,3],[1,6]]: trace 8, det 9 -> Tr (C1 C2)^{1/2} = sqrt(8 + 2*3) = sqrt(14)
  Eigen::VectorXd mu1(2), mu2(2);
  mu1 << 0, 0;
  mu2 << 1, 2;
  const double expected = 5.0 + (4.0 + 4.0) - 2.0 * std::sqrt(14.0);
  REQUIRE(frechet_distance(mu1, c1, mu2, c2) == Approx(expected).epsilon(1e-12));

  // 6x6 random SPD: compare with the general eigensolver on C1 C2.
  const Eigen::MatrixXd d1 = random_spd(6, 21), d2 = random_spd(6, 22);
  const Eigen::VectorXd m1 = gaussian_matrix(6, 1, 23), m2 = gaussian_matrix(6, 1, 24);
  const double independent =
      (m1 - m2).squaredNorm() + d1.trace() + d2.trace() - 2.0 * trace_sqrt_product_general(d1, d2);
  REQUIRE(frechet_distance(m1, d1, m2, d2) == Approx(independent).epsilon(1e-9));
}

TEST_CASE("FID: a pure mean shift adds ||shift||^2, rises with the shift, and is symmetric", "[eval]") {
  const Eigen::MatrixXd a = gaussian_matrix(300, 8, 5);
  Eigen::RowVectorXd dir = Eigen::RowVectorXd::Zero(8);
  dir(0) = 0.6;
  dir(3) = 0.8;  // unit vector
  double previous = -1.0;
  for (double shift : {0.0, 0.5, 1.0, 2.0}) {
    const Eigen::MatrixXd b = a.rowwise() + shift * dir;  // same covariance, mean moved by `shift`
    const double f = fid(a, b);
    REQUIRE(f == Approx(shift * shift).margin(1e-8));
    REQUIRE(f > previous);
    previous = f;
  }
  const Eigen::MatrixXd c = 1.5 * gaussian_matrix(250, 8, 6);
  REQUIRE(fid(a, c) == Approx(fid(c, a)).epsilon(1e-10));
  REQUIRE(fid(a, c) > 0.1);
}

TEST_CASE("KID on a hand-computed 1-D example", "[eval][health]") {
  // D = 1, k(x, y) = (x y + 1)^3. a = {0, 1}: k(0, 1) = 1. b = {1, 2}: k(1, 2) = 27.
  // Cross terms: k(0,1) + k(0,2) + k(1,1) + k(1,2) = 1 + 1 + 8 + 27 = 37.
  // KID = 2/2 + 54/2 - 2 * 37 / 4 = 1 + 27 - 18.5 = 9.5.
  Eigen::MatrixXd a(2, 1), b(2, 1);
  a << 0, 1;
  b << 1, 2;
  REQUIRE(kid(a, b) == Approx(9.5).epsilon(1e-14));
  REQUIRE(kid(b, a) == Approx(9.5).epsilon(1e-14));
  // D = 2 divides the dot product: a = {(0,0), (2,0)}, b = {(2,0), (2,2)}.
  // k = (x.y / 2 + 1)^3: aa off-diagonal 1; bb: ((4 + 0)/2 + 1)^3 = 27;
  // ab: 1 + 1 + 27 + 27 = 56 -> 1 + 27 - 2 * 56 / 4 = 0.
  Eigen::MatrixXd c(2, 2), d(2, 2);
  c << 0, 0, 2, 0;
  d << 2, 0, 2, 2;
  REQUIRE(kid(c, d) == Approx(0.0).margin(1e-12));
}

TEST_CASE("KID is unbiased: its mean over same-distribution pairs is ~0 where FID's is not", "[eval][health]") {
  // 400 independent pairs of 8-sample sets from N(0, I_4). The unbiased estimate
  // averages to 0 within 4 standard errors; FID (biased at small N) averages far
  // above 0, and a plug-in MMD^2 that keeps the diagonal k(x_i, x_i) would too.
  const int trials = 400, n = 8, D = 4;
  double sum = 0.0, sum_sq = 0.0, fid_sum = 0.0, vstat_sum = 0.0;
  for (int r = 0; r < trials; ++r) {
    const Eigen::MatrixXd a = gaussian_matrix(n, D, 1000 + 2 * r), b = gaussian_matrix(n, D, 1001 + 2 * r);
    const double k = kid(a, b);
    sum += k;
    sum_sq += k * k;
    fid_sum += fid(a, b);
    auto kern = [&](const Eigen::MatrixXd& x, const Eigen::MatrixXd& y) {
      return ((x * y.transpose()).array() / D + 1.0).cube().matrix().eval();
    };
    vstat_sum += kern(a, a).mean() + kern(b, b).mean() - 2 * kern(a, b).mean();
  }
  const double mean = sum / trials, se = std::sqrt((sum_sq / trials - mean * mean) / trials);
  INFO("mean KID " << mean << " +- " << se << ", mean FID " << fid_sum / trials << ", V-statistic "
                   << vstat_sum / trials);
  CHECK(std::abs(mean) < 4 * se);
  CHECK(fid_sum / trials > 0.5);
  CHECK(vstat_sum / trials > mean + 10 * se);
}

TEST_CASE("KID of two halves of one set is ~0, it grows with a mean shift and is symmetric", "[eval][health]") {
  const Eigen::MatrixXd all = gaussian_matrix(600, 8, 41);
  const Eigen::MatrixXd a = all.topRows(300), b = all.bottomRows(300);
  const double halves = kid(a, b);
  Eigen::RowVectorXd dir = Eigen::RowVectorXd::Zero(8);
  dir(2) = 1.0;
  double previous = halves;
  for (double shift : {0.5, 1.0, 2.0}) {
    const double k = kid(a, b.rowwise() + shift * dir);
    INFO("shift " << shift << ": KID " << k << " vs halves " << halves);
    CHECK(k > previous);
    previous = k;
  }
  // Halves sit near 0 (sampling noise only); a plug-in estimate keeping k(x_i, x_i)
  // would add about 2 (E k(x, x) - E k(x, y)) / 300 ~ 0.06 here, above this bound.
  CHECK(std::abs(halves) < 0.2 * kid(a, b.rowwise() + 0.5 * dir));
  const Eigen::MatrixXd c = 1.5 * gaussian_matrix(250, 8, 6);
  CHECK(kid(a, c) == Approx(kid(c, a)).epsilon(1e-12));
}

TEST_CASE("KID rejects bad input with clear messages", "[eval][health]") {
  REQUIRE_USER_ERROR(kid(gaussian_matrix(1, 3, 1), gaussian_matrix(5, 3, 2)), "at least 2");
  REQUIRE_USER_ERROR(kid(gaussian_matrix(4, 3, 1), gaussian_matrix(5, 2, 2)), "dimensions differ");
  Eigen::MatrixXd nan = gaussian_matrix(4, 3, 1);
  nan(1, 1) = std::nan("");
  REQUIRE_USER_ERROR(kid(nan, gaussian_matrix(5, 3, 2)), "NaN");
}

TEST_CASE("R-precision is 1 for aligned embeddings and drops the last partial pool", "[eval]") {
  const Eigen::MatrixXd t = gaussian_matrix(32 * 3 + 7, 16, 1);
  Eigen::MatrixXd m = t;
  // Scramble only the 7 rows of the partial pool: they must not count.
  m.bottomRows(7) = gaussian_matrix(7, 16, 2);
  const std::vector<double> r = r_precision(t, m);
  REQUIRE(r.size() == 3);
  for (double v : r) REQUIRE(v == 1.0);
}

TEST_CASE("R-precision on a hand-computed pool of 2, with ties broken by index", "[eval]") {
  Eigen::MatrixXd t(4, 1), m(4, 1);
  t << 0, 1, 10, 11;
  m << 0.9, 0, 10, 11;
  // pool 1: text 0 is nearer motion 1 (0 < 0.9) and text 1 nearer motion 0 (0.1 < 1): both miss top-1, hit top-2.
  // pool 2: aligned.
  const std::vector<double> r = r_precision(t, m, 2, 2);
  REQUIRE(r[0] == Approx(0.5));
  REQUIRE(r[1] == Approx(1.0));

  // Tie: text 0 is at distance 1 from both motions; the lower index (its own) ranks
  // first, so it hits. Text 1 (at 5) is nearer motion 0 and misses top-1.
  Eigen::MatrixXd tt(2, 1), mm(2, 1);
  tt << 0, 5;
  mm << 1, -1;
  const std::vector<double> tie = r_precision(tt, mm, 2, 2);
  REQUIRE(tie[0] == Approx(0.5));
  REQUIRE(tie[1] == Approx(1.0));
}

TEST_CASE("R-precision on random embeddings is at chance k/32", "[eval]") {
  const int pools = 400;
  const Eigen::MatrixXd t = gaussian_matrix(32 * pools, 8, 101);
  const Eigen::MatrixXd m = gaussian_matrix(32 * pools, 8, 202);
  const std::vector<double> r = r_precision(t, m, 32, 3);
  // Binomial standard errors over 12800 texts: 0.0015, 0.0021, 0.0026; allow ~4 sigma.
  REQUIRE(r[0] == Approx(1.0 / 32).margin(0.006));
  REQUIRE(r[1] == Approx(2.0 / 32).margin(0.009));
  REQUIRE(r[2] == Approx(3.0 / 32).margin(0.011));
  REQUIRE(r[0] <= r[1]);
  REQUIRE(r[1] <= r[2]);
}

TEST_CASE("matching score is the mean paired distance", "[eval]") {
  Eigen::MatrixXd t(2, 2), m(2, 2);
  t << 0, 0,
       1, 1;
  m << 3, 4,
       1, 1;
  REQUIRE(matching_score(t, m) == Approx(2.5));
}

TEST_CASE("diversity: identical embeddings give 0, two alternating clusters give d per differing pair", "[eval]") {
  std::mt19937_64 rng(3);
  const Eigen::MatrixXd same = Eigen::MatrixXd::Constant(400, 4, 2.5);
  REQUIRE(diversity(same, 300, rng) == 0.0);

  // Even rows at the origin, odd rows at (3, 4): paired distance is 5 when the parities differ, else 0.
  Eigen::MatrixXd clusters = Eigen::MatrixXd::Zero(400, 2);
  for (int i = 1; i < 400; i += 2) clusters.row(i) << 3, 4;
  // Exact value for one seed, reproducing the two draws by hand.
  std::mt19937_64 a(9), b(9);
  const std::vector<int> f = sample_without_replacement(b, 400, 300), s = sample_without_replacement(b, 400, 300);
  int differ = 0;
  for (int i = 0; i < 300; ++i) differ += (f[i] % 2) != (s[i] % 2);
  REQUIRE(diversity(clusters, 300, a) == Approx(5.0 * differ / 300.0));
  // Over many seeds the mean is 5 * P(parities differ) = 5 * 1/2.
  double sum = 0.0;
  for (uint64_t seed = 0; seed < 50; ++seed) {
    std::mt19937_64 r(seed);
    sum += diversity(clusters, 300, r);
  }
  REQUIRE(sum / 50 == Approx(2.5).margin(0.05));  // sd of the mean ~ 0.02
}

TEST_CASE("multimodality: identical generations per text give 0, alternating clusters give d/2", "[eval]") {
  std::vector<Embeddings> groups;
  for (int i = 0; i < 20; ++i) groups.push_back(Eigen::MatrixXd::Constant(30, 3, 10.0 * i));  // texts differ
  std::mt19937_64 rng(4);
  REQUIRE(multimodality(groups, 10, rng) == 0.0);

  std::vector<Embeddings> alt;
  for (int i = 0; i < 100; ++i) {
    Eigen::MatrixXd e = Eigen::MatrixXd::Constant(30, 2, static_cast<double>(i));
    for (int g = 1; g < 30; g += 2) e.row(g) += Eigen::RowVector2d(6, 8);  // distance 10 between parities
    alt.push_back(e);
  }
  std::mt19937_64 a(12), b(12);
  const std::vector<int> f = sample_without_replacement(b, 30, 10), s = sample_without_replacement(b, 30, 10);
  int differ = 0;
  for (int i = 0; i < 10; ++i) differ += (f[i] % 2) != (s[i] % 2);
  // The same index draw serves all 100 texts.
  REQUIRE(multimodality(alt, 10, a) == Approx(10.0 * differ / 10.0));
  double sum = 0.0;
  for (uint64_t seed = 0; seed < 200; ++seed) {
    std::mt19937_64 r(seed);
    sum += multimodality(alt, 10, r);
  }
  REQUIRE(sum / 200 == Approx(5.0).margin(0.25));  // sd of the mean ~ 0.11
}

TEST_CASE("embedding metrics reject bad input with clear messages", "[eval]") {
  std::mt19937_64 rng(0);
  const Eigen::MatrixXd a = gaussian_matrix(40, 4, 1);
  REQUIRE_USER_ERROR(fid(a, gaussian_matrix(40, 5, 2)), "dimensions differ");
  REQUIRE_USER_ERROR(fid(a, Eigen::MatrixXd(0, 4)), "at least 2 embeddings");
  REQUIRE_USER_ERROR(gaussian_stats(a.topRows(1)), "at least 2 embeddings");
  REQUIRE_USER_ERROR(r_precision(a, a.topRows(39)), "need one motion row per text row");
  REQUIRE_USER_ERROR(r_precision(a.topRows(20), a.topRows(20)), "do not fill one pool of 32");
  REQUIRE_USER_ERROR(r_precision(Eigen::MatrixXd(0, 4), Eigen::MatrixXd(0, 4)), "no (text, motion) pairs");
  REQUIRE_USER_ERROR(matching_score(a, gaussian_matrix(40, 3, 2)), "text embeddings are 40x4");
  REQUIRE_USER_ERROR(diversity(a, 300, rng), "need at least 300 samples for 300 pairs, got 40");
  REQUIRE_USER_ERROR(multimodality({}, 10, rng), "no texts");
  REQUIRE_USER_ERROR(multimodality({gaussian_matrix(30, 4, 1), gaussian_matrix(29, 4, 2)}, 10, rng),
                     "same number of generations");
  REQUIRE_USER_ERROR(multimodality({gaussian_matrix(5, 4, 1)}, 10, rng), "at least 10 generations");
  Eigen::MatrixXd bad = a;
  bad(3, 2) = std::nan("");
  REQUIRE_USER_ERROR(fid(a, bad), "NaN");
  Eigen::VectorXd mu(2);
  mu << 0, 0;
  REQUIRE_USER_ERROR(frechet_distance(mu, Eigen::MatrixXd::Identity(3, 3), mu, Eigen::MatrixXd::Identity(2, 2)),
                     "shapes disagree");
}
