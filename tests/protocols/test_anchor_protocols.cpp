// The AnchorRoute protocols: tasks per clip and K whose specs convert back to the
// drawn anchors, zero control error on the source clip, determinism per seed, config errors.
#include <catch2/catch.hpp>

#include "control/anchors.h"
#include "control/linear_observation.h"
#include "core/config.h"
#include "eval/observation_errors.h"
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

namespace {
// A `protocol:` component parsed from YAML, as a generate config or table row would.
struct ProtocolFile : Config {
  Component protocol{"protocol"};
  void visit(FieldVisitor& v) override { v("protocol", protocol, "the protocol"); }
};
std::vector<ControlTask> tasks_of(const std::string& yaml, const MotionSet& data, const std::vector<size_t>& clips) {
  ProtocolFile f;
  parse_config(config_from_string(yaml, "protocol.yaml"), f);
  return as_protocol(f.protocol).make_tasks(data, clips, 5);
}
}  // namespace

TEST_CASE("with_floor and anchor directions: the base tasks plus items the ground truth meets", "[anchors][inequality]") {
  MotionSet data = random_motion_set({40, 64, 33, 50, 45}, {"test"});
  const std::string base = "{type: anchors, families: [root_3d, body_point], anchor_counts: [2, 8, 32]";
  auto plain = tasks_of("protocol: " + base + "}", data, {0, 1, 2, 3, 4});
  auto floored = tasks_of("protocol: {type: with_floor, height: -2.0, base: " + base + "}}", data, {0, 1, 2, 3, 4});
  REQUIRE(floored.size() == plain.size());
  for (size_t i = 0; i < plain.size(); ++i) {
    CHECK(floored[i].id == plain[i].id);
    CHECK(floored[i].group == plain[i].group);
    REQUIRE(floored[i].spec.items.size() == plain[i].spec.items.size() + 1);
    CHECK(floored[i].spec.items.back().type == "floor");
    CHECK(floored[i].spec.items.back().height == -2.0);
    LinearObservation obs = compile(floored[i].spec, floored[i].length, data.skeleton, floored[i].source.data());
    CHECK(obs.inequalities() == 2 * floored[i].length);
    CHECK(max_inequality_violation(obs, floored[i].source.data()) == 0.0);  // the clip is above y = -2 (noise in ±1.5)
  }
  auto with_dirs = tasks_of("protocol: " + base + ", directions: {tangent: true, facing: true}}", data, {0, 1, 2, 3, 4});
  auto scored = tasks_of("protocol: " + base + ", directions: {tangent: true, facing: true, score_only: true}}", data,
                         {0, 1, 2, 3, 4});
  int probes = 0;
  for (size_t i = 0; i < plain.size(); ++i) {
    const auto& t = with_dirs[i];
    CHECK(t.id == plain[i].id);
    // the anchors are the plain protocol's: directions only add items
    CHECK(anchors_from_spec(t.spec, t.length, data.skeleton) == anchors_from_spec(plain[i].spec, t.length, data.skeleton));
    LinearObservation obs = compile(t.spec, t.length, data.skeleton, t.source.data());
    LinearObservation only = compile(scored[i].spec, t.length, data.skeleton, t.source.data());
    LinearObservation none = compile(plain[i].spec, t.length, data.skeleton, t.source.data());
    CHECK(obs.inequalities() == static_cast<int>(obs.directions.size()));
    CHECK(only.rows() == none.rows());  // score_only: no rows ...
    CHECK(only.inequalities() == 0);
    CHECK(only.directions.size() == obs.directions.size());  // ... the same probes
    CHECK(max_inequality_violation(obs, t.source.data()) <= 1e-6);
    for (double a : direction_errors(obs, t.source.data())) CHECK(a < 1e-3);
    probes += static_cast<int>(obs.directions.size());
  }
  CHECK(probes > 20);
  // defaults leave the dumped protocol unchanged (row caches keep their keys)
  ProtocolFile f;
  parse_config(config_from_string("protocol: " + base + "}", "p.yaml"), f);
  CHECK(dump_config(f).find("directions") == std::string::npos);
}
