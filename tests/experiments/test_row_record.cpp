// Cached table rows keyed by the weights they used (experiments/row_record.*): the
// check of a row's record against its components now, over seeded random component
// sets and changes (weights rewritten, the same bytes rewritten, a component added,
// dropped or swapped for another run), the legacy rule (make's rule on DONE times),
// and `motionctl reproduce` end to end: a second replay reuses the row, a component's
// final.pt rewritten in place recomputes it, a legacy row is adopted when its
// components are older and recomputed when one is newer, and the same row under another
// id reuses the finished directory of its key.
#include <catch2/catch.hpp>

#include <yaml-cpp/yaml.h>

#include <random>
#include <regex>
#include <sstream>

#include <fmt/ranges.h>

#include "core/atomic_file.h"
#include "experiments/row_record.h"
#include "train/pretrained.h"
#include "test_util.h"

using namespace mc;
using namespace mc::test;

namespace {

// A finished fake run: checkpoints/final.pt of `bytes`, DONE holding `done`.
void write_run(const fs::path& dir, const std::string& bytes, const std::string& done) {
  fs::create_directories(dir / "checkpoints");
  write_file_atomic(dir / "checkpoints" / "final.pt", bytes);  // a rename: a new inode, as training writes it
  write_file_atomic(dir / "DONE", done + "\n");
}

// Weights of version v: the size differs per version, so no two versions can share the
// (inode, size, mtime) that weights_sha1 caches on even when an inode is reused at once.
std::string weights(std::mt19937& rng, int v) {
  std::string s(1000 + v, '\0');
  for (auto& c : s) c = static_cast<char>(rng());
  return s;
}

std::string iso_time(int minute) { return fmt::format("2026-11-24T{:02d}:{:02d}:00Z", minute / 60, minute % 60); }

RowComponents components_of(const std::vector<std::pair<std::string, fs::path>>& runs) {
  RowComponents c;
  for (const auto& [what, dir] : runs) {
    c.all.push_back({what, dir.string(), "", {}, weights_sha1(dir)});
    c.trained.push_back(dir.string());
  }
  return c;
}

std::string joined(const RowReuse& r) { return fmt::format("{}", fmt::join(r.reasons, "; ")); }

}  // namespace

