// The table replay end to end at a reduced smoke scale: `motionctl reproduce` on a
// small fixture, a briefly trained evaluator and prior; every table file present
// and well-formed, the ProjFlow rows exact, cached rows reused, bad specs exit 2, and
// the commit stamp marks uncommitted code (+dirty).
#include <catch2/catch.hpp>

#include <H5Cpp.h>
#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <fstream>
#include <map>
#include <regex>
#include <sstream>

#include "experiments/experiment.h"
#include "experiments/reproduce.h"
#include "test_util.h"

using namespace mc::test;

namespace {

std::vector<std::string> split(const std::string& s, char sep) {
  std::vector<std::string> out;
  std::string cur;
  bool quoted = false;
  for (char c : s) {
    if (c == '"') quoted = !quoted;
    if (c == sep && !quoted) {
      out.push_back(cur);
      cur.clear();
    } else {
      cur += c;
    }
  }
  out.push_back(cur);
  return out;
}

// Writes a reduced profile: its own fixture, evaluator and runs, tiny training.
std::string write_profile(const fs::path& dir) {
  const std::string fx = (dir / "fx.h5").string(), runs = (dir / "runs").string();
  std::ofstream ev(dir / "evaluator.yaml");
  ev << "run: {experiment: evaluator, name: ci, seed: 7, log_every: 20, checkpoint_every: 100, root: " << runs << "}\n"
     << "data: {path: " << fx << ", fixture: '', window: 0}\n"
     << "model: {type: t2m_evaluator, word_dim: 32, text_hidden: 32, movement_dim: 32, motion_hidden: 32, "
        "embed_dim: 32, max_words: 24, margin: 10.0, dropout: 0.0}\n"
     << "optim: {steps: 40, batch_size: 16, lr: 1.0e-3, warmup: 5, schedule: cosine, min_lr_ratio: 0.1, "
        "grad_clip: 1.0, ema_decay: 0.0}\n";
  ev.close();
  std::ofstream p(dir / "ci.yaml");
  p << "profile:\n  name: ci\n  data: " << fx << "\n  data_fixture: ''\n  evaluator: " << (dir / "evaluator.yaml").string()
    << "\n  split: test\n  num_samples: 5\n  repeats: 2\n  seed: 1\n  threads: 1\n  device: cpu\n"
    << "  substitutions:\n"
    << "    - \"generator.prior.overrides=[optim.steps=20, optim.warmup=2, optim.batch_size=8, data.path=" << fx
    << ", run.root=" << runs << ", run.threads=1]\"\n"
    << "    - generator.sampler.steps=6\n"
    << "    - generator.opt_steps=2\n"
    << "    - generator.ode_steps=2\n"
    << "    - generator.steps=6\n"
    // the ControlNet trains briefly on top of the same briefly trained prior (same overrides = same run)
    << "    - \"generator.controlnet.overrides=[optim.steps=4, optim.warmup=1, optim.batch_size=4, data.path=" << fx
    << ", run.root=" << runs << ", run.threads=1, 'model.base.overrides=[optim.steps=20, optim.warmup=2, "
    << "optim.batch_size=8, data.path=" << fx << ", run.root=" << runs << ", run.threads=1]']\"\n"
    << "  runs_root: " << runs << "\n  results_root: " << (dir / "results").string() << "\n"
    << "protocol: {r_precision_pool: 4, diversity_pairs: 4, multimodality_pairs: 2, foot_skating_padded_196: false, "
       "control_thresholds: [0.5, 0.2]}\n";
  return (dir / "ci.yaml").string();
}

}  // namespace

