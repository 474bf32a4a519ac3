// Seeded fuzzing of the motionctl binary (issue 16): random config overrides,
// byte flips in motion files (sealed and unsealed), byte flips and truncation of a
// checkpoint, and mutated constraint specs. Any input may be refused (exit 2) or
// accepted (exit 0); a crash (signal), an internal error (exit 1), a hang or an
// output file left behind by a failed run fails the test. Every case prints its
// seed and input on failure so it can be replayed by hand. About a minute on two
// idle cores (each run loads libtorch, ~1 s); tagged [fuzz].
#include <catch2/catch.hpp>

#include <algorithm>
#include <random>

#include "core/job_memory.h"
#include "core/resources.h"
#include "test_util.h"

using namespace mc::test;

namespace {

constexpr unsigned kSeed = 16;  // issue 16

std::string slurp_binary(const fs::path& p) {
  std::ifstream f(p, std::ios::binary);
  std::stringstream ss;
  ss << f.rdbuf();
  return ss.str();
}

struct FuzzResult {
  int status = 0;  // exit code, or 128 + signal, or 124 for a time-out (timeout(1)'s codes)
  std::string output;
};

// Runs motionctl under timeout(1), so a hang ends as 124 and a crash as 128 + signal.
FuzzResult run_fuzzed(const std::string& args, int timeout_s = 120) {
  std::string cmd = fmt::format("cd '{}' && CI=1 OMP_NUM_THREADS=1 timeout -s KILL {} '{}' {} 2>&1; echo \"@status=$?\"",
                                MOTIONCTL_SOURCE_DIR, timeout_s, MOTIONCTL_BINARY, args);
  FuzzResult r;
  FILE* p = ::popen(cmd.c_str(), "r");
  char buf[4096];
  size_t n;
  while ((n = fread(buf, 1, sizeof buf, p)) > 0) r.output.append(buf, n);
  ::pclose(p);
  auto at = r.output.rfind("@status=");
  r.status = at == std::string::npos ? -1 : std::atoi(r.output.c_str() + at + 8);
  return r;
}

std::string quote(const std::string& s) {
  std::string q = "'";
  for (char c : s) q += c == '\'' ? std::string("'\\''") : std::string(1, c);
  return q + "'";
}

// Exit 0 or 2 only; no temporary or partial files in `dir`; `output` exists only
// after a success.
void check_outcome(const FuzzResult& r, const std::string& what, const fs::path& dir = {},
                   const fs::path& output = {}) {
  INFO("seed " << kSeed << ": " << what << "\n" << r.output);
  CHECK((r.status == 0 || r.status == 2));
  if (!dir.empty())
    for (auto& e : fs::directory_iterator(dir)) CHECK(e.path().filename().string().find(".tmp") == std::string::npos);
  if (!output.empty() && r.status != 0) CHECK_FALSE(fs::exists(output));
}

std::string nasty_value(std::mt19937& rng) {
  static const std::vector<std::string> values = {
      "-1", "0", "1", "2", "0.5", "1e308", "-1e308", "1e999", "nan", ".inf", "9999999999", "2000000000", "abc",
      "''", "~", "[1,2]", "[]", "{a: 1}", "{}", "'[1, {b: [2]}]'", "true", "'a: 1'", "'? [a]'", "'&x [*x]'",
      "'x\n---\ny'", "'['", "'}'", "'!!binary AAAA'", "'a: 1\na: 2'", "-0", "0x10", "1_000", "'  '", "/", "/dev/null",
      "..", "configs", "4096", "100000"};
  return values[rng() % values.size()];
}

// Builds one small sealed fixture in `dir` (shared by the motion-file and spec cases).
fs::path tiny_fixture(const fs::path& dir) {
  auto path = dir / "tiny.h5";
  auto r = run_fuzzed(fmt::format("fixture configs/data/smoke.yaml output={} fixture.num_clips=4 fixture.max_frames=60",
                                  path.string()));
  INFO(r.output);
  REQUIRE(r.status == 0);
  return path;
}

}  // namespace