TEST_CASE("row record: reused while every component keeps its weights, and any change recomputes, naming it",
          "[experiments][row_record]") {
  TempDir t("rowrec");
  std::mt19937 rng(20261124);
  const std::vector<std::string> experiments = {"prior", "tokenizer", "tmd", "adapter"};
  int version = 0;
  for (int trial = 0; trial < 40; ++trial) {
    const fs::path root = t.path / fmt::format("t{}", trial);
    const fs::path row = root / "rows" / "row-abc";
    fs::create_directories(row);
    write_file_atomic(row / "DONE", iso_time(600) + "\n");
    const int n = 1 + static_cast<int>(rng() % 4);
    std::vector<std::pair<std::string, fs::path>> runs;
    for (int i = 0; i < n; ++i) {
      const fs::path dir = root / experiments[i] / fmt::format("{}_tiny-{}", experiments[i], i);
      write_run(dir, weights(rng, ++version), iso_time(static_cast<int>(rng() % 500)));
      runs.push_back({experiments[i], dir});
    }
    const fs::path ev_dir = root / "evaluator" / "ci";
    write_run(ev_dir, weights(rng, ++version), iso_time(0));
    const ResolvedDependency ev = evaluator_component(ev_dir.string(), "evaluator.yaml");
    write_row_record(row, components_of(runs), ev, "test");

    RowComponents now = components_of(runs);
    CHECK(check_row(row, now, ev).state == RowReuse::State::reuse);
    // A moved runs root is the same set (run.root is no part of a run's identity).
    RowComponents moved = now;
    for (auto& d : moved.all) d.run = "/elsewhere/" + run_key(d.run);
    CHECK(check_row(row, moved, ev).state == RowReuse::State::reuse);

    const int k = static_cast<int>(rng() % n);
    const std::string key = run_key(runs[k].second.string());
    const std::string old_sha = now.all[k].sha1;
    INFO("trial " << trial << ", " << n << " components, change to " << key);
    switch (trial % 5) {
      case 0: {  // retrained in place to other weights
        write_run(runs[k].second, weights(rng, ++version), iso_time(700));
        now = components_of(runs);
        const RowReuse r = check_row(row, now, ev);
        CHECK(r.state == RowReuse::State::recompute);
        CHECK(r.reasons.size() == 1);
        CHECK_THAT(joined(r), Catch::Contains(key) && Catch::Contains(old_sha.substr(0, 12)) &&
                                  Catch::Contains(now.all[k].sha1.substr(0, 12)));
        break;
      }
      case 1: {  // the same bytes written again (a new file, a new time): content, not time
        write_run(runs[k].second, read_file(runs[k].second / "checkpoints" / "final.pt"), iso_time(700));
        now = components_of(runs);
        CHECK(now.all[k].sha1 == old_sha);
        CHECK(check_row(row, now, ev).state == RowReuse::State::reuse);
        break;
      }
      case 2: {  // no longer used
        now.all.erase(now.all.begin() + k);
        const RowReuse r = check_row(row, now, ev);
        CHECK(r.state == RowReuse::State::recompute);
        CHECK_THAT(joined(r), Catch::Contains(key) && Catch::Contains("no longer uses"));
        break;
      }
      case 3: {  // one more component
        const fs::path extra = root / "text" / "text_clip-x";
        write_run(extra, weights(rng, ++version), iso_time(1));
        now.all.push_back({"text", extra.string(), "", {}, weights_sha1(extra)});
        const RowReuse r = check_row(row, now, ev);
        CHECK(r.state == RowReuse::State::recompute);
        CHECK_THAT(joined(r), Catch::Contains("text/text_clip-x"));
        break;
      }
      default: {  // another run of the same component (its config changed)
        const fs::path other = runs[k].second.parent_path() / "other-run";
        write_run(other, weights(rng, ++version), iso_time(1));
        now.all[k] = {runs[k].first, other.string(), "", {}, weights_sha1(other)};
        const RowReuse r = check_row(row, now, ev);
        CHECK(r.state == RowReuse::State::recompute);
        CHECK(r.reasons.size() == 1);  // one clause naming both runs, not two
        CHECK_THAT(joined(r), Catch::Contains(key) && Catch::Contains("other-run"));
      }
    }
  }
}

TEST_CASE("row record: the evaluator is recorded, and an unreadable record recomputes the row", "[experiments][row_record]") {
  TempDir t("rowrec_ev");
  std::mt19937 rng(7);
  const fs::path row = t.path / "rows" / "gt-1", ev_dir = t.path / "evaluator" / "ci";
  fs::create_directories(row);
  write_run(ev_dir, weights(rng, 1), iso_time(0));
  const ResolvedDependency ev = evaluator_component(ev_dir.string(), "evaluator.yaml");
  write_row_record(row, {}, ev, "test");
  auto rec = read_dependency_record(row);
  REQUIRE(rec.has_value());
  REQUIRE(rec->size() == 1);
  CHECK(rec->front().what == "evaluator");
  CHECK(rec->front().sha1 == file_sha1(ev_dir / "checkpoints" / "final.pt"));
  CHECK(check_row(row, {}, ev).state == RowReuse::State::reuse);
  write_run(ev_dir, weights(rng, 2), iso_time(1));
  CHECK(check_row(row, {}, evaluator_component(ev_dir.string(), "evaluator.yaml")).state ==
        RowReuse::State::recompute);
  write_file_atomic(row / "dependencies.yaml", "dependencies: 3\n");
  const RowReuse r = check_row(row, {}, ev);
  CHECK(r.state == RowReuse::State::recompute);
  CHECK_THAT(joined(r), Catch::Contains("dependencies.yaml"));
}

