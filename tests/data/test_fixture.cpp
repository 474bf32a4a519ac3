// The synthetic fixture: geometry (bones, floor, facing), layout, determinism,
// and agreement between captions/labels and the motion itself.
#include <catch2/catch.hpp>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <map>
#include <set>
#include <sstream>

#include "core/config.h"
#include "core/error.h"
#include "data/fixture/fixture.h"
#include "test_util.h"

using mc::test::user_error_of;

namespace {

using mc::MotionSet;
using Vec3 = Eigen::Vector3d;

const mc::Skeleton& skel() { return mc::humanml3d_skeleton(); }

mc::FixtureConfig small_config(int n, int64_t seed = 11) {
  mc::FixtureConfig c;
  c.num_clips = n;
  c.seed = seed;
  return c;
}
// Only one kind of clip, so a small set still has many of that kind.
mc::FixtureConfig only(const std::string& kind, int n, int64_t seed = 11) {
  mc::FixtureConfig c = small_config(n, seed);
  c.weight_locomotion = kind == "locomotion";
  c.weight_action = kind == "action";
  c.weight_overlay = kind == "overlay";
  c.weight_sequence = kind == "sequence";
  return c;
}

Vec3 joint(const MotionSet& m, size_t i, int t, int j) {
  const float* p = m.at(i, t, j);
  return {p[0], p[1], p[2]};
}
int J(const char* name) { return skel().joint_index(name); }

// Facing direction (xz, unit) from the hips: across (right -> left hip) x up.
Vec3 facing(const MotionSet& m, size_t i, int t) {
  Vec3 across = joint(m, i, t, J("l_hip")) - joint(m, i, t, J("r_hip"));
  Vec3 f = across.cross(Vec3::UnitY());
  f.y() = 0;
  return f.normalized();
}

// Heading change over the clip, unwrapped (rad, + = turned left).
double total_turn(const MotionSet& m, size_t i) {
  double sum = 0;
  for (int t = 1; t < m.lengths[i]; ++t) {
    Vec3 a = facing(m, i, t - 1), b = facing(m, i, t);
    sum += std::atan2(a.cross(b).y(), a.dot(b));
  }
  return sum;
}

// Mean horizontal root speed over the middle 60% of the clip (m/s).
double cruise_speed(const MotionSet& m, size_t i) {
  int T = m.lengths[i], a = T / 5, b = T - T / 5;
  double d = 0;
  for (int t = a + 1; t < b; ++t) {
    Vec3 v = joint(m, i, t, 0) - joint(m, i, t - 1, 0);
    d += std::hypot(v.x(), v.z());
  }
  return d * m.fps / (b - a - 1);
}

bool is_pure(const std::string& label) { return label.find_first_of("+>") == std::string::npos; }
bool starts_with(const std::string& s, const std::string& p) { return s.rfind(p, 0) == 0; }

bool any_caption_has(const MotionSet& m, size_t i, const std::vector<std::string>& words) {
  for (const auto& c : m.captions[i])
    for (const auto& w : words)
      if (c.find(w) != std::string::npos) return true;
  return false;
}
bool all_captions_have(const MotionSet& m, size_t i, const std::vector<std::string>& words) {
  for (const auto& c : m.captions[i]) {
    bool hit = false;
    for (const auto& w : words) hit = hit || c.find(w) != std::string::npos;
    if (!hit) return false;
  }
  return true;
}

// Some caption word starts with one of `prefixes` ("unhurriedly" is not "hurr...").
bool any_word_starts(const MotionSet& m, size_t i, const std::vector<std::string>& prefixes) {
  for (const auto& c : m.captions[i]) {
    std::istringstream in(c);
    for (std::string w; in >> w;)
      for (const auto& p : prefixes)
        if (starts_with(w, p)) return true;
  }
  return false;
}

const std::vector<std::string> kSlowWords = {"slow", "leisurely", "stroll", "amble", "saunter", "unhurried"};
const std::vector<std::string> kFastWords = {"quick", "fast", "brisk", "rapid", "hurr", "hast", "sprint", "dash",
                                             "race"};

mc::FixtureJobConfig load_job(const std::string& path) {
  mc::FixtureJobConfig job;
  mc::parse_config(mc::compose_config(mc::resolve_data_path(path)), job);
  return job;
}

}  // namespace