TEST_CASE("motionctl reproduce: reduced smoke replay of the ProjFlow tables", "[experiments][slow]") {
  TempDir dir("reproduce");
  REQUIRE(run_motionctl(fmt::format("fixture configs/data/smoke.yaml output={} fixture.num_clips=60",
                                    (dir.path / "fx.h5").string()))
              .exit_code == 0);
  const std::string profile = write_profile(dir.path);
  auto r = run_motionctl(fmt::format("reproduce --profile {} --tables projflow --no-figures", profile));
  INFO(r.output);
  REQUIRE(r.exit_code == 0);

  const fs::path out = dir.path / "results" / "ci";
  for (std::string t : {"table1", "table2", "table3"}) {
    for (std::string ext : {".md", ".csv", ".tex"}) {
      INFO(t << ext);
      REQUIRE(fs::exists(out / "projflow" / (t + ext)));
      CHECK(fs::file_size(out / "projflow" / (t + ext)) > 100);
    }
    // CSV: a header and rows of the same width; every ours row has a finite mean.
    std::ifstream csv(out / "projflow" / (t + ".csv"));
    std::string line;
    REQUIRE(std::getline(csv, line));
    const auto header = split(line, ',');
    REQUIRE(header.size() == 10);
    std::map<std::string, double> avg_err;
    int ours = 0;
    while (std::getline(csv, line)) {
      auto f = split(line, ',');
      REQUIRE(f.size() == header.size());
      if (f[3] != "ours") continue;
      ++ours;
      REQUIRE(!f[5].empty());
      double mean = std::stod(f[5]);
      CHECK(std::isfinite(mean));
      if (f[4] == "avg_err" || f[4] == "avg_err_2d" || f[4] == "mpjpe_2d") avg_err[f[1] + ":" + f[4]] = mean;
    }
    CHECK(ours > 0);
    // ProjFlow rows: zero control error (hard constraints hold exactly).
    for (auto& [k, v] : avg_err)
      if (k.find("projflow") != std::string::npos && k.find("ddnm") == std::string::npos) {
        INFO(t << " " << k);
        CHECK(v <= 1e-4);
      }
    std::string md = slurp(out / "projflow" / (t + ".md"));
    CHECK(md.find("| Method |") != std::string::npos);
    CHECK(md.find("paper") != std::string::npos);
  }
  REQUIRE(fs::exists(out / "results.h5"));
  REQUIRE(fs::exists(out / "summary.md"));
  // The prior the rows used is health-checked; every table names its verdict at the top.
  REQUIRE(fs::exists(out / "health.md"));
  REQUIRE(fs::exists(out / "health.json"));
  CHECK(slurp(out / "health.md").find("| flow_prior |") != std::string::npos);
  for (std::string t : {"table1", "table2", "table3"}) {
    const std::string md = slurp(out / "projflow" / (t + ".md"));
    INFO(t);
    CHECK(md.find("Prior health") < md.find("| Method |"));
  }
  std::string summary = slurp(out / "summary.md");
  CHECK(summary.find("ProjFlow satisfies every joint's constraints exactly") != std::string::npos);
  CHECK(summary.find("](projflow/table1.md)") != std::string::npos);  // links resolve beside summary.md
  {
    H5::H5File f((out / "results.h5").string(), H5F_ACC_RDONLY);
    CHECK(f.nameExists("tables"));
    CHECK(f.nameExists("examples"));
    CHECK(f.nameExists("skeleton"));
    CHECK(f.openGroup("training").getNumObjs() >= 2);  // the evaluator and the prior
    // Each row keeps kExamplesPerRow samples; results.h5 copies the first kExamplesInResults,
    // and their captions, line for line.
    REQUIRE(f.nameExists("examples/projflow|table3/projflow"));
    H5::Group ex = f.openGroup("examples/projflow|table3/projflow");
    hsize_t dims[4];
    ex.openDataSet("joints").getSpace().getSimpleExtentDims(dims);
    CHECK(dims[0] == mc::kExamplesInResults);
    CHECK(dims[1] > 0);
    std::string caps;
    ex.openAttribute("captions").read(ex.openAttribute("captions").getStrType(), caps);
    CHECK(static_cast<unsigned long long>(std::count(caps.begin(), caps.end(), '\n')) == mc::kExamplesInResults - 1);
  }

  // Every row's sample files carry their per-sample specs (/control), so `score` alone
  // re-scores them; ProjFlow's hard constraints hold on the stored targets too.
  int scored = 0, exact = 0;
  for (auto& e : fs::recursive_directory_iterator(dir.path / "runs"))
    if (e.path().filename() == "samples_r0.h5") {
      auto sc = run_motionctl(fmt::format("score {} --csv", e.path().string()));
      INFO(e.path() << "\n" << sc.output);
      REQUIRE(sc.exit_code == 0);
      ++scored;
      const std::string row = e.path().parent_path().filename().string();
      if (row.find("projflow") == std::string::npos || row.find("ddnm") != std::string::npos) continue;
      std::smatch m;
      if (!std::regex_search(sc.output, m, std::regex("avg_err,([^\n]+)"))) continue;
      CHECK(sc.output.find("constraint specs stored in") != std::string::npos);
      CHECK(std::stod(m[1]) <= 1e-4);
      ++exact;
    }
  CHECK(scored > 5);
  CHECK(exact > 0);

  // A second run reuses every finished row.
  auto again = run_motionctl(fmt::format("reproduce --profile {} --tables projflow/table3 --no-figures", profile));
  INFO(again.output);
  REQUIRE(again.exit_code == 0);
  CHECK(again.output.find("(cached)") != std::string::npos);
  // ... and merges: Tables 1 and 2 and their claims stay in results.h5 and summary.md.
  {
    H5::H5File f((out / "results.h5").string(), H5F_ACC_RDONLY);
    CHECK(f.nameExists("tables/projflow|table1"));
    CHECK(f.nameExists("tables/projflow|table2"));
    CHECK(f.nameExists("examples/projflow|table1"));
  }
  CHECK(slurp(out / "summary.md").find("ProjFlow satisfies every joint's constraints exactly") != std::string::npos);
  CHECK(slurp(out / "summary.md").find("](projflow/table1.md)") != std::string::npos);

  // Unknown table ids and broken profiles are exit 2 with a message.
  auto bad = run_motionctl(fmt::format("reproduce --profile {} --tables nosuchtable --no-figures", profile));
  CHECK(bad.exit_code == 2);
  CHECK(bad.output.find("nosuchtable") != std::string::npos);
  auto missing = run_motionctl("reproduce --profile nosuchprofile --no-figures");
  CHECK(missing.exit_code == 2);
  CHECK(missing.output.find("nosuchprofile") != std::string::npos);
}

