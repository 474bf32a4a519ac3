// The motion-file shape check behind `motionctl score` and `motionctl export` (issue
// 16), at the command level: a small fixture is edited with h5py (one defect per
// file) and sealed anew with tools/motionio.py, so the file passes its checksum and
// the shape check, not the seal, is what refuses it. Each command must exit 2 with a
// message naming the file and the offending dataset and value, and write nothing.
// The data-layer reader has its own unit tests (tests/data/test_motion_io.cpp);
// these run the binary, so a crash, exit 1 or a silent success fails them.
#include <catch2/catch.hpp>

#include "test_util.h"

using namespace mc::test;

namespace {

// One defect: `edit` is a Python expression over the open file `f` (h5py, "r+"),
// with helpers put(key, array, **kw) (replace a dataset), J(f) (the joints array),
// changed(array, index, value) (a copy with one entry set), no_clips(f, put) (every
// per-clip dataset emptied) and STR (h5py's UTF-8 string type). `expect`: what the
// error message must contain besides the file's path.
struct ShapeCase {
  std::string name, edit;
  std::vector<std::string> expect;
};

// Writes <dir>/<case>.h5 for every case, each a copy of `good` with its edit, sealed
// anew (and the seal checked) by tools/motionio.py.
void write_bad_files(const fs::path& good, const fs::path& dir, const std::vector<ShapeCase>& cases) {
  std::string py = R"(import os, shutil, sys
import numpy as np
import h5py
sys.path.insert(0, os.path.join(sys.argv[1], "tools"))
import motionio
good, out = sys.argv[2], sys.argv[3]
STR = h5py.string_dtype()
def J(f):
    return f["joints"][...]
def changed(a, index, value):
    a = np.array(a)
    a[index] = value
    return a
def case(name, edit):
    path = os.path.join(out, name + ".h5")
    shutil.copyfile(good, path)
    with h5py.File(path, "r+") as f:
        def put(key, data, **kw):
            del f[key]
            f.create_dataset(key, data=data, **kw)
        edit(f, put)
    motionio.seal_h5_file(path)
    assert motionio.check_h5_seal(path), path
def no_clips(f, put):
    put("joints", np.zeros((0,) + f["joints"].shape[1:], np.float32))
    put("lengths", np.zeros(0, np.int32))
    for key in ("ids", "split", "labels", "captions/text"):
        put(key, np.array([], object), dtype=STR)
    put("captions/offsets", np.zeros(1, np.int64))
)";
  for (const auto& c : cases) py += fmt::format("case('{}', lambda f, put: {})\n", c.name, c.edit);
  const fs::path script = dir / "make_bad_files.py";
  std::ofstream(script) << py;
  auto r = run_shell(fmt::format("'{}' '{}' '{}' '{}' '{}' 2>&1", MOTIONCTL_PYTHON, script.string(),
                                 MOTIONCTL_SOURCE_DIR, good.string(), dir.string()));
  INFO(py << "\n" << r.output);
  REQUIRE(r.exit_code == 0);
}

// A 4-clip fixture, 40 to 60 frames per clip, T_max 60.
fs::path small_fixture(const fs::path& dir) {
  const fs::path path = dir / "good.h5";
  auto r = run_motionctl(fmt::format("fixture configs/data/smoke.yaml output={} fixture.num_clips=4 "
                                     "fixture.min_frames=40 fixture.max_frames=60 fixture.t_max=60",
                                     path.string()));
  INFO(r.output);
  REQUIRE(r.exit_code == 0);
  return path;
}

// Exit 2, the file and every fragment named, and no sign that the seal (rather than
// the shape check) or a crash ended the command.
void check_refused(const CommandResult& r, const std::string& args, const fs::path& file,
                   const std::vector<std::string>& expect) {
  INFO("motionctl " << args << "\n" << r.output);
  CHECK(r.exit_code == 2);
  CHECK(r.output.find(file.string()) != std::string::npos);
  for (const auto& e : expect) CHECK(r.output.find(e) != std::string::npos);
  // The seal's refusals (core/h5_seal.cpp) name the checksum or the size it was written with.
  CHECK(r.output.find("checksum") == std::string::npos);
  CHECK(r.output.find("was written with") == std::string::npos);
  CHECK(r.output.find("internal error") == std::string::npos);
}

}  // namespace

