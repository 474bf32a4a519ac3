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

struct TableResult {
  TableSpec spec;
  std::optional<PaperTable> paper;
  std::vector<RowResult> rows;
  double seconds = 0;
  std::string health;  // Markdown line on the health of the priors its rows used ('' = none checked)
  std::string evaluator;     // evaluator run the table was scored with ('' = unknown)
  int num_samples = 0, repeats = 0;
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

// results.h5: /tables/<table id>/<row id>/<metric> = replicate values (attrs mean,
// ci95), row attrs label/run_dir/generator; /paper/<table id>/... the paper's cells.
// /examples/<table>/<row>/ copies each row's examples.h5 (a few samples with their
// targets, for figures), /skeleton the skeleton to draw them, /training/<run>/ the
// metrics.csv columns of every trained component the rows used.
void write_results_h5(const std::string& path, const std::vector<TableResult>& tables, const std::string& profile,
                      const std::string& commit, const Skeleton* skeleton = nullptr,
                      const std::vector<std::string>& extra_components = {});

// A claim of a paper checked on our numbers (experiments/claims.yaml).
struct ClaimCheck {
  std::string id, text, table, verdict;  // verdict: holds | contradicted | undecided | not run
  std::string evidence;                  // the paired difference, its 95% interval and how it was drawn
  std::string power;                     // undecided: the samples that would decide it at the observed effect
};
struct ClaimOptions {
  const RealismReference* reference = nullptr;  // FID/KID on resampled samples (nullptr: replicate fallback)
  const EvalProtocol* protocol = nullptr;       // diversity pairs (nullptr: defaults)
  BootstrapOptions bootstrap;
};
std::vector<ClaimCheck> check_claims(const std::string& claims_file, const std::vector<TableResult>& tables,
                                     const ClaimOptions& options = {});
std::string render_summary(const std::vector<ClaimCheck>& claims, const std::vector<TableResult>& tables,
                           const std::string& profile, double seconds, const std::string& commit);

// The value shown for (row, column): `key` of the row's replicates; "" when absent.
std::string format_cell(const std::map<std::string, std::vector<double>>& values, const std::string& key, bool with_ci);

}  // namespace mc
