// Partial replays (`motionctl reproduce --tables`) merge into results/<profile>/: on
// two synthetic tables of ground-truth rows (nothing to train but a tiny evaluator),
// a table re-run replaces only its own entries and claims, the other table's stay
// byte for byte, a settings mismatch or a damaged or pre-merge results.h5 is exit 2
// leaving every file as it was, and a table whose rows fail keeps its earlier entry.
#include <catch2/catch.hpp>

#include <H5Cpp.h>

#include <fstream>
#include <regex>

#include "test_util.h"

using namespace mc::test;

namespace {

// Every object under `path` of an HDF5 file as text: names, string attributes and the
// raw bytes of each dataset (hex), so two dumps are equal iff the subtree is.
void dump_object(H5::H5File& f, const std::string& path, std::string& out) {
  auto dump_attrs = [&](H5::H5Object& o) {
    std::vector<std::string> lines;
    for (int i = 0; i < o.getNumAttrs(); ++i) {
      H5::Attribute a = o.openAttribute(static_cast<unsigned>(i));
      std::string v;
      a.read(a.getStrType(), v);
      lines.push_back("  @" + a.getName() + "=" + v + "\n");
    }
    std::sort(lines.begin(), lines.end());
    for (auto& l : lines) out += l;
  };
  if (f.childObjType(path) == H5O_TYPE_GROUP) {
    H5::Group g = f.openGroup(path);
    out += path + "/\n";
    dump_attrs(g);
    std::vector<std::string> names;
    for (hsize_t i = 0; i < g.getNumObjs(); ++i) names.push_back(g.getObjnameByIdx(i));
    for (auto& n : names) dump_object(f, path + "/" + n, out);
  } else {
    H5::DataSet ds = f.openDataSet(path);
    const size_t bytes = static_cast<size_t>(ds.getSpace().getSimpleExtentNpoints()) * ds.getDataType().getSize();
    std::vector<unsigned char> buf(bytes);
    if (bytes) ds.read(buf.data(), ds.getDataType());
    out += path + " =";
    for (unsigned char c : buf) out += fmt::format("{:02x}", c);
    out += "\n";
    dump_attrs(ds);
  }
}

std::string dump(const fs::path& file, const std::string& path) {
  H5::H5File f(file.string(), H5F_ACC_RDONLY);
  if (!f.nameExists(path)) return "<missing " + path + ">";
  std::string out;
  dump_object(f, path, out);
  return out;
}

std::vector<std::string> table_ids(const fs::path& file) {
  H5::H5File f(file.string(), H5F_ACC_RDONLY);
  H5::Group g = f.openGroup("tables");
  std::vector<std::string> out;
  for (hsize_t i = 0; i < g.getNumObjs(); ++i) out.push_back(g.getObjnameByIdx(i));
  return out;
}

std::string attr(const fs::path& file, const std::string& path, const std::string& name) {
  H5::H5File f(file.string(), H5F_ACC_RDONLY);
  H5::Group g = f.openGroup(path);
  H5::Attribute a = g.openAttribute(name);
  std::string v;
  a.read(a.getStrType(), v);
  return v;
}

// The summary line of a claim (its text is unique in the test's claims.yaml).
std::string claim_line(const std::string& summary, const std::string& text) {
  const size_t at = summary.find("| " + text + " |");
  if (at == std::string::npos) return "<no line for " + text + ">";
  return summary.substr(at, summary.find('\n', at) - at);
}

void write_spec(const fs::path& file, const std::string& id, const std::string& rows) {
  fs::create_directories(file.parent_path());
  std::ofstream(file) << "table:\n  id: " << id << "\n  title: \"synthetic " << id << "\"\n"
                      << "  protocol: experiments/protocols/anchors_root_3d.yaml\n"
                      << "  columns: [control_error, fid]\nrows:\n"
                      << rows;
}

const std::string kGt = "  - {id: gt, label: Ground truth, generator: experiments/generators/ground_truth.yaml}\n";

}  // namespace