TEST_CASE("fixture bones keep the skeleton's lengths in every frame", "[fixture]") {
  MotionSet m = mc::generate_fixture(small_config(60), skel());
  const auto& s = skel();
  double worst = 0;
  for (size_t i = 0; i < m.size(); ++i)
    for (int t = 0; t < m.lengths[i]; ++t)
      for (int j = 1; j < s.num_joints(); ++j)
        worst = std::max(worst, std::abs((joint(m, i, t, j) - joint(m, i, t, s.parents[j])).norm() - s.bone_lengths[j]));
  CHECK(worst < 1e-5);
}

TEST_CASE("fixture bone lengths follow the skeleton it is given", "[fixture]") {
  mc::Skeleton big = skel();
  for (auto& l : big.bone_lengths) l *= 1.1;
  MotionSet m = mc::generate_fixture(small_config(10), big);
  CHECK(m.skeleton == big);
  for (size_t i = 0; i < m.size(); ++i)
    for (int j = 1; j < big.num_joints(); ++j)
      CHECK((joint(m, i, m.lengths[i] / 2, j) - joint(m, i, m.lengths[i] / 2, big.parents[j])).norm() ==
            Approx(big.bone_lengths[j]).margin(1e-5));
  mc::Skeleton renamed = skel();
  renamed.joint_names[J("l_knee")] = "left_knee";
  CHECK_THAT(user_error_of([&] { mc::generate_fixture(small_config(2), renamed); }), Catch::Matchers::Contains("l_knee"));
}

TEST_CASE("fixture clips stand on the floor: min y = 0 exactly, touched by a foot", "[fixture]") {
  MotionSet m = mc::generate_fixture(small_config(80), skel());
  const std::set<int> feet = {J("l_ankle"), J("r_ankle"), J("l_foot"), J("r_foot")};
  for (size_t i = 0; i < m.size(); ++i) {
    float lowest = 1e9f;
    int lowest_joint = -1;
    for (int t = 0; t < m.lengths[i]; ++t)
      for (int j = 0; j < m.num_joints(); ++j)
        if (m.at(i, t, j)[1] < lowest) lowest = m.at(i, t, j)[1], lowest_joint = j;
    INFO(m.labels[i]);
    CHECK(lowest == 0.0f);
    CHECK(feet.count(lowest_joint) == 1);
  }
}

TEST_CASE("fixture clips face +Z with the root at the origin at frame 0", "[fixture]") {
  MotionSet m = mc::generate_fixture(small_config(80), skel());
  for (size_t i = 0; i < m.size(); ++i) {
    INFO(m.labels[i]);
    Vec3 root = joint(m, i, 0, 0);
    CHECK(root.x() == 0.0);
    CHECK(root.z() == 0.0);
    // Left hip on +X; across-hips x up points forward along +Z.
    Vec3 across = joint(m, i, 0, J("l_hip")) - joint(m, i, 0, J("r_hip"));
    CHECK(across.x() > 0.9 * across.norm());
    CHECK(facing(m, i, 0).z() > 0.95);
    CHECK(joint(m, i, 0, J("l_shoulder")).x() > joint(m, i, 0, J("r_shoulder")).x());
    // Upright at the start: head well above the pelvis.
    CHECK(joint(m, i, 0, J("head")).y() > root.y() + 0.3);
  }
}

TEST_CASE("fixture layout: lengths in range, zero padding, ids, labels, captions", "[fixture]") {
  mc::FixtureConfig cfg = small_config(50);
  cfg.min_frames = 60;
  cfg.max_frames = 150;
  cfg.t_max = 160;
  cfg.captions_per_clip = 4;
  MotionSet m = mc::generate_fixture(cfg, skel());
  REQUIRE(m.size() == 50);
  CHECK(m.t_max == 160);
  CHECK(m.fps == 20.0);
  CHECK(m.joints.size() == 50u * 160 * 22 * 3);
  CHECK(m.ids[7] == "fx000007");
  std::set<std::string> ids(m.ids.begin(), m.ids.end());
  CHECK(ids.size() == m.size());
  for (size_t i = 0; i < m.size(); ++i) {
    CHECK(m.lengths[i] >= 60);
    CHECK(m.lengths[i] <= 150);
    float pad = 0;
    for (int t = m.lengths[i]; t < m.t_max; ++t)
      for (int j = 0; j < 22; ++j)
        for (int a = 0; a < 3; ++a) pad = std::max(pad, std::abs(m.at(i, t, j)[a]));
    CHECK(pad == 0.0f);
    CHECK(!m.labels[i].empty());
    REQUIRE(m.captions[i].size() == 4);
    std::set<std::string> distinct(m.captions[i].begin(), m.captions[i].end());
    CHECK(distinct.size() == 4);
    for (const auto& c : m.captions[i]) {  // tidy lowercase text, e.g. "clapping" or "a man walks forward"
      CHECK(!c.empty());
      CHECK(c.find("  ") == std::string::npos);
      CHECK(c.front() != ' ');
      CHECK(c.back() != ' ');
      CHECK(std::none_of(c.begin(), c.end(), [](char ch) { return std::isupper(static_cast<unsigned char>(ch)); }));
    }
  }
}

