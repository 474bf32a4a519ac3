// Rendering the replay: per table Markdown/CSV/LaTeX (ours +- CI beside the
// paper's numbers), results.h5 with every raw replicate, and the claims summary.
#pragma once
#include <map>
#include <optional>
#include <string>
#include <vector>

#include "data/skeleton.h"
#include "experiments/experiment.h"

namespace mc {

// experiments/paper_numbers/<paper>/tableN.yaml (format: experiments/paper_numbers/README.md).
struct PaperColumn {
  std::string key, name, better;  // better: lower | higher | closer_to_real | ""
};
struct PaperRow {
  std::string method, section, kind, ours_id;
  std::map<std::string, std::optional<double>> values;
};
struct PaperTable {
  std::string file, paper, title, source;
  int table = 0;
  std::vector<PaperColumn> columns;
  std::vector<PaperRow> rows;
  const PaperRow* find(const std::string& ours_id, const std::string& section) const;
  std::string column_name(const std::string& key) const;  // the paper's header, or the key
};
PaperTable load_paper_table(const std::string& file);  // UserError naming the file and row

// The run a table of results.h5 came from. A partial replay (`--tables`) replaces the
// tables it re-ran and keeps the others from the runs that produced them, so every
// table carries its own (docs/choices.md, "Partial replays").
struct ReplayRun {
  std::string commit, date;            // git commit of the source tree; UTC start of the run
  int threads = 0;                     // profile.threads: shown, not checked (it does not change what is measured)
  std::vector<std::string> overrides;  // the run's --set overrides
  // What the numbers depend on, key=value (profile.num_samples, data_sha1, protocol.*, ...):
  // a partial replay refuses to keep tables whose settings differ from its own.
  std::vector<std::pair<std::string, std::string>> settings;
  bool same_run(const ReplayRun& o) const {
    return commit == o.commit && date == o.date && threads == o.threads && overrides == o.overrides;
  }
};

struct TableResult {
  TableSpec spec;
  std::optional<PaperTable> paper;
  std::vector<RowResult> rows;
  double seconds = 0;
  std::string health;  // Markdown line on the health of the priors its rows used ('' = none checked)
  std::string evaluator;     // evaluator run the table was scored with ('' = unknown)
  int num_samples = 0, repeats = 0;
  ReplayRun run;
  bool kept = false;  // read back from an earlier run's results.h5: rows without per-sample records
};

// The columns a table shows: its spec's, each followed by its labelled companions when
// some row has them (fid: the ground-truth floor at the same N, KID and its floor;
// group-averaged metrics: the pooled mean; foot_skating: the other frame convention).
std::vector<std::string> display_columns(const TableResult& t);
// The caption under a table: evaluator, N, replicates, averaging and frame conventions,
// and every remaining difference from the paper's protocol.
std::string table_caption(const TableResult& t);

struct RenderedTable {
  std::string markdown, csv, latex;
};
RenderedTable render_table(const TableResult& t);

// A claim of a paper checked on our numbers (experiments/claims.yaml).
struct ClaimCheck {
  std::string id, text, table, verdict;  // verdict: holds | contradicted | undecided | not run
  std::string evidence;                  // the paired difference, its 95% interval and how it was drawn
  std::string power;                     // undecided: the samples that would decide it at the observed effect
  std::string definition;  // the claim's entry without its text: a kept verdict needs the same one
};

// results.h5 (layout: docs/formats.md): /tables/<table id>/<row id>/<metric> = replicate
// values, table attrs with the run it came from (ReplayRun), row attrs label/run_dir/
// generator/components; /tables/<table>/_paper the paper's cells; /examples/<table>/<row>/
// a few samples of each row with their targets (figures), /skeleton to draw them,
// /training/<run>/ the metrics.csv columns of every trained component the rows used;
// /claims/<id> every claim's verdict. Tables with `kept` set are copied verbatim from
// `kept_from` (an earlier results.h5) with their examples and training curves.
// Written atomically and sealed (core/h5_seal.h).
void write_results_h5(const std::string& path, const std::vector<TableResult>& tables, const std::string& profile,
                      const Skeleton* skeleton = nullptr, const std::vector<std::string>& extra_components = {},
                      const std::vector<ClaimCheck>& claims = {}, const std::string& kept_from = "");

// What an earlier replay left in results.h5: its tables (kept = true; rows with their
// replicate values and components, no per-sample records) and the claims it decided.
// A file written before tables recorded their run has empty ReplayRun settings. Its
// seal (core/h5_seal.h) is checked first; one written before seals is read in a
// forked child first. Either way a damaged file is a UserError naming it and the fix,
// never a crash or a kept table with wrong numbers.
struct StoredResults {
  std::string file;
  std::vector<TableResult> tables;
  std::vector<ClaimCheck> claims;
  const TableResult* find(const std::string& table_id) const;
  const ClaimCheck* claim(const std::string& id) const;
};
StoredResults read_results_h5(const std::string& path);
struct ClaimOptions {
  const RealismReference* reference = nullptr;  // FID/KID on resampled samples (nullptr: replicate fallback)
  const EvalProtocol* protocol = nullptr;       // diversity pairs (nullptr: defaults)
  BootstrapOptions bootstrap;
};
std::vector<ClaimCheck> check_claims(const std::string& claims_file, const std::vector<TableResult>& tables,
                                     const ClaimOptions& options = {});
// summary.md. `tables` holds every table of results.h5, kept ones included; its header
// says which run (commit, date, threads, --set overrides) each table comes from and the
// settings they share. `seconds`: this run's wall time.
std::string render_summary(const std::vector<ClaimCheck>& claims, const std::vector<TableResult>& tables,
                           const std::string& profile, double seconds);

// The value shown for (row, column): `key` of the row's replicates; "" when absent.
std::string format_cell(const std::map<std::string, std::vector<double>>& values, const std::string& key, bool with_ci);

}  // namespace mc