namespace {

// A repo training config shrunk for the test: a few steps on the test's fixture, its
// own run root (runs named by config hash), one thread. Nested configs it names are redirected by the profile too.
std::string shrink_config(const fs::path& dir, const std::string& repo_config, const std::string& name, int steps) {
  YAML::Node n = YAML::LoadFile((fs::path(MOTIONCTL_SOURCE_DIR) / repo_config).string());
  n["run"]["root"] = (dir / "runs").string();
  n["run"]["threads"] = 1;
  n["run"]["log_every"] = 5;
  n["run"]["checkpoint_every"] = 10;
  n["data"]["path"] = (dir / "fx.h5").string();
  n["data"]["fixture"] = "";
  n["optim"]["steps"] = steps;
  n["optim"]["warmup"] = 2;
  n["optim"]["batch_size"] = 8;
  const fs::path out = dir / (name + ".yaml");
  std::ofstream(out) << YAML::Dump(n) << "\n";
  return repo_config + "=" + out.string();
}

}  // namespace

TEST_CASE("motionctl reproduce: reduced smoke replay of the AnchorRoute and cross-method tables",
          "[experiments][slow]") {
  TempDir dir("reproduce_ar");
  REQUIRE(run_motionctl(fmt::format("fixture configs/data/smoke.yaml output={} fixture.num_clips=60",
                                    (dir.path / "fx.h5").string()))
              .exit_code == 0);
  write_profile(dir.path);
  // Every trained component is swapped for a shrunk copy through profile.trained_configs.
  std::vector<std::string> swaps = {
      shrink_config(dir.path, "configs/tokenizer/vq_tiny.yaml", "vq", 10),
      shrink_config(dir.path, "configs/tmd/tmd_tiny.yaml", "tmd", 10),
      shrink_config(dir.path, "configs/masked/masked_tiny.yaml", "masked", 10),
      shrink_config(dir.path, "configs/adapter/anchorkv_tiny.yaml", "adapter", 10),
      shrink_config(dir.path, "configs/prior/flow_tiny.yaml", "flow", 10)};
  std::ofstream p(dir.path / "ar.yaml");
  p << "profile:\n  name: ci_ar\n  data: " << (dir.path / "fx.h5").string()
    << "\n  data_fixture: ''\n  evaluator: " << (dir.path / "evaluator.yaml").string()
    << "\n  split: test\n  num_samples: 5\n  repeats: 2\n  seed: 1\n  threads: 1\n  device: cpu\n"
    << "  trained_configs:\n";
  for (auto& s : swaps) p << "    - \"" << s << "\"\n";
  // Rows that ask for longer training (Table IV's 4,500-step adapter) train the shrunk
  // config's 10 steps: uncapped, that one adapter was 520 of the test's 640 s.
  p << "  lengthen_training: false\n";
  p << "  substitutions: [generator.sampler.steps=4]\n"
    << "  runs_root: " << (dir.path / "runs").string() << "\n  results_root: " << (dir.path / "results").string()
    << "\nprotocol: {r_precision_pool: 4, diversity_pairs: 4, multimodality_pairs: 2, foot_skating_padded_196: false, "
       "control_thresholds: [0.5, 0.2]}\n";
  p.close();
  auto r = run_motionctl(fmt::format("reproduce --profile {} --tables anchorroute cross --no-figures",
                                     (dir.path / "ar.yaml").string()));
  INFO(r.output);
  REQUIRE(r.exit_code == 0);
  CHECK(r.output.find("FAILED") == std::string::npos);
  // The swapped configs were trained (in the test's run root), not the repo's tiny ones.
  CHECK(fs::exists(dir.path / "runs" / "tmd"));
  CHECK(fs::exists(dir.path / "runs" / "adapter"));
  CHECK(fs::exists(dir.path / "runs" / "masked"));
  // profile.lengthen_training: false: no adapter trained longer than the shrunk config's
  // 10 steps, though Table IV's 4,500-step rows asked for it.
  int adapters = 0;
  for (const auto& run : fs::directory_iterator(dir.path / "runs" / "adapter")) {
    INFO(run.path());
    const YAML::Node c = YAML::LoadFile((run.path() / "config.yaml").string());
    CHECK(c["optim"]["steps"].as<int>() <= 10);
    ++adapters;
  }
  CHECK(adapters >= 10);

  const fs::path out = dir.path / "results" / "ci_ar";
  std::map<std::string, std::map<std::string, double>> means;  // table:row -> metric -> mean
  std::vector<std::string> tables = {"anchorroute/table1", "anchorroute/table2", "anchorroute/table3",
                                     "anchorroute/table4", "anchorroute/table4_explore", "anchorroute/table4_recipe",
                                     "anchorroute/table5",
                                     "anchorroute/table6",
                                     "anchorroute/table7", "cross/benchmark"};
  for (const auto& t : tables) {
    for (std::string ext : {".md", ".csv", ".tex"}) {
      INFO(t << ext);
      REQUIRE(fs::exists(out / (t + ext)));
    }
    std::ifstream csv(out / (t + ".csv"));
    std::string line;
    REQUIRE(std::getline(csv, line));
    const auto header = split(line, ',');
    while (std::getline(csv, line)) {
      auto f = split(line, ',');
      REQUIRE(f.size() == header.size());
      // A metric the row does not measure (e.g. direction_error on a row without
      // direction items) is an empty cell.
      if (f[3] != "ours" || f[5].empty()) continue;
      INFO(line);
      double mean = std::stod(f[5]);
      CHECK(std::isfinite(mean));
      means[t + ":" + f[1]][f[4]] = mean;
    }
  }
  // Table I: the multimodality pass ran for the sampled priors; ground truth has none.
  CHECK(means["anchorroute/table1:tmd"].count("multimodality"));
  CHECK(means["anchorroute/table1:tmd"]["multimodality"] > 0);
  CHECK(means["anchorroute/table1:gt"]["multimodality"] == Approx(0).margin(1e-3));  // float noise of the embedding only
  // Table IV: parameter counts come from the trained adapters; AnchorKV is the smallest path.
  const double kv = means["anchorroute/table4:anchorkv"]["params"];
  CHECK(kv > 0);
  CHECK(means["anchorroute/table4:controlnet_adapter"]["params"] > kv);
  CHECK(means["anchorroute/table4:anchorkv/no_dual_context_no_anchor_loss"]["params"] < kv);
  // Table IV's exploratory rows (their own table since 2026-12-07): the feedback and
  // rollout adapters trained, every row's control error measured.
  for (std::string row : {"tmd/no_adapter", "anchorkv", "anchorkv/rollout_anchor", "anchorkv/feedback",
                          "anchorkv/rollout_anchor_4500", "anchorkv/text_slots"}) {
    INFO(row);
    CHECK(means["anchorroute/table4_explore:" + row].count("control_error"));
  }
  // Table IV under one recipe: every path trained (feedback channels and rollout states),
  // the ControlNet adapter still the largest, every row's control error measured.
  const double kv_recipe = means["anchorroute/table4_recipe:anchorkv"]["params"];
  CHECK(kv_recipe > 0);
  CHECK(means["anchorroute/table4_recipe:controlnet_adapter"]["params"] > kv_recipe);
  for (std::string row : {"tmd/no_adapter", "cross_attn_adapter", "controlnet_adapter", "anchorkv",
                          "anchorkv/zeroed_features"}) {
    INFO(row);
    CHECK(means["anchorroute/table4_recipe:" + row].count("control_error"));
  }
  // Table VII: refinement steps as configured, cost relative to the generator alone.
  CHECK(means["anchorroute/table7:rs0"]["relative_cost"] == Approx(1.0));
  CHECK(means["anchorroute/table7:rs500"]["steps"] == Approx(500));
  CHECK(means["anchorroute/table7:rs500"]["relative_cost"] > 1.0);
  // Cross benchmark: ProjFlow meets every anchor exactly; the RouteSolver reduces AnchorKV's error.
  for (std::string fam : {"root3d", "planar", "body"}) {
    INFO(fam);
    CHECK(means["cross/benchmark:" + fam + "/projflow"]["control_error"] <= 1e-4);
  }
  CHECK(means["cross/benchmark:root3d/anchorroute"]["control_error"] <
        means["cross/benchmark:root3d/anchorkv"]["control_error"]);
  // Issue 20 rows: the hard floor holds, exact AnchorRoute meets its anchors, imposed
  // directions are met where the plain row (same tasks, scored only) misses them.
  for (std::string row : {"root3d/projflow_floor", "body/projflow_floor"}) {
    INFO(row);
    CHECK(means["cross/benchmark:" + row]["floor_penetration"] <= 1e-5);
    CHECK(means["cross/benchmark:" + row]["control_error"] <= 1e-4);
  }
  for (std::string row : {"root3d/anchorroute_exact", "root3d/anchorkv_exact", "planar/anchorroute_exact",
                          "body/anchorroute_exact"}) {
    INFO(row);
    CHECK(means["cross/benchmark:" + row]["control_error"] <= 1e-4);
  }
  CHECK(means["cross/benchmark:dir/projflow"]["direction_error"] < 1.0);
  CHECK(means["cross/benchmark:dir/projflow"]["direction_error"] <
        means["cross/benchmark:dir/projflow_plain"]["direction_error"]);
  CHECK(means["cross/benchmark:dir/anchorroute_exact"]["direction_error"] < 1.0);
}

