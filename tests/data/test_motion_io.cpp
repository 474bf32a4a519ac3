// Motion file (HDF5) round trips, byte determinism, and the reader's refusal of
// every kind of broken file with a UserError that names the file and dataset.
#include <hdf5.h>
#include <unistd.h>

#include <catch2/catch.hpp>
#include <chrono>
#include <fstream>
#include <thread>

#include "core/atomic_file.h"
#include "core/error.h"
#include "core/h5_seal.h"
#include "data/motion_set.h"
#include "data_test_util.h"
#include "test_util.h"

using namespace mc;
using namespace mc::test;
using Catch::Matchers::Contains;

namespace {

// A set that exercises every part of the format: varied lengths (incl. 1 and
// T_max), several captions with non-ASCII text, labels, stats and a vocabulary.
MotionSet full_motion_set() {
  MotionSet m = random_motion_set({12, 1, 7, 12, 3}, {"train", "val", "test", "train", "sample"}, 11);
  m.captions[0] = {"a person walks forward", "someone strolls ahead slowly"};
  m.captions[1] = {"ça marche — une personne marche", "人が前に歩く", "émoji 🚶 walk"};
  m.captions[3] = {"a", "b", "c", "d"};
  m.labels = {"walk(2.0)", "", "turn(90)", "jump", "ñandú"};
  m.provenance = {"motionctl test", "0.1.0", 1234567890123LL, "data:\n  clips: 5\n", "2026-01-01T00:00:00Z"};
  NormStats s;
  s.joint_mean = {0.1f, 0.9f, -0.2f};
  s.joint_std = {0.5f, 0.6f, 0.7f};
  s.feature_mean = {1, 2, 3, 4, 5};
  s.feature_std = {0.1f, 0.2f, 0.3f, 0.4f, 0.5f};
  s.feature_layout = "mc67";
  m.stats = s;
  m.vocab = {"<pad>", "<unk>", "<sos>", "<eos>", "walks", "person", "ça"};
  return m;
}

std::vector<char> file_bytes(const std::string& path) {
  std::ifstream f(path, std::ios::binary);
  return std::vector<char>(std::istreambuf_iterator<char>(f), {});
}

// Opens a written file read-write so a test can damage one dataset the way a
// buggy external writer would.
// Edits a written file in place, then re-seals it (core/h5_seal.h) so the reader
// gets past the checksum to the defect under test.
struct H5Patch {
  explicit H5Patch(const std::string& p) : path(p), file(H5Fopen(p.c_str(), H5F_ACC_RDWR, H5P_DEFAULT)) {
    REQUIRE(file >= 0);
  }
  ~H5Patch() {
    H5Fclose(file);
    seal_h5_file(path, "patched test file");
  }
  std::string path;
  void replace_float_dataset(const char* name, const std::vector<hsize_t>& dims, const std::vector<float>& data) {
    REQUIRE(H5Ldelete(file, name, H5P_DEFAULT) >= 0);
    hid_t space = H5Screate_simple(static_cast<int>(dims.size()), dims.data(), nullptr);
    hid_t d = H5Dcreate2(file, name, H5T_IEEE_F32LE, space, H5P_DEFAULT, H5P_DEFAULT, H5P_DEFAULT);
    REQUIRE(d >= 0);
    REQUIRE(H5Dwrite(d, H5T_NATIVE_FLOAT, H5S_ALL, H5S_ALL, H5P_DEFAULT, data.data()) >= 0);
    H5Dclose(d);
    H5Sclose(space);
  }
  void overwrite(const char* name, hid_t mem_type, const void* data) {
    hid_t d = H5Dopen2(file, name, H5P_DEFAULT);
    REQUIRE(d >= 0);
    REQUIRE(H5Dwrite(d, mem_type, H5S_ALL, H5S_ALL, H5P_DEFAULT, data) >= 0);
    H5Dclose(d);
  }
  void overwrite_strings(const char* name, const std::vector<const char*>& values) {
    hid_t t = H5Tcopy(H5T_C_S1);
    H5Tset_size(t, H5T_VARIABLE);
    H5Tset_cset(t, H5T_CSET_UTF8);
    overwrite(name, t, values.data());
    H5Tclose(t);
  }
  void remove(const char* name) { REQUIRE(H5Ldelete(file, name, H5P_DEFAULT) >= 0); }
  hid_t file;
};

}  // namespace

