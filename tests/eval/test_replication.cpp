// Replication summaries: hand-computed mean / population std / 95% CI, and the
// seed sweep that summarises every named metric.
#include "eval_test_util.h"

using namespace mc;

TEST_CASE("summarize: mean, population std and 1.96 std / sqrt(N)", "[eval]") {
  const Replicated r = summarize({1.0, 2.0, 3.0, 4.0});
  REQUIRE(r.n == 4);
  REQUIRE(r.mean == Approx(2.5));
  // squared deviations 2.25 + 0.25 + 0.25 + 2.25 = 5, / N = 1.25 (np.std, ddof = 0)
  REQUIRE(r.std == Approx(std::sqrt(1.25)));
  REQUIRE(r.ci95 == Approx(1.96 * std::sqrt(1.25) / 2.0));
  const Replicated one = summarize({0.7});
  REQUIRE(one.mean == Approx(0.7));
  REQUIRE(one.std == 0.0);
  REQUIRE(one.ci95 == 0.0);
  REQUIRE_USER_ERROR(summarize({}), "no values");
  REQUIRE_USER_ERROR(summarize({1.0, std::nan("")}), "not finite");
}

TEST_CASE("replicate runs seeds seed0..seed0+N-1 and summarises each metric", "[eval]") {
  std::vector<uint64_t> seen;
  const auto out = replicate(4, 10, [&](uint64_t seed) {
    seen.push_back(seed);
    return MetricValues{{"a", static_cast<double>(seed)}, {"b", 2.0 * seed}};
  });
  REQUIRE(seen == std::vector<uint64_t>{10, 11, 12, 13});
  REQUIRE(out.size() == 2);
  REQUIRE(out.at("a").mean == Approx(11.5));
  REQUIRE(out.at("a").std == Approx(std::sqrt(1.25)));
  REQUIRE(out.at("b").mean == Approx(23.0));
  REQUIRE(out.at("b").ci95 == Approx(1.96 * 2.0 * std::sqrt(1.25) / 2.0));
  REQUIRE(out.at("b").n == 4);

  REQUIRE_USER_ERROR(replicate(0, 0, [](uint64_t) { return MetricValues{{"a", 1.0}}; }), "at least 1 replication");
  REQUIRE_USER_ERROR(replicate(3, 0,
                               [](uint64_t s) {
                                 return s == 1 ? MetricValues{{"x", 1.0}} : MetricValues{{"a", 1.0}};
                               }),
                     "reported 'x', which the first run did not");
  REQUIRE_USER_ERROR(replicate(2, 0,
                               [](uint64_t s) {
                                 return MetricValues{{"a", s == 1 ? std::nan("") : 1.0}};
                               }),
                     "metric 'a': summarize");
}
