// Issue 16, the result files: metrics.h5 (eval/evaluation.cpp), a row's samples.h5
// (experiments/paired.cpp) and examples.h5 (experiments/row_runner.cpp) and results.h5 (experiments/report.cpp) are sealed like
// motion files (core/h5_seal.h). Each kind round-trips; a changed byte anywhere past
// the seal block, or a truncation, is refused naming the file and what to do; a damaged
// row cache is a cache miss (read_cached_row_records) rather than a failed row; files
// written before seals (the user block zeroed, or none at all: the committed
// results/archive/standard_2026-11-28/results.h5) are still read, under crash isolation.
#include <catch2/catch.hpp>

#include <H5Cpp.h>

#include <cmath>
#include <fstream>

#include "core/error.h"
#include "core/h5_seal.h"
#include "eval/eval_outputs.h"
#include "eval/evaluation.h"
#include "data/motion_set.h"
#include "data/skeleton.h"
#include "experiments/experiment.h"
#include "experiments/paired.h"
#include "experiments/report.h"
#include "test_util.h"

using namespace mc;
using namespace mc::test;
using Catch::Matchers::Contains;

namespace {

// Whole files as bytes: slurp (test_util.h) reads them, put_bytes writes them back.
void put_bytes(const fs::path& p, const std::string& b) { std::ofstream(p, std::ios::binary | std::ios::trunc) << b; }

// Flips one bit of `stride`-spaced bytes past the seal block, one at a time, and
// checks `read` refuses each with a message holding every fragment; then a
// truncation; the file is restored afterwards. Returns how many flips were tried.
template <class Read>
int check_flips_refused(const fs::path& file, int flips, Read read, const std::vector<std::string>& fragments) {
  const std::string good = slurp(file);
  REQUIRE(good.size() > kH5SealBlock);
  const size_t stride = std::max<size_t>(1, (good.size() - kH5SealBlock) / flips);
  int tried = 0;
  for (size_t pos = kH5SealBlock; pos < good.size(); pos += stride, ++tried) {
    std::string bad = good;
    bad[pos] = static_cast<char>(bad[pos] ^ 0x04);
    put_bytes(file, bad);
    const std::string msg = user_error_of(read);
    INFO("byte " << pos << " of " << good.size() << ": " << msg);
    CHECK_THAT(msg, Contains("damaged"));
    for (const auto& f : fragments) CHECK_THAT(msg, Contains(f));
  }
  put_bytes(file, good.substr(0, good.size() - 9));
  const std::string msg = user_error_of(read);
  CHECK_THAT(msg, Contains("truncated"));
  for (const auto& f : fragments) CHECK_THAT(msg, Contains(f));
  put_bytes(file, good);
  return tried;
}

// What a file looks like to a reader when written before seals: no seal in the
// first 512 bytes (libhdf5 still finds the superblock after the user block).
void drop_seal(const fs::path& file) {
  std::string b = slurp(file);
  std::fill(b.begin(), b.begin() + kH5SealBlock, '\0');
  put_bytes(file, b);
  REQUIRE(check_h5_seal(file.string(), "test file") == H5Seal::absent);
}

std::map<std::string, std::vector<double>> some_values() {
  return {{"fid", {1.25, 1.5, 1.75}},
          {"control_error@family=root3d/K=8", {0.1, 0.2, 0.3}},
          {"foot_skating", {0.05, 0.0625, 0.075}}};
}

RowSamples some_samples() {
  RowSamples s;
  s.task_ids = {"0|a", "1|b", "2|c"};
  s.groups = {"K=2", "family=x/K=8", ""};
  for (int r = 0; r < 2; ++r) {
    s.motion.push_back(Embeddings::Constant(3, 4, 0.5 + r));
    s.text.push_back(Embeddings::Constant(3, 4, -0.25 * r));
    s.seeds.push_back(1 + 1000 * r);
    s.metrics.push_back({{"avg_err", {0.1, std::nan(""), 0.3 + r}}, {"control_error@K=2", {1, 2, 3}}});
  }
  return s;
}

TableResult some_table(const std::string& id, double shift) {
  TableResult t;
  t.spec.table.id = id;
  t.spec.table.title = "synthetic " + id;
  t.spec.table.columns = {"fid", "control_error"};
  t.num_samples = 4;
  t.repeats = 2;
  t.run.commit = "abc123";
  t.run.date = "2026-01-01T00:00:00.000Z";
  t.run.threads = 1;
  t.run.settings = {{"profile.num_samples", "4"}, {"data_sha1", "0123"}};
  for (const char* row : {"gt", "projflow"}) {
    RowResult r;
    r.row_id = row;
    r.label = std::string("label ") + row;
    r.values = {{"fid", {1 + shift, 2 + shift}}, {"control_error", {0.5 * shift, 0.25}}};
    t.rows.push_back(r);
    RowConfig rc;
    rc.id = row;
    t.spec.rows.push_back(rc);
  }
  return t;
}

}  // namespace