TEST_CASE("score and export refuse motion files of the wrong shape with exit 2 naming the file and dataset",
          "[cli][robust]") {
  TempDir t("shapes");
  const fs::path good = small_fixture(t.path);
  const std::vector<ShapeCase> cases = {
      // Resealed but unchanged: both commands accept it, so the edits alone are refused.
      {"unchanged", "None", {}},
      {"fewer_joints", "put('joints', J(f)[:, :, :-1])",
       {"dataset 'joints' has 21 joints per frame", "skeleton 'humanml3d22' has 22"}},
      {"more_joints", "put('joints', np.concatenate([J(f), J(f)[:, :, :1]], axis=2))",
       {"dataset 'joints' has 23 joints per frame"}},
      {"two_coordinates", "put('joints', J(f)[..., :2])",
       {"dataset 'joints' has shape [4, 60, 22, 2]", "[N, T_max, J, 3]"}},
      {"four_coordinates", "put('joints', np.concatenate([J(f), J(f)[..., :1]], axis=3))",
       {"dataset 'joints' has shape [4, 60, 22, 4]"}},
      {"flat_joints", "put('joints', J(f).reshape(4, 60, 66))", {"dataset 'joints' has shape [4, 60, 66]"}},
      {"fewer_lengths", "put('lengths', f['lengths'][:-1])",
       {"dataset 'joints' has 4 clips but dataset 'lengths' has 3"}},
      {"more_lengths", "put('lengths', np.append(f['lengths'][...], 50).astype(np.int32))",
       {"dataset 'joints' has 4 clips but dataset 'lengths' has 5"}},
      {"lengths_2d", "put('lengths', f['lengths'][...][:, None])", {"dataset 'lengths' has shape [4, 1]"}},
      {"lengths_float", "put('lengths', f['lengths'][...].astype(np.float32))",
       {"dataset 'lengths' holds the wrong type (expected integers)"}},
      {"zero_frames", "put('joints', np.zeros((4, 0, 22, 3), np.float32))",
       {"dataset 'joints' has shape [4, 0, 22, 3]: 0 frames per clip"}},
      {"length_zero", "put('lengths', changed(f['lengths'], 1, 0))",
       {"'lengths' of clip 1", "is 0, outside 1..T_max = 60"}},
      {"length_negative", "put('lengths', changed(f['lengths'], 1, -5))", {"'lengths' of clip 1", "is -5, outside"}},
      {"length_past_t_max", "put('lengths', changed(f['lengths'], 0, 61))",
       {"'lengths' of clip 0", "is 61, outside 1..T_max = 60"}},
      {"length_int_max", "put('lengths', changed(f['lengths'], 3, 2**31 - 1))",
       {"'lengths' of clip 3", "is 2147483647, outside 1..T_max = 60"}},
      {"frames_claimed_past_the_file",
       "(f.__delitem__('joints'), f.create_dataset('joints', shape=(4, 10**8, 22, 3), dtype='f4', "
       "chunks=(1, 64, 22, 3)))",
       {"dataset 'joints' has shape [4, 100000000, 22, 3]", "more than a"}},
      {"nan_joint", "put('joints', changed(J(f), (2, 3, 5, 1), np.nan))",
       {"dataset 'joints' holds a non-finite value (clip 2, frame 3, joint 5)"}},
      {"inf_joint", "put('joints', changed(J(f), (0, 0, 0, 0), np.inf))",
       {"dataset 'joints' holds a non-finite value (clip 0, frame 0, joint 0)"}},
      // Past the shortest clip's length (the fixture's clips are 40 to 60 frames).
      {"nonzero_padding",
       "put('joints', changed(J(f), (int(np.argmin(f['lengths'])), int(min(f['lengths'])), 0, 0), 1.0))",
       {"'joints' of clip", "is not zero at padding frame"}},
      {"fewer_ids", "put('ids', f['ids'][:-1], dtype=STR)", {"dataset 'ids' has shape [3] but [4] was expected"}},
      {"more_splits", "put('split', np.append(f['split'][...], b'train').astype(object), dtype=STR)",
       {"dataset 'split' has shape [5] but [4] was expected"}},
      {"short_caption_offsets", "put('captions/offsets', f['captions/offsets'][:-1])",
       {"dataset 'captions/offsets' has shape [4] but [5] was expected"}},
      {"joint_mean_of_4", "put('stats/joint_mean', np.zeros(4, np.float32))",
       {"dataset 'stats/joint_mean' has shape [4] but [3] was expected"}},
      {"short_parents", "put('skeleton/parents', f['skeleton/parents'][:-1])",
       {"dataset 'skeleton/parents' disagrees with attribute 'yaml'"}},
      {"fps_nan", "f.attrs.__setitem__('fps', np.nan)", {"fps is nan"}},
      {"no_clips", "no_clips(f, put)",
       {"holds no clips (its dataset 'lengths' is empty)"}},
  };
  write_bad_files(good, t.path, cases);
  for (const auto& c : cases) {
    const fs::path file = t.path / (c.name + ".h5");
    const fs::path out = t.path / ("bvh_" + c.name);
    const std::string score = "score " + file.string();
    const std::string bvh = fmt::format("export --format bvh {} --out {}", file.string(), out.string());
    auto s = run_motionctl(score);
    auto e = run_motionctl(bvh);
    if (c.name == "unchanged") {
      INFO(s.output << "\n" << e.output);
      CHECK(s.exit_code == 0);
      CHECK(s.output.find("foot_skating") != std::string::npos);
      CHECK(e.exit_code == 0);
      CHECK(std::distance(fs::directory_iterator(out), fs::directory_iterator{}) == 4);
      continue;
    }
    check_refused(s, score, file, c.expect);
    check_refused(e, bvh, file, c.expect);
    CHECK_FALSE(fs::exists(out));
  }
}

