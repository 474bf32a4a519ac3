// The reproduce orchestrator: profile -> tables -> rows (cached) -> rendered
// tables, results.h5, claims summary and figures. A partial replay (--tables) merges
// its tables into what results/<profile>/ already holds.
#include "experiments/reproduce.h"

#include <algorithm>
#include <fmt/ranges.h>
#include <chrono>
#include <cstdio>
#include <ctime>
#include <filesystem>
#include <iostream>
#include <optional>
#include <set>

#include <yaml-cpp/yaml.h>

#include "core/atomic_file.h"
#include "core/error.h"
#include "core/job_memory.h"
#include "core/resources.h"
#include "core/source_dir.h"
#include "data/skeleton.h"
#include "experiments/experiment.h"
#include "experiments/prior_health.h"
#include "experiments/report.h"
#include "experiments/row_evaluator.h"
#include "train/pretrained.h"
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

static std::string run_git(const std::string& dir, const std::string& args) {
  std::string out;
  FILE* p = popen(("git -C '" + dir + "' " + args + " 2>/dev/null").c_str(), "r");
  if (!p) return out;
  char buf[256];
  while (fgets(buf, sizeof buf, p)) out += buf;
  pclose(p);
  return out;
}

std::string source_commit(const std::string& dir) {
  std::string head = run_git(dir, "rev-parse --short HEAD");
  while (!head.empty() && (head.back() == '\n' || head.back() == '\r')) head.pop_back();
  if (head.empty()) return "unknown";
  // Untracked files are left out: run outputs (runs/, results/) and editor files are not code.
  const std::string changed = run_git(
      dir, "status --porcelain --untracked-files=no -- src eval experiments configs tools CMakeLists.txt");
  return changed.empty() ? head : head + "+dirty";
}

// What the numbers of a replay depend on besides the specs, key=value, from the
// profile's own declarations (dump_config): a partial replay keeps an earlier table only
// when these match. profile.threads is left out (shown, not checked: it does not change
// what is measured), and so is protocol.repeats (ignored: profile.repeats counts
// replications). The data and evaluator are added by content once they exist
// (content_settings).
static std::vector<std::pair<std::string, std::string>> replay_settings(ProfileFile& pf) {
  YAML::Node root = YAML::Load(dump_config(pf));
  std::vector<std::pair<std::string, std::string>> out;
  auto text = [](const YAML::Node& n) {
    if (n.IsScalar()) return n.as<std::string>();
    YAML::Emitter e;
    e << YAML::Flow << n;
    return std::string(e.c_str());
  };
  for (const char* k : {"num_samples", "repeats", "seed", "split", "data", "evaluator", "device", "substitutions",
                        "trained_configs"})
    out.emplace_back(fmt::format("profile.{}", k), text(root["profile"][k]));
  for (auto it = root["protocol"].begin(); it != root["protocol"].end(); ++it) {
    const std::string k = it->first.as<std::string>();
    if (k != "repeats") out.emplace_back("protocol." + k, text(it->second));
  }
  return out;
}

// The ground truth and evaluator by content: the ground truth by what it holds (a
// fixture rebuilt with the same clips is the same data, one with other clips is not),
// the evaluator by its checkpoint's bytes; known once the fixture is built and the
// evaluator trained.
static std::vector<std::pair<std::string, std::string>> content_settings(const RowEvaluator& ev) {
  const std::string& evaluator_run = ev.evaluator_run();
  return {{"data_content_sha1", ev.data_content_sha1()},
          {"evaluator_sha1", file_sha1(fs::path(evaluator_run) / "checkpoints" / "final.pt")}};
}