TEST_CASE("metrics.h5 is sealed: round trip, a changed byte refused naming the file and the fix, legacy read",
          "[eval][robust][io]") {
  TempDir dir("seal_metrics");
  const fs::path file = dir.path / "metrics.h5";
  write_metric_results(dir.path.string(), some_values());
  CHECK(check_h5_seal(file.string(), "metrics file") == H5Seal::valid);
  CHECK(slurp(file).rfind("motionctl-h5-seal 1\n", 0) == 0);
  CHECK(read_metric_results(dir.path.string()) == some_values());  // bit for bit

  check_flips_refused(
      file, 29, [&] { read_metric_results(dir.path.string()); },
      {file.string(), "delete the run directory '" + dir.path.string() + "'"});

  // `motionctl eval`'s metrics.h5 with embeddings: the same seal, the same refusal.
  EvalEmbeddings e;
  e.motion = Embeddings::Constant(3, 2, 0.5);
  e.text = Embeddings::Constant(3, 2, -1.0);
  e.gt_motion = Embeddings::Constant(4, 2, 2.0);
  e.captions = {"a", "b", "c"};
  EvalSampleRecord rec;
  rec.embeddings = &e;
  rec.ids = {"x", "y", "z"};
  rec.reference_ids = {"g0", "g1", "g2", "g3"};
  rec.lengths = {10, 11, 12};
  rec.metrics["matching"] = {0.5, 0.25, 0.125};
  std::map<std::string, Replicated> summaries;
  for (auto& [k, v] : some_values()) summaries[k] = summarize(v);
  write_eval_results(dir.path.string(), some_values(), summaries, rec);
  CHECK(check_h5_seal(file.string(), "metrics file") == H5Seal::valid);
  CHECK(read_eval_embeddings(dir.path.string()).gt_motion.isApprox(e.gt_motion));
  check_flips_refused(file, 13, [&] { read_eval_embeddings(dir.path.string()); }, {file.string()});

  // Written before seals: read as before, through the crash-isolated probe.
  drop_seal(file);
  CHECK(read_metric_results(dir.path.string()) == some_values());
  CHECK(read_eval_embeddings(dir.path.string()).captions == e.captions);
  // An unsealed file libhdf5 cannot make sense of is exit 2 naming it, not a crash.
  std::string b = slurp(file);
  std::fill(b.begin() + kH5SealBlock, b.begin() + kH5SealBlock + 64, '\x5a');  // the superblock
  put_bytes(file, b);
  CHECK_THAT(user_error_of([&] { read_metric_results(dir.path.string()); }),
             Contains(file.string()) && Contains("delete the run directory"));
  fs::remove(file);
  CHECK_THAT(user_error_of([&] { read_metric_results(dir.path.string()); }),
             Contains(file.string()) && Contains("does not exist"));
}

