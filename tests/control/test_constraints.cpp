// Constraint specs: YAML and HDF5 reading, compiling every item type into rows
// (checked against the source motion they were taken from), the 2D camera rows,
// and every validation error naming the item and the key.
#include <catch2/catch.hpp>

#include <cmath>

#include "control/camera_rows.h"
#include "control/constraint_spec.h"
#include "control/linear_observation.h"
#include "control_test_util.h"
#include "core/error.h"
#include "data/skeleton.h"
#include "tests/test_util.h"

using namespace mc;
using namespace mc::test;

namespace {

const Skeleton& skel() { return humanml3d_skeleton(); }

// Compiles a YAML spec; `T` frames; with a random source motion unless `with_source` is false.
LinearObservation compile_yaml(const std::string& yaml, int T = 8, bool with_source = true) {
  std::mt19937_64 rng(7);
  auto src = random_motion(rng, T, skel());
  return compile(parse_constraint_spec_yaml(yaml, "spec.yaml"), T, skel(), with_source ? src.data() : nullptr);
}

}  // namespace

TEST_CASE("camera rows are s * P * R_z(roll) R_x(pitch) R_y(yaw)", "[control]") {
  const double pitch = 0.3, yaw = -0.7, roll = 0.2, s = 1.1;
  Eigen::Matrix3d ry, rx, rz;
  ry << std::cos(yaw), 0, std::sin(yaw), 0, 1, 0, -std::sin(yaw), 0, std::cos(yaw);
  rx << 1, 0, 0, 0, std::cos(pitch), -std::sin(pitch), 0, std::sin(pitch), std::cos(pitch);
  rz << std::cos(roll), -std::sin(roll), 0, std::sin(roll), std::cos(roll), 0, 0, 0, 1;
  Eigen::Matrix<double, 2, 3> expected = s * (rz * rx * ry).topRows<2>();
  CHECK((camera_rows(s, pitch, yaw, roll) - expected).norm() < 1e-15);
  // Orthogonal rows of length s, so A R^-1 A^T stays well conditioned.
  Eigen::Matrix<double, 2, 3> c = camera_rows(s, pitch, yaw, roll);
  CHECK((c * c.transpose() - s * s * Eigen::Matrix2d::Identity()).norm() < 1e-14);
  // Identity camera: u = s x, v = s y.
  Eigen::Matrix<double, 2, 3> id = camera_rows(2.0, 0, 0, 0);
  CHECK(id(0, 0) == 2.0);
  CHECK(id(1, 1) == 2.0);
  CHECK(id(0, 2) == 0.0);
}