// A partial replay keeps `kept` from `stored`: refuses (exit 2) when one of them was
// replayed with other settings than `current`, naming the setting, both values and the
// ways out.
static void check_kept_settings(const StoredResults& stored, const std::vector<const TableResult*>& kept,
                                const std::vector<std::pair<std::string, std::string>>& current,
                                const std::string& profile) {
  const std::string ways_out = fmt::format(
      "re-run every table to replace all of results/{0}/ (omit --tables), or write this replay to a new "
      "folder (--set profile.name=<new name>)",
      profile);
  for (const TableResult* t : kept)
    if (t->run.settings.empty())
      fail("{}: table {} was written before replays recorded their settings, so a partial replay cannot tell whether "
           "it is comparable with this one; {}, or move {} away (results.h5 and summary.md then start from this "
           "replay; the tables' .md/.csv/.tex files stay)",
           stored.file, t->spec.table.id, ways_out, stored.file);
  for (const auto& [key, value] : current) {
    std::vector<std::string> differ;
    std::string was;
    for (const TableResult* t : kept) {
      auto it = std::find_if(t->run.settings.begin(), t->run.settings.end(),
                             [&, k = key](const auto& kv) { return kv.first == k; });
      const std::string v = it == t->run.settings.end() ? "(not recorded)" : it->second;
      if (v == value) continue;
      if (differ.empty()) was = v;
      if (v == was) differ.push_back(t->spec.table.id);
    }
    if (differ.empty()) continue;
    const bool by_content = key == "data_content_sha1" || key == "evaluator_sha1";
    const std::string restore =
        was == "(not recorded)" ? "replay them again with this version"
        : by_content ? fmt::format("restore the {} they were replayed with",
                                   key == "data_content_sha1" ? "ground-truth data" : "evaluator checkpoint")
                     : fmt::format("re-run with the earlier value (--set {}={})", key, was);
    fail("{}: a partial replay keeps the tables it does not re-run, but {} {} replayed with {}={} and this run has "
         "{}={}: a summary mixing them would compare different protocols. Either {}, {}",
         stored.file, fmt::join(differ, ", "), differ.size() == 1 ? "was" : "were", key, was, key, value, restore,
         ways_out);
  }
}

// Claims of a merged summary: those on re-run tables as decided now; those on kept
// tables as the run that produced the table decided them, when claims.yaml still
// defines them the same way (else "not run", naming the table to re-run).
static std::vector<ClaimCheck> merge_claims(std::vector<ClaimCheck> decided, const std::set<std::string>& rerun,
                                            const std::vector<TableResult>& tables, const StoredResults* stored) {
  for (auto& c : decided) {
    if (rerun.count(c.table)) continue;
    auto t = std::find_if(tables.begin(), tables.end(), [&](const TableResult& x) { return x.spec.table.id == c.table; });
    if (t == tables.end() || !t->kept || !stored) continue;
    const ClaimCheck* old = stored->claim(c.id);
    if (old && old->table == c.table && old->definition == c.definition) {
      c.verdict = old->verdict;
      c.evidence = old->evidence;
      c.power = old->power;
    } else {
      c.verdict = "not run";
      c.evidence = fmt::format("table {} is kept from run {} ({}), which did not decide this claim as claims.yaml "
                               "now defines it; re-run the table: --tables {}",
                               c.table, t->run.commit, t->run.date.empty() ? "date unknown" : t->run.date, c.table);
      c.power.clear();
    }
  }
  return decided;
}

// UTC start of a run, to the millisecond: it tells two runs of the same commit apart.
static std::string run_timestamp() {
  const auto now = std::chrono::system_clock::now();
  const std::time_t t = std::chrono::system_clock::to_time_t(now);
  const auto ms = std::chrono::duration_cast<std::chrono::milliseconds>(now.time_since_epoch()).count() % 1000;
  std::tm tm{};
  gmtime_r(&t, &tm);
  char buf[32];
  std::strftime(buf, sizeof buf, "%Y-%m-%dT%H:%M:%S", &tm);
  return fmt::format("{}.{:03d}Z", buf, static_cast<int>(ms));
}