TEST_CASE("fuzz: random config overrides never crash, exit 1 or leave partial files", "[fuzz][cli]") {
  TempDir t("fuzzcfg");
  std::mt19937 rng(kSeed);
  const std::vector<std::string> train_keys = {
      "run.seed", "run.threads", "run.device", "run.name", "run.root", "data.path", "data.window", "model.width",
      "model.latent", "model.down_stages", "model.res_depth", "model.type", "optim.lr", "optim.batch_size",
      "optim.steps", "model", "data", "run", "a.b.c", "model.width.x", "defaults", "optim.warmup"};
  const std::vector<std::string> fixture_keys = {
      "fixture.seed", "fixture.t_max", "fixture.min_frames", "fixture.max_frames", "fixture.train_fraction",
      "fixture.captions_per_clip", "fixture.weight_locomotion", "fixture.max_travel", "fixture.idle_noise",
      "skeleton", "fixture", "fixture.num_clips", "fixture.val_fraction"};
  // Validation only for training configs (`config` resolves and checks, never trains).
  for (int i = 0; i < 10; ++i) {
    std::string ov = train_keys[rng() % train_keys.size()] + "=" + nasty_value(rng);
    auto r = run_fuzzed("config configs/train/autoencoder_smoke.yaml " + quote(ov));
    check_outcome(r, "config override " + ov);
  }
  // The fixture is built for real (4 clips), so outputs are checked too.
  const fs::path out = t.path / "fx.h5";
  for (int i = 0; i < 8; ++i) {
    std::string ov = fixture_keys[rng() % fixture_keys.size()] + "=" + nasty_value(rng);
    auto r = run_fuzzed(fmt::format("fixture configs/data/smoke.yaml output={} fixture.num_clips=4 {}", out.string(),
                                    quote(ov)));
    check_outcome(r, "fixture override " + ov, t.path, out);
    fs::remove(out);
  }
}

TEST_CASE("fuzz: byte flips in motion files are refused or harmless, never a crash", "[fuzz][cli]") {
  TempDir t("fuzzh5");
  const fs::path good = tiny_fixture(t.path);
  const std::string bytes = slurp_binary(good);
  std::mt19937 rng(kSeed + 1);
  // Global heaps (variable-length strings, where the reported crashes were) and the
  // first 4 KB (superblock, root object headers) are where damage hurts libhdf5.
  std::vector<size_t> heaps;
  for (size_t at = bytes.find("GCOL"); at != std::string::npos; at = bytes.find("GCOL", at + 1)) heaps.push_back(at);
  auto pick = [&](int k) -> size_t {
    if (k % 3 == 0 && !heaps.empty()) return heaps[rng() % heaps.size()] + rng() % 4096;
    if (k % 3 == 1) return rng() % 4096;
    return rng() % bytes.size();
  };
  for (bool sealed : {true, false}) {
    std::string base = bytes;
    // Without its seal the file is read as an older or foreign one: in a child process.
    if (!sealed) std::fill(base.begin(), base.begin() + 512, '\0');
    for (int k = 0; k < (sealed ? 5 : 12); ++k) {
      std::string damaged = base;
      const size_t pos = std::min(pick(k), damaged.size() - 1);
      const int mask = 1 + static_cast<int>(rng() % 255);
      damaged[pos] = static_cast<char>(damaged[pos] ^ mask);
      const fs::path f = t.path / "damaged.h5";
      std::ofstream(f, std::ios::binary) << damaged;
      auto r = run_fuzzed("score " + f.string());
      check_outcome(r, fmt::format("{} motion file, byte {} ^= {:#x}", sealed ? "sealed" : "unsealed", pos, mask));
      // A sealed file with a changed byte after its seal block is always refused.
      if (sealed && pos >= 512) CHECK(r.status == 2);
    }
  }
  // Truncation.
  for (size_t keep : {size_t(100), size_t(600), bytes.size() / 2, bytes.size() - 1}) {
    const fs::path f = t.path / "short.h5";
    std::ofstream(f, std::ios::binary) << bytes.substr(0, keep);
    auto r = run_fuzzed("score " + f.string());
    check_outcome(r, fmt::format("motion file truncated to {} bytes", keep));
    CHECK(r.status == 2);
  }
}

TEST_CASE("fuzz: damaged checkpoints are refused or harmless, never a crash", "[fuzz][cli]") {
  TempDir t("fuzzckpt");
  const fs::path shipped = fs::path(MOTIONCTL_SOURCE_DIR) / "pretrained/prior/flow_tiny-fc61388ed1df";
  REQUIRE(fs::exists(shipped / "checkpoints/final.pt"));
  const fs::path run = t.path / "run";
  fs::copy(shipped, run, fs::copy_options::recursive);
  const fs::path ckpt = run / "checkpoints/final.pt";
  const std::string bytes = slurp_binary(ckpt);
  std::mt19937 rng(kSeed + 2);
  const fs::path out = t.path / "out" / "s.h5";
  fs::create_directories(out.parent_path());
  for (int k = 0; k < 6; ++k) {
    std::string damaged = bytes;
    std::string what;
    if (k < 2) {
      const size_t keep = k == 0 ? bytes.size() / 3 : bytes.size() - 30;
      damaged.resize(keep);
      what = fmt::format("checkpoint truncated to {} bytes", keep);
    } else {
      // zip headers and the pickled structure sit at both ends of a torch file
      const size_t pos = k % 2 ? rng() % 2048 : bytes.size() - 1 - rng() % 4096;
      const int mask = 1 + static_cast<int>(rng() % 255);
      damaged[pos] = static_cast<char>(damaged[pos] ^ mask);
      what = fmt::format("checkpoint byte {} ^= {:#x}", pos, mask);
    }
    std::ofstream(ckpt, std::ios::binary | std::ios::trunc) << damaged;
    auto r = run_fuzzed(fmt::format("sample configs/sample/t2m_smoke.yaml prior.run_dir={} texts.from_split= "
                                    "'texts.prompts=[walk]' texts.length=20 sampler.steps=2 output={} run.threads=1",
                                    run.string(), out.string()));
    check_outcome(r, what, out.parent_path(), out);
    fs::remove(out);
  }
}

