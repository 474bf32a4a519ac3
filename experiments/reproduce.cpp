// The reproduce orchestrator: profile -> tables -> rows (cached) -> rendered
// tables, results.h5, claims summary and figures.
#include "experiments/reproduce.h"

#include <algorithm>
#include <fmt/ranges.h>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <iostream>

#include "core/atomic_file.h"
#include "core/error.h"
#include "core/source_dir.h"
#include "data/skeleton.h"
#include "experiments/experiment.h"
#include "experiments/prior_health.h"
#include "experiments/report.h"
#include "experiments/row_evaluator.h"
#include "train/train_job.h"

namespace mc {
namespace fs = std::filesystem;

std::vector<std::string> list_table_specs(const std::string& specs_root) {
  std::vector<std::string> out;
  fs::path root = resolve_data_path(specs_root);
  if (!fs::exists(root)) fail("experiment specs folder '{}' does not exist", specs_root);
  for (auto& e : fs::recursive_directory_iterator(root)) {
    if (!e.is_regular_file() || e.path().extension() != ".yaml") continue;
    auto rel = fs::relative(e.path(), root).string();
    if (rel.rfind("paper_numbers", 0) == 0 || rel.rfind("generators", 0) == 0 || rel.rfind("protocols", 0) == 0)
      continue;
    if (e.path().filename() == "claims.yaml") continue;
    out.push_back(e.path().string());
  }
  std::sort(out.begin(), out.end());
  return out;
}

static bool selected(const std::string& id, const std::vector<std::string>& wanted) {
  if (wanted.empty()) return true;
  for (auto& w : wanted)
    if (id == w || id.rfind(w + "/", 0) == 0 || (w.size() && id.rfind(w, 0) == 0 && w.back() == '/')) return true;
  return false;
}

static std::string git_commit() {
  std::string out;
  FILE* p = popen(("git -C " + source_dir() + " rev-parse --short HEAD 2>/dev/null").c_str(), "r");
  if (!p) return "unknown";
  char buf[64];
  while (fgets(buf, sizeof buf, p)) out += buf;
  pclose(p);
  while (!out.empty() && (out.back() == '\n' || out.back() == '\r')) out.pop_back();
  return out.empty() ? "unknown" : out;
}

ReproduceResult reproduce(const ReproduceOptions& opt) {
  auto t0 = std::chrono::steady_clock::now();
  std::string profile_file = opt.profile;
  if (profile_file.find('/') == std::string::npos && profile_file.find(".yaml") == std::string::npos)
    profile_file = resolve_data_path("configs/profile/" + profile_file + ".yaml");
  if (!fs::exists(profile_file))
    fail("profile '{}' not found ({} does not exist); profiles are the files in configs/profile/", opt.profile,
         profile_file);
  ProfileFile pf = load_job<ProfileFile>(profile_file, opt.profile_overrides);
  set_config_redirects(pf.profile.trained_configs, profile_file + ": profile.trained_configs");

  // Load and check every selected spec before anything runs: a typo fails in seconds.
  std::vector<TableSpec> specs;
  std::set<std::string> seen;
  for (const auto& file : list_table_specs(opt.specs_root)) {
    TableSpec s = load_table_spec(file);
    if (!seen.insert(s.table.id).second) fail("{}: table id '{}' is used by two specs", file, s.table.id);
    if (!selected(s.table.id, opt.tables)) continue;
    for (auto& row : s.rows) resolve_row(pf.profile, s, row);
    specs.push_back(std::move(s));
  }
  if (specs.empty()) {
    std::string ids;
    for (auto& id : seen) ids += " " + id;
    fail("--tables {} matched no experiment spec; known tables:{}", fmt::format("{}", fmt::join(opt.tables, ",")), ids);
  }

  ReproduceResult res;
  fs::path out_dir = fs::path(resolve_data_path(pf.profile.results_root)) / pf.profile.name;
  fs::create_directories(out_dir);
  res.results_dir = out_dir.string();
  const std::string commit = git_commit();

  // Row runs and every component the rows train live under profile.runs_root.
  RunsRootScope components_root(pf.profile.runs_root);
  take_trained_runs();
  RowEvaluator ev(pf.profile);
  const std::vector<std::string> evaluator_runs = take_trained_runs();  // its training curve goes in results.h5
  ProfileHealth health(pf, ev.data());  // every prior the rows use, checked once
  std::vector<TableResult> results;
  for (const auto& spec : specs) {
    auto ts = std::chrono::steady_clock::now();
    TableResult tr;
    tr.spec = spec;
    tr.evaluator = ev.evaluator_run();
    tr.num_samples = spec.table.num_samples > 0 ? spec.table.num_samples : pf.profile.num_samples;
    tr.repeats = pf.profile.repeats;
    if (!spec.table.paper_numbers.empty()) {
      std::string pn = resolve_data_path(spec.table.paper_numbers);
      if (!fs::exists(pn)) fail("{}: table.paper_numbers '{}' does not exist", spec.file, spec.table.paper_numbers);
      tr.paper = load_paper_table(pn);
    }
    std::cerr << fmt::format("== {} ({} rows)\n", spec.table.id, spec.rows.size());
    std::vector<RowConfig> kept;
    for (const auto& row : spec.rows) {
      try {
        RowResult r = run_row(pf, spec, row, ev);
        std::cerr << fmt::format("   {:<28} {}{}\n", row.id, r.cached ? "(cached) " : "",
                                 format_cell(r.values, spec.table.columns.front(), true));
        tr.rows.push_back(std::move(r));
        kept.push_back(row);
      } catch (const UserError& e) {
        res.failures.push_back(fmt::format("{} / {}: {}", spec.table.id, row.id, e.what()));
        std::cerr << fmt::format("   {:<28} FAILED: {}\n", row.id, e.what());
      }
    }
    tr.spec.rows = kept;
    // Derived columns (table.derived, e.g. Table VII's cost relative to the generator
    // alone): computed from the measured metric once every row is in. Without the base
    // row (it failed) or its metric the column stays empty.
    for (const auto& d : spec.table.derived) {
      const DerivedColumn dc = parse_derived_column(d, spec.file);
      auto base_row = std::find_if(tr.rows.begin(), tr.rows.end(), [&](const RowResult& r) {
        return r.row_id == dc.base_row && r.values.count(dc.metric) && !r.values.at(dc.metric).empty();
      });
      if (base_row == tr.rows.end()) continue;
      const double base = summarize(base_row->values.at(dc.metric)).mean;
      for (auto& r : tr.rows) {
        if (!r.values.count(dc.metric)) continue;
        auto& out = r.values[dc.column];
        out.clear();
        for (double v : r.values.at(dc.metric)) out.push_back(v / std::max(base, 1e-12));
      }
    }
    if (pf.profile.health) tr.health = health.table_line(tr);  // before the timing: not the table's cost
    tr.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - ts).count();
    RenderedTable rt = render_table(tr);
    fs::path base = out_dir / spec.table.id;
    fs::create_directories(base.parent_path());
    write_file_atomic(base.string() + ".md", rt.markdown);
    write_file_atomic(base.string() + ".csv", rt.csv);
    write_file_atomic(base.string() + ".tex", rt.latex);
    res.table_files.push_back(base.string() + ".md");
    results.push_back(std::move(tr));
  }
  write_results_h5((out_dir / "results.h5").string(), results, pf.profile.name, commit, &ev.data().skeleton,
                   evaluator_runs);
  if (pf.profile.health) {
    health.write(out_dir);
    res.health_file = (out_dir / "health.md").string();
    for (const auto& c : health.components()) {
      ++res.priors_checked;
      res.priors_healthy += c.healthy();
    }
  }
  double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  std::vector<ClaimCheck> claims;
  fs::path claims_file = fs::path(resolve_data_path(opt.specs_root)) / "claims.yaml";
  ClaimOptions co;
  co.reference = &ev.realism();
  co.protocol = &pf.protocol;
  if (fs::exists(claims_file)) claims = check_claims(claims_file.string(), results, co);
  for (auto& c : claims)
    (c.verdict == "holds"          ? res.claims_hold
     : c.verdict == "contradicted" ? res.claims_contradicted
     : c.verdict == "undecided"    ? res.claims_undecided
                                   : res.claims_not_run)++;
  std::string summary = render_summary(claims, results, pf.profile.name, seconds, commit);
  if (res.priors_checked > 0)
    summary += fmt::format("\nPrior health ([health.md](health.md)): {} of {} trained priors and tokenizers healthy "
                           "at N = {}.\n",
                           res.priors_healthy, res.priors_checked, health.samples());
  if (!res.failures.empty()) {
    summary += "\n## Rows that failed\n\n";
    for (auto& f : res.failures) summary += "- " + f + "\n";
  }
  write_file_atomic(out_dir / "summary.md", summary);
  if (opt.figures) {
    std::string cmd = fmt::format("\"{}\" \"{}\" \"{}\" --out \"{}\"", opt.python,
                                  resolve_data_path("tools/figures.py"), (out_dir / "results.h5").string(),
                                  (out_dir / "figures").string());
    if (std::system(cmd.c_str()) != 0) res.failures.push_back("figures: tools/figures.py failed (see above)");
  }
  return res;
}

}  // namespace mc