TEST_CASE("fixture is deterministic in its seed", "[fixture]") {
  MotionSet a = mc::generate_fixture(small_config(40, 5), skel());
  MotionSet b = mc::generate_fixture(small_config(40, 5), skel());
  MotionSet c = mc::generate_fixture(small_config(40, 6), skel());
  CHECK(a.joints == b.joints);
  CHECK(a.captions == b.captions);
  CHECK(a.labels == b.labels);
  CHECK(a.splits == b.splits);
  CHECK(a.lengths == b.lengths);
  CHECK(a.joints != c.joints);
  CHECK(a.labels != c.labels);
  // Clip i does not depend on how many clips are generated.
  MotionSet d = mc::generate_fixture(small_config(20, 5), skel());
  CHECK(std::equal(d.joints.begin(), d.joints.end(), a.joints.begin()));
  CHECK(std::equal(d.captions.begin(), d.captions.end(), a.captions.begin()));
}

TEST_CASE("fixture splits follow the fractions and cover every motion family", "[fixture]") {
  MotionSet m = mc::generate_fixture(small_config(200), skel());
  std::map<std::string, int> n;
  for (auto& s : m.splits) n[s]++;
  CHECK(n.size() == 3);
  CHECK(n["train"] == 160);
  CHECK(n["val"] == 20);
  CHECK(n["test"] == 20);
  // Stratified: the commonest family (walking) appears in val and test too.
  std::set<std::string> walk_splits;
  for (size_t i = 0; i < m.size(); ++i)
    if (starts_with(m.labels[i], "walk/")) walk_splits.insert(m.splits[i]);
  CHECK(walk_splits.size() == 3);
}

TEST_CASE("fixture captions about one hand move that hand's wrist more", "[fixture]") {
  MotionSet m = mc::generate_fixture(only("action", 160), skel());
  int checked[2] = {0, 0};
  for (size_t i = 0; i < m.size(); ++i) {
    bool left = any_caption_has(m, i, {"left hand", "left arm", "left fist"});
    bool right = any_caption_has(m, i, {"right hand", "right arm", "right fist"});
    if (left == right) continue;
    // Wrist path relative to the pelvis: whole-body motion cancels out.
    double path[2] = {0, 0};
    for (int t = 1; t < m.lengths[i]; ++t)
      for (int s = 0; s < 2; ++s) {
        int w = J(s == 0 ? "l_wrist" : "r_wrist");
        Vec3 d = (joint(m, i, t, w) - joint(m, i, t, 0)) - (joint(m, i, t - 1, w) - joint(m, i, t - 1, 0));
        path[s] += d.norm();
      }
    INFO(m.labels[i] << ": left wrist " << path[0] << " m, right wrist " << path[1] << " m");
    CHECK((left ? path[0] > 1.3 * path[1] : path[1] > 1.3 * path[0]));
    checked[left ? 0 : 1]++;
  }
  CHECK(checked[0] >= 5);
  CHECK(checked[1] >= 5);
}