TEST_CASE("YAML spec: every item type parses", "[control]") {
  const std::string yaml = R"(
constraints:
  - {type: keyframe, name: pelvis keys, joints: [pelvis, 10], frames: [0, 3], axes: xz, from_source: true}
  - type: trajectory
    name: wrist path
    joints: l_wrist
    frames: {start: 1, stop: 5}
    values: [[0.1, 0.2, 0.3], [0.1, 0.2, 0.3], [0.1, 0.2, 0.3], [0.1, 0.2, 0.3]]
    variance: 0.01
  - {type: planar_root, frames: all, from_source: true, variance: 0.5}
  - type: camera_2d
    joints: [l_wrist, r_wrist]
    frames: [2]
    camera: {scale: 1.1, pitch_deg: 10, yaw_deg: -30}
    values: [[[0.1, 0.2], [0.3, 0.4]]]
  - {type: relative, joints: [l_wrist, r_wrist], frames: [2], axes: [x], values: [0.4]}
  - {type: loop, up_to_root_translation: true}
  - {type: upper_body_edit, hard: false, variance: 0.1}
)";
  ConstraintSpec spec = parse_constraint_spec_yaml(yaml, "spec.yaml");
  REQUIRE(spec.items.size() == 7);
  CHECK(spec.items[0].joints[0].name == "pelvis");
  CHECK(spec.items[0].joints[1].index == 10);
  CHECK(spec.items[0].axes == std::vector<int>{0, 2});
  CHECK(spec.items[1].variance == 0.01);
  CHECK(spec.items[1].frames.kind == FrameSelection::Kind::range);
  CHECK(spec.items[1].values.shape == std::vector<int>{4, 3});
  CHECK(spec.items[3].camera.scale == 1.1);
  CHECK(spec.items[3].values.shape == std::vector<int>{1, 2, 2});
  CHECK(spec.items[4].axes == std::vector<int>{0});
  CHECK(spec.items[5].up_to_root_translation);
  CHECK(spec.item_label(0) == "item 0 'pelvis keys' (keyframe)");
  CHECK(spec.item_label(2) == "item 2 (planar_root)");

  std::mt19937_64 rng(1);
  auto src = random_motion(rng, 8, skel());
  LinearObservation obs = compile(spec, 8, skel(), src.data());
  // keyframe 2*2*2 + trajectory 4*3 + planar 8*2 + camera 2*2 + relative 1 + loop (22*3 - 2) + lower body 8*9*3.
  // (Relative x and y on the two camera joints would be redundant: with the two
  // 2D rows per joint they make four rows on the three axes of x_a - x_b.)
  CHECK(obs.rows() == 8 + 12 + 16 + 4 + 1 + 64 + 216);
  CHECK(obs.item_labels.size() == 7);
  CHECK(obs.variance[8] == 0.01);
  CHECK(obs.variance[0] == 0.0);
}

TEST_CASE("compiled rows reproduce the source motion they were taken from (every type)", "[control]") {
  // Property: with targets from the source, A x_source = y exactly, for random
  // items of every type, frame counts and axis subsets.
  std::mt19937_64 rng(20240601);
  for (const auto& type : constraint_types())
    for (int trial = 0; trial < 20; ++trial) {
      const int T = uniform_int(rng, 2, 8);
      auto src = random_motion(rng, T, skel());
      ConstraintItem it = random_item(type, rng, T, skel(), 0.0);
      if (it.values.given()) it.values = {}, it.from_source = true;
      if (type == "loop") continue;  // has no source form; checked below
      ConstraintSpec spec;
      spec.items = {it};
      LinearObservation obs = compile(spec, T, skel(), src.data());
      INFO(type << " trial " << trial);
      REQUIRE(obs.rows() > 0);
      CHECK(obs.A.cols() == 3 * 22 * T);
      Eigen::VectorXd x = to_vector(src);
      // float source -> double rows: exact up to the float's own rounding
      CHECK((obs.A * x - obs.y).cwiseAbs().maxCoeff() < 1e-12);
    }
}

TEST_CASE("explicit targets land on the rows in frame, joint, axis order", "[control]") {
  LinearObservation obs = compile_yaml(R"(
- {type: keyframe, joints: [l_wrist, 0], frames: [5, 1], axes: zy,
   values: [[[1, 2], [3, 4]], [[5, 6], [7, 8]]]}
)");
  REQUIRE(obs.rows() == 8);
  // row 0: frame 5, joint 20, axis z -> column (5*22 + 20)*3 + 2
  CHECK(obs.A.coeff(0, (5 * 22 + 20) * 3 + 2) == 1.0);
  CHECK(obs.y[0] == 1.0);
  CHECK(obs.A.coeff(1, (5 * 22 + 20) * 3 + 1) == 1.0);
  CHECK(obs.A.coeff(3, (5 * 22 + 0) * 3 + 1) == 1.0);
  CHECK(obs.y[3] == 4.0);
  CHECK(obs.A.coeff(4, (1 * 22 + 20) * 3 + 2) == 1.0);
  CHECK(obs.y[7] == 8.0);
}