TEST_CASE("row record: a legacy row is adopted when every component finished before it, else recomputed",
          "[experiments][row_record]") {
  TempDir t("rowrec_legacy");
  std::mt19937 rng(11);
  int version = 0;
  for (int trial = 0; trial < 60; ++trial) {
    const fs::path root = t.path / fmt::format("t{}", trial), row = root / "rows" / "row-1";
    fs::create_directories(row);
    const int row_done = 300 + static_cast<int>(rng() % 300);
    write_file_atomic(row / "DONE", iso_time(row_done) + "\n");
    const int n = static_cast<int>(rng() % 4);  // 0: a row with no trained component (ground truth)
    std::vector<std::pair<std::string, fs::path>> runs;
    bool newer = false;
    for (int i = 0; i < n; ++i) {
      const int done = static_cast<int>(rng() % 700);  // sometimes after the row
      newer = newer || done > row_done;
      const fs::path dir = root / fmt::format("exp{}", i) / "run";
      write_run(dir, weights(rng, ++version), iso_time(done));
      runs.push_back({fmt::format("exp{}", i), dir});
    }
    RowComponents now = components_of(runs);
    // components.txt lists the generator's own components (the last one resolved, the
    // others being its dependencies), by the paths of the root it ran under; sometimes a
    // run the row resolves to no more.
    std::string listed;
    if (n > 0) listed += "old_root/" + run_key(runs.back().second.string()) + "\n";
    const bool gone = rng() % 4 == 0;
    if (gone) listed += "old_root/exp0/an-older-run\n";
    write_file_atomic(row / "components.txt", listed);
    const fs::path ev_dir = root / "evaluator" / "ci";
    write_run(ev_dir, weights(rng, ++version), iso_time(650));  // later than the row: not checked by time
    const ResolvedDependency ev = evaluator_component(ev_dir.string(), "evaluator.yaml");
    const RowReuse r = check_row(row, now, ev);
    INFO("trial " << trial << ": " << n << " components, a newer one " << newer << ", a listed run gone " << gone
                  << "; " << joined(r));
    if (gone) {
      CHECK(r.state == RowReuse::State::recompute);
      CHECK_THAT(joined(r), Catch::Contains("an-older-run") && Catch::Contains("no longer resolves to"));
    } else if (newer) {
      CHECK(r.state == RowReuse::State::recompute);
      CHECK_THAT(joined(r), Catch::Contains("trained again at"));
    } else {
      CHECK(r.state == (n > 0 ? RowReuse::State::adopt : RowReuse::State::reuse));
      CHECK(r.reasons.empty());
    }
  }
}

namespace {

std::string prior_overrides(const std::string& fx, const std::string& runs, const std::string& sep) {
  return fmt::format("optim.steps=20{0}optim.warmup=2{0}optim.batch_size=8{0}data.path={1}{0}run.root={2}{0}"
                     "run.threads=1",
                     sep, fx, runs);
}

// A reduced profile: its own evaluator (10 steps) and a 20-step flow prior for one
// imputation row; runs and results under `dir`.
fs::path write_row_profile(const fs::path& dir, const std::string& fx) {
  const std::string runs = (dir / "runs").string();
  std::ofstream(dir / "evaluator.yaml")
      << "run: {experiment: evaluator, name: ci, seed: 7, log_every: 10, checkpoint_every: 100, root: " << runs << "}\n"
      << "data: {path: " << fx << ", fixture: '', window: 0}\n"
      << "model: {type: t2m_evaluator, word_dim: 32, text_hidden: 32, movement_dim: 32, motion_hidden: 32, "
         "embed_dim: 32, max_words: 24, margin: 10.0, dropout: 0.0}\n"
      << "optim: {steps: 10, batch_size: 8, lr: 1.0e-3, warmup: 2, schedule: cosine, min_lr_ratio: 0.1, "
         "grad_clip: 1.0, ema_decay: 0.0}\n";
  std::ofstream(dir / "ci.yaml") << "profile:\n  name: ci\n  data: " << fx << "\n  data_fixture: ''\n  evaluator: "
                                 << (dir / "evaluator.yaml").string()
                                 << "\n  split: test\n  num_samples: 4\n  repeats: 1\n  seed: 1\n  threads: 1\n"
                                 << "  health: false\n  substitutions:\n"
                                 << "    - \"generator.prior.overrides=[" << prior_overrides(fx, runs, ", ") << "]\"\n"
                                 << "    - generator.sampler.steps=4\n"
                                 << "  runs_root: " << runs << "\n  results_root: " << (dir / "results").string()
                                 << "\nprotocol: {r_precision_pool: 4, diversity_pairs: 4, multimodality_pairs: 2, "
                                    "control_thresholds: [0.5, 0.2]}\n";
  const fs::path spec = dir / "specs" / "t" / "a.yaml";
  fs::create_directories(spec.parent_path());
  std::ofstream(spec) << "table:\n  id: t/a\n  title: \"rows keyed by weights\"\n"
                      << "  protocol: experiments/protocols/anchors_root_3d.yaml\n"
                      << "  columns: [control_error, fid]\nrows:\n"
                      << "  - {id: imputation, label: Imputation, generator: experiments/generators/imputation.yaml}\n";
  return dir / "ci.yaml";
}

// The one directory under `root` whose name starts with `prefix`.
fs::path find_dir(const fs::path& root, const std::string& prefix) {
  std::vector<fs::path> found;
  for (const auto& e : fs::recursive_directory_iterator(root))
    if (e.is_directory() && e.path().filename().string().rfind(prefix, 0) == 0) found.push_back(e.path());
  REQUIRE(found.size() == 1);
  return found.front();
}

// The `key` line of a run's summary.csv.
std::string summary_line(const fs::path& run, const std::string& key) {
  std::stringstream in(slurp(run / "summary.csv"));
  for (std::string line; std::getline(in, line);)
    if (line.rfind(key + ",", 0) == 0) return line;
  return "<no " + key + ">";
}

std::string recorded_sha(const fs::path& row, const std::string& what) {
  const auto record = read_dependency_record(row);
  if (record)
    for (const auto& d : *record)
      if (d.what == what) return d.sha1;
  return "<not recorded>";
}

}  // namespace

