// Foot skating ratio on synthetic sliding toes whose skating transitions are
// counted by hand, including the zero-padded centred moving-average edges.
#include "eval_test_util.h"

using namespace mc;
using mc::test::Clip;

namespace {

constexpr int J = 22, kLeftToe = 10, kRightToe = 11;
const std::vector<int> kToes = {kLeftToe, kRightToe};

// A clip whose toe `toe` moves along +z with speed speeds[t] (m/s at 20 fps)
// between frames t and t+1, at height `height`; every other joint sits still.
void slide(Clip& c, int toe, const std::vector<double>& speeds, double height, double x) {
  double z = 0.0;
  for (int t = 0; t < c.length; ++t) {
    c.set(t, toe, x, height, z);
    if (t < static_cast<int>(speeds.size())) z += speeds[t] / 20.0;
  }
}

std::vector<double> speed_profile(int transitions, std::vector<std::pair<int, int>> blocks, double v) {
  std::vector<double> s(transitions, 0.0);
  for (auto [a, b] : blocks)  // transitions a..b inclusive
    for (int t = a; t <= b; ++t) s[t] = v;
  return s;
}

int count(const std::vector<uint8_t>& f) {
  int n = 0;
  for (uint8_t x : f) n += x;
  return n;
}

std::vector<int> on(const std::vector<uint8_t>& f) {
  std::vector<int> idx;
  for (size_t t = 0; t < f.size(); ++t)
    if (f[t]) idx.push_back(static_cast<int>(t));
  return idx;
}

// T = 40 (39 transitions): toe 10 at 2 cm slides at 1 m/s over transitions 10..19
// and in a 2-transition burst 30..31; toe 11 stands still 50 cm up.
Clip sliding_clip(int frames = 40, int length = 40) {
  Clip c(frames, J, length);
  slide(c, kLeftToe, speed_profile(39, {{10, 19}, {30, 31}}, 1.0), 0.02, 0.1);
  slide(c, kRightToe, {}, 0.5, -0.1);
  return c;
}

}  // namespace

TEST_CASE("foot skating: a toe sliding at 1 m/s on the ground, counted by hand", "[eval]") {
  const Clip c = sliding_clip();
  const std::vector<uint8_t> f = foot_skating_flags(c.view(), kToes);
  REQUIRE(f.size() == 39);
  // Block 10..19: every transition has v = 1 > 0.5 and at least 3 of its 5 window
  // entries at 1 m/s (0.6 > 0.5), the block edges included. The burst 30..31 has
  // v = 1 but its window average is at most 2/5 = 0.4: no skating.
  std::vector<int> expected;
  for (int t = 10; t <= 19; ++t) expected.push_back(t);
  REQUIRE(on(f) == expected);
  REQUIRE(foot_skating_ratio(c.view(), kToes) == Approx(10.0 / 39));
}

TEST_CASE("foot skating: the moving average is centred and zero padded at both clip ends", "[eval]") {
  // T = 20 (19 transitions), 0.8 m/s over transitions 0..5 and 13..18 (the last one).
  // A transition skates iff >= 4 of its 5 centred window entries are at 0.8 (4*0.8/5 =
  // 0.64 > 0.5; 3*0.8/5 = 0.48 is not), padding counting as 0 m/s:
  //   0: {0,1,2} -> no; 1..4 -> yes; 5: {3,4,5} -> no; 13: {13,14,15} -> no;
  //   14..17 -> yes; 18: {16,17,18} + 2 padded zeros -> no.
  Clip c(20, J);
  slide(c, kLeftToe, speed_profile(19, {{0, 5}, {13, 18}}, 0.8), 0.01, 0.1);
  slide(c, kRightToe, {}, 0.5, -0.1);
  const std::vector<uint8_t> f = foot_skating_flags(c.view(), kToes);
  REQUIRE(on(f) == std::vector<int>{1, 2, 3, 4, 14, 15, 16, 17});
  REQUIRE(foot_skating_ratio(c.view(), kToes) == Approx(8.0 / 19));
  // A 3-frame window (an option) lets every block transition through: 2*0.8/3 > 0.5.
  FootSkatingOptions w3;
  w3.window = 3;
  REQUIRE(count(foot_skating_flags(c.view(), kToes, w3)) == 12);
}