TEST_CASE("loop rows: start equals end, optionally up to root translation", "[control]") {
  std::mt19937_64 rng(3);
  const int T = 6;
  auto src = random_motion(rng, T, skel());
  // Make the last frame the first one moved by a root translation in xz and
  // check which loop variant it satisfies.
  for (int j = 0; j < 22; ++j)
    for (int c = 0; c < 3; ++c)
      src[((T - 1) * 22 + j) * 3 + c] = src[j * 3 + c] + (c == 0 ? 0.7f : c == 2 ? -0.4f : 0.0f);
  Eigen::VectorXd x = to_vector(src);
  auto plain = compile_yaml("- {type: loop}", T);
  auto relative = compile_yaml("- {type: loop, up_to_root_translation: true}", T);
  CHECK(plain.rows() == 66);
  CHECK(relative.rows() == 64);  // the root's own x and z rows vanish
  CHECK((plain.A * x - plain.y).cwiseAbs().maxCoeff() > 0.3);
  CHECK((relative.A * x - relative.y).cwiseAbs().maxCoeff() < 1e-6);
}

TEST_CASE("relative offsets: constant, per frame, from source", "[control]") {
  auto constant = compile_yaml("- {type: relative, joints: [l_wrist, r_wrist], frames: [0, 2], axes: x, values: [0.5]}");
  REQUIRE(constant.rows() == 2);
  CHECK(constant.A.coeff(1, (2 * 22 + 20) * 3) == 1.0);
  CHECK(constant.A.coeff(1, (2 * 22 + 21) * 3) == -1.0);
  CHECK(constant.y[1] == 0.5);
  auto per_frame =
      compile_yaml("- {type: relative, joints: [20, 21], frames: [0, 2], axes: xz, values: [[1, 2], [3, 4]]}");
  CHECK(per_frame.y[3] == 4.0);
}

TEST_CASE("affine_to_model moves the normaliser inside the operator", "[control]") {
  std::mt19937_64 rng(5);
  auto src = random_motion(rng, 4, skel());
  auto obs = compile_yaml(R"(
- {type: keyframe, joints: [0, 20], frames: [1, 3], from_source: true}
- {type: camera_2d, joints: [15], camera: {scale: 1.0, pitch_deg: 20, yaw_deg: 30}, from_source: true, variance: 0.1}
)", 4);
  std::array<double, 3> scale{0.5148, 0.6101, 0.8716}, offset{1.6e-4, 0.3766, 0.3102};
  auto model = affine_to_model(obs, scale, offset);
  // For any x_model: A_m x_model - y_m = A x_world - y.
  Eigen::VectorXd xm = Eigen::VectorXd::Random(obs.dim());
  Eigen::VectorXd xw(obs.dim());
  for (int i = 0; i < obs.dim(); ++i) xw[i] = scale[i % 3] * xm[i] + offset[i % 3];
  CHECK((model.A * xm - model.y - (obs.A * xw - obs.y)).cwiseAbs().maxCoeff() < 1e-12);
  CHECK(model.variance == obs.variance);
  expect_user_error([&] { affine_to_model(obs, {1, 0, 1}, offset); }, {"axis y", "scale"});
}