TEST_CASE("reproduce: a cached row is reused while its components keep their weights, recomputed when one changes",
          "[experiments][row_record]") {
  TempDir dir("rowfresh");
  const std::string fx = shared_smoke_fixture(60), runs = (dir.path / "runs").string();
  const fs::path profile = write_row_profile(dir.path, fx);
  auto replay = [&] {
    auto r = run_motionctl(fmt::format("reproduce --profile {} --specs {} --no-figures", profile.string(),
                                       (dir.path / "specs").string()));
    INFO(r.output);
    REQUIRE(r.exit_code == 0);
    return r.output;
  };
  const std::regex cached_line(R"(imputation\s+\(cached\))");

  // (a) Computed once, with a record of the prior and the evaluator; reused by the next replay.
  std::string out = replay();
  CHECK_FALSE(std::regex_search(out, cached_line));
  const fs::path row = find_dir(dir.path / "runs", "imputation-");
  const std::vector<std::string> listed = read_row_components(row);
  REQUIRE(listed.size() == 1);
  const fs::path prior = listed.front();
  CHECK(run_key(prior.string()).rfind("prior/flow_tiny-", 0) == 0);
  const std::string sha0 = recorded_sha(row, "prior");
  CHECK(sha0 == weights_sha1(prior));
  CHECK(recorded_sha(row, "evaluator") == weights_sha1(dir.path / "runs" / "evaluator" / "ci"));
  const std::string fid0 = summary_line(row, "fid");
  out = replay();
  CHECK(std::regex_search(out, cached_line));
  CHECK(out.find("recomputing") == std::string::npos);

  // (b) The prior's final.pt rewritten in place with other weights (a twin trained with
  // another seed): the row is recomputed where it is, its numbers and record change.
  auto twin = run_motionctl(fmt::format("train configs/prior/flow_tiny.yaml {} run.seed=4",
                                        prior_overrides(fx, runs, " ")));
  INFO(twin.output);
  REQUIRE(twin.exit_code == 0);
  fs::path twin_dir;
  for (const auto& e : fs::directory_iterator(prior.parent_path()))
    if (e.path() != prior) twin_dir = e.path();
  REQUIRE(fs::exists(twin_dir / "checkpoints" / "final.pt"));
  write_file_atomic(prior / "checkpoints" / "final.pt", read_file(twin_dir / "checkpoints" / "final.pt"));
  const std::string sha1 = weights_sha1(prior);
  REQUIRE(sha1 != sha0);
  out = replay();
  CHECK_FALSE(std::regex_search(out, cached_line));
  CHECK_THAT(out, Catch::Contains("recomputing it") && Catch::Contains(sha0.substr(0, 12)) &&
                      Catch::Contains(sha1.substr(0, 12)) && Catch::Contains(run_key(prior.string())));
  CHECK(recorded_sha(row, "prior") == sha1);
  CHECK(summary_line(row, "fid") != fid0);
  CHECK(slurp(row / "log.txt").find("recomputing it") != std::string::npos);  // the cleared row's new log says why

  // The same bytes written again (new file, new time): content, not time, so reused.
  write_file_atomic(prior / "checkpoints" / "final.pt", read_file(twin_dir / "checkpoints" / "final.pt"));
  CHECK(std::regex_search(replay(), cached_line));

  // (c) A legacy row (no record): adopted once with a warning when its prior finished
  // before it did, then recorded, so the next replay is silent.
  fs::remove(row / "dependencies.yaml");
  out = replay();
  CHECK(std::regex_search(out, cached_line));
  CHECK_THAT(out, Catch::Contains("warning: row imputation") && Catch::Contains("no record of the weights"));
  REQUIRE(read_dependency_record(row).has_value());
  CHECK(recorded_sha(row, "prior") == sha1);
  out = replay();
  CHECK(std::regex_search(out, cached_line));
  CHECK(out.find("warning: row") == std::string::npos);
  // ...and recomputed when its prior finished after it did (make's rule on DONE times).
  fs::remove(row / "dependencies.yaml");
  write_file_atomic(row / "DONE", "2000-01-01T00:00:00Z\n");
  out = replay();
  CHECK_FALSE(std::regex_search(out, cached_line));
  CHECK_THAT(out, Catch::Contains("recomputing it") && Catch::Contains("trained again at"));
  CHECK(read_dependency_record(row).has_value());
  CHECK(slurp(row / "DONE").rfind("2000-", 0) != 0);

  // (d) A damaged cache (a byte of the sealed metrics.h5 changed, then samples.h5
  // missing) is a miss: the row is recomputed with a warning naming the file, not failed.
  REQUIRE(std::regex_search(replay(), cached_line));
  const std::string fid_before = summary_line(row, "fid");
  std::string bytes = read_file(row / "metrics.h5");
  REQUIRE(bytes.size() > 4096);
  bytes[bytes.size() / 2] = static_cast<char>(bytes[bytes.size() / 2] ^ 0x5a);
  write_file_atomic(row / "metrics.h5", bytes);
  out = replay();
  CHECK_FALSE(std::regex_search(out, cached_line));
  CHECK_THAT(out, Catch::Contains("cache cannot be used, recomputing it") && Catch::Contains("metrics.h5"));
  CHECK(summary_line(row, "fid") == fid_before);  // deterministic: the same numbers again
  CHECK(std::regex_search(replay(), cached_line));
  fs::remove(row / "samples.h5");
  out = replay();
  CHECK_FALSE(std::regex_search(out, cached_line));
  CHECK_THAT(out, Catch::Contains("cache cannot be used") && Catch::Contains("samples.h5"));
  CHECK(fs::exists(row / "samples.h5"));

  // (e) The same row under another id (renamed, or shared by two tables) is the same
  // computation: reused from the finished directory of the same key, none made for it.
  const std::string fid_row = summary_line(row, "fid");
  std::ofstream(dir.path / "specs" / "t" / "a.yaml")
      << "table:\n  id: t/a\n  title: \"rows keyed by weights\"\n"
      << "  protocol: experiments/protocols/anchors_root_3d.yaml\n"
      << "  columns: [control_error, fid]\nrows:\n"
      << "  - {id: renamed, label: Imputation, generator: experiments/generators/imputation.yaml}\n";
  out = replay();
  CHECK(std::regex_search(out, std::regex(R"(renamed\s+\(cached\))")));
  bool made = false;
  for (const auto& e : fs::recursive_directory_iterator(dir.path / "runs"))
    if (e.is_directory() && e.path().filename().string().rfind("renamed-", 0) == 0) made = true;
  CHECK_FALSE(made);
  CHECK(summary_line(row, "fid") == fid_row);
  CHECK(slurp(row / "log.txt").find("row renamed: the same computation") != std::string::npos);
}