TEST_CASE("samples.h5 is sealed, and a damaged row cache is a cache miss naming the file", "[experiments][robust][io]") {
  TempDir dir("seal_samples");
  const fs::path samples = dir.path / "samples.h5", metrics = dir.path / "metrics.h5";
  const RowSamples s = some_samples();
  write_row_samples(samples.string(), s);
  write_metric_results(dir.path.string(), some_values());
  CHECK(check_h5_seal(samples.string(), "per-sample record") == H5Seal::valid);
  RowSamples back = read_row_samples(samples.string());
  CHECK(back.task_ids == s.task_ids);
  CHECK(back.groups == s.groups);
  CHECK(back.seeds == s.seeds);
  REQUIRE(back.replicates() == 2);
  CHECK(back.motion[1] == s.motion[1]);
  CHECK(std::isnan(back.metrics[0].at("avg_err")[1]));

  check_flips_refused(
      samples, 29, [&] { read_row_samples(samples.string()); },
      {samples.string(), "delete the row's run directory '" + dir.path.string() + "'", "re-run reproduce"});

  // The replay's cache: both files intact -> read; either one damaged -> not usable,
  // saying which file, with nothing half-read.
  CachedRowRecords ok = read_cached_row_records(dir.path.string());
  REQUIRE(ok.usable());
  CHECK(ok.values == some_values());
  CHECK(ok.samples.task_ids == s.task_ids);
  for (const fs::path& file : {metrics, samples}) {
    const std::string good = slurp(file);
    std::string bad = good;
    bad[good.size() / 2] = static_cast<char>(bad[good.size() / 2] ^ 0x01);
    put_bytes(file, bad);
    CachedRowRecords c = read_cached_row_records(dir.path.string());
    INFO(c.damage);
    CHECK_FALSE(c.usable());
    CHECK_THAT(c.damage, Contains(file.string()) && Contains("damaged"));
    CHECK(c.values.empty());
    CHECK(c.samples.empty());
    put_bytes(file, good);
  }
  fs::remove(samples);
  CHECK_THAT(read_cached_row_records(dir.path.string()).damage, Contains("samples.h5") && Contains("does not exist"));

  // Written before seals (the 56 rows cached under runs/standard_rows): still a cache hit.
  write_row_samples(samples.string(), s);
  drop_seal(samples);
  drop_seal(metrics);
  CachedRowRecords legacy = read_cached_row_records(dir.path.string());
  INFO(legacy.damage);
  REQUIRE(legacy.usable());
  CHECK(legacy.values == some_values());
  CHECK(legacy.samples.text[1] == s.text[1]);
}

TEST_CASE("results.h5 is sealed: kept tables round-trip, a changed byte is exit 2 naming the file, legacy read",
          "[experiments][robust][io]") {
  TempDir dir("seal_results");
  const fs::path first = dir.path / "first.h5", merged = dir.path / "results.h5";
  ClaimCheck claim;
  claim.id = "a_exact";
  claim.table = "t/a";
  claim.text = "A exact";
  claim.verdict = "holds";
  write_results_h5(first.string(), {some_table("t/a", 0.5), some_table("t/b", 1.5)}, "ci", nullptr, {}, {claim});
  CHECK(check_h5_seal(first.string(), "results file") == H5Seal::valid);
  StoredResults stored = read_results_h5(first.string());
  REQUIRE(stored.tables.size() == 2);
  REQUIRE(stored.find("t/b"));
  CHECK(stored.find("t/b")->rows.at(1).values.at("fid") == std::vector<double>{2.5, 3.5});
  CHECK(stored.find("t/a")->run.settings == some_table("t/a", 0).run.settings);
  REQUIRE(stored.claim("a_exact"));
  CHECK(stored.claim("a_exact")->verdict == "holds");

  // A partial replay's merge: t/a re-run, t/b kept from the sealed earlier file, sealed anew.
  write_results_h5(merged.string(), {some_table("t/a", 2.5), *stored.find("t/b")}, "ci", nullptr, {}, {claim},
                   first.string());
  CHECK(check_h5_seal(merged.string(), "results file") == H5Seal::valid);
  StoredResults m = read_results_h5(merged.string());
  REQUIRE(m.find("t/a"));
  REQUIRE(m.find("t/b"));
  CHECK(m.find("t/a")->rows.at(0).values.at("fid") == std::vector<double>{3.5, 4.5});
  CHECK(m.find("t/b")->rows.at(0).values.at("fid") == std::vector<double>{2.5, 3.5});

  check_flips_refused(
      merged, 37, [&] { read_results_h5(merged.string()); },
      {merged.string(), "earlier replay's results", "omit --tables"});

  // Written before seals: read through the probe, which copies every object a partial
  // replay may copy.
  drop_seal(merged);
  CHECK(read_results_h5(merged.string()).find("t/b")->rows.at(0).values.at("fid") == std::vector<double>{2.5, 3.5});

  // The committed results/archive/standard_2026-11-28/results.h5 (written with no user block
  // at all, before claims were stored in it): all 11 tables with their rows.
  const fs::path committed =
      fs::path(MOTIONCTL_SOURCE_DIR) / "results" / "archive" / "standard_2026-11-28" / "results.h5";
  REQUIRE(fs::exists(committed));
  StoredResults old = read_results_h5(committed.string());
  CHECK(old.tables.size() >= 10);
  for (const auto& tab : old.tables) CHECK_FALSE(tab.rows.empty());
}

