// Issue 16, part B, piece by piece: strict YAML names the line, sealed HDF5 files
// refuse any changed byte before libhdf5 reads them, unsealed ones are read under
// crash isolation, and sizes or thread counts the machine cannot give are refused.
#include <catch2/catch.hpp>

#include <yaml-cpp/yaml.h>

#include <csignal>
#include <fstream>
#include <thread>

#include "core/config.h"
#include "core/error.h"
#include "core/h5_seal.h"
#include "core/isolated.h"
#include "core/job_memory.h"
#include "core/resources.h"
#include "core/yaml_strict.h"
#include "data/motion_set.h"
#include "data/skeleton.h"
#include "test_util.h"

using namespace mc;
using namespace mc::test;
using Catch::Matchers::Contains;

namespace {

std::string bytes_of(const fs::path& p) {
  std::ifstream f(p, std::ios::binary);
  return std::string(std::istreambuf_iterator<char>(f), {});
}

MotionSet small_set() {
  MotionSet m;
  m.skeleton = load_skeleton((fs::path(MOTIONCTL_SOURCE_DIR) / "configs/skeletons/humanml3d22.yaml").string());
  m.t_max = 4;
  for (int i = 0; i < 2; ++i) {
    m.lengths.push_back(3);
    m.ids.push_back("c" + std::to_string(i));
    m.splits.push_back("train");
    m.captions.push_back({"a person walks"});
  }
  m.joints.assign(m.size() * m.clip_stride(), 0.25f);
  m.clear_padding();
  return m;
}

}  // namespace

TEST_CASE("strict YAML: duplicate keys, extra documents and complex keys name the line", "[core][robust]") {
  CHECK_THAT(user_error_of([] { parse_yaml_strict("a: 1\nb:\n  c: 2\n  c: 3\n", "f.yaml"); }),
             Contains("f.yaml:4") && Contains("'c' is given twice") && Contains("line 3"));
  CHECK_THAT(user_error_of([] { parse_yaml_strict("a: 1\n---\nb: 2\n", "f.yaml"); }),
             Contains("f.yaml:3") && Contains("second document"));
  CHECK_THAT(user_error_of([] { parse_yaml_strict("a: 1\n---\n", "f.yaml"); }), Contains("second document"));
  CHECK_THAT(user_error_of([] { parse_yaml_strict("a: 1\n? [x, y]\n: 2\n", "f.yaml"); }),
             Contains("f.yaml:2") && Contains("complex key"));
  CHECK_THAT(user_error_of([] { parse_yaml_strict("a: &x [*x]\n", "f.yaml"); }), Contains("deeper than 64"));
  std::string bomb = "a0: &a0 [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]\n";
  for (int i = 1; i < 7; ++i)
    bomb += fmt::format("a{}: &a{} [*a{}, *a{}, *a{}, *a{}, *a{}, *a{}, *a{}, *a{}, *a{}, *a{}]\n", i, i, i - 1, i - 1,
                        i - 1, i - 1, i - 1, i - 1, i - 1, i - 1, i - 1, i - 1);
  CHECK_THAT(user_error_of([&] { parse_yaml_strict(bomb, "f.yaml"); }), Contains("million"));
  CHECK(parse_yaml_strict("a: 1\nb: [1, 2]\nc: {d: 3}\n", "f.yaml")["c"]["d"].as<int>() == 3);
  CHECK(parse_yaml_strict("---\na: 1\n", "f.yaml")["a"].as<int>() == 1);  // one explicit document is fine
}

TEST_CASE("configs: duplicate keys, bad defaults entries and directories are exit-2 errors", "[core][robust]") {
  TempDir t("strictcfg");
  auto write = [&](const char* name, const char* text) {
    std::ofstream(t.path / name) << text;
    return (t.path / name).string();
  };
  CHECK_THAT(user_error_of([&] { compose_config(write("dup.yaml", "x: 1\nx: 2\n")); }),
             Contains("dup.yaml:2") && Contains("twice"));
  CHECK_THAT(user_error_of([&] { compose_config(write("dl.yaml", "defaults:\n  - data: [a, b]\n")); }),
             Contains("dl.yaml:2") && Contains("names a list"));
  CHECK_THAT(user_error_of([&] { compose_config(write("dm.yaml", "defaults:\n  - [a]\n")); }),
             Contains("dm.yaml:2") && Contains("defaults entries"));
  CHECK_THAT(user_error_of([&] { compose_config(t.path.string()); }), Contains("is a directory"));
  CHECK_THAT(user_error_of([&] { compose_config(write("ok.yaml", "x: 1\n"), {"x={[1]: 2}"}); }),
             Contains("complex key"));
}