// Refuses, before anything is built, trained or generated, a replay whose kept values
// cannot fit (core/job_memory.h): every row keeps, per replicate, its columns and at
// least one per-sample value (the paired tests and results.h5 need them all at the
// end). profile.num_samples is capped by the split and the sampler sizes by their
// declared ranges, so profile.repeats is the size that is unbounded.
static void check_replay_memory(const ProfileFile& pf, const std::vector<TableSpec>& specs, const std::string& file) {
  long double values = 0, rows = 0;
  for (const auto& s : specs) {
    rows += s.rows.size();
    values += static_cast<long double>(s.rows.size()) * (s.table.columns.size() + 1);
    // A multimodality pass generates texts x generations motions at once (at least
    // one text of one frame and one joint each).
    if (s.table.multimodality_texts > 0)
      require_memory(generated_motions_bytes(s.table.multimodality_generations, 1, 1),
                     fmt::format("the multimodality pass of table {}", s.table.id),
                     fmt::format("table.multimodality_generations={} generations of at least one text",
                                 s.table.multimodality_generations),
                     "lower table.multimodality_generations in its spec (T2M: 30)");
  }
  require_memory(replicated_values_bytes(pf.profile.repeats, values), fmt::format("{}: this replay", file),
                 fmt::format("profile.repeats={} replicates x {} rows of the selected tables x their columns + 1 "
                             "per-sample value, kept as doubles",
                             pf.profile.repeats, static_cast<double>(rows)),
                 "lower profile.repeats (the papers use 20)");
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
  set_lengthened_training(pf.profile.lengthen_training);

  // Load and check every selected spec before anything runs: a typo fails in seconds.
  std::vector<TableSpec> specs;
  std::vector<std::string> spec_ids;  // every known table, in spec order
  std::set<std::string> seen;
  for (const auto& file : list_table_specs(opt.specs_root)) {
    TableSpec s = load_table_spec(file);
    if (!seen.insert(s.table.id).second) fail("{}: table id '{}' is used by two specs", file, s.table.id);
    spec_ids.push_back(s.table.id);
    if (!selected(s.table.id, opt.tables)) continue;
    for (auto& row : s.rows) resolve_row(pf.profile, s, row);
    specs.push_back(std::move(s));
  }
  if (specs.empty()) {
    std::string ids;
    for (auto& id : seen) ids += " " + id;
    fail("--tables {} matched no experiment spec; known tables:{}", fmt::format("{}", fmt::join(opt.tables, ",")), ids);
  }
  for (const auto& e : pf.profile.table_num_samples) {
    const std::string id = e.substr(0, e.rfind('='));  // well-formed: ProfileConfig::validate
    if (!seen.count(id)) {
      std::string ids;
      for (auto& k : seen) ids += " " + k;
      fail("{}: profile.table_num_samples names table '{}', which no experiment spec defines; known tables:{}",
           profile_file, id, ids);
    }
  }
  std::set<std::string> selected_ids;
  for (const auto& s : specs) selected_ids.insert(s.table.id);
  check_replay_memory(pf, specs, profile_file);

  ReproduceResult res;
  fs::path out_dir = fs::path(resolve_data_path(pf.profile.results_root)) / pf.profile.name;
  fs::create_directories(out_dir);
  res.results_dir = out_dir.string();
  const fs::path results_file = out_dir / "results.h5";
  ReplayRun run;
  run.commit = source_commit(source_dir());
  run.date = run_timestamp();
  run.threads = pf.profile.threads;
  run.overrides = opt.profile_overrides;
  run.settings = replay_settings(pf);

  // A partial replay (--tables) merges into what results/<profile>/ holds: every other
  // known table stays as its run left it, if that run had the same settings. Checked
  // before anything trains or runs; a full replay replaces everything.
  std::optional<StoredResults> stored;
  std::vector<const TableResult*> kept;
  if (!opt.tables.empty() && fs::exists(results_file)) {
    stored = read_results_h5(results_file.string());
    for (const auto& t : stored->tables) {
      if (selected_ids.count(t.spec.table.id)) continue;
      if (!seen.count(t.spec.table.id)) {
        std::cerr << fmt::format("note: {} holds table {}, which no spec defines any more: dropped\n",
                                 results_file.string(), t.spec.table.id);
        continue;
      }
      kept.push_back(&t);
    }
    check_kept_settings(*stored, kept, run.settings, pf.profile.name);
  }

  // Row runs and every component the rows train live under profile.runs_root.
  RunsRootScope components_root(pf.profile.runs_root);
  take_trained_runs();
  RowEvaluator ev(pf.profile);
  const std::vector<std::string> evaluator_runs = take_trained_runs();  // its training curve goes in results.h5
  {
    auto by_content = content_settings(ev);
    if (stored) check_kept_settings(*stored, kept, by_content, pf.profile.name);
    run.settings.insert(run.settings.end(), by_content.begin(), by_content.end());
  }
  ProfileHealth health(pf, ev.data());  // every prior the rows use, checked once
  std::vector<TableResult> results;
  std::set<std::string> failed_tables;
  for (const auto& spec : specs) {
    auto ts = std::chrono::steady_clock::now();
    TableResult tr;
    tr.spec = spec;
    tr.evaluator = ev.evaluator_run();
    tr.num_samples = table_tasks(pf.profile, spec.table);
    tr.repeats = pf.profile.repeats;
    tr.run = run;
    if (!spec.table.paper_numbers.empty()) {
      std::string pn = resolve_data_path(spec.table.paper_numbers);
      if (!fs::exists(pn)) fail("{}: table.paper_numbers '{}' does not exist", spec.file, spec.table.paper_numbers);
      tr.paper = load_paper_table(pn);
    }
    std::cerr << fmt::format("== {} ({} rows)\n", spec.table.id, spec.rows.size());
    std::vector<RowConfig> kept_rows;
    for (const auto& row : spec.rows) {
      try {
        RowResult r = run_row(pf, spec, row, ev);
        std::cerr << fmt::format("   {:<28} {}{}\n", row.id, r.cached ? "(cached) " : "",
                                 format_cell(r.values, spec.table.columns.front(), true));
        tr.rows.push_back(std::move(r));
        kept_rows.push_back(row);
      } catch (const UserError& e) {
        res.failures.push_back(fmt::format("{} / {}: {}", spec.table.id, row.id, e.what()));
        failed_tables.insert(spec.table.id);
        std::cerr << fmt::format("   {:<28} FAILED: {}\n", row.id, e.what());
      }
    }
    tr.spec.rows = kept_rows;
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
    results.push_back(std::move(tr));
  }

  // Every known table in spec order: re-run ones as run now, the others as kept. A
  // re-run table whose rows failed does not replace a complete earlier one of the same
  // settings (a failed partial replay leaves the previous results as they were).
  std::vector<TableResult> tables;
  std::set<std::string> replaced;
  for (const auto& id : spec_ids) {
    auto fresh = std::find_if(results.begin(), results.end(), [&](const TableResult& t) { return t.spec.table.id == id; });
    const TableResult* old = stored ? stored->find(id) : nullptr;
    if (fresh != results.end()) {
      if (!opt.tables.empty() && failed_tables.count(id) && old && old->run.settings == run.settings) {
        res.failures.push_back(fmt::format("{}: rows failed, so the table is kept from run {} ({})", id,
                                           old->run.commit, old->run.date));
        tables.push_back(*old);
        continue;
      }
      replaced.insert(id);
      tables.push_back(std::move(*fresh));
    } else if (old && std::find(kept.begin(), kept.end(), old) != kept.end()) {
      tables.push_back(*old);
    }
  }

  // Prior health over every table of the merged results (kept tables' components were
  // checked by their run: the checks are reused from RUN_DIR/health.json).
  if (pf.profile.health) {
    for (const auto& t : tables)
      if (t.kept) health.table_line(t);
  }
  double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  std::vector<ClaimCheck> claims;
  fs::path claims_file = fs::path(resolve_data_path(opt.specs_root)) / "claims.yaml";
  ClaimOptions co;
  co.reference = &ev.realism();
  co.protocol = &pf.protocol;
  if (fs::exists(claims_file))
    claims = merge_claims(check_claims(claims_file.string(), tables, co), replaced, tables, stored ? &*stored : nullptr);
  for (auto& c : claims)
    (c.verdict == "holds"          ? res.claims_hold
     : c.verdict == "contradicted" ? res.claims_contradicted
     : c.verdict == "undecided"    ? res.claims_undecided
                                   : res.claims_not_run)++;
  std::string summary = render_summary(claims, tables, pf.profile.name, seconds);
  if (pf.profile.health) {
    for (const auto& c : health.components()) {
      ++res.priors_checked;
      res.priors_healthy += c.healthy();
    }
  }
  if (res.priors_checked > 0)
    summary += fmt::format("\nPrior health ([health.md](health.md)): {} of {} trained priors and tokenizers healthy "
                           "at N = {}.\n",
                           res.priors_healthy, res.priors_checked, health.samples());
  if (!res.failures.empty()) {
    summary += "\n## Rows that failed\n\n";
    for (auto& f : res.failures) summary += "- " + f + "\n";
  }

  // Written last, results.h5 first: a replay that stops before here leaves every file of
  // results/<profile>/ as it was. Tables kept from earlier runs keep their files.
  write_results_h5(results_file.string(), tables, pf.profile.name, &ev.data().skeleton, evaluator_runs, claims,
                   stored ? stored->file : "");
  for (const auto& t : tables) {
    if (t.kept) continue;
    RenderedTable rt = render_table(t);
    fs::path base = out_dir / t.spec.table.id;
    fs::create_directories(base.parent_path());
    write_file_atomic(base.string() + ".md", rt.markdown);
    write_file_atomic(base.string() + ".csv", rt.csv);
    write_file_atomic(base.string() + ".tex", rt.latex);
    res.table_files.push_back(base.string() + ".md");
  }
  if (pf.profile.health) {
    health.write(out_dir);
    res.health_file = (out_dir / "health.md").string();
  }
  write_file_atomic(out_dir / "summary.md", summary);
  // Figures from the merged results.h5: every table's, so they never disagree with it.
  if (opt.figures) {
    std::string cmd = fmt::format("\"{}\" \"{}\" \"{}\" --out \"{}\"", opt.python,
                                  resolve_data_path("tools/figures.py"), results_file.string(),
                                  (out_dir / "figures").string());
    if (std::system(cmd.c_str()) != 0) res.failures.push_back("figures: tools/figures.py failed (see above)");
  }
  return res;
}

}  // namespace mc