TEST_CASE("HDF5 spec round trip keeps every field", "[control]") {
  std::mt19937_64 rng(11);
  ConstraintSpec spec;
  spec.source = "mem";
  for (const auto& type : constraint_types()) spec.items.push_back(random_item(type, rng, 8, skel(), 0.0));
  spec.items[1].variance = 0.25;
  spec.items[0].frames = FrameSelection{FrameSelection::Kind::all, {}, 0, -1, 1};
  spec.items[0].values = {};
  spec.items[0].from_source = true;
  ConstraintItem range = random_item("trajectory", rng, 8, skel(), 0.0);
  range.frames = FrameSelection{FrameSelection::Kind::range, {}, 2, -1, 3};
  spec.items.push_back(range);
  spec.items.back().role = "upper_body";
  spec.items.back().type = "upper_body_edit";
  spec.items.back().joints.clear();
  spec.items.back().values = {};
  spec.items.back().from_source = false;
  TempDir dir("spec");
  std::string path = (dir.path / "targets.h5").string();
  save_constraint_spec_h5(spec, path);
  ConstraintSpec back = load_constraint_spec(path);
  REQUIRE(back.items.size() == spec.items.size());
  for (size_t i = 0; i < spec.items.size(); ++i) {
    INFO("item " << i << " " << spec.items[i].type);
    CHECK(back.items[i] == spec.items[i]);
  }
  // Compiles to the same rows as the in-memory spec.
  auto src = random_motion(rng, 8, skel());
  try {
    auto a = compile(spec, 8, skel(), src.data());
    auto b = compile(back, 8, skel(), src.data());
    CHECK((Eigen::MatrixXd(a.A) - Eigen::MatrixXd(b.A)).norm() == 0.0);
    CHECK(a.y == b.y);
  } catch (const UserError& e) {
    // random items may overlap; the round trip itself is what is tested here
    INFO(e.what());
    CHECK(std::string(e.what()).find("hard constraints") != std::string::npos);
  }
}

TEST_CASE("HDF5 spec errors name the item group and the key", "[control]") {
  TempDir dir("spec");
  std::string path = (dir.path / "bad.h5").string();
  ConstraintSpec spec;
  ConstraintItem it;
  it.type = "trajectory";
  it.name = "dense wrist";
  it.joints = {JointRef{20, ""}};
  it.values = values_of({2, 3}, {0, 1, 2, 3, std::nan(""), 5});
  spec.items = {it};
  save_constraint_spec_h5(spec, path);
  expect_user_error([&] { load_constraint_spec(path); }, {"item_000", "'dense wrist'", "'values'", "not finite"});
  expect_user_error([&] { load_constraint_spec_h5(path, "nope"); }, {"no group 'nope'"});
  expect_user_error([&] { load_constraint_spec((dir.path / "missing.h5").string()); }, {"missing.h5"});
}