// Writes `yaml` to dir/file and runs `reproduce` on it as the profile (the bad-profile tests).
static CommandResult reproduce_with_profile(const TempDir& dir, const std::string& file, const std::string& yaml) {
  std::ofstream(dir.path / file) << yaml;
  return run_motionctl(fmt::format("reproduce --profile {} --no-figures", (dir.path / file).string()));
}

TEST_CASE("profile.trained_configs: malformed entries and missing files are exit 2 naming the entry",
          "[experiments]") {
  TempDir dir("reproduce_bad");
  auto r = reproduce_with_profile(dir, "bad.yaml",
                                  "profile:\n  name: bad\n  trained_configs: [configs/prior/flow_tiny.yaml=configs/prior/nosuch.yaml]\n");
  CHECK(r.exit_code == 2);
  CHECK(r.output.find("nosuch.yaml") != std::string::npos);
  auto r2 = reproduce_with_profile(dir, "bad2.yaml",
                                   "profile:\n  name: bad\n  trained_configs: [configs/prior/flow_tiny.yaml]\n");
  CHECK(r2.exit_code == 2);
  CHECK(r2.output.find("from=to") != std::string::npos);
}

TEST_CASE("profile.table_num_samples: malformed entries and unknown tables are exit 2 naming the entry",
          "[experiments]") {
  TempDir dir("reproduce_tasks");
  auto r = reproduce_with_profile(dir, "bad.yaml",
                                  "profile:\n  name: bad\n  table_num_samples: [anchorroute/nosuch=64]\n");
  CHECK(r.exit_code == 2);
  CHECK(r.output.find("anchorroute/nosuch") != std::string::npos);
  CHECK(r.output.find("anchorroute/table4") != std::string::npos);  // the known tables are listed
  auto r2 = reproduce_with_profile(dir, "bad2.yaml",
                                   "profile:\n  name: bad\n  table_num_samples: [anchorroute/table4]\n");
  CHECK(r2.exit_code == 2);
  CHECK(r2.output.find("table_id=N") != std::string::npos);
}

