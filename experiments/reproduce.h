// `motionctl reproduce`: every table of both papers (and the cross-method
// benchmark) on the fixture under one profile, rendered to results/<profile>/.
#pragma once
#include <string>
#include <vector>

namespace mc {

struct ReproduceOptions {
  std::string profile = "smoke";               // name (configs/profile/<name>.yaml) or file
  std::vector<std::string> tables;             // ids or prefixes ("projflow", "anchorroute/table4"); empty = all
  std::vector<std::string> profile_overrides;  // e.g. profile.num_samples=8
  std::string specs_root = "experiments";      // where the table specs live
  bool figures = true;
  std::string python = "/usr/bin/python3";
};

struct ReproduceResult {
  std::string results_dir;
  std::vector<std::string> table_files;  // Markdown per table
  std::vector<std::string> failures;     // "table/row: message"
  int claims_hold = 0, claims_contradicted = 0, claims_undecided = 0, claims_not_run = 0;
  std::string health_file;             // results/<profile>/health.md
  int priors_checked = 0, priors_healthy = 0;
};

// Lists the experiment specs under specs_root (tableN.yaml files outside paper_numbers/), sorted.
std::vector<std::string> list_table_specs(const std::string& specs_root);

// The commit a replay stamps on its results: `git rev-parse --short HEAD` of the
// checkout at `dir`, with "+dirty" when a tracked file under what the numbers depend on
// (src, eval, experiments, configs, tools, CMakeLists.txt) differs from HEAD, so a
// summary made by uncommitted code does not claim a commit's name; "unknown" outside a
// git checkout or without git.
std::string source_commit(const std::string& dir);

ReproduceResult reproduce(const ReproduceOptions& opt);

}  // namespace mc