TEST_CASE("reproduce --tables merges into results/<profile>/: other tables and their claims stay, settings must match",
          "[experiments]") {
  TempDir dir("partial");
  REQUIRE(run_motionctl(fmt::format("fixture configs/data/smoke.yaml output={} fixture.num_clips=60",
                                    (dir.path / "fx.h5").string()))
              .exit_code == 0);
  const std::string fx = (dir.path / "fx.h5").string(), runs = (dir.path / "runs").string();
  std::ofstream(dir.path / "evaluator.yaml")
      << "run: {experiment: evaluator, name: ci, seed: 7, log_every: 10, checkpoint_every: 100, root: " << runs << "}\n"
      << "data: {path: " << fx << ", fixture: '', window: 0}\n"
      << "model: {type: t2m_evaluator, word_dim: 32, text_hidden: 32, movement_dim: 32, motion_hidden: 32, "
         "embed_dim: 32, max_words: 24, margin: 10.0, dropout: 0.0}\n"
      << "optim: {steps: 10, batch_size: 8, lr: 1.0e-3, warmup: 2, schedule: cosine, min_lr_ratio: 0.1, "
         "grad_clip: 1.0, ema_decay: 0.0}\n";
  const fs::path profile = dir.path / "ci.yaml";
  std::ofstream(profile) << "profile:\n  name: ci\n  data: " << fx << "\n  data_fixture: ''\n  evaluator: "
                         << (dir.path / "evaluator.yaml").string()
                         << "\n  split: test\n  num_samples: 4\n  repeats: 2\n  seed: 1\n  threads: 1\n"
                         << "  runs_root: " << runs << "\n  results_root: " << (dir.path / "results").string() << "\n"
                         << "protocol: {r_precision_pool: 4, diversity_pairs: 4, multimodality_pairs: 2, "
                            "control_thresholds: [0.5, 0.2]}\n";
  const fs::path specs = dir.path / "specs";
  write_spec(specs / "t" / "a.yaml", "t/a", kGt);
  write_spec(specs / "t" / "b.yaml", "t/b", kGt);
  auto write_claims = [&](const std::string& extra) {
    std::ofstream(specs / "claims.yaml")
        << "claims:\n"
        << "  - {id: a_exact, table: t/a, kind: zero, row: gt, metric: control_error, tol: 1.0e-4, text: A exact}\n"
        << "  - {id: b_exact, table: t/b, kind: zero, row: gt, metric: control_error, tol: 1.0e-4, text: B exact}\n"
        << extra;
  };
  write_claims("");
  auto replay = [&](const std::string& args) {
    auto r = run_motionctl(fmt::format("reproduce --profile {} --specs {} --no-figures {}", profile.string(),
                                       specs.string(), args));
    INFO(args << "\n" << r.output);
    return r;
  };
  const fs::path out = dir.path / "results" / "ci", h5 = out / "results.h5", summary = out / "summary.md";

  // Table A alone, then table B alone: both tables and both verdicts end up there.
  REQUIRE(replay("--tables t/a").exit_code == 0);
  CHECK(table_ids(h5) == std::vector<std::string>{"t|a"});
  CHECK(claim_line(slurp(summary), "A exact").find("**holds**") != std::string::npos);
  CHECK(claim_line(slurp(summary), "B exact").find("**not run**") != std::string::npos);
  const std::string a_md = slurp(out / "t" / "a.md");
  REQUIRE(replay("--tables t/b").exit_code == 0);
  CHECK(table_ids(h5) == std::vector<std::string>{"t|a", "t|b"});
  std::string s = slurp(summary);
  CHECK(claim_line(s, "A exact").find("**holds**") != std::string::npos);
  CHECK(claim_line(s, "B exact").find("**holds**") != std::string::npos);
  CHECK(s.find("Assembled from 2 runs") != std::string::npos);
  CHECK(s.find("profile.num_samples=4") != std::string::npos);
  CHECK(s.find("[t/a](t/a.md)") != std::string::npos);
  CHECK(s.find("[t/b](t/b.md)") != std::string::npos);
  CHECK(slurp(out / "t" / "a.md") == a_md);  // the other table's files are left alone
  CHECK(fs::exists(out / "t" / "a.csv"));
  CHECK(fs::exists(out / "t" / "a.tex"));
  // Each table says which run it came from.
  CHECK(attr(h5, "/tables/t|a", "date") != attr(h5, "/tables/t|b", "date"));
  CHECK(attr(h5, "/tables/t|a", "settings").find("profile.num_samples=4") != std::string::npos);
  CHECK(attr(h5, "/tables/t|a", "settings").find("data_content_sha1=") != std::string::npos);
  CHECK(attr(h5, "/claims/b_exact", "verdict") == "holds");

  // Re-running A (now with a second row and a new claim on B) replaces A and leaves B's
  // entries, examples and claim byte for byte; the new claim on B was never decided.
  const std::string b_before = dump(h5, "/tables/t|b") + dump(h5, "/examples/t|b") + dump(h5, "/claims/b_exact");
  const std::string b_line = claim_line(s, "B exact");
  write_spec(specs / "t" / "a.yaml", "t/a",
             kGt + "  - {id: gt2, label: Ground truth again, generator: experiments/generators/ground_truth.yaml}\n");
  write_claims("  - {id: b_new, table: t/b, kind: zero, row: gt, metric: fid, tol: 1.0e-4, text: B new}\n");
  REQUIRE(replay("--tables t/a").exit_code == 0);
  CHECK(dump(h5, "/tables/t|b") + dump(h5, "/examples/t|b") + dump(h5, "/claims/b_exact") == b_before);
  CHECK(dump(h5, "/tables/t|a").find("/tables/t|a/gt2/") != std::string::npos);
  s = slurp(summary);
  CHECK(claim_line(s, "B exact") == b_line);
  CHECK(claim_line(s, "B new").find("**not run**") != std::string::npos);
  CHECK(claim_line(s, "B new").find("--tables t/b") != std::string::npos);

  // A full replay on the same cached rows, into another folder, decides B's claim the
  // same way and stores the same replicate values: a merged summary is what a full run gives.
  REQUIRE(replay("--set profile.results_root=" + (dir.path / "full").string()).exit_code == 0);
  const fs::path full = dir.path / "full" / "ci" / "results.h5";
  CHECK(dump(full, "/tables/t|b/gt/control_error") == dump(h5, "/tables/t|b/gt/control_error"));
  CHECK(dump(full, "/tables/t|b/gt/fid") == dump(h5, "/tables/t|b/gt/fid"));
  CHECK(claim_line(slurp(dir.path / "full" / "ci" / "summary.md"), "B exact") == b_line);

  // Other settings than the kept table's: exit 2 naming the setting, both values and the
  // ways out; nothing in results/ci/ changes.
  const std::string h5_bytes = slurp(h5), summary_bytes = slurp(summary);
  {
    auto r = replay("--tables t/a --set profile.num_samples=3");
    CHECK(r.exit_code == 2);
    CHECK(r.output.find("profile.num_samples=4") != std::string::npos);
    CHECK(r.output.find("profile.num_samples=3") != std::string::npos);
    CHECK(r.output.find("t/b") != std::string::npos);
    CHECK(r.output.find("--set profile.num_samples=4") != std::string::npos);
    CHECK(r.output.find("omit --tables") != std::string::npos);
    auto p = replay("--tables t/a --set protocol.diversity_pairs=3");
    CHECK(p.exit_code == 2);
    CHECK(p.output.find("protocol.diversity_pairs") != std::string::npos);
  }
  CHECK(slurp(h5) == h5_bytes);
  CHECK(slurp(summary) == summary_bytes);

  // The ground truth counts by what it holds, not by its bytes: the same fixture built
  // elsewhere (its provenance names another output path, so other bytes) and moved into
  // place keeps the tables comparable; a fixture with other clips at the same path does not.
  {
    const fs::path saved = dir.path / "fx_saved.h5", elsewhere = dir.path / "fx_elsewhere.h5";
    fs::copy_file(fx, saved);
    REQUIRE(run_motionctl(fmt::format("fixture configs/data/smoke.yaml output={} fixture.num_clips=60",
                                      elsewhere.string()))
                .exit_code == 0);
    REQUIRE(slurp(elsewhere) != slurp(saved));
    fs::copy_file(elsewhere, fx, fs::copy_options::overwrite_existing);
    CHECK(replay("--tables t/a").exit_code == 0);
    REQUIRE(run_motionctl(fmt::format("fixture configs/data/smoke.yaml output={} fixture.num_clips=60 fixture.seed=99 "
                                      "--force",
                                      fx))
                .exit_code == 0);
    auto r = replay("--tables t/a");
    CHECK(r.exit_code == 2);
    CHECK(r.output.find("data_content_sha1") != std::string::npos);
    CHECK(r.output.find("ground-truth data") != std::string::npos);
    fs::copy_file(saved, fx, fs::copy_options::overwrite_existing);
  }

  // A re-run table whose rows fail keeps its earlier entry (non-zero exit, the failure listed).
  {
    const std::string a_before = dump(h5, "/tables/t|a");
    write_spec(specs / "t" / "a.yaml", "t/a",
               kGt + "  - {id: broken, generator: experiments/generators/ground_truth.yaml, overrides: "
                     "[generator.joints=21]}\n");
    auto r = replay("--tables t/a");
    INFO(r.output);
    CHECK(r.exit_code != 0);  // failed rows: reproduce reports them and fails
    CHECK(r.output.find("broken") != std::string::npos);
    CHECK(dump(h5, "/tables/t|a") == a_before);
    CHECK(dump(h5, "/tables/t|b") + dump(h5, "/examples/t|b") + dump(h5, "/claims/b_exact") == b_before);
    CHECK(slurp(summary).find("kept from run") != std::string::npos);
  }

  // A damaged results.h5 and one written before tables recorded their settings are
  // exit 2 naming the file, and stay as they were.
  {
    const fs::path legacy_dir = dir.path / "results" / "legacy";
    fs::create_directories(legacy_dir);
    std::ofstream(legacy_dir / "results.h5") << "not an HDF5 file";
    auto r = replay("--tables t/a --set profile.name=legacy");
    CHECK(r.exit_code == 2);
    CHECK(r.output.find((legacy_dir / "results.h5").string()) != std::string::npos);
    CHECK(slurp(legacy_dir / "results.h5") == "not an HDF5 file");
    fs::remove(legacy_dir / "results.h5");
    {
      H5::H5File f((legacy_dir / "results.h5").string(), H5F_ACC_TRUNC);
      H5::Group t = f.createGroup("tables").createGroup("t|b");
      H5::StrType type(H5::PredType::C_S1, 5);
      t.createAttribute("title", type, H5::DataSpace(H5S_SCALAR)).write(type, std::string("old B"));
    }
    auto l = replay("--tables t/a --set profile.name=legacy");
    CHECK(l.exit_code == 2);
    CHECK(l.output.find("before replays recorded their settings") != std::string::npos);
    CHECK(l.output.find("t/b") != std::string::npos);
    CHECK(!fs::exists(legacy_dir / "summary.md"));
  }
}