TEST_CASE("validation errors name the item, the key and the value", "[control]") {
  SECTION("joint index out of range") {
    expect_user_error([] { compile_yaml("- {type: keyframe, name: kf, joints: [22], frames: [0], from_source: true}"); },
                      {"spec.yaml:1", "item 0 'kf' (keyframe)", "'joints'", "joint 22", "out of range"});
  }
  SECTION("unknown joint name suggests the closest") {
    expect_user_error(
        [] { compile_yaml("- {type: trajectory, name: hand, joints: [l_wirst], from_source: true}"); },
        {"item 0 'hand' (trajectory)", "'joints'", "l_wirst", "did you mean 'l_wrist'"});
  }
  SECTION("frame out of range") {
    expect_user_error([] { compile_yaml("- {type: keyframe, joints: [0], frames: [3, 8], from_source: true}", 8); },
                      {"item 0 (keyframe)", "'frames'", "frame 8", "0..7"});
    expect_user_error([] { compile_yaml("- {type: planar_root, frames: {start: 2, stop: 9}, from_source: true}", 8); },
                      {"item 0 (planar_root)", "'frames'", "stop 9"});
  }
  SECTION("bad axis") {
    expect_user_error([] { parse_constraint_spec_yaml("- {type: keyframe, joints: [0], frames: [0], axes: xw}", "s"); },
                      {"item 0 (keyframe)", "'axes'", "'w'"});
    expect_user_error([] { parse_constraint_spec_yaml("- {type: keyframe, joints: [0], frames: [0], axes: [3]}", "s"); },
                      {"'axes'", "axis 3"});
  }
  SECTION("target shape mismatch") {
    expect_user_error(
        [] { compile_yaml("- {type: keyframe, name: k, joints: [0, 1], frames: [0], values: [[[1, 2, 3]]]}"); },
        {"item 0 'k' (keyframe)", "'values'", "shape mismatch", "[1, 1, 3]", "[1, 2, 3]"});
    expect_user_error([] { compile_yaml("- {type: planar_root, frames: [0, 1], values: [[1, 2, 3], [4, 5, 6]]}"); },
                      {"'values'", "[2, 3]", "[2, 2]"});
    expect_user_error([] { parse_constraint_spec_yaml("- {type: planar_root, values: [[1, 2], [3]]}", "s"); },
                      {"'values'", "ragged"});
  }
  SECTION("non-finite values") {
    expect_user_error([] { parse_constraint_spec_yaml("- {type: planar_root, frames: [0], values: [[1, .nan]]}", "s"); },
                      {"item 0 (planar_root)", "'values'", "values[0, 1]", "not finite"});
    expect_user_error([] { parse_constraint_spec_yaml("- {type: loop, variance: .inf}", "s"); },
                      {"'variance'", "finite"});
  }
  SECTION("negative variance") {
    expect_user_error([] { parse_constraint_spec_yaml("- {type: loop, name: cyc, variance: -0.5}", "s"); },
                      {"item 0 'cyc' (loop)", "'variance'", "-0.5"});
    expect_user_error([] { parse_constraint_spec_yaml("- {type: loop, hard: false}", "s"); },
                      {"'variance'", "soft"});
    expect_user_error([] { parse_constraint_spec_yaml("- {type: loop, hard: true, variance: 1}", "s"); },
                      {"'hard'", "contradicts"});
  }
  SECTION("missing source motion") {
    expect_user_error(
        [] { compile_yaml("- {type: keyframe, name: k, joints: [0], frames: [0], from_source: true}", 8, false); },
        {"item 0 'k' (keyframe)", "'from_source'", "source motion"});
    expect_user_error([] { compile_yaml("- {type: upper_body_edit}", 8, false); },
                      {"item 0 (upper_body_edit)", "source motion"});
  }
  SECTION("non-finite source motion") {
    std::mt19937_64 rng(1);
    auto src = random_motion(rng, 4, skel());
    src[(2 * 22 + 0) * 3 + 1] = std::nanf("");
    auto spec = parse_constraint_spec_yaml("- {type: trajectory, joints: [pelvis], from_source: true}", "s");
    expect_user_error([&] { compile(spec, 4, skel(), src.data()); },
                      {"'from_source'", "not finite", "frame 2", "joint 0 ('pelvis')", "axis y"});
  }
  SECTION("values and from_source together, or neither") {
    expect_user_error(
        [] { parse_constraint_spec_yaml("- {type: planar_root, from_source: true, values: [[0, 0]]}", "s"); },
        {"'from_source'", "not both"});
    expect_user_error([] { compile_yaml("- {type: keyframe, joints: [0], frames: [0]}"); },
                      {"'values'", "from_source"});
  }
  SECTION("unknown keys, inapplicable keys, unknown types") {
    expect_user_error([] { parse_constraint_spec_yaml("- {type: keyframe, joints: [0], frame: [0]}", "s"); },
                      {"'frame'", "did you mean 'frames'"});
    expect_user_error([] { parse_constraint_spec_yaml("- {type: loop, values: [1]}", "s"); },
                      {"item 0 (loop)", "'values'", "does not apply"});
    expect_user_error([] { parse_constraint_spec_yaml("- {type: keyfarme}", "s"); },
                      {"item 0", "'type'", "did you mean 'keyframe'"});
    expect_user_error([] { parse_constraint_spec_yaml("constraint: []", "s"); }, {"did you mean 'constraints'"});
  }
  SECTION("item-specific structure") {
    expect_user_error([] { compile_yaml("- {type: relative, name: r, joints: [20], values: [0, 0, 0]}"); },
                      {"item 0 'r' (relative)", "'joints'", "exactly two"});
    expect_user_error([] { compile_yaml("- {type: keyframe, joints: [0, pelvis], frames: [0], from_source: true}"); },
                      {"'joints'", "listed twice"});
    expect_user_error([] { compile_yaml("- {type: camera_2d, joints: [0], from_source: true}"); },
                      {"item 0 (camera_2d)", "'camera'"});
    expect_user_error(
        [] { parse_constraint_spec_yaml("- {type: camera_2d, camera: {scale: 0}, from_source: true}", "s"); },
        {"'camera'", "scale"});
    expect_user_error([] { parse_constraint_spec_yaml("- {type: camera_2d, camera: {pitch: 3}}", "s"); },
                      {"'camera'", "did you mean 'pitch_deg'"});
    expect_user_error([] { compile_yaml("- {type: upper_body_edit, role: lower_bod}"); },
                      {"item 0 (upper_body_edit)", "'role'", "did you mean 'lower_body'"});
    expect_user_error([] { compile_yaml("- {type: loop, frames: [0, 1, 2]}"); }, {"'frames'", "two frames"});
  }
  SECTION("contradictory hard constraints name both items") {
    expect_user_error(
        [] {
          compile_yaml(R"(
- {type: keyframe, name: start pose, joints: [pelvis], frames: [2], axes: x, values: [[[0.5]]]}
- {type: trajectory, name: pelvis path, joints: [pelvis], axes: x, values: [[0], [0], [0], [0], [0], [0], [0], [0]]}
)");
        },
        {"contradictory", "item 0 'start pose' (keyframe)", "item 1 'pelvis path' (trajectory)", "frame 2"});
  }
  SECTION("duplicated hard rows are redundant, named") {
    expect_user_error(
        [] {
          compile_yaml(R"(
- {type: keyframe, name: a, joints: [l_wrist], frames: [4], from_source: true}
- {type: keyframe, name: b, joints: [l_wrist], frames: [4], from_source: true}
)");
        },
        {"redundant", "item 0 'a' (keyframe)", "item 1 'b' (keyframe)", "frame 4"});
  }
  SECTION("dependence through coupled rows: loop plus both end frames pinned") {
    expect_user_error(
        [] {
          compile_yaml(R"(
- {type: keyframe, name: ends, joints: [l_foot], frames: [0, 7], values: [[[0, 0, 0]], [[1, 0, 0]]]}
- {type: loop, name: cycle, joints: [l_foot]}
- {type: keyframe, name: unrelated, joints: [head], frames: [3], from_source: true}
)");
        },
        {"contradictory", "item 0 'ends' (keyframe)", "item 1 'cycle' (loop)"});
    // the third item is not involved
    try {
      compile_yaml(R"(
- {type: keyframe, name: ends, joints: [l_foot], frames: [0, 7], values: [[[0, 0, 0]], [[1, 0, 0]]]}
- {type: loop, name: cycle, joints: [l_foot]}
- {type: keyframe, name: unrelated, joints: [head], frames: [3], from_source: true}
)");
    } catch (const UserError& e) {
      CHECK(std::string(e.what()).find("unrelated") == std::string::npos);
    }
  }
  SECTION("two cameras on the same joint and frame over-determine it") {
    expect_user_error(
        [] {
          compile_yaml(R"(
- {type: camera_2d, name: front, joints: [head], frames: [1], camera: {scale: 1}, from_source: true}
- {type: camera_2d, name: side, joints: [head], frames: [1], camera: {scale: 1, yaw_deg: 90}, from_source: true}
)");
        },
        {"redundant", "'front'", "'side'"});
  }
  SECTION("soft duplicates are fine") {
    CHECK_NOTHROW(compile_yaml(R"(
- {type: keyframe, joints: [l_wrist], frames: [4], from_source: true}
- {type: keyframe, joints: [l_wrist], frames: [4], values: [[[0, 0, 0]]], variance: 0.01}
)"));
  }
}