TEST_CASE("motion file round trip preserves every field", "[data][io]") {
  ScratchDir dir;
  MotionSet m = full_motion_set();
  write_motion_file(dir.file("set.h5"), m);
  MotionSet back = read_motion_file(dir.file("set.h5"));
  CHECK(same_motion_set(m, back));
  // Chains and roles travel only in the yaml attribute.
  CHECK(back.skeleton.role("face") == std::vector<int>{2, 1, 17, 16});
  CHECK(back.skeleton.chains == m.skeleton.chains);
  CHECK(back.captions[1][1] == "人が前に歩く");
  CHECK(back.provenance.seed == 1234567890123LL);

  SECTION("optional parts stay absent") {
    MotionSet bare = random_motion_set({4, 2}, {"train"});
    write_motion_file(dir.file("bare.h5"), bare);
    MotionSet b = read_motion_file(dir.file("bare.h5"));
    CHECK(same_motion_set(bare, b));
    CHECK(b.labels.empty());
    CHECK_FALSE(b.stats.has_value());
    CHECK(b.vocab.empty());
  }
  SECTION("joint statistics without feature statistics (a converted dataset) round-trip") {
    m.stats->feature_mean.clear();
    m.stats->feature_std.clear();
    m.stats->feature_layout = "none";
    write_motion_file(dir.file("joint_stats.h5"), m);
    MotionSet b = read_motion_file(dir.file("joint_stats.h5"));
    REQUIRE(b.stats.has_value());
    CHECK(b.stats->joint_std == m.stats->joint_std);
    CHECK(b.stats->feature_mean.empty());
    CHECK(b.stats->feature_layout == "none");
  }
  SECTION("an empty set round-trips") {
    MotionSet empty = random_motion_set({}, {"train"});
    write_motion_file(dir.file("empty.h5"), empty);
    MotionSet e = read_motion_file(dir.file("empty.h5"));
    CHECK(e.size() == 0);
    CHECK(e.skeleton == empty.skeleton);
  }
}

TEST_CASE("motion files are byte-identical when the same set is written twice", "[data][io]") {
  ScratchDir dir;
  MotionSet m = full_motion_set();
  write_motion_file(dir.file("a.h5"), m);
  // HDF5 object timestamps have one-second resolution: wait so they would differ.
  std::this_thread::sleep_for(std::chrono::milliseconds(1100));
  write_motion_file(dir.file("b.h5"), m);
  auto a = file_bytes(dir.file("a.h5")), b = file_bytes(dir.file("b.h5"));
  REQUIRE(a.size() > 1000);
  CHECK(a == b);

  m.provenance.created = "2026-01-02T00:00:00Z";
  write_motion_file(dir.file("c.h5"), m);
  CHECK(file_bytes(dir.file("c.h5")) != a);
}

TEST_CASE("joints are stored chunked per clip with gzip", "[data][io]") {
  ScratchDir dir;
  MotionSet m = full_motion_set();
  write_motion_file(dir.file("set.h5"), m);
  hid_t f = H5Fopen(dir.file("set.h5").c_str(), H5F_ACC_RDONLY, H5P_DEFAULT);
  hid_t d = H5Dopen2(f, "joints", H5P_DEFAULT);
  hid_t dcpl = H5Dget_create_plist(d);
  hsize_t chunk[4] = {0, 0, 0, 0};
  REQUIRE(H5Pget_chunk(dcpl, 4, chunk) == 4);
  CHECK(chunk[0] == 1);
  CHECK(chunk[1] == static_cast<hsize_t>(m.t_max));
  CHECK(chunk[2] == 22);
  CHECK(chunk[3] == 3);
  unsigned flags = 0, level = 0;
  size_t nelmts = 1;
  REQUIRE(H5Pget_filter_by_id2(dcpl, H5Z_FILTER_DEFLATE, &flags, &nelmts, &level, 0, nullptr, nullptr) >= 0);
  CHECK(level == 4);
  H5Pclose(dcpl);
  H5Dclose(d);
  H5Fclose(f);
}