TEST_CASE("sealed motion files: any changed byte is refused before libhdf5 reads it", "[core][robust][io]") {
  TempDir t("seal");
  const auto path = (t.path / "m.h5").string();
  write_motion_file(path, small_set());
  CHECK(check_h5_seal(path, "motion file") == H5Seal::valid);
  CHECK(bytes_of(path).rfind("motionctl-h5-seal 1\n", 0) == 0);
  const std::string good = bytes_of(path);

  // Every position past the seal block: a sample of them, each flip refused.
  for (size_t pos = kH5SealBlock; pos < good.size(); pos += good.size() / 37) {
    std::string bad = good;
    bad[pos] = static_cast<char>(bad[pos] ^ 0x10);
    std::ofstream(path, std::ios::binary | std::ios::trunc) << bad;
    INFO("byte " << pos);
    CHECK_THAT(user_error_of([&] { read_motion_file(path); }), Contains("m.h5") && Contains("damaged"));
  }
  std::ofstream(path, std::ios::binary | std::ios::trunc) << good.substr(0, good.size() - 7);
  CHECK_THAT(user_error_of([&] { read_motion_file(path); }), Contains("truncated"));

  // Without a seal (an older file, or h5py's) it is read as before.
  std::string unsealed = good;
  std::fill(unsealed.begin(), unsealed.begin() + kH5SealBlock, '\0');
  std::ofstream(path, std::ios::binary | std::ios::trunc) << unsealed;
  CHECK(check_h5_seal(path, "motion file") == H5Seal::absent);
  CHECK(read_motion_file(path).size() == 2);
}

TEST_CASE("isolated_probe turns a crash, a hang or an exception in the child into a UserError", "[core][robust]") {
  isolated_probe("nothing", [] {});
  CHECK_THAT(user_error_of([] { isolated_probe("file 'x.h5'", [] { std::raise(SIGSEGV); }); }),
             Contains("file 'x.h5'") && Contains("crashed"));
  CHECK_THAT(user_error_of([] { isolated_probe("x", [] { fail("the child's own message"); }); }),
             Contains("the child's own message"));
  CHECK_THAT(user_error_of([] { isolated_probe("x", [] { throw std::bad_alloc(); }); }), Contains("more memory"));
  CHECK_THAT(user_error_of([] {
               isolated_probe("file 'slow.h5'", [] { std::this_thread::sleep_for(std::chrono::seconds(30)); }, 0.5);
             }),
             Contains("slow.h5") && Contains("did not finish"));
}

TEST_CASE("sizes and thread counts the machine cannot give are refused naming the key", "[core][robust]") {
  CHECK(available_memory_bytes() > 0);
  require_memory(1e6L, "a small thing", "", "");
  CHECK_THAT(user_error_of([] { require_memory(1e18L, "the fixture", "fixture.num_clips=1e12", "lower it"); }),
             Contains("fixture.num_clips") && Contains("available") && Contains("lower it"));
  check_thread_count(0, "run.threads");
  check_thread_count(usable_cpus(), "run.threads");
  CHECK_THAT(user_error_of([] { check_thread_count(4096, "run.threads"); }),
             Contains("run.threads=4096") && Contains("CPU"));
}

TEST_CASE("memory estimates of generate, sample, eval and reproduce: what runs today fits, absurd sizes do not",
          "[core][robust]") {
  // The standard profile: 32 samples x 3 replicates of 196 frames and 22 joints;
  // eval's 20 resamples; a full replay of every table (86 rows, ~10 columns).
  const long double gen = generated_motions_bytes(32, 196, 22);
  CHECK(gen == 32.0L * 196 * 22 * 3 * 4 * 4);  // float32 xyz, four copies
  CHECK(gen < 1e7L);
  require_memory(gen, "generate", "", "");
  require_memory(generated_motions_bytes(1000, 196, 22), "the paper profile's 1,000 samples", "", "");
  require_memory(replicated_values_bytes(20, 3), "eval", "", "");
  require_memory(replicated_values_bytes(3, 86 * 11), "reproduce", "", "");
  require_memory(replicated_values_bytes(20, 86 * 11), "the paper profile's 20 replicates", "", "");
  // Each formula grows linearly in every size, so the absurd values the commands are
  // tested with (tests/cli/test_fuzz.cpp) are far past any machine's memory.
  CHECK(generated_motions_bytes(2, 2000000000, 22) == 1000000000.0L * generated_motions_bytes(2, 2, 22));
  CHECK(generated_motions_bytes(1, 2000000000, 1) > 9e10L);
  CHECK(replicated_values_bytes(2000000000, 3) > 4.7e10L);
  CHECK_THAT(user_error_of([] {
               require_memory(generated_motions_bytes(8, 2e12L, 22), "this generate job", "custom.length=2e12",
                              "lower custom.length");
             }),
             Contains("custom.length=2e12") && Contains("lower custom.length") && Contains("available"));
}