TEST_CASE("fixture turns go the way the label and captions say", "[fixture]") {
  MotionSet m = mc::generate_fixture(only("locomotion", 200), skel());
  int curves = 0, circles = 0;
  for (size_t i = 0; i < m.size(); ++i) {
    const std::string& l = m.labels[i];
    INFO(l << " | " << m.captions[i][0]);
    bool curve_left = l.find("/curve_left/") != std::string::npos;
    bool curve_right = l.find("/curve_right/") != std::string::npos;
    if (curve_left || curve_right) {
      double sign = curve_left ? 1 : -1;
      Vec3 end = joint(m, i, m.lengths[i] - 1, 0);
      CHECK(sign * end.x() > 0.3);                                   // ended up on that side (+X is left)
      CHECK(sign * facing(m, i, m.lengths[i] - 1).x() > 0.5);        // and faces that way
      CHECK(sign * total_turn(m, i) > 0.8);
      CHECK(all_captions_have(m, i, {curve_left ? "left" : "right"}));
      CHECK_FALSE(any_caption_has(m, i, {curve_left ? "right" : "left"}));
      ++curves;
    }
    if (l.find("/circle_left/") != std::string::npos) {
      CHECK(total_turn(m, i) > 5.0);
      ++circles;
    }
    if (l.find("/circle_right/") != std::string::npos) {
      CHECK(total_turn(m, i) < -5.0);
      ++circles;
    }
    if (l.find("/turn_around_") != std::string::npos) {
      CHECK(std::abs(total_turn(m, i)) > 2.5);
      CHECK(facing(m, i, m.lengths[i] - 1).z() < -0.5);  // came back facing -Z
    }
    if (starts_with(l, "sidestep_left/") || starts_with(l, "sidestep_right/")) {
      double sign = starts_with(l, "sidestep_left/") ? 1 : -1;
      Vec3 end = joint(m, i, m.lengths[i] - 1, 0);
      CHECK(sign * end.x() > 0.5);
      CHECK(std::abs(end.z()) < 0.5 * std::abs(end.x()));
    }
    if (starts_with(l, "walk_backward/")) CHECK(joint(m, i, m.lengths[i] - 1, 0).z() < -0.5);
    if (starts_with(l, "walk/straight/")) CHECK(joint(m, i, m.lengths[i] - 1, 0).z() > 1.0);
  }
  CHECK(curves >= 8);
  CHECK(circles >= 4);
}

TEST_CASE("fixture speed words and gaits match root speed", "[fixture]") {
  MotionSet m = mc::generate_fixture(only("locomotion", 300), skel());
  std::map<std::string, std::vector<double>> walk, gait;
  for (size_t i = 0; i < m.size(); ++i) {
    const std::string& l = m.labels[i];
    if (!is_pure(l) || l.find("/straight/") == std::string::npos) continue;
    double v = cruise_speed(m, i);
    std::string g = l.substr(0, l.find('/'));
    bool slow = any_word_starts(m, i, kSlowWords), fast = any_word_starts(m, i, kFastWords);
    INFO(l << " | " << m.captions[i][0]);
    CHECK_FALSE((slow && fast));
    if (g == "walk") walk[slow ? "slow" : fast ? "fast" : "normal"].push_back(v);
    if (l.find("/normal") != std::string::npos) gait[g].push_back(v);
  }
  auto mean = [](const std::vector<double>& x) {
    double s = 0;
    for (double v : x) s += v;
    return s / std::max<size_t>(1, x.size());
  };
  REQUIRE(walk["slow"].size() >= 3);
  REQUIRE(walk["normal"].size() >= 3);
  REQUIRE(walk["fast"].size() >= 3);
  CHECK(*std::max_element(walk["slow"].begin(), walk["slow"].end()) <
        *std::min_element(walk["fast"].begin(), walk["fast"].end()));
  CHECK(mean(walk["slow"]) + 0.15 < mean(walk["normal"]));
  CHECK(mean(walk["normal"]) + 0.15 < mean(walk["fast"]));
  REQUIRE(!gait["jog"].empty());
  REQUIRE(!gait["run"].empty());
  CHECK(mean(gait["walk"]) + 0.5 < mean(gait["jog"]));
  CHECK(mean(gait["jog"]) + 0.5 < mean(gait["run"]));
}

TEST_CASE("fixture walking plants its feet and does not skate", "[fixture]") {
  MotionSet m = mc::generate_fixture(only("locomotion", 120), skel());
  const int toes[2] = {J("l_foot"), J("r_foot")};
  int walks = 0;
  for (size_t i = 0; i < m.size(); ++i) {
    const std::string& l = m.labels[i];
    if (!is_pure(l)) continue;
    const int T = m.lengths[i];
    int planted = 0, skating = 0;
    for (int t = 0; t + 1 < T; ++t) {
      double slowest = 1e9;
      bool skate = false;
      for (int toe : toes) {
        Vec3 a = joint(m, i, t, toe), b = joint(m, i, t + 1, toe);
        double v = std::hypot(b.x() - a.x(), b.z() - a.z()) * m.fps;
        slowest = std::min(slowest, v);
        skate = skate || (a.y() < 0.05 && b.y() < 0.05 && v > 0.5);  // reference-facts §5, no smoothing
      }
      planted += slowest < 0.1;
      skating += skate;
    }
    INFO(l);
    CHECK(static_cast<double>(skating) / (T - 1) < 0.05);
    if (starts_with(l, "walk/")) {
      CHECK(static_cast<double>(planted) / (T - 1) > 0.6);  // a walker always has a foot down
      ++walks;
    }
  }
  CHECK(walks >= 10);
}

