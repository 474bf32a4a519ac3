// ProjFlow's application protocols as fair tasks (issue 14): relative joints hold one
// fixed offset over the whole motion (Fig. 1c), and an upper-body edit asks for the
// caption of a different motion of the same split, never the clip's own paraphrase.
#include <catch2/catch.hpp>

#include "control/control_task.h"
#include "control/linear_observation.h"
#include "core/config.h"
#include "core/error.h"
#include "data/data_test_util.h"

using namespace mc;
using namespace mc::test;

namespace {

struct ProtocolFile : Config {
  Component protocol{"protocol"};
  void visit(FieldVisitor& v) override { v("protocol", protocol, "protocol"); }
};
std::vector<ControlTask> tasks_of(const std::string& yaml, const MotionSet& data, const std::vector<size_t>& clips) {
  ProtocolFile f;
  parse_config(config_from_string(yaml), f);
  return as_protocol(f.protocol).make_tasks(data, clips, 1);
}

}  // namespace

TEST_CASE("relative protocol: one offset, the clip's at frame 0, held at every frame", "[protocols]") {
  MotionSet data = random_motion_set({40, 25, 33}, {"test"}, 3);
  const std::vector<int> joints = {20, 15};
  const auto tasks =
      tasks_of("protocol: {type: application, application: relative, relative_joints: [20, 15]}", data, {0, 1, 2});
  REQUIRE(tasks.size() == 3);
  for (size_t c = 0; c < tasks.size(); ++c) {
    const ControlTask& t = tasks[c];
    LinearObservation o = compile(t.spec, t.length, data.skeleton, t.source.data());
    REQUIRE(o.rows() == 3 * t.length);  // every frame, x y z
    // Row r targets x_a - x_b on one axis; each axis has a single target over all frames.
    const Eigen::MatrixXd A = Eigen::MatrixXd(o.A);
    for (int r = 0; r < o.rows(); ++r) {
      Eigen::VectorXd row = A.row(r).transpose();
      int axis = -1;
      for (int k = 0; k < row.size(); ++k)
        if (row[k] == 1.0) axis = k % 3;
      REQUIRE(axis >= 0);
      const double first = static_cast<double>(data.at(c, 0, joints[0])[axis]) - data.at(c, 0, joints[1])[axis];
      CHECK(o.y[r] == Approx(first).margin(1e-6));
    }
    // The clip itself meets it at frame 0 and (random joints) not at every other frame:
    // the target is no longer the clip's per-frame offset.
    Eigen::VectorXd x(o.dim());
    for (int k = 0; k < o.dim(); ++k) x[k] = t.source[k];
    Eigen::VectorXd r = o.A * x - o.y;
    CHECK(r.head(3).cwiseAbs().maxCoeff() < 1e-5);
    CHECK(r.cwiseAbs().maxCoeff() > 1e-2);
  }
}

TEST_CASE("upper-body edit protocol: the caption of another motion of the same split", "[protocols]") {
  MotionSet data = random_motion_set({40, 41, 42, 43, 44, 45}, {"test", "val"}, 4);
  // Labels (the fixture's motion programs): clips 0, 2 share one program, 4 another.
  data.labels = {"walk", "wave", "walk", "walk", "jump", "jump"};
  data.captions[2] = {"a person walks number 0"};  // same caption as clip 0 too
  const auto tasks = tasks_of("protocol: {type: application, application: upper_body_edit}", data, {0, 2, 4});
  REQUIRE(tasks.size() == 3);
  // Test clips are 0, 2, 4: clip 0 skips 2 (same program and caption) and takes 4;
  // clip 2 takes 4; clip 4 (jump) wraps to 0 (walk).
  CHECK(tasks[0].caption == data.captions[4].front());
  CHECK(tasks[1].caption == data.captions[4].front());
  CHECK(tasks[2].caption == data.captions[0].front());
  for (size_t i = 0; i < tasks.size(); ++i) {
    const size_t c = std::vector<size_t>{0, 2, 4}[i];
    CHECK(tasks[i].caption != data.captions[c].front());
    // The lower body still comes from the clip itself.
    CHECK(tasks[i].clip_id == data.ids[c]);
    CHECK(compile(tasks[i].spec, tasks[i].length, data.skeleton, tasks[i].source.data()).rows() > 0);
  }
  // Deterministic in the data alone, and independent of which other clips are requested.
  CHECK(tasks_of("protocol: {type: application, application: upper_body_edit}", data, {2})[0].caption ==
        tasks[1].caption);

  // Without labels, the next clip of the split with a different caption.
  MotionSet plain = random_motion_set({40, 41, 42}, {"test"}, 5);
  const auto t2 = tasks_of("protocol: {type: application, application: upper_body_edit}", plain, {0, 1, 2});
  CHECK(t2[0].caption == plain.captions[1].front());
  CHECK(t2[2].caption == plain.captions[0].front());

  // A split whose clips all say the same thing has nothing to edit towards: a clear error.
  MotionSet same = random_motion_set({40, 41}, {"test"}, 6);
  same.captions[1] = same.captions[0];
  try {
    tasks_of("protocol: {type: application, application: upper_body_edit}", same, {0});
    FAIL("expected a UserError");
  } catch (const UserError& e) {
    CHECK(std::string(e.what()).find("upper_body_edit") != std::string::npos);
    CHECK(std::string(e.what()).find("clip0") != std::string::npos);
  }
}
