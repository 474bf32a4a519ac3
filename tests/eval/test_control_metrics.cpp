// Control metrics (OmniControl Traj./Loc./Avg. err, AnchorRoute control error) on a
// hand-made three-sample example with errors on both sides of the thresholds.
#include "eval_test_util.h"

using namespace mc;
using mc::test::Clip;

namespace {

constexpr int T = 4, J = 22;

struct Sample {
  Clip gen{T, J}, target{T, J};
  std::vector<uint8_t> mask = std::vector<uint8_t>(T * J * 3, 0);
  void control(int t, int j, bool x, bool y, bool z) {
    uint8_t* m = mask.data() + (t * J + j) * 3;
    m[0] = x;
    m[1] = y;
    m[2] = z;
  }
  ControlSample view() const {
    return ControlSample{gen.view(), target.view(), mask_view(mask, T, J, 3)};
  }
};

// Three samples; all offsets are exactly representable in float except 0.1 / 0.3.
//  A: root xyz at frames 0, 2 with errors 0.1, 0.3.
//  B: planar root (x, z) at frames 1, 3 with xz offsets (0.375, 0.5) -> 0.625 and
//     (0, 0.125) -> 0.125, plus large y offsets that must be ignored.
//  C: wrist 20 @0 error exactly 0.5 (not > 0.5), toe 10 @2 error 0.25, head 15 @3 error 0.
std::vector<Sample> hand_made() {
  std::vector<Sample> s(3);
  for (auto& x : s)
    for (int t = 0; t < T; ++t)
      for (int j = 0; j < J; ++j) {
        x.target.set(t, j, 0.25 * j, 1.0, -0.5 * t);
        x.gen.set(t, j, 0.25 * j, 1.0, -0.5 * t);
      }
  // A
  s[0].control(0, 0, true, true, true);
  s[0].gen.set(0, 0, 0.1, 1.0, 0.0);
  s[0].control(2, 0, true, true, true);
  s[0].gen.set(2, 0, 0.0, 1.3, -1.0);
  // B
  s[1].control(1, 0, true, false, true);
  s[1].gen.set(1, 0, 0.375, 6.0, -0.5 + 0.5);
  s[1].control(3, 0, true, false, true);
  s[1].gen.set(3, 0, 0.0, 10.0, -1.5 + 0.125);
  // C
  s[2].control(0, 20, true, true, true);
  s[2].gen.set(0, 20, 5.0 + 0.5, 1.0, 0.0);
  s[2].control(2, 10, true, true, true);
  s[2].gen.set(2, 10, 2.5, 1.0, -1.0 + 0.25);
  s[2].control(3, 15, true, true, true);
  return s;
}

std::vector<ControlSample> views(const std::vector<Sample>& s) {
  std::vector<ControlSample> v;
  for (const auto& x : s) v.push_back(x.view());
  return v;
}

}  // namespace

TEST_CASE("controlled entry errors use only the masked axes", "[eval]") {
  const auto s = hand_made();
  const std::vector<double> a = controlled_entry_errors(s[0].view());
  REQUIRE(a.size() == 2);
  REQUIRE(a[0] == Approx(0.1).margin(1e-6));
  REQUIRE(a[1] == Approx(0.3).margin(1e-6));
  const std::vector<double> b = controlled_entry_errors(s[1].view());
  REQUIRE(b == std::vector<double>{0.625, 0.125});  // y offsets of 5 and 9 are ignored
  const std::vector<double> c = controlled_entry_errors(s[2].view());
  REQUIRE(c == std::vector<double>{0.5, 0.25, 0.0});
}

TEST_CASE("control metrics on the hand-made three-sample example", "[eval]") {
  const auto s = hand_made();
  const ControlMetrics m = control_metrics(views(s));
  REQUIRE(m.samples == 3);
  REQUIRE(m.samples_without_control == 0);
  REQUIRE(m.controlled_entries == 7);
  REQUIRE(m.rates.size() == 2);
  // 0.5 m: only B fails (0.625); C's 0.5 is not strictly above.
  REQUIRE(m.rates[0].threshold == 0.5);
  REQUIRE(m.traj_err == Approx(1.0 / 3));
  REQUIRE(m.loc_err == Approx((0.0 + 0.5 + 0.0) / 3));
  REQUIRE(m.rates[0].traj_err == m.traj_err);
  REQUIRE(m.rates[0].loc_err == m.loc_err);
  // 0.2 m: every sample fails somewhere; per-sample fractions 1/2, 1/2, 2/3.
  REQUIRE(m.rates[1].threshold == 0.2);
  REQUIRE(m.rates[1].traj_err == Approx(1.0));
  REQUIRE(m.rates[1].loc_err == Approx((0.5 + 0.5 + 2.0 / 3) / 3));
  // Avg. err: per-sample means 0.2, 0.375, 0.25, then their mean.
  REQUIRE(m.avg_err == Approx((0.2 + 0.375 + 0.25) / 3).margin(1e-7));
  // AnchorRoute control error pools the 7 entries.
  REQUIRE(m.control_error == Approx((0.1 + 0.3 + 0.625 + 0.125 + 0.5 + 0.25 + 0.0) / 7).margin(1e-7));
}

TEST_CASE("control metrics skip and count samples without controlled entries, custom thresholds", "[eval]") {
  auto s = hand_made();
  s.emplace_back();  // no controlled entry
  ControlOptions opt;
  opt.thresholds = {0.24};
  const ControlMetrics m = control_metrics(views(s), opt);
  REQUIRE(m.samples == 3);
  REQUIRE(m.samples_without_control == 1);
  REQUIRE(m.rates.size() == 1);
  REQUIRE(m.traj_err == Approx(1.0));                                // A 0.3, B 0.625, C 0.5/0.25
  REQUIRE(m.loc_err == Approx((0.5 + 0.5 + 2.0 / 3) / 3));
  REQUIRE(m.avg_err == Approx((0.2 + 0.375 + 0.25) / 3).margin(1e-7));  // unchanged by the empty sample
}

TEST_CASE("control metrics reject bad input with clear messages", "[eval]") {
  auto s = hand_made();
  REQUIRE_USER_ERROR(control_metrics({}), "no samples");
  std::vector<ControlSample> v = views(s);
  Clip short_target(T - 1, J);
  v[1].target = short_target.view();
  REQUIRE_USER_ERROR(control_metrics(v), "control sample 1: generated is [4, 22, 3] but target is [3, 22, 3]");
  v = views(s);
  const std::vector<uint8_t> flat(T * J, 1);
  v[2].mask = mask_view(flat, T, J, 1);
  REQUIRE_USER_ERROR(control_metrics(v), "need one flag per axis");
  Sample empty;
  REQUIRE_USER_ERROR(control_metrics({empty.view()}), "none of the 1 samples has a controlled entry");
  Clip padded(T, J, 2);
  v = views(s);
  v[0].generated = padded.view();  // frame 2 is controlled but beyond the valid length
  REQUIRE_USER_ERROR(control_metrics(v), "only 2 valid frames");
  ControlOptions bad;
  bad.thresholds = {};
  REQUIRE_USER_ERROR(control_metrics(views(s), bad), "no thresholds");
  REQUIRE_USER_ERROR(mask_view(flat, T, J, 3), "do not form [4, 22, 3]");
}