TEST_CASE("motion files that are well formed but cannot be scored or exported are named, never a crash",
          "[cli][robust]") {
  TempDir t("shapes2");
  const fs::path good = small_fixture(t.path);
  write_bad_files(good, t.path,
                  {{"one_frame_clips",
                    "(put('lengths', np.ones(4, np.int32)), put('joints', changed(J(f), np.s_[:, 1:], 0)))", {}},
                   {"no_clips", "no_clips(f, put)", {}},
                   {"two_coordinates", "put('joints', J(f)[..., :2])", {}}});
  const fs::path one = t.path / "one_frame_clips.h5", none = t.path / "no_clips.h5";
  const fs::path bad = t.path / "two_coordinates.h5";

  // 1-frame clips: foot skating has no transition to score, so score names the
  // clip; BVH takes them (one frame is a valid BVH).
  std::string args = "score " + one.string();
  check_refused(run_motionctl(args), args, one, {"clip 0", "has 'lengths' 1", "at least 2 frames"});
  const fs::path out_one = t.path / "bvh_one";
  auto e = run_motionctl(fmt::format("export --format bvh {} --out {}", one.string(), out_one.string()));
  {
    INFO(e.output);
    CHECK(e.exit_code == 0);
    CHECK(e.output.find(": 1 frames") != std::string::npos);
    REQUIRE(fs::is_directory(out_one));
    CHECK(std::distance(fs::directory_iterator(out_one), fs::directory_iterator{}) == 4);
  }

  // Foot skating over the padded 196 frames of clips stored with 60.
  args = "score --padded-196 " + good.string();
  check_refused(run_motionctl(args), args, good, {"dataset 'joints' holds 60 (T_max)", "--padded-196"});

  // --ids on a file with no clips indexed its first id (a segfault before the check).
  const fs::path out_none = t.path / "bvh_none";
  args = fmt::format("export --format bvh {} --out {} --ids fx000000", none.string(), out_none.string());
  check_refused(run_motionctl(args), args, none, {"holds no clips"});
  CHECK_FALSE(fs::exists(out_none));

  // score --source reads its file through the same check.
  args = fmt::format("score {} --source {}", good.string(), bad.string());
  check_refused(run_motionctl(args), args, bad, {"dataset 'joints' has shape [4, 60, 22, 2]"});
}