TEST_CASE("reading a broken motion file is a UserError naming the file and dataset", "[data][io]") {
  ScratchDir dir;
  const std::string good = dir.file("good.h5");
  MotionSet m = full_motion_set();
  write_motion_file(good, m);

  SECTION("missing file") {
    auto msg = user_error_of([&] { read_motion_file(dir.file("nope.h5")); });
    CHECK_THAT(msg, Contains("nope.h5") && Contains("does not exist"));
  }
  SECTION("a text file renamed .h5") {
    std::ofstream(dir.file("text.h5")) << "id,caption\n1,a person walks\n";
    auto msg = user_error_of([&] { read_motion_file(dir.file("text.h5")); });
    CHECK_THAT(msg, Contains("text.h5") && Contains("not an HDF5 file"));
  }
  SECTION("an empty file") {
    std::ofstream(dir.file("empty.h5")).flush();
    CHECK_THAT(user_error_of([&] { read_motion_file(dir.file("empty.h5")); }), Contains("empty.h5"));
  }
  SECTION("a truncated file") {
    auto bytes = file_bytes(good);
    for (size_t keep : {bytes.size() / 2, bytes.size() - 100, size_t(600)}) {
      std::ofstream(dir.file("cut.h5"), std::ios::binary).write(bytes.data(), static_cast<std::streamsize>(keep));
      CHECK_THAT(user_error_of([&] { read_motion_file(dir.file("cut.h5")); }), Contains("cut.h5"));
    }
  }
  SECTION("joints of the wrong rank") {
    {
      H5Patch p(good);
      p.replace_float_dataset("joints", {5, 12, 66}, std::vector<float>(5 * 12 * 66, 0.0f));
    }
    auto msg = user_error_of([&] { read_motion_file(good); });
    CHECK_THAT(msg, Contains("good.h5") && Contains("'joints'") && Contains("[5, 12, 66]"));
  }
  SECTION("joints with fewer joints than the skeleton") {
    {
      H5Patch p(good);
      p.replace_float_dataset("joints", {5, 12, 21, 3}, std::vector<float>(5 * 12 * 21 * 3, 0.0f));
    }
    auto msg = user_error_of([&] { read_motion_file(good); });
    CHECK_THAT(msg, Contains("good.h5") && Contains("'joints'") && Contains("21") && Contains("humanml3d22"));
  }
  SECTION("joints with a clip count other than lengths") {
    {
      H5Patch p(good);
      p.replace_float_dataset("joints", {4, 12, 22, 3}, std::vector<float>(4 * 12 * 22 * 3, 0.0f));
    }
    CHECK_THAT(user_error_of([&] { read_motion_file(good); }), Contains("good.h5") && Contains("'lengths'"));
  }
  SECTION("NaN joints") {
    MotionSet bad = m;
    bad.at(2, 3, 5)[1] = std::nanf("");
    {
      H5Patch p(good);
      p.overwrite("joints", H5T_NATIVE_FLOAT, bad.joints.data());
    }
    auto msg = user_error_of([&] { read_motion_file(good); });
    CHECK_THAT(msg, Contains("good.h5") && Contains("'joints'") && Contains("clip 2, frame 3, joint 5"));
  }
  SECTION("duplicate ids") {
    {
      H5Patch p(good);
      p.overwrite_strings("ids", {"a", "b", "c", "b", "e"});
    }
    auto msg = user_error_of([&] { read_motion_file(good); });
    CHECK_THAT(msg, Contains("good.h5") && Contains("'ids'") && Contains("'b' twice"));
  }
  SECTION("a length out of range") {
    std::vector<int> lengths = {12, 1, 13, 12, 3};
    {
      H5Patch p(good);
      p.overwrite("lengths", H5T_NATIVE_INT, lengths.data());
    }
    CHECK_THAT(user_error_of([&] { read_motion_file(good); }), Contains("good.h5") && Contains("'lengths'"));
  }
  SECTION("non-zero padding") {
    MotionSet bad = m;
    bad.at(1, 5, 0)[0] = 1.0f;  // clip 1 has length 1
    {
      H5Patch p(good);
      p.overwrite("joints", H5T_NATIVE_FLOAT, bad.joints.data());
    }
    CHECK_THAT(user_error_of([&] { read_motion_file(good); }), Contains("good.h5") && Contains("padding"));
  }
  SECTION("a clip without captions") {
    std::vector<int64_t> offsets = {0, 2, 2, 6, 10, 11};  // clip 1 loses its 3 captions
    {
      H5Patch p(good);
      p.overwrite("captions/offsets", H5T_NATIVE_INT64, offsets.data());
    }
    CHECK_THAT(user_error_of([&] { read_motion_file(good); }),
               Contains("good.h5") && Contains("'captions/offsets'") && Contains("clip 1"));
  }
  SECTION("an unknown split") {
    {
      H5Patch p(good);
      p.overwrite_strings("split", {"train", "val", "test", "training", "sample"});
    }
    CHECK_THAT(user_error_of([&] { read_motion_file(good); }), Contains("good.h5") && Contains("'split'"));
  }
  SECTION("a missing dataset") {
    {
      H5Patch p(good);
      p.remove("lengths");
    }
    CHECK_THAT(user_error_of([&] { read_motion_file(good); }),
               Contains("good.h5") && Contains("'lengths'") && Contains("missing"));
  }
  SECTION("an HDF5 file of another kind") {
    hid_t f = H5Fcreate(dir.file("other.h5").c_str(), H5F_ACC_TRUNC, H5P_DEFAULT, H5P_DEFAULT);
    H5Fclose(f);
    CHECK_THAT(user_error_of([&] { read_motion_file(dir.file("other.h5")); }),
               Contains("other.h5") && Contains("'format'"));
  }
  SECTION("skeleton datasets contradicting the yaml attribute") {
    std::vector<int> parents(22, 0);
    parents[0] = -1;
    {
      H5Patch p(good);
      p.overwrite("skeleton/parents", H5T_NATIVE_INT, parents.data());
    }
    CHECK_THAT(user_error_of([&] { read_motion_file(good); }),
               Contains("good.h5") && Contains("'skeleton/parents'"));
  }
}

