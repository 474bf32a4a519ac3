// Table rendering (Markdown, CSV, LaTeX), results.h5 and the claims summary of
// `motionctl reproduce`. Our numbers are mean +- 95% CI over replications; the
// paper's numbers sit beside them and rows we do not reproduce are marked so.
#include "experiments/report.h"

#include <H5Cpp.h>
#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <functional>
#include <optional>
#include <filesystem>
#include <fstream>
#include <set>
#include <sstream>

#include "core/atomic_file.h"
#include "core/error.h"
#include "core/h5_seal.h"
#include "eval/metrics.h"
#include "experiments/paired.h"

namespace mc {
namespace fs = std::filesystem;

// ------------------------------------------------------------------ paper numbers

static std::string str_or(const YAML::Node& n, const char* key, const std::string& dflt = "") {
  return n[key] && !n[key].IsNull() ? n[key].as<std::string>() : dflt;
}

PaperTable load_paper_table(const std::string& file) {
  PaperTable t;
  t.file = file;
  YAML::Node root;
  try {
    root = YAML::LoadFile(file);
  } catch (const YAML::Exception& e) {
    fail("{}: cannot read the paper numbers: {}", file, e.what());
  }
  t.paper = str_or(root, "paper");
  t.title = str_or(root, "title");
  t.source = str_or(root, "source");
  t.table = root["table"] ? root["table"].as<int>() : 0;
  if (!root["columns"] || !root["rows"]) fail("{}: paper numbers need `columns:` and `rows:`", file);
  for (auto c : root["columns"]) t.columns.push_back({str_or(c, "key"), str_or(c, "name"), str_or(c, "better")});
  int i = 0;
  for (auto r : root["rows"]) {
    PaperRow row;
    row.method = str_or(r, "method");
    row.section = str_or(r, "section");
    row.kind = str_or(r, "kind");
    row.ours_id = str_or(r, "ours_id");
    if (r["values"])
      for (auto kv : r["values"]) {
        std::string k = kv.first.as<std::string>();
        if (kv.second.IsNull()) {
          row.values[k] = std::nullopt;
        } else {
          try {
            row.values[k] = kv.second.as<double>();
          } catch (const YAML::Exception&) {
            fail("{}: rows[{}] ('{}'): value of '{}' is not a number: {}", file, i, row.method, k,
                 kv.second.as<std::string>());
          }
        }
      }
    t.rows.push_back(row);
    ++i;
  }
  return t;
}

const PaperRow* PaperTable::find(const std::string& ours_id, const std::string& section) const {
  for (const auto& r : rows)
    if (r.ours_id == ours_id && (section.empty() || r.section == section)) return &r;
  return nullptr;
}

std::string PaperTable::column_name(const std::string& key) const {
  std::string base = key.substr(0, key.find('@'));
  for (const auto& c : columns)
    if (c.key == base) return key == base ? c.name : c.name + " (" + key.substr(key.find('@') + 1) + ")";
  return key;
}

// ------------------------------------------------------------------ cells

static int decimals_for(double v) {
  double a = std::fabs(v);
  if (a == 0) return 3;
  if (a >= 1000) return 0;
  if (a >= 100) return 1;
  if (a >= 10) return 2;
  if (a >= 0.1) return 3;
  return 4;
}

std::string format_cell(const std::map<std::string, std::vector<double>>& values, const std::string& key,
                        bool with_ci) {
  auto it = values.find(key);
  if (it == values.end() || it->second.empty()) return "";
  Replicated r = summarize(it->second);
  int d = decimals_for(r.mean);
  if (!with_ci || r.n < 2) return fmt::format("{:.{}f}", r.mean, d);
  return fmt::format("{:.{}f} ± {:.{}f}", r.mean, d, r.ci95, d);
}

static std::string companion_name(const std::string& k, const PaperTable* paper);

static std::string paper_cell(const PaperRow* p, const std::string& key) {
  if (!p || !companion_name(key, nullptr).empty()) return "";
  auto it = p->values.find(key.substr(0, key.find('@')));
  if (it == p->values.end() || !it->second) return key.find('@') == std::string::npos ? "–" : "";
  double v = *it->second;
  return fmt::format("{:.{}f}", v, decimals_for(v));
}

static std::string diff_cell(const std::map<std::string, std::vector<double>>& values, const PaperRow* p,
                             const std::string& key) {
  auto it = values.find(key);
  if (!p || it == values.end() || it->second.empty()) return "";
  auto pv = p->values.find(key);
  if (pv == p->values.end() || !pv->second) return "";
  double d = summarize(it->second).mean - *pv->second;
  return fmt::format("{:+.{}f}", d, decimals_for(d));
}

static std::string csv_escape(const std::string& s) {
  if (s.find_first_of(",\"\n") == std::string::npos) return s;
  std::string o = "\"";
  for (char c : s) o += c == '"' ? std::string("\"\"") : std::string(1, c);
  return o + "\"";
}

static std::string tex_escape(const std::string& s) {
  std::string o;
  for (size_t i = 0; i < s.size(); ++i) {
    if (s.compare(i, 2, "\u00b1") == 0) {  // UTF-8 plus-minus
      o += "$\\pm$";
      ++i;
      continue;
    }
    const char c = s[i];
    if (c == '_' || c == '%' || c == '&' || c == '#' || c == '$') o += '\\';
    o += c;
  }
  return o;
}

// ------------------------------------------------------------------ tables

std::vector<std::string> display_columns(const TableResult& t) {
  auto any_row = [&](const std::string& k) {
    for (const auto& r : t.rows)
      if (r.values.count(k)) return true;
    return false;
  };
  std::vector<std::string> out;
  for (const auto& c : t.spec.table.columns) {
    out.push_back(c);
    std::vector<std::string> extra;
    if (c == "fid") extra = {"fid_floor", "kid", "kid_floor"};
    else if (c == "foot_skating")
      extra = {t.spec.table.foot_skating == "valid_frames" ? "foot_skating_padded" : "foot_skating_valid"};
    else if (c.find('@') == std::string::npos && group_averaged_metric(c))
      extra = {c + "_pooled"};
    for (auto& e : extra)
      if (any_row(e) && std::find(out.begin(), out.end(), e) == out.end()) out.push_back(e);
  }
  return out;
}

// Headers of the companion columns display_columns adds.
static std::string companion_name(const std::string& k, const PaperTable* paper) {
  auto base = [&](const std::string& b) { return paper ? paper->column_name(b) : b; };
  if (k == "fid_floor") return "FID GT floor (same N)";
  if (k == "kid") return "KID";
  if (k == "kid_floor") return "KID GT floor";
  if (k == "foot_skating_valid") return base("foot_skating") + " (valid frames)";
  if (k == "foot_skating_padded") return base("foot_skating") + " (padded 196)";
  const std::string suffix = "_pooled";
  if (k.size() > suffix.size() && k.compare(k.size() - suffix.size(), suffix.size(), suffix) == 0)
    return base(k.substr(0, k.size() - suffix.size())) + " (pooled)";
  return "";
}

std::string table_caption(const TableResult& t) {
  const TableConfig& tc = t.spec.table;
  std::set<std::string> groups;
  for (const auto& r : t.rows)
    for (const auto& g : r.samples.groups) groups.insert(g);
  std::string s = "**Protocol.** ";
  s += fmt::format("Evaluator: the T2M-style evaluator trained on the fixture{}. ",
                   t.evaluator.empty() ? "" : " (`" + t.evaluator + "`)");
  if (t.num_samples > 0)
    s += fmt::format("{} tasks per row × {} replicates, each a fresh generation; every row of the table draws the "
                     "same tasks, captions and seeds (initial noise), so rows are paired. ",
                     t.num_samples, t.repeats);
  s += "Control errors, lifting errors and foot skating are averaged as the paper does: the mean over task groups of "
       "per-group means";
  if (!groups.empty()) s += fmt::format(" ({} groups, e.g. `{}`)", groups.size(), *groups.begin());
  s += "; *(pooled)* columns are the plain mean over all tasks. ";
  s += tc.foot_skating == "valid_frames"
           ? "Foot skating over each clip's valid frames (/ (T − 1)); the padded-196 variant is labelled. "
           : "Foot skating over all 196 stored frames, padding included (/ 195), as the published "
             "OmniControl/GMD script; the valid-frame variant is labelled. ";
  s += "FID sits beside the ground-truth floor at the same N (held-out ground-truth clips against the same "
       "reference) and KID (unbiased at small N). ± = 95% CI over replicates (1.96 std / √n).\n\n";
  s += "**Differences from the paper's protocol.**\n";
  std::vector<std::string> diffs = {
      "synthetic fixture and a fixture-trained evaluator, not HumanML3D and the T2M evaluator: compare trends, not "
      "absolute values",
      fmt::format("{} tasks × {} replicates instead of the full test split × 20 replications", t.num_samples,
                  t.repeats),
      "FID, R-precision, matching and diversity are computed once over all tasks of a row, not per setting and then "
      "averaged (a setting holds too few tasks for a covariance)"};
  diffs.insert(diffs.end(), tc.differences.begin(), tc.differences.end());
  for (auto& d : diffs) s += "- " + d + "\n";
  return s;
}

RenderedTable render_table(const TableResult& t) {
  RenderedTable out;
  const std::vector<std::string> cols = display_columns(t);
  const PaperTable* paper = t.paper ? &*t.paper : nullptr;
  auto header_name = [&](const std::string& k) {
    std::string c = companion_name(k, paper);
    if (!c.empty()) return c;
    return paper ? paper->column_name(k) : k;
  };

  // Which paper rows we reproduce.
  std::set<const PaperRow*> matched;
  std::vector<const PaperRow*> row_paper;
  for (size_t i = 0; i < t.rows.size(); ++i) {
    const RowConfig& rc = t.spec.rows[i];
    const PaperRow* p = paper ? paper->find(rc.paper_id.empty() ? rc.id : rc.paper_id, rc.paper_section) : nullptr;
    row_paper.push_back(p);
    if (p) matched.insert(p);
  }

  // Markdown
  std::string& md = out.markdown;
  md += fmt::format("### {} — {}\n\n", t.spec.table.id, t.spec.table.title);
  if (!t.health.empty()) md += t.health + "\n\n";
  if (paper) md += fmt::format("Paper: {} ({}).\n\n", paper->source, paper->file);
  md += "| Method | Source |";
  for (auto& c : cols) md += " " + header_name(c) + " |";
  md += "\n|---|---|";
  for (size_t i = 0; i < cols.size(); ++i) md += "---:|";
  md += "\n";
  for (size_t i = 0; i < t.rows.size(); ++i) {
    const auto& r = t.rows[i];
    md += fmt::format("| **{}** | ours (fixture) |", r.label);
    for (auto& c : cols) md += " " + format_cell(r.values, c, true) + " |";
    md += "\n";
    if (row_paper[i]) {
      md += fmt::format("| ↳ {} | paper |", row_paper[i]->method);
      for (auto& c : cols) md += " " + paper_cell(row_paper[i], c) + " |";
      md += "\n| ↳ difference | ours − paper |";
      for (auto& c : cols) md += " " + diff_cell(r.values, row_paper[i], c) + " |";
      md += "\n";
    }
  }
  if (paper) {
    bool any = false;
    for (const auto& p : paper->rows) {
      if (matched.count(&p)) continue;
      if (!any) {
        md += "| *Paper rows not reproduced here* | | " + std::string(cols.size() > 1 ? "" : "") + "\n";
        any = true;
      }
      std::string label = p.method + (p.section.empty() ? "" : " [" + p.section + "]");
      md += fmt::format("| {} † | paper only |", label);
      for (auto& c : cols) md += " " + paper_cell(&p, c) + " |";
      md += "\n";
    }
  }
  md += "\nOurs: mean ± 95% CI over replications on the synthetic fixture (not HumanML3D: compare trends, not "
        "absolute values). † the paper's number, not reproduced by this framework.\n\n";
  md += table_caption(t);

  // CSV (long format: one line per row and metric)
  out.csv = "table,row,label,source,metric,mean,ci95,n,paper,difference\n";
  for (size_t i = 0; i < t.rows.size(); ++i) {
    const auto& r = t.rows[i];
    for (auto& c : cols) {
      auto it = r.values.find(c);
      std::string mean, ci, n;
      if (it != r.values.end() && !it->second.empty()) {
        Replicated s = summarize(it->second);
        mean = fmt::format("{:.8g}", s.mean);
        ci = fmt::format("{:.8g}", s.ci95);
        n = std::to_string(s.n);
      }
      std::string pv = paper_cell(row_paper[i], c);
      if (pv == "–") pv.clear();
      out.csv += fmt::format("{},{},{},ours,{},{},{},{},{},{}\n", csv_escape(t.spec.table.id), csv_escape(r.row_id),
                             csv_escape(r.label), csv_escape(c), mean, ci, n, pv, diff_cell(r.values, row_paper[i], c));
    }
  }
  if (paper)
    for (const auto& p : paper->rows) {
      if (matched.count(&p)) continue;
      for (auto& c : cols) {
        std::string pv = paper_cell(&p, c);
        if (pv.empty() || pv == "–") continue;
        out.csv += fmt::format("{},,{},paper only,{},,,,{},\n", csv_escape(t.spec.table.id),
                               csv_escape(p.method + (p.section.empty() ? "" : " [" + p.section + "]")), csv_escape(c),
                               pv);
      }
    }

  // LaTeX
  std::string& tex = out.latex;
  tex += "% " + t.spec.table.id + ": generated by `motionctl reproduce`; do not edit.\n";
  tex += "\\begin{tabular}{l" + std::string(cols.size(), 'r') + "}\n\\toprule\nMethod";
  for (auto& c : cols) tex += " & " + tex_escape(header_name(c));
  tex += " \\\\\n\\midrule\n";
  for (size_t i = 0; i < t.rows.size(); ++i) {
    const auto& r = t.rows[i];
    tex += tex_escape(r.label);
    for (auto& c : cols) {
      auto it = r.values.find(c);
      if (it == r.values.end() || it->second.empty()) {
        tex += " & ";
        continue;
      }
      Replicated s = summarize(it->second);
      int d = decimals_for(s.mean);
      tex += fmt::format(" & ${:.{}f}{{\\scriptstyle\\pm {:.{}f}}}$", s.mean, d, s.ci95, d);
    }
    tex += " \\\\\n";
    if (row_paper[i]) {
      tex += "\\quad\\textit{paper}";
      for (auto& c : cols) tex += " & " + paper_cell(row_paper[i], c);
      tex += " \\\\\n";
    }
  }
  if (paper) {
    bool any = false;
    for (const auto& p : paper->rows) {
      if (matched.count(&p)) continue;
      if (!any) {
        tex += "\\midrule\n";
        any = true;
      }
      tex += tex_escape(p.method) + "$^\\dagger$";
      for (auto& c : cols) {
        std::string pv = paper_cell(&p, c);
        tex += " & " + (pv == "–" ? std::string("--") : pv);
      }
      tex += " \\\\\n";
    }
  }
  tex += "\\bottomrule\n\\end{tabular}\n";
  return out;
}

// ------------------------------------------------------------------ results.h5

static void write_string_attr(H5::H5Object& obj, const char* name, const std::string& value) {
  H5::StrType type(H5::PredType::C_S1, std::max<size_t>(1, value.size()));
  H5::DataSpace scalar(H5S_SCALAR);
  obj.createAttribute(name, type, scalar).write(type, value.empty() ? std::string(" ") : value);
}

static std::string h5_name(std::string s) {
  for (char& c : s)
    if (c == '/') c = '|';
  return s;
}

// Copies the first `keep` samples of a row's examples.h5 (every dataset is indexed by
// sample along dim 0; the captions and task_ids attributes list one sample per line)
// into `dst`. The figures draw the first sample or two, and results.h5 is committed when
// it stays under 20 MB, so it keeps fewer samples than the row directory does.
static void copy_examples(const fs::path& file, H5::Group& dst, hsize_t keep) {
  H5::H5File f(file.string(), H5F_ACC_RDONLY);
  for (hsize_t i = 0; i < f.getNumObjs(); ++i) {
    std::string name = f.getObjnameByIdx(i);
    H5::DataSet ds = f.openDataSet(name);
    H5::DataSpace space = ds.getSpace();
    H5::DataType type = ds.getDataType();
    const int rank = space.getSimpleExtentNdims();
    std::vector<hsize_t> dims(std::max(rank, 1), 1);
    if (rank >= 1) space.getSimpleExtentDims(dims.data());
    if (rank >= 1 && dims[0] > keep) {
      std::vector<hsize_t> start(rank, 0), count(dims);
      count[0] = keep;
      space.selectHyperslab(H5S_SELECT_SET, count.data(), start.data());
      dims[0] = keep;
    }
    H5::DataSpace out_space = rank >= 1 ? H5::DataSpace(rank, dims.data()) : H5::DataSpace(H5S_SCALAR);
    const size_t elem = type.getSize();
    size_t n = 1;
    for (int d = 0; d < rank; ++d) n *= dims[d];
    std::vector<char> buf(ds.getStorageSize() > 0 ? n * elem : 0);
    if (!buf.empty()) ds.read(buf.data(), type, out_space, space);
    // Deflated: padded frames and masks are mostly zeros.
    H5::DSetCreatPropList props;
    if (rank >= 1 && n > 0) {
      props.setChunk(rank, dims.data());
      props.setShuffle();
      props.setDeflate(6);
    }
    H5::DataSet out = dst.createDataSet(name, type, out_space, props);
    if (!buf.empty()) out.write(buf.data(), type);
  }
  for (int i = 0; i < f.getNumAttrs(); ++i) {
    H5::Attribute a = f.openAttribute(static_cast<unsigned>(i));
    H5::StrType st = a.getStrType();
    std::string v;
    a.read(st, v);
    if (a.getName() == "captions" || a.getName() == "task_ids") {
      size_t cut = std::string::npos;
      for (hsize_t k = 0; k < keep; ++k) {  // the keep-th line break ends the kept lines
        cut = v.find('\n', k == 0 ? 0 : cut + 1);
        if (cut == std::string::npos) break;
      }
      if (cut != std::string::npos) v.resize(cut);
    }
    write_string_attr(dst, a.getName().c_str(), v);
  }
}

// A row's examples.h5 (written sealed by write_examples, experiments/row_runner.cpp;
// rows cached before that are unsealed) read as every HDF5 input is: a sealed one is
// checked, an unsealed one is copied once in a forked child first, so a damaged file is a UserError naming it, never a crash
// half-way through writing results.h5.
static void copy_row_examples(const fs::path& file, H5::Group& dst) {
  const std::string fix = fmt::format("delete the row's run directory '{}' and re-run reproduce to recompute it",
                                      file.parent_path().string());
  auto copy = [&](H5::Group& g) {
    try {
      copy_examples(file, g, kExamplesInResults);
    } catch (const H5::Exception& e) {
      fail("{}: cannot copy the row's examples ({}); {}", file.string(), e.getDetailMsg(), fix);
    }
  };
  guard_h5_read(file.string(), "row examples file", fix, [&] {
    H5::FileAccPropList fapl;
    fapl.setCore(1 << 20, false);  // in memory, never written
    H5::H5File mem("examples_probe.h5", H5F_ACC_TRUNC, H5::FileCreatPropList::DEFAULT, fapl);
    H5::Group g = mem.createGroup("probe");
    copy(g);
  });
  copy(dst);
}

// metrics.csv of a training run as one dataset per column.
static void copy_training_curves(const fs::path& run_dir, H5::Group& dst) {
  std::ifstream in(run_dir / "metrics.csv");
  std::string header;
  if (!std::getline(in, header)) return;
  std::vector<std::string> cols;
  std::stringstream hs(header);
  for (std::string c; std::getline(hs, c, ',');) cols.push_back(c);
  std::vector<std::vector<double>> data(cols.size());
  for (std::string line; std::getline(in, line);) {
    std::stringstream ls(line);
    size_t i = 0;
    for (std::string cell; std::getline(ls, cell, ',') && i < cols.size(); ++i) {
      char* end = nullptr;
      double v = std::strtod(cell.c_str(), &end);
      data[i].push_back(end == cell.c_str() ? std::nan("") : v);
    }
    for (; i < cols.size(); ++i) data[i].push_back(std::nan(""));
  }
  for (size_t i = 0; i < cols.size(); ++i) {
    if (cols[i].empty() || dst.nameExists(h5_name(cols[i]))) continue;
    hsize_t n = data[i].size();
    H5::DataSpace space(1, &n);
    dst.createDataSet(h5_name(cols[i]), H5::PredType::NATIVE_DOUBLE, space)
        .write(data[i].data(), H5::PredType::NATIVE_DOUBLE);
  }
  write_string_attr(dst, "run_dir", run_dir.string());
}

// One '\n'-joined attribute for a list (components, overrides, settings).
static std::string join_lines(const std::vector<std::string>& v) {
  std::string s;
  for (size_t i = 0; i < v.size(); ++i) s += (i ? "\n" : "") + v[i];
  return s;
}

// /training/<experiment>|<run> of a component run directory.
static std::string training_name(const std::string& run_dir) {
  return fs::path(run_dir).parent_path().filename().string() + "|" + fs::path(run_dir).filename().string();
}

static void write_table_group(H5::Group& g, const TableResult& t) {
  write_string_attr(g, "title", t.spec.table.title);
  std::string cols;
  for (auto& c : t.spec.table.columns) cols += (cols.empty() ? "" : ",") + c;
  write_string_attr(g, "columns", cols);
  // The run the table comes from: a partial replay keeps it beside tables of other runs.
  write_string_attr(g, "commit", t.run.commit);
  write_string_attr(g, "date", t.run.date);
  write_string_attr(g, "threads", std::to_string(t.run.threads));
  write_string_attr(g, "overrides", join_lines(t.run.overrides));
  std::vector<std::string> settings;
  for (const auto& [k, v] : t.run.settings) settings.push_back(k + "=" + v);
  write_string_attr(g, "settings", join_lines(settings));
  write_string_attr(g, "seconds", fmt::format("{:.3f}", t.seconds));
  write_string_attr(g, "num_samples", std::to_string(t.num_samples));
  write_string_attr(g, "repeats", std::to_string(t.repeats));
  write_string_attr(g, "evaluator", t.evaluator);
  write_string_attr(g, "health", t.health);
  for (size_t i = 0; i < t.rows.size(); ++i) {
    const auto& r = t.rows[i];
    H5::Group rg = g.createGroup(h5_name(r.row_id));
    write_string_attr(rg, "label", r.label);
    write_string_attr(rg, "run_dir", r.run_dir);
    write_string_attr(rg, "generator", r.generator_description);
    write_string_attr(rg, "order", std::to_string(i));
    write_string_attr(rg, "components", join_lines(r.components));
    for (const auto& [k, v] : r.values) {
      hsize_t n = v.size();
      H5::DataSpace space(1, &n);
      auto ds = rg.createDataSet(h5_name(k), H5::PredType::NATIVE_DOUBLE, space);
      ds.write(v.data(), H5::PredType::NATIVE_DOUBLE);
    }
  }
  if (t.paper) {
    H5::Group pg = g.createGroup("_paper");
    write_string_attr(pg, "source", t.paper->source);
    for (size_t i = 0; i < t.paper->rows.size(); ++i) {
      const auto& p = t.paper->rows[i];
      H5::Group rg = pg.createGroup(fmt::format("{:03d}", i));
      write_string_attr(rg, "method", p.method);
      write_string_attr(rg, "section", p.section);
      write_string_attr(rg, "kind", p.kind);
      write_string_attr(rg, "ours_id", p.ours_id);
      for (const auto& [k, v] : p.values) {
        if (!v) continue;
        H5::DataSpace scalar(H5S_SCALAR);
        double x = *v;
        rg.createDataSet(h5_name(k), H5::PredType::NATIVE_DOUBLE, scalar).write(&x, H5::PredType::NATIVE_DOUBLE);
      }
    }
  }
}

// Copies `name` (an absolute path) of `src` to the same path in `dst`, bytes as they were.
static void copy_object(const H5::H5File& src, H5::H5File& dst, const std::string& name) {
  if (H5Ocopy(src.getId(), name.c_str(), dst.getId(), name.c_str(), H5P_DEFAULT, H5P_DEFAULT) < 0)
    fail("{}: cannot copy {} from the earlier results; move the file away or re-run every table (omit --tables)",
         src.getFileName(), name);
}

void write_results_h5(const std::string& path, const std::vector<TableResult>& tables, const std::string& profile,
                      const Skeleton* skeleton, const std::vector<std::string>& extra_components,
                      const std::vector<ClaimCheck>& claims, const std::string& kept_from) {
  bool any_kept = false;
  for (const auto& t : tables) any_kept = any_kept || t.kept;
  if (any_kept && kept_from.empty()) fail("write_results_h5: kept tables need the results.h5 they come from");
  AtomicOutput out(path);
  {
    H5::Exception::dontPrint();
    std::optional<H5::H5File> old;
    if (any_kept) try {
        old.emplace(kept_from, H5F_ACC_RDONLY);
      } catch (const H5::Exception& e) {
        fail("{}: cannot read the earlier replay's results ({}); move it away or re-run every table (omit --tables)",
             kept_from, e.getDetailMsg());
      }
    // The user block holds the checksum seal (core/h5_seal.h), written once the file is closed.
    H5::FileCreatPropList fcpl;
    fcpl.setUserblock(kH5SealBlock);
    H5::H5File f(out.tmp_path().string(), H5F_ACC_TRUNC, fcpl);
    H5::Group root = f.openGroup("/");
    write_string_attr(root, "profile", profile);
    // Every commit the tables come from, in table order (one for a full replay).
    std::vector<std::string> commits;
    for (const auto& t : tables)
      if (std::find(commits.begin(), commits.end(), t.run.commit) == commits.end()) commits.push_back(t.run.commit);
    std::string commit;
    for (size_t i = 0; i < commits.size(); ++i) commit += (i ? ", " : "") + commits[i];
    write_string_attr(root, "commit", commit);
    H5::Group tg = f.createGroup("tables");
    for (const auto& t : tables) {
      if (t.kept) {
        copy_object(*old, f, "/tables/" + h5_name(t.spec.table.id));
        continue;
      }
      H5::Group g = tg.createGroup(h5_name(t.spec.table.id));
      write_table_group(g, t);
    }
    // Examples of each row (figures), the skeleton to draw them, training curves.
    H5::Group eg = f.createGroup("examples");
    std::set<std::string> components(extra_components.begin(), extra_components.end());
    std::set<std::string> kept_components;
    for (const auto& t : tables) {
      if (t.kept) {
        const std::string name = "/examples/" + h5_name(t.spec.table.id);
        if (old->nameExists(name)) copy_object(*old, f, name);
        for (const auto& r : t.rows) kept_components.insert(r.components.begin(), r.components.end());
        continue;
      }
      H5::Group tg2;
      bool made = false;
      for (const auto& r : t.rows) {
        for (auto& c : r.components) components.insert(c);
        fs::path ex = fs::path(r.run_dir) / "examples.h5";
        if (!fs::exists(ex)) continue;
        if (!made) {
          tg2 = eg.createGroup(h5_name(t.spec.table.id));
          made = true;
        }
        H5::Group rg = tg2.createGroup(h5_name(r.row_id));
        copy_row_examples(ex, rg);
      }
    }
    if (skeleton) {
      H5::Group sg = f.createGroup("skeleton");
      std::vector<int32_t> parents(skeleton->parents.begin(), skeleton->parents.end());
      hsize_t n = parents.size();
      H5::DataSpace space(1, &n);
      sg.createDataSet("parents", H5::PredType::NATIVE_INT32, space).write(parents.data(), H5::PredType::NATIVE_INT32);
      std::string names;
      for (size_t j = 0; j < skeleton->joint_names.size(); ++j) names += (j ? "\n" : "") + skeleton->joint_names[j];
      write_string_attr(sg, "joint_names", names);
    }
    H5::Group trg = f.createGroup("training");
    for (const auto& c : components) {
      if (!fs::exists(fs::path(c) / "metrics.csv")) continue;
      std::string name = training_name(c);
      if (trg.nameExists(name)) continue;
      H5::Group cg = trg.createGroup(name);
      copy_training_curves(c, cg);
    }
    // Kept tables' components: their curves as the earlier run stored them.
    for (const auto& c : kept_components) {
      const std::string name = training_name(c);
      if (!trg.nameExists(name) && old->nameExists("/training/" + name)) copy_object(*old, f, "/training/" + name);
    }
    H5::Group cg = f.createGroup("claims");
    for (size_t i = 0; i < claims.size(); ++i) {
      const auto& c = claims[i];
      if (cg.nameExists(h5_name(c.id))) continue;
      H5::Group g = cg.createGroup(h5_name(c.id));
      write_string_attr(g, "table", c.table);
      write_string_attr(g, "text", c.text);
      write_string_attr(g, "verdict", c.verdict);
      write_string_attr(g, "evidence", c.evidence);
      write_string_attr(g, "power", c.power);
      write_string_attr(g, "definition", c.definition);
      write_string_attr(g, "order", std::to_string(i));
    }
  }  // closed (flushed) here, the earlier file too, before the seal covers its bytes
  seal_h5_file(out.tmp_path().string(), fmt::format("results file '{}'", path));
  out.commit();
}

// ------------------------------------------------------------------ results.h5, read back

namespace {

// What to do about an earlier results.h5 that cannot be read: a full replay writes it anew.
constexpr const char* kResultsFix = "move it away or re-run every table (omit --tables)";

std::string read_string_attr(const H5::H5Object& obj, const char* name) {
  if (!obj.attrExists(name)) return "";
  H5::Attribute a = obj.openAttribute(name);
  std::string v;
  a.read(a.getStrType(), v);
  while (!v.empty() && v.back() == '\0') v.pop_back();
  return v == " " ? "" : v;  // write_string_attr stores an empty string as one space
}

std::vector<std::string> split_lines(const std::string& s) {
  std::vector<std::string> out;
  std::stringstream in(s);
  for (std::string line; std::getline(in, line);)
    if (!line.empty()) out.push_back(line);
  return out;
}

std::string from_h5_name(std::string s) {
  for (char& c : s)
    if (c == '|') c = '/';
  return s;
}

double number_attr(const H5::H5Object& obj, const char* name, const std::string& where) {
  const std::string v = read_string_attr(obj, name);
  if (v.empty()) return 0;
  char* end = nullptr;
  const double x = std::strtod(v.c_str(), &end);
  if (end == v.c_str() || *end != '\0' || !std::isfinite(x))
    fail("{}: attribute `{}` is '{}', not a number", where, name, v);
  return x;
}

StoredResults read_results_h5_unchecked(const std::string& path, bool copy_all) {
  StoredResults s;
  s.file = path;
  H5::Exception::dontPrint();
  try {
    H5::H5File f(path, H5F_ACC_RDONLY);
    if (!f.nameExists("tables"))
      fail("{}: no /tables group, so this is not a results.h5 of `motionctl reproduce`; move it away or re-run every "
           "table (omit --tables)",
           path);
    const std::string root_commit = read_string_attr(f.openGroup("/"), "commit");
    H5::Group tables = f.openGroup("tables");
    for (hsize_t i = 0; i < tables.getNumObjs(); ++i) {
      const std::string name = tables.getObjnameByIdx(i);
      H5::Group g = tables.openGroup(name);
      const std::string where = path + ": /tables/" + name;
      TableResult t;
      t.kept = true;
      t.spec.table.id = from_h5_name(name);
      t.spec.table.title = read_string_attr(g, "title");
      std::stringstream cols(read_string_attr(g, "columns"));
      for (std::string c; std::getline(cols, c, ',');) t.spec.table.columns.push_back(c);
      // Written before tables recorded their run: the file's commit, no date or settings.
      t.run.commit = g.attrExists("commit") ? read_string_attr(g, "commit") : root_commit;
      t.run.date = read_string_attr(g, "date");
      t.run.threads = static_cast<int>(number_attr(g, "threads", where));
      t.run.overrides = split_lines(read_string_attr(g, "overrides"));
      for (const auto& line : split_lines(read_string_attr(g, "settings"))) {
        const size_t eq = line.find('=');
        if (eq == std::string::npos) fail("{}: settings line '{}' is not key=value", where, line);
        t.run.settings.emplace_back(line.substr(0, eq), line.substr(eq + 1));
      }
      t.seconds = number_attr(g, "seconds", where);
      t.num_samples = static_cast<int>(number_attr(g, "num_samples", where));
      t.repeats = static_cast<int>(number_attr(g, "repeats", where));
      t.evaluator = read_string_attr(g, "evaluator");
      t.health = read_string_attr(g, "health");
      std::vector<std::pair<double, RowResult>> rows;
      for (hsize_t j = 0; j < g.getNumObjs(); ++j) {
        const std::string rname = g.getObjnameByIdx(j);
        if (rname == "_paper") continue;
        H5::Group rg = g.openGroup(rname);
        RowResult r;
        r.row_id = from_h5_name(rname);
        r.label = read_string_attr(rg, "label");
        r.run_dir = read_string_attr(rg, "run_dir");
        r.generator_description = read_string_attr(rg, "generator");
        r.components = split_lines(read_string_attr(rg, "components"));
        r.cached = true;
        for (hsize_t k = 0; k < rg.getNumObjs(); ++k) {
          const std::string metric = rg.getObjnameByIdx(k);
          H5::DataSet ds = rg.openDataSet(metric);
          const hssize_t n = ds.getSpace().getSimpleExtentNpoints();
          std::vector<double> v(static_cast<size_t>(std::max<hssize_t>(n, 0)));
          if (!v.empty()) ds.read(v.data(), H5::PredType::NATIVE_DOUBLE);
          r.values[from_h5_name(metric)] = std::move(v);
        }
        rows.emplace_back(number_attr(rg, "order", where + "/" + rname), std::move(r));
      }
      std::stable_sort(rows.begin(), rows.end(), [](const auto& a, const auto& b) { return a.first < b.first; });
      for (auto& [order, r] : rows) {
        RowConfig rc;
        rc.id = r.row_id;
        rc.label = r.label;
        t.spec.rows.push_back(rc);
        t.rows.push_back(std::move(r));
      }
      s.tables.push_back(std::move(t));
    }
    if (f.nameExists("claims")) {
      H5::Group cg = f.openGroup("claims");
      for (hsize_t i = 0; i < cg.getNumObjs(); ++i) {
        H5::Group g = cg.openGroup(cg.getObjnameByIdx(i));
        ClaimCheck c;
        c.id = from_h5_name(cg.getObjnameByIdx(i));
        c.table = read_string_attr(g, "table");
        c.text = read_string_attr(g, "text");
        c.verdict = read_string_attr(g, "verdict");
        c.evidence = read_string_attr(g, "evidence");
        c.power = read_string_attr(g, "power");
        c.definition = read_string_attr(g, "definition");
        s.claims.push_back(std::move(c));
      }
    }
    // Every object a partial replay may copy, copied once into memory: a damaged one
    // fails here (in the probe's child), not half-way through writing the merged file.
    if (copy_all) {
      H5::FileAccPropList fapl;
      fapl.setCore(1 << 20, false);
      H5::H5File mem("results_probe.h5", H5F_ACC_TRUNC, H5::FileCreatPropList::DEFAULT, fapl);
      for (const char* top : {"tables", "examples", "training"})
        if (f.nameExists(top)) copy_object(f, mem, std::string("/") + top);
    }
  } catch (const H5::Exception& e) {
    fail("{}: cannot read the earlier replay's results ({}); {}", path, e.getDetailMsg(), kResultsFix);
  }
  return s;
}

}  // namespace

const TableResult* StoredResults::find(const std::string& table_id) const {
  for (const auto& t : tables)
    if (t.spec.table.id == table_id) return &t;
  return nullptr;
}

const ClaimCheck* StoredResults::claim(const std::string& id) const {
  for (const auto& c : claims)
    if (c.id == id) return &c;
  return nullptr;
}

// results.h5 is sealed: a changed byte is refused before libhdf5 reads it (a byte flip
// could otherwise crash it or, worse, put a wrong number in a kept table). One written
// before seals is read in a forked child first, copying everything a partial replay may
// copy, so a damaged one fails there and not half-way through the merged file.
StoredResults read_results_h5(const std::string& path) {
  guard_h5_read(path, "the earlier replay's results", kResultsFix, [&] { read_results_h5_unchecked(path, true); });
  return read_results_h5_unchecked(path, false);
}

// ------------------------------------------------------------------ claims

namespace {

const TableResult* find_table(const std::vector<TableResult>& tables, const std::string& id) {
  for (const auto& t : tables)
    if (t.spec.table.id == id) return &t;
  return nullptr;
}
const RowResult* find_row(const TableResult& t, const std::string& id) {
  for (const auto& r : t.rows)
    if (r.row_id == id) return &r;
  return nullptr;
}
bool has(const RowResult* r, const std::string& metric) {
  return r && r->values.count(metric) && !r->values.at(metric).empty();
}

}  // namespace

// The test of row a against row b (b = nullptr: of a alone) on `metric`: the stratified
// (Rao-Wu) paired bootstrap over tasks when both rows kept per-sample records for it, else the
// paired replicate differences (metrics kept per replicate only: time, parameters,
// multimodality).
static std::optional<PairedTest> test_rows(const RowResult& a, const RowResult* b, const std::string& metric,
                                           const ClaimOptions& o) {
  EvalProtocol p = o.protocol ? *o.protocol : EvalProtocol{};
  if (auto t = bootstrap_difference(a.samples, b ? &b->samples : nullptr, metric, o.reference, p, o.bootstrap))
    return t;
  if (!has(&a, metric) || (b && !has(b, metric))) return std::nullopt;
  return replicate_difference(a.values.at(metric), b ? &b->values.at(metric) : nullptr, o.bootstrap.factor);
}

static std::string describe_test(const std::string& what, const PairedTest& t) {
  return fmt::format("{} = {:.4g} [{:.4g}, {:.4g}] ({})", what, t.estimate, t.lo, t.hi, t.method);
}

// For an undecided test: how many tasks (bootstrap) or replicates would decide it.
static std::string power_note(const PairedTest& t, double margin, bool bootstrap) {
  const double n = samples_to_decide(t, margin);
  if (!std::isfinite(n)) return "no observed effect: no sample size decides it";
  return fmt::format("≈ {:.0f} {} would decide it at the observed effect (now {})", n,
                     bootstrap ? "tasks per row" : "replicates", t.n);
}

// Folds several verdicts (best: every other row; monotone: every consecutive pair).
static std::string fold_verdicts(const std::vector<std::string>& v) {
  if (std::count(v.begin(), v.end(), "contradicted")) return "contradicted";
  if (std::count(v.begin(), v.end(), "undecided")) return "undecided";
  return "holds";
}

// claims.yaml: a list of {id, text, table, kind, ...}:
//   better:   row a beats row b on metric (direction lower|higher): the paired difference a - b;
//             with `factor: f` (lower only), a beats f x b: the paired a - f b
//   zero:     row's metric <= tol: its bootstrap interval against tol
//   monotone: rows in order improve on metric (direction): every consecutive pair is a better test
//   best:     row beats each of `others` on metric
// better, best and monotone take `metrics: [...]` instead of `metric`: every pair is
// tested on each metric and all must hold (per-group keys such as avg_err@density=1).
// Verdicts: holds (the interval excludes the other side), contradicted (the interval lies
// on the wrong side), undecided (it contains 0, or tol). No verdict from overlapping intervals.
std::vector<ClaimCheck> check_claims(const std::string& claims_file, const std::vector<TableResult>& tables,
                                     const ClaimOptions& opt) {
  std::vector<ClaimCheck> out;
  YAML::Node root;
  try {
    root = YAML::LoadFile(claims_file);
  } catch (const YAML::Exception& e) {
    fail("{}: cannot read claims: {}", claims_file, e.what());
  }
  if (!root["claims"] || !root["claims"].IsSequence()) fail("{}: expected a `claims:` list", claims_file);
  int idx = 0;
  for (auto c : root["claims"]) {
    ClaimCheck cc;
    cc.id = str_or(c, "id", fmt::format("claim{}", idx));
    cc.text = str_or(c, "text");
    cc.table = str_or(c, "table");
    {  // what a kept verdict must match: the entry as written, its text aside
      YAML::Node def = YAML::Clone(c);
      def.remove("text");
      YAML::Emitter e;
      e << YAML::Flow << def;
      cc.definition = e.c_str();
    }
    std::string kind = str_or(c, "kind");
    std::string metric = str_or(c, "metric");
    // `metrics: [m1, m2, ...]` instead of `metric`: every pair is tested on each of them
    // and all must hold (e.g. "at every density": avg_err@density=1, ...).
    std::vector<std::string> metrics;
    if (c["metrics"]) {
      if (c["metric"]) fail("{}: claim '{}' sets both metric and metrics; keep one", claims_file, cc.id);
      if (!c["metrics"].IsSequence() || c["metrics"].size() == 0)
        fail("{}: claim '{}': metrics must be a non-empty list of metric keys", claims_file, cc.id);
      for (auto m : c["metrics"]) metrics.push_back(m.as<std::string>());
      if (kind == "zero") fail("{}: claim '{}': metrics (a list) is for better, best and monotone claims", claims_file, cc.id);
      metric = metrics.front();
    } else {
      metrics.push_back(metric);
    }
    std::string dir = str_or(c, "direction", "lower");
    if (dir != "lower" && dir != "higher")
      fail("{}: claim '{}': direction '{}' is not lower or higher", claims_file, cc.id, dir);
    ++idx;
    if (kind != "better" && kind != "best" && kind != "zero" && kind != "monotone")
      fail("{}: claim '{}' has unknown kind '{}' (better, best, zero, monotone)", claims_file, cc.id, kind);
    const TableResult* t = find_table(tables, cc.table);
    if (!t || t->kept) {  // a kept table's claims keep their run's verdicts (reproduce.cpp, merge_claims)
      cc.verdict = "not run";
      cc.evidence = "table " + cc.table + " was not part of this reproduction";
      out.push_back(cc);
      continue;
    }
    // Each claim draws its own deterministic bootstrap stream (seeded by its id).
    ClaimOptions o = opt;
    o.bootstrap.seed = opt.bootstrap.seed ^ std::hash<std::string>{}(cc.id);
    if (c["factor"]) {
      if (kind != "better" || dir != "lower")
        fail("{}: claim '{}': factor is for better claims with direction lower (a <= factor x b)", claims_file, cc.id);
      try {
        o.bootstrap.factor = c["factor"].as<double>();
      } catch (const YAML::Exception&) {
        o.bootstrap.factor = -1;
      }
      if (!(o.bootstrap.factor > 0) || !std::isfinite(o.bootstrap.factor))
        fail("{}: claim '{}': factor must be a positive number (a <= factor x b), got '{}'", claims_file, cc.id,
             YAML::Dump(c["factor"]));
    }
    std::vector<std::string> rows;
    if (c["rows"])
      for (auto r : c["rows"]) rows.push_back(r.as<std::string>());
    // (a, b) pairs to test as "a better than b".
    std::vector<std::pair<std::string, std::string>> pairs;
    if (kind == "better") pairs.push_back({str_or(c, "row"), str_or(c, "than")});
    if (kind == "best")
      for (auto& r : rows) pairs.push_back({str_or(c, "row"), r});
    if (kind == "monotone")
      for (size_t i = 1; i < rows.size(); ++i) pairs.push_back({rows[i], rows[i - 1]});
    std::vector<std::string> verdicts, evidence, power;
    bool missing = false;
    if (kind == "zero") {
      const double tol = c["tol"] ? c["tol"].as<double>() : 1e-4;
      const RowResult* ra = find_row(*t, str_or(c, "row"));
      auto test = ra ? test_rows(*ra, nullptr, metric, o) : std::nullopt;
      if (!test) {
        missing = true;
      } else {
        verdicts.push_back(zero_verdict(*test, tol));
        evidence.push_back(describe_test(fmt::format("{} {}", ra->row_id, metric), *test) +
                           fmt::format("; tolerance {:.1g}", tol));
        if (verdicts.back() == "undecided") power.push_back(power_note(*test, tol, !ra->samples.empty()));
      }
    }
    for (auto& [a, b] : pairs) {
      const RowResult* ra = find_row(*t, a);
      const RowResult* rb = find_row(*t, b);
      for (const std::string& m : metrics) {
        auto test = ra && rb ? test_rows(*ra, rb, m, o) : std::nullopt;
        if (!test) {
          missing = true;
          metric = m;
          break;
        }
        verdicts.push_back(better_verdict(*test, dir));
        evidence.push_back(describe_test(
            o.bootstrap.factor == 1.0 ? fmt::format("{} {} − {}", m, a, b)
                                      : fmt::format("{} {} − {:g} × {}", m, a, o.bootstrap.factor, b),
            *test));
        if (verdicts.back() == "undecided")
          power.push_back(a + " vs " + b + (metrics.size() > 1 ? " (" + m + ")" : "") + ": " +
                          power_note(*test, 0.0, !ra->samples.empty() && !rb->samples.empty()));
      }
      if (missing) break;
    }
    if (missing || verdicts.empty()) {
      cc.verdict = "not run";
      cc.evidence = "a row or the metric " + metric + " is missing";
    } else {
      cc.verdict = fold_verdicts(verdicts);
      for (size_t i = 0; i < evidence.size(); ++i) cc.evidence += (i ? "; " : "") + evidence[i];
      cc.evidence += fmt::format(" ({} is better)", dir);
      if (cc.verdict == "undecided")
        for (auto& p : power) cc.power += (cc.power.empty() ? "" : "; ") + p;
    }
    out.push_back(cc);
  }
  return out;
}

std::string render_summary(const std::vector<ClaimCheck>& claims, const std::vector<TableResult>& tables,
                           const std::string& profile, double seconds) {
  std::string s = fmt::format("# Reproduction summary — profile `{}`\n\n", profile);
  // The runs the tables come from, in table order: one for a full replay, more when a
  // partial replay (`--tables`) kept tables of earlier runs.
  std::vector<std::pair<const ReplayRun*, std::vector<const TableResult*>>> runs;
  std::map<const TableResult*, size_t> run_of;
  int fresh = 0;
  for (const auto& t : tables) {
    fresh += !t.kept;
    auto it = std::find_if(runs.begin(), runs.end(), [&](const auto& r) { return r.first->same_run(t.run); });
    if (it == runs.end()) {
      runs.emplace_back(&t.run, std::vector<const TableResult*>{});
      it = runs.end() - 1;
    }
    it->second.push_back(&t);
    run_of[&t] = static_cast<size_t>(it - runs.begin()) + 1;
  }
  if (runs.size() <= 1) {
    s += fmt::format("Commit {}; {} tables; wall time {:.1f} min (including training of missing components).\n\n",
                     runs.empty() ? "" : runs[0].first->commit, tables.size(), seconds / 60.0);
  } else {
    s += fmt::format("**Assembled from {} runs.** A partial replay (`--tables`) replaces the tables it re-runs and "
                     "keeps every other table, and the verdicts of its claims, as the run that produced it left them "
                     "(docs/choices.md, \"Partial replays\"). The latest run re-ran {} of the {} tables in {:.1f} min "
                     "(including training of missing components).\n\n",
                     runs.size(), fresh, tables.size(), seconds / 60.0);
  }
  s += "| Run | Commit | Date (UTC) | Threads | Overrides (`--set`) | Tables |\n|---|---|---|---|---|---|\n";
  for (size_t i = 0; i < runs.size(); ++i) {
    const ReplayRun& r = *runs[i].first;
    const bool latest = std::any_of(runs[i].second.begin(), runs[i].second.end(), [](auto* t) { return !t->kept; });
    std::string ov, ids;
    for (auto& o : r.overrides) ov += (ov.empty() ? "`" : ", `") + o + "`";
    for (auto* t : runs[i].second) ids += (ids.empty() ? "" : ", ") + t->spec.table.id;
    s += fmt::format("| {}{} | {} | {} | {} | {} | {} |\n", i + 1, latest ? " (latest)" : "", r.commit,
                     r.date.empty() ? "unknown" : r.date, r.threads > 0 ? std::to_string(r.threads) : "all cores",
                     ov.empty() ? "–" : ov, ids);
  }
  // Settings are checked equal across runs before a partial replay keeps a table, so
  // the first table's stand for all of them.
  const TableResult* with_settings = nullptr;
  for (const auto& t : tables)
    if (!t.run.settings.empty()) with_settings = with_settings ? with_settings : &t;
  if (with_settings) {
    std::string list;
    for (const auto& [k, v] : with_settings->run.settings) list += (list.empty() ? "`" : ", `") + k + "=" + v + "`";
    s += fmt::format("\nSettings of every table (a partial replay refuses to keep tables replayed with others): {}.\n",
                     list);
  }
  s += "\n";
  int holds = 0, contra = 0, undecided = 0, notrun = 0;
  for (auto& c : claims)
    (c.verdict == "holds" ? holds : c.verdict == "contradicted" ? contra : c.verdict == "undecided" ? undecided : notrun)++;
  const int run = holds + contra + undecided;
  s += fmt::format("Claims: {} hold, {} contradicted, {} undecided, {} not run ({} of {} run claims decided, {:.0f}%).\n\n",
                   holds, contra, undecided, notrun, holds + contra, run, run ? 100.0 * (holds + contra) / run : 0.0);
  s += "Each claim is tested on the paired difference between its rows: every row of a table sees the same tasks, "
       "captions and initial noise (same seed per replicate), and resampling over tasks gives a 95% interval [lo, hi] "
       "of the difference: strata are the task groups, coarsened until each holds at least 2 tasks; per-sample "
       "metrics by the Rao-Wu bootstrap (n_h - 1 draws with replacement per stratum), set-level ones (FID, KID, "
       "diversity) recomputed from the stored embeddings of half-samples drawn without replacement, re-centred on "
       "the estimate; the same draws for both rows; mean over replicates (docs/choices.md, \"Bootstrap strata and "
       "draws\"). **holds**: the "
       "interval lies on the claimed side of 0 (of the tolerance for zero claims); **contradicted**: on the other "
       "side; **undecided**: it contains 0. Metrics kept per replicate only (time, parameters, multimodality) use a "
       "Student-t interval of the paired replicate differences. For undecided claims the last column gives the tasks "
       "that would decide them at the observed effect: n ≈ ((1.96 + 0.84) sd / effect)², sd = the bootstrap SE × √n.\n\n";
  s += "| Claim | Table | Verdict | Evidence | Samples to decide |\n|---|---|---|---|---|\n";
  for (auto& c : claims)
    s += fmt::format("| {} | {} | **{}** | {} | {} |\n", c.text, c.table, c.verdict, c.evidence, c.power);
  s += "\n## Tables\n\n";
  for (auto& t : tables)
    s += fmt::format("- [{}]({}.md): {} ({} rows, {:.0f} s{})\n", t.spec.table.id, t.spec.table.id,
                     t.spec.table.title, t.rows.size(), t.seconds,
                     runs.size() > 1 ? fmt::format(", run {}", run_of[&t]) : "");
  return s;
}

}  // namespace mc