TEST_CASE("fuzz: mutated constraint specs are refused or scored, never a crash", "[fuzz][cli]") {
  TempDir t("fuzzspec");
  const fs::path motions = tiny_fixture(t.path);
  const std::string base = R"(constraints:
  - {type: keyframe, name: keys, joints: [pelvis, 10], frames: [0, 3], axes: xz, from_source: true}
  - type: trajectory
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
)";
  const std::vector<std::string> tokens = {"nan", "1e999", "-1", "99999999999", "[[[[", "*a", "&a ", "? ",
                                           "\n---\n", "{", "}", ",", ": ", "- ", "frames: all", "joints: [x]",
                                           "type: loop", "\ntype: keyframe\n", "!!map ", "'", "\"", "|", "\t"};
  std::mt19937 rng(kSeed + 3);
  const fs::path spec = t.path / "spec.yaml";
  for (int k = 0; k < 10; ++k) {
    std::string text = base;
    for (int m = 0, n = 1 + static_cast<int>(rng() % 3); m < n; ++m) {
      const size_t pos = rng() % text.size();
      switch (rng() % 3) {
        case 0: text.insert(pos, tokens[rng() % tokens.size()]); break;
        case 1: text.erase(pos, 1 + rng() % 12); break;
        default: {  // repeat a line (duplicate keys, repeated items)
          size_t a = text.rfind('\n', pos), b = text.find('\n', pos);
          a = a == std::string::npos ? 0 : a + 1;
          if (b != std::string::npos) text.insert(b + 1, text.substr(a, b - a + 1));
        }
      }
    }
    std::ofstream(spec) << text;
    auto r = run_fuzzed(fmt::format("score {} --source {} --constraints {}", motions.string(), motions.string(),
                                    spec.string()));
    check_outcome(r, "constraint spec:\n" + text);
  }
}

// Issue 16: the sizes of the commands outside training (core/job_memory.h). Each
// absurd value is refused with exit 2 naming the key and the estimate, before the
// command trains, loads or allocates anything (so each case takes the binary's
// start-up, no generation) and with nothing written. A machine with more memory than
// the estimate skips that case (the refusal would be wrong there), saying so.
TEST_CASE("generate, sample, eval and reproduce refuse sizes that cannot fit, naming the key", "[cli][robust]") {
  TempDir dir("sizes");
  const std::string fx = shared_smoke_fixture(20), out = (dir.path / "out.h5").string();
  const fs::path runs = dir.path / "runs", results = dir.path / "results";
  struct Case {
    std::string args, key;
    long double estimate;
  };
  const std::vector<Case> cases = {
      {fmt::format("generate configs/control/keyframes_smoke.yaml data.path={} data.num_samples=2 "
                   "custom.length=2000000000 run.root={} output={}",
                   fx, runs.string(), out),
       "custom.length=2000000000", mc::generated_motions_bytes(2, 2e9L, 22)},
      {fmt::format("sample configs/sample/t2m_smoke.yaml texts.from_split= 'texts.prompts=[walk]' "
                   "texts.length=2000000000 output={}",
                   out),
       "texts.length=2000000000", mc::generated_motions_bytes(1, 2e9L, 1)},
      {fmt::format("eval configs/eval/t2m_smoke.yaml eval.reference={} protocol.repeats=2000000000 run.root={}", fx,
                   runs.string()),
       "protocol.repeats=2000000000", mc::replicated_values_bytes(2e9L, 3)},
      {fmt::format("reproduce --profile smoke --tables projflow/table1 --no-figures --set profile.repeats=2000000000 "
                   "--set profile.data={} --set profile.runs_root={} --set profile.results_root={}",
                   fx, runs.string(), results.string()),
       "profile.repeats=2000000000", mc::replicated_values_bytes(2e9L, 2)},
  };
  for (const auto& c : cases) {
    if (static_cast<long double>(mc::available_memory_bytes()) >= c.estimate) {
      WARN("skipped (this machine has the memory): " << c.args);
      continue;
    }
    const bool replay = c.args.rfind("reproduce", 0) == 0;
    auto r = run_fuzzed(c.args + (replay ? " --set profile.threads=1" : " run.threads=1"), 60);
    INFO(c.args << "\n" << r.output);
    CHECK(r.status == 2);
    CHECK(r.output.find(c.key) != std::string::npos);
    CHECK(r.output.find("available") != std::string::npos);
    CHECK(!fs::exists(out));
    CHECK(!fs::exists(runs));
    CHECK(!fs::exists(results));
  }
}