TEST_CASE("a skeleton without the yaml attribute is rebuilt from its datasets", "[data][io]") {
  ScratchDir dir;
  MotionSet m = full_motion_set();
  write_motion_file(dir.file("set.h5"), m);
  hid_t f = H5Fopen(dir.file("set.h5").c_str(), H5F_ACC_RDWR, H5P_DEFAULT);
  REQUIRE(H5Adelete_by_name(f, "skeleton", "yaml", H5P_DEFAULT) >= 0);
  H5Fclose(f);
  seal_h5_file(dir.file("set.h5"), "edited test file");  // edited on purpose
  MotionSet back = read_motion_file(dir.file("set.h5"));
  CHECK(back.skeleton.name == "humanml3d22");
  CHECK(back.skeleton.joint_names == m.skeleton.joint_names);
  CHECK(back.skeleton.parents == m.skeleton.parents);
  CHECK(back.skeleton.bone_lengths == m.skeleton.bone_lengths);
  CHECK(back.skeleton.roles.empty());  // roles live only in the yaml
}

TEST_CASE("a failed write leaves no file behind and keeps the old one", "[data][io]") {
  ScratchDir dir;
  const std::string path = dir.file("set.h5");
  MotionSet m = full_motion_set();

  SECTION("invalid set: nothing is written") {
    MotionSet bad = m;
    bad.at(0, 0, 0)[2] = std::numeric_limits<float>::infinity();
    CHECK_THAT(user_error_of([&] { write_motion_file(path, bad); }), Contains("set.h5") && Contains("'joints'"));
    CHECK(dir.entries().empty());
  }
  SECTION("an existing file survives a failed overwrite") {
    write_motion_file(path, m);
    auto before = file_bytes(path);
    MotionSet bad = m;
    bad.ids[4] = bad.ids[0];
    CHECK_THAT(user_error_of([&] { write_motion_file(path, bad); }), Contains("'ids'"));
    CHECK(file_bytes(path) == before);
    CHECK(dir.entries() == std::vector<std::string>{"set.h5"});
  }
  SECTION("the rename fails: the temporary is removed") {
    fs::create_directories(dir.path() / "taken" / "inside");  // a non-empty directory cannot be replaced
    CHECK_THAT(user_error_of([&] { write_motion_file(dir.file("taken"), m); }), Contains("taken"));
    CHECK(dir.entries() == std::vector<std::string>{"taken"});
  }
}

