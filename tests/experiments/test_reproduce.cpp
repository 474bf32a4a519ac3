// The table replay end to end at a reduced smoke scale: `motionctl reproduce` on a
// small fixture, a briefly trained evaluator and prior; every table file present
// and well-formed, the ProjFlow rows exact, cached rows reused, bad specs exit 2.
#include <catch2/catch.hpp>

#include <H5Cpp.h>

#include <fstream>
#include <map>
#include <sstream>

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
  std::string summary = slurp(out / "summary.md");
  CHECK(summary.find("ProjFlow satisfies every joint's constraints exactly") != std::string::npos);
  {
    H5::H5File f((out / "results.h5").string(), H5F_ACC_RDONLY);
    CHECK(f.nameExists("tables"));
    CHECK(f.nameExists("examples"));
    CHECK(f.nameExists("skeleton"));
    CHECK(f.openGroup("training").getNumObjs() >= 2);  // the evaluator and the prior
  }

  // A second run reuses every finished row.
  auto again = run_motionctl(fmt::format("reproduce --profile {} --tables projflow/table3 --no-figures", profile));
  INFO(again.output);
  REQUIRE(again.exit_code == 0);
  CHECK(again.output.find("(cached)") != std::string::npos);

  // Unknown table ids and broken profiles are exit 2 with a message.
  auto bad = run_motionctl(fmt::format("reproduce --profile {} --tables nosuchtable --no-figures", profile));
  CHECK(bad.exit_code == 2);
  CHECK(bad.output.find("nosuchtable") != std::string::npos);
  auto missing = run_motionctl("reproduce --profile nosuchprofile --no-figures");
  CHECK(missing.exit_code == 2);
  CHECK(missing.output.find("nosuchprofile") != std::string::npos);
}