TEST_CASE("results.h5: a row's unreadable examples.h5 is exit 2 naming it, and nothing is written",
          "[experiments][robust][io]") {
  TempDir dir("seal_examples");
  const fs::path row_dir = dir.path / "rows" / "gt-123", out = dir.path / "results.h5";
  fs::create_directories(row_dir);
  TableResult t = some_table("t/a", 0);
  t.rows[0].run_dir = row_dir.string();
  // Good examples are copied (at most kExamplesInResults samples)...
  {
    H5::H5File f((row_dir / "examples.h5").string(), H5F_ACC_TRUNC);
    hsize_t n = 3;
    std::vector<int32_t> lengths = {5, 6, 7};
    f.createDataSet("lengths", H5::PredType::NATIVE_INT32, H5::DataSpace(1, &n))
        .write(lengths.data(), H5::PredType::NATIVE_INT32);
  }
  write_results_h5(out.string(), {t}, "ci");
  {
    H5::H5File f(out.string(), H5F_ACC_RDONLY);
    CHECK(f.openDataSet("/examples/t|a/gt/lengths").getSpace().getSimpleExtentNpoints() == 2);
  }
  // ... a damaged one stops the write before results.h5 is replaced.
  const std::string before = slurp(out);
  put_bytes(row_dir / "examples.h5", "not an HDF5 file, but long enough to look like one might");
  CHECK_THAT(user_error_of([&] { write_results_h5(out.string(), {t}, "ci"); }),
             Contains((row_dir / "examples.h5").string()) && Contains("delete the row's run directory"));
  CHECK(slurp(out) == before);
}

TEST_CASE("examples.h5 is sealed: round trip into results.h5, a changed byte refused naming the file",
          "[experiments][robust][io]") {
  TempDir dir("seal_examples_writer");
  const fs::path row_dir = dir.path / "rows" / "projflow-456", out = dir.path / "results.h5";
  fs::create_directories(row_dir);
  const fs::path examples = row_dir / "examples.h5";
  MotionSet gen;
  gen.skeleton = humanml3d_skeleton();
  gen.t_max = 6;
  const int J = gen.num_joints();
  std::vector<ControlTask> tasks(3);
  for (int i = 0; i < 3; ++i) {
    gen.lengths.push_back(4 + i);
    tasks[i].id = fmt::format("clip{}", i);
    tasks[i].caption = fmt::format("a person walks {} steps", i);
    tasks[i].length = 4 + i;
  }
  gen.joints.resize(3 * gen.clip_stride());
  for (size_t k = 0; k < gen.joints.size(); ++k) gen.joints[k] = 0.001f * static_cast<float>(k % 977);
  write_examples(examples.string(), gen, tasks, 2);
  CHECK(check_h5_seal(examples.string(), "row examples file") == H5Seal::valid);
  CHECK(slurp(examples).rfind("motionctl-h5-seal 1\n", 0) == 0);

  TableResult t = some_table("t/a", 0);
  t.rows[1].run_dir = row_dir.string();
  write_results_h5(out.string(), {t}, "ci");
  {
    H5::H5File f(out.string(), H5F_ACC_RDONLY);
    H5::DataSet d = f.openDataSet("/examples/t|a/projflow/joints");
    hsize_t dims[4];
    REQUIRE(d.getSpace().getSimpleExtentNdims() == 4);
    d.getSpace().getSimpleExtentDims(dims);
    CHECK(dims[0] == 2);
    CHECK(dims[1] == 6);
    CHECK(dims[2] == static_cast<hsize_t>(J));
    std::vector<float> back(dims[0] * dims[1] * dims[2] * 3);
    d.read(back.data(), H5::PredType::NATIVE_FLOAT);
    // Sample i's valid frames are the generated ones; its padding is zero.
    for (size_t i = 0; i < 2; ++i)
      for (size_t k = 0; k < gen.clip_stride(); ++k)
        CHECK(back[i * gen.clip_stride() + k] ==
              (k < static_cast<size_t>(gen.lengths[i]) * J * 3 ? gen.clip(i)[k] : 0.f));
  }
  const std::string good_results = slurp(out);
  check_flips_refused(
      examples, 23, [&] { write_results_h5(out.string(), {t}, "ci"); },
      {examples.string(), "delete the row's run directory '" + row_dir.string() + "'"});
  CHECK(slurp(out) == good_results);  // a refused copy never replaces results.h5
}