TEST_CASE("check rejects inconsistent in-memory sets", "[data][io]") {
  MotionSet m = full_motion_set();
  m.check("ok");
  SECTION("per-clip arrays of the wrong size") {
    m.captions.pop_back();
    CHECK_THAT(user_error_of([&] { m.check("src"); }), Contains("src") && Contains("'captions'"));
  }
  SECTION("joints buffer not matching N x T x J x 3") {
    m.joints.resize(m.joints.size() - 3);
    CHECK_THAT(user_error_of([&] { m.check("src"); }), Contains("'joints'"));
  }
  SECTION("stats with the wrong shape") {
    m.stats->joint_std = {1.0f, 1.0f};
    CHECK_THAT(user_error_of([&] { m.check("src"); }), Contains("stats/joint_std"));
  }
  SECTION("a vocabulary without the special tokens (converter 1.0's sorted word list)") {
    m.vocab = {"person", "walks"};
    CHECK_THAT(user_error_of([&] { m.check("src"); }),
               Contains("src") && Contains("<pad>") && Contains("humanml3d_to_h5.py"));
  }
  SECTION("an empty caption list") {
    m.captions[2].clear();
    CHECK_THAT(user_error_of([&] { m.check("src"); }), Contains("clip 2"));
  }
  SECTION("clear_padding repairs non-zero padding") {
    m.at(1, 4, 3)[0] = 2.0f;
    CHECK_THAT(user_error_of([&] { m.check("src"); }), Contains("padding"));
    m.clear_padding();
    m.check("src");
    CHECK(m.at(1, 4, 3)[0] == 0.0f);
  }
}

TEST_CASE("split indices and subsets keep clips intact", "[data]") {
  MotionSet m = full_motion_set();
  CHECK(m.indices_of_split("train") == std::vector<size_t>{0, 3});
  CHECK(m.indices_of_split("sample") == std::vector<size_t>{4});
  CHECK(m.indices_of_split("nothing").empty());

  MotionSet s = m.subset({3, 1});
  REQUIRE(s.size() == 2);
  CHECK(s.ids == std::vector<std::string>{"clip3", "clip1"});
  CHECK(s.lengths == std::vector<int>{12, 1});
  CHECK(s.labels == std::vector<std::string>{"jump", ""});
  CHECK(s.captions[1] == m.captions[1]);
  CHECK(s.t_max == m.t_max);
  CHECK(same_stats(s.stats, m.stats));
  CHECK(s.vocab == m.vocab);
  for (int t = 0; t < m.t_max; ++t)
    for (int j = 0; j < 22; ++j)
      for (int a = 0; a < 3; ++a) REQUIRE(s.at(0, t, j)[a] == m.at(3, t, j)[a]);
  s.check("subset");
  CHECK_THROWS_AS(m.subset({5}), std::out_of_range);
}
