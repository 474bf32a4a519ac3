// The AnchorRoute protocols: tasks per clip and K whose specs convert back to the
// drawn anchors, zero control error on the source clip, determinism per seed, config errors.
#include <catch2/catch.hpp>

#include "control/anchors.h"
#include "core/config.h"
#include "core/error.h"
#include "data/data_test_util.h"
#include "protocols/anchor_protocols.h"

using namespace mc;
using namespace mc::test;

TEST_CASE("anchor_route protocol: one task per clip and K, specs convert back to anchors", "[anchors]") {
  MotionSet data = random_motion_set({40, 64, 33}, {"test"});
  Component c("protocol", "anchor_route");
  auto& p = c.as<AnchorRouteProtocol>();
  for (std::string fam : {"root_3d", "planar_root", "body_point"}) {
    p.family = fam;
    auto tasks = as_protocol(c).make_tasks(data, {0, 1, 2}, 9);
    REQUIRE(tasks.size() == 15u);
    for (const auto& t : tasks) {
      const int K = std::stoi(t.id.substr(t.id.find("#K") + 2));
      CHECK(t.group == "family=" + fam + "/K=" + std::to_string(K));
      AnchorSet set = anchors_from_spec(t.spec, t.length, data.skeleton, t.source.data(), parse_anchor_family(fam));
      CHECK(set.size() == K);
      for (double e : anchor_errors(set, t.source.data(), data.num_joints())) CHECK(e == 0.0);
    }
    // Deterministic per seed; a task does not depend on the other clips requested.
    auto again = as_protocol(c).make_tasks(data, {2}, 9);
    CHECK((again[0].spec.items == tasks[10].spec.items));
    CHECK((as_protocol(c).make_tasks(data, {2}, 10)[0].spec.items != tasks[10].spec.items));
  }
  p.anchor_counts = {50};
  CHECK_THROWS_AS(as_protocol(c).make_tasks(data, {0}, 1), UserError);  // 40 frames < 50 anchors
}

TEST_CASE("anchor_keyjoint protocol: six joints at ~30% of the frames", "[anchors]") {
  MotionSet data = random_motion_set({40, 60}, {"test"});
  AnchorKeyjointProtocol p;
  auto tasks = p.make_tasks(data, {0, 1}, 3);
  REQUIRE(tasks.size() == 2u);
  AnchorSet set = anchors_from_spec(tasks[1].spec, 60, data.skeleton, nullptr);
  CHECK(set.family == AnchorFamily::body_point);
  CHECK(set.times().size() == 18u);
  CHECK(set.joints() == std::vector<int>{0, 10, 11, 15, 20, 21});
  p.joints = {0, 30};
  CHECK_THROWS_AS(p.make_tasks(data, {0}, 3), UserError);
}