TEST_CASE("foot skating: a lifted toe and a still toe never skate", "[eval]") {
  Clip high(40, J);
  slide(high, kLeftToe, speed_profile(39, {{0, 38}}, 2.0), 0.06, 0.1);  // fast but 6 cm up
  slide(high, kRightToe, speed_profile(39, {{0, 38}}, 2.0), 0.3, -0.1);
  REQUIRE(foot_skating_ratio(high.view(), kToes) == 0.0);

  Clip still(40, J);
  slide(still, kLeftToe, {}, 0.0, 0.1);  // planted
  slide(still, kRightToe, {}, 0.01, -0.1);
  REQUIRE(foot_skating_ratio(still.view(), kToes) == 0.0);
}

TEST_CASE("foot skating: contact needs the toe low at both t and t+1", "[eval]") {
  Clip c = sliding_clip();
  c.at(15, kLeftToe)[1] = 0.2f;  // lifted at frame 15 only: transitions 14 and 15 lose contact
  const std::vector<uint8_t> f = foot_skating_flags(c.view(), kToes);
  REQUIRE(on(f) == std::vector<int>{10, 11, 12, 13, 16, 17, 18, 19});
}

TEST_CASE("foot skating: a frame counts once when either or both toes skate", "[eval]") {
  Clip c = sliding_clip();
  // Right toe on the ground sliding over 10..19 (same frames) and 25..29 (its own).
  slide(c, kRightToe, speed_profile(39, {{10, 19}, {25, 29}}, 1.0), 0.03, -0.1);
  REQUIRE(foot_skating_ratio(c.view(), kToes) == Approx(15.0 / 39));
}

TEST_CASE("foot skating: padded_196 evaluates 196 stored frames and divides by 195", "[eval]") {
  FootSkatingOptions padded;
  padded.padded_196 = true;
  // Padding that repeats the last valid pose adds no skating: 10 / 195 instead of 10 / 39.
  Clip held = sliding_clip(196, 40);
  for (int t = 40; t < 196; ++t)
    for (int j = 0; j < J; ++j)
      for (int a = 0; a < 3; ++a) held.at(t, j)[a] = held.at(39, j)[a];
  REQUIRE(foot_skating_ratio(held.view(), kToes) == Approx(10.0 / 39));
  REQUIRE(foot_skating_ratio(held.view(), kToes, padded) == Approx(10.0 / 195));
  // Zero padding (as in MotionSet): the jump from the last valid toe position (xz
  // distance ~0.61 m from the origin) to the origin at 2 cm -> 0 m height is one
  // more skating transition (39): 11 / 195. Documented artefact of padded_196.
  const Clip zeros = sliding_clip(196, 40);
  const std::vector<uint8_t> f = foot_skating_flags(zeros.view(), kToes, padded);
  REQUIRE(f.size() == 195);
  REQUIRE(f[39] == 1);
  REQUIRE(count(f) == 11);
  REQUIRE(foot_skating_ratio(zeros.view(), kToes, padded) == Approx(11.0 / 195));
  REQUIRE_USER_ERROR(foot_skating_ratio(sliding_clip().view(), kToes, padded), "fewer than padded_length = 196");
}

TEST_CASE("foot skating over clips takes the toes from the skeleton and averages per clip", "[eval]") {
  const Skeleton& sk = humanml3d_skeleton();
  REQUIRE(sk.role("toes") == kToes);
  const Clip sliding = sliding_clip();
  Clip still(30, J);
  REQUIRE(foot_skating_ratio({sliding.view(), still.view()}, sk) == Approx((10.0 / 39 + 0.0) / 2));
}

TEST_CASE("foot skating rejects bad input with clear messages", "[eval]") {
  const Skeleton& sk = humanml3d_skeleton();
  REQUIRE_USER_ERROR(foot_skating_ratio(std::vector<JointsView>{}, sk), "no clips");
  Clip wrong(40, 21);
  REQUIRE_USER_ERROR(foot_skating_ratio({wrong.view()}, sk), "clip 0 has 21 joints but skeleton");
  Clip one(1, J);
  REQUIRE_USER_ERROR(foot_skating_ratio(one.view(), kToes), "at least 2 frames");
  FootSkatingOptions even;
  even.window = 4;
  REQUIRE_USER_ERROR(foot_skating_ratio(sliding_clip().view(), kToes, even), "positive odd number");
  REQUIRE_USER_ERROR(foot_skating_ratio(sliding_clip().view(), {22}, {}), "toe joint 22 is outside [0, 22)");
  std::vector<float> buffer(10);
  REQUIRE_USER_ERROR(joints_view(buffer, 40, J), "10 values do not form [40, 22, 3]");
}