TEST_CASE("fixture motion is continuous and humanly proportioned", "[fixture]") {
  MotionSet m = mc::generate_fixture(small_config(100), skel());
  for (size_t i = 0; i < m.size(); ++i) {
    INFO(m.labels[i]);
    double vmax = 0, pelvis_lo = 9, pelvis_hi = 0;
    for (int t = 0; t < m.lengths[i]; ++t) {
      pelvis_lo = std::min(pelvis_lo, joint(m, i, t, 0).y());
      pelvis_hi = std::max(pelvis_hi, joint(m, i, t, 0).y());
      if (t > 0)
        for (int j = 0; j < 22; ++j) vmax = std::max(vmax, (joint(m, i, t, j) - joint(m, i, t - 1, j)).norm() * m.fps);
    }
    CHECK(vmax < 15.0);  // no joint jumps between frames
    CHECK(pelvis_lo > 0.45);
    CHECK(pelvis_hi < 1.45);
    // Pelvis height at frame 0: standing (~0.93 m) or mid-stride (runners crouch lower).
    double y0 = joint(m, i, 0, 0).y();
    CHECK(y0 > 0.78);
    CHECK(y0 < 1.0);
    if (m.labels[i].find('/') == std::string::npos) CHECK(y0 == Approx(0.93).margin(0.04));
  }
}

TEST_CASE("smoke config parses, builds in seconds, and has a rich vocabulary", "[fixture]") {
  mc::FixtureJobConfig job = load_job("configs/data/smoke.yaml");
  CHECK(job.output == "data/fixture_smoke.h5");
  CHECK(job.fixture.num_clips == 400);
  auto t0 = std::chrono::steady_clock::now();
  MotionSet m = mc::generate_fixture(job.fixture, mc::load_skeleton(job.skeleton));
  double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  CHECK(seconds < 10.0);
  std::set<std::string> words;
  std::set<std::string> families;
  for (size_t i = 0; i < m.size(); ++i) {
    for (const auto& c : m.captions[i]) {
      std::istringstream in(c);
      for (std::string w; in >> w;) {
        w.erase(std::remove_if(w.begin(), w.end(), [](char ch) { return !std::isalnum(ch) && ch != '-'; }), w.end());
        if (!w.empty()) words.insert(w);
      }
    }
    families.insert(m.labels[i].substr(0, m.labels[i].find_first_of("/+>")));
  }
  CHECK(words.size() >= 150);
  CHECK(families.size() >= 25);  // 6 gaits and most of the 28 actions
  for (const char* s : {"train", "val", "test"}) CHECK(std::count(m.splits.begin(), m.splits.end(), s) > 0);
}

TEST_CASE("standard config parses and asks for thousands of clips", "[fixture]") {
  mc::FixtureJobConfig job = load_job("configs/data/standard.yaml");
  CHECK(job.fixture.num_clips >= 2000);
  CHECK(job.output == "data/fixture_standard.h5");
}

TEST_CASE("bad fixture config values are user errors naming the key", "[fixture]") {
  auto parse = [](const std::string& yaml) {
    mc::FixtureJobConfig job;
    mc::parse_config(mc::config_from_string(yaml, "job.yaml"), job);
    return job;
  };
  CHECK(parse("fixture: {num_clips: 7}").fixture.num_clips == 7);
  CHECK_THAT(user_error_of([&] { parse("fixture: {captions_per_clip: 2}"); }), Catch::Matchers::Contains("captions_per_clip"));
  CHECK_THAT(user_error_of([&] { parse("fixture: {train_fraction: 0.9}"); }), Catch::Matchers::Contains("train_fraction"));
  CHECK_THAT(user_error_of([&] { parse("fixture: {max_frames: 300}"); }), Catch::Matchers::Contains("t_max"));
  CHECK_THAT(user_error_of([&] { parse("fixture: {num_clip: 3}"); }), Catch::Matchers::Contains("did you mean 'num_clips'"));
  mc::FixtureConfig bad = small_config(3);
  bad.weight_locomotion = bad.weight_action = bad.weight_overlay = bad.weight_sequence = 0;
  CHECK_THAT(user_error_of([&] { mc::generate_fixture(bad, skel()); }), Catch::Matchers::Contains("weight_"));
}
