// Per-sample constraint specs inside motion files: targets taken from the source
// motion are written out so the spec compiles to the same rows without it, and
// the /control group round-trips through a motion file.
#include <catch2/catch.hpp>

#include "control/constraint_spec.h"
#include "control/linear_observation.h"
#include "control/sample_constraints.h"
#include "control_test_util.h"
#include "core/error.h"
#include "data/motion_file_extra.h"
#include "data/motion_set.h"
#include "data/skeleton.h"
#include "tests/test_util.h"

#include <chrono>
#include <thread>

using namespace mc;
using namespace mc::test;

namespace {

const Skeleton& sk() { return humanml3d_skeleton(); }

void require_same_rows(const LinearObservation& a, const LinearObservation& b) {
  REQUIRE(a.rows() == b.rows());
  REQUIRE(a.dim() == b.dim());
  CHECK(a.y == b.y);  // exact: the written targets are the compiled ones
  CHECK(a.variance == b.variance);
  CHECK(a.item_of_row == b.item_of_row);
  Eigen::SparseMatrix<double, Eigen::RowMajor> d = a.A - b.A;
  CHECK(d.norm() == 0.0);
}

}  // namespace

TEST_CASE("with_explicit_targets: the spec compiles to the same rows without the source (every type)",
          "[control][outside]") {
  std::mt19937_64 rng(77);
  for (const auto& type : constraint_types())
    for (int trial = 0; trial < 12; ++trial) {
      const int T = uniform_int(rng, 2, 9);
      auto src = random_motion(rng, T, sk());
      ConstraintSpec spec;
      spec.items = {random_item(type, rng, T, sk(), trial % 3 == 0 ? 0.01 : 0.0)};
      INFO(type << " trial " << trial);
      LinearObservation with_source = compile(spec, T, sk(), src.data());
      ConstraintSpec explicit_spec = with_explicit_targets(spec, T, sk(), src.data());
      for (auto& it : explicit_spec.items) CHECK_FALSE(it.from_source);
      require_same_rows(with_source, compile(explicit_spec, T, sk(), nullptr));
      // The original needs the source whenever it reads from it.
      if (spec.items[0].from_source || type == "upper_body_edit")
        CHECK_THROWS_AS(compile(spec, T, sk(), nullptr), UserError);
    }
}

TEST_CASE("per-sample specs round-trip through a motion file's /control group", "[control][outside]") {
  std::mt19937_64 rng(5);
  const int T = 6;
  MotionSet m;
  m.skeleton = sk();
  m.t_max = T;
  std::vector<ConstraintSpec> specs;
  std::vector<int> frames;
  std::vector<std::vector<float>> sources;
  for (int i = 0; i < 3; ++i) {
    auto src = random_motion(rng, T, sk());
    m.joints.insert(m.joints.end(), src.begin(), src.end());
    m.lengths.push_back(T);
    m.ids.push_back("s" + std::to_string(i));
    m.splits.push_back("sample");
    m.captions.push_back({"a person walks"});
    ConstraintSpec spec;
    if (i == 0) {  // a lifting task: 2D targets seen through a camera
      spec.items = {random_item("camera_2d", rng, T, sk(), 0.0)};
      spec.items[0].values = {}, spec.items[0].from_source = true;
    } else if (i == 2) {
      spec.items = {random_item("upper_body_edit", rng, T, sk(), 0.0)};
    }  // sample 1 is unconstrained: an empty spec
    specs.push_back(with_explicit_targets(spec, T, sk(), src.data()));
    frames.push_back(T);
    sources.push_back(src);
  }
  TempDir dir("control");
  const std::string path = (dir.path / "gen.h5").string();
  write_motion_file(path, m, [&](int64_t f) { write_sample_constraints(f, specs, frames, path); });
  // The same samples and specs written again give the same bytes (no HDF5 modification times).
  const std::string again = (dir.path / "gen_again.h5").string();
  std::this_thread::sleep_for(std::chrono::milliseconds(1100));  // HDF5 times have 1 s resolution
  write_motion_file(again, m, [&](int64_t f) { write_sample_constraints(f, specs, frames, again); });
  CHECK(slurp(path) == slurp(again));
  MotionSet back = read_motion_file(path);  // still a valid motion file
  CHECK(back.size() == 3);
  SampleConstraints sc = read_sample_constraints(path);
  REQUIRE(sc.specs.size() == 3);
  CHECK(sc.frames == frames);
  CHECK(sc.specs[1].items.empty());
  CHECK(any_constraints(sc.specs));
  for (size_t i = 0; i < 3; ++i) {
    INFO("sample " << i);
    REQUIRE(sc.specs[i].items.size() == specs[i].items.size());
    for (size_t k = 0; k < specs[i].items.size(); ++k) CHECK(sc.specs[i].items[k] == specs[i].items[k]);
    if (i != 1) {
      if (i == 0) CHECK(sc.specs[i].items[0].has_camera);  // the camera travels with its item
      if (i == 2) CHECK(sc.specs[i].items[0].type == "trajectory");
      require_same_rows(compile(sc.specs[i], T, sk(), nullptr), compile(specs[i], T, sk(), nullptr));
    }
  }
  // A file without the group has no specs; a plain motion file stays readable as before.
  write_motion_file((dir.path / "plain.h5").string(), m);
  CHECK(read_sample_constraints((dir.path / "plain.h5").string()).specs.empty());
}
