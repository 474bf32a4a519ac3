// Replication summaries: hand-computed mean / population std / 95% CI, and the
// seed sweep that summarises every named metric.
#include "eval_test_util.h"
#include "eval/evaluation.h"

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

TEST_CASE("bootstrap_summary: the full set's value, the resamples' sample SD, 1.96 SD", "[eval]") {
  const Replicated r = bootstrap_summary(10.0, {1.0, 2.0, 3.0, 4.0});
  REQUIRE(r.n == 4);
  REQUIRE(r.mean == 10.0);  // never the resamples' mean (2.5)
  // squared deviations sum to 5; / (n - 1) = 5/3
  REQUIRE(r.std == Approx(std::sqrt(5.0 / 3.0)));
  REQUIRE(r.ci95 == Approx(1.96 * std::sqrt(5.0 / 3.0)));  // not / sqrt(n)
  const Replicated one = bootstrap_summary(0.5, {0.7});
  REQUIRE(one.mean == 0.5);
  REQUIRE(one.ci95 == 0.0);
  REQUIRE_USER_ERROR(bootstrap_summary(std::nan(""), {1.0, 2.0}), "not finite");
  REQUIRE_USER_ERROR(bootstrap_summary(1.0, {1.0, std::nan("")}), "not finite");
}

TEST_CASE("select_rows picks motion/text rows and captions, repeats included, the reference stays whole", "[eval]") {
  EvalEmbeddings e;
  e.motion = Embeddings::Zero(4, 2);
  e.text = Embeddings::Zero(4, 2);
  e.gt_motion = Embeddings::Ones(5, 2);
  for (int i = 0; i < 4; ++i) {
    e.motion(i, 0) = i;
    e.text(i, 1) = 10 * i;
    e.captions.push_back(std::to_string(i));
  }
  EvalEmbeddings s = select_rows(e, {2, 2, 0});
  REQUIRE(s.motion.rows() == 3);
  CHECK(s.motion(0, 0) == 2);
  CHECK(s.motion(1, 0) == 2);
  CHECK(s.motion(2, 0) == 0);
  CHECK(s.text(0, 1) == 20);
  CHECK(s.captions == std::vector<std::string>{"2", "2", "0"});
  CHECK(s.gt_motion.rows() == 5);
  REQUIRE_USER_ERROR(select_rows(e, {4}), "out of 4");
}