TEST_CASE("table.derived: a derived column is declared in the spec, malformed entries are exit 2 naming the spec",
          "[experiments]") {
  // Table VII's cost column is declared, not recognised by its name.
  mc::TableSpec t7 = mc::load_table_spec(std::string(MOTIONCTL_SOURCE_DIR) + "/experiments/anchorroute/table7.yaml");
  REQUIRE(t7.table.derived == std::vector<std::string>{"relative_cost=time_per_sample/rs0"});
  mc::DerivedColumn d = mc::parse_derived_column(t7.table.derived[0], "table7");
  CHECK(d.column == "relative_cost");
  CHECK(d.metric == "time_per_sample");
  CHECK(d.base_row == "rs0");

  TempDir dir("derived");
  auto spec_with = [&](const std::string& derived) {
    const fs::path f = dir.path / "t.yaml";
    std::ofstream(f) << "table:\n  id: test/derived\n  protocol: experiments/protocols/anchors_all.yaml\n"
                        "  columns: [time_per_sample, cost]\n  derived: " << derived << "\n"
                     << "rows:\n  - {id: base, generator: experiments/generators/anchorroute.yaml}\n"
                        "  - {id: other, generator: experiments/generators/anchorroute.yaml}\n";
    return f.string();
  };
  CHECK(mc::load_table_spec(spec_with("[cost=time_per_sample/base]")).table.derived.size() == 1);
  for (const auto& [entry, fragment] : std::vector<std::pair<std::string, std::string>>{
           {"[cost=time_per_sample]", "not column=metric/row"},
           {"[cost]", "not column=metric/row"},
           {"[nocolumn=time_per_sample/base]", "which table.columns does not list"},
           {"[cost=time_per_sample/nosuchrow]", "not a row of the table"}}) {
    INFO(entry);
    const std::string msg = user_error_of([&] { mc::load_table_spec(spec_with(entry)); });
    CHECK(msg.find(fragment) != std::string::npos);
    CHECK(msg.find("t.yaml") != std::string::npos);
  }
}

TEST_CASE("source_commit: the replay's commit stamp says +dirty when tracked code differs from HEAD",
          "[experiments]") {
  TempDir dir("commit_stamp");
  const std::string d = dir.path.string();
  CHECK(mc::source_commit(d) == "unknown");  // not a git checkout
  fs::create_directories(dir.path / "src");
  std::ofstream(dir.path / "src" / "a.cpp") << "int a;\n";
  const std::string git = "git -C '" + d + "' -c user.name=t -c user.email=t@t ";
  REQUIRE(std::system((git + "init -q && " + git + "add src && " + git + "commit -qm c >/dev/null").c_str()) == 0);
  const std::string clean = mc::source_commit(d);
  CHECK(clean != "unknown");
  CHECK(clean.find("+dirty") == std::string::npos);
  fs::create_directories(dir.path / "runs");
  std::ofstream(dir.path / "runs" / "out.txt") << "x\n";  // untracked run output: still clean
  CHECK(mc::source_commit(d) == clean);
  std::ofstream(dir.path / "src" / "a.cpp") << "int b;\n";
  CHECK(mc::source_commit(d) == clean + "+dirty");
}
