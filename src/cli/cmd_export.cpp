// `motionctl export --format bvh FILE.h5 --out DIR [--ids a,b] [--translations auto|root|all]`:
// one BVH per clip of any motion file (dataset, `sample`/`generate` output), on the
// file's own skeleton, each re-read after writing to report its round-trip error.
// `motionctl export --format weights RUN_DIR --out FILE.h5 [--probe]`: a trained flow
// prior's weights as HDF5 for Python (models/flow_weights.h), with the C++ output on a
// fixed input when --probe is given (samplers/flow_probe.h).
#include <filesystem>
#include <iostream>
#include <map>
#include <sstream>

#include "cli/commands.h"
#include "core/atomic_file.h"
#include "core/error.h"
#include "data/bvh.h"
#include "data/motion_set.h"
#include "models/flow_prior.h"
#include "models/flow_weights.h"
#include "models/trained_run.h"
#include "samplers/flow_probe.h"
#include "train/train_job.h"

namespace mc {
namespace fs = std::filesystem;

namespace {

std::string safe_file_name(const std::string& id) {
  std::string out;
  for (char c : id) out += (std::isalnum(static_cast<unsigned char>(c)) || c == '-' || c == '.' || c == '_') ? c : '_';
  while (!out.empty() && out.front() == '_') out.erase(out.begin());
  while (!out.empty() && out.back() == '_') out.pop_back();
  return out.empty() ? "clip" : out;
}

std::vector<size_t> select_clips(const MotionSet& m, const std::string& ids, const std::string& file) {
  std::vector<size_t> out;
  if (ids.empty()) {
    for (size_t i = 0; i < m.size(); ++i) out.push_back(i);
    return out;
  }
  std::map<std::string, size_t> index;
  for (size_t i = 0; i < m.size(); ++i) index[m.ids[i]] = i;
  std::stringstream ss(ids);
  for (std::string id; std::getline(ss, id, ',');) {
    if (id.empty()) continue;
    auto it = index.find(id);
    if (it == index.end())
      fail("--ids: {} has no clip with id '{}' (its first ids: {}{})", file, id, m.ids[0],
           m.size() > 1 ? ", " + m.ids[1] : "");
    out.push_back(it->second);
  }
  if (out.empty()) fail("--ids '{}' names no clip; give comma-separated clip ids", ids);
  return out;
}

// The finished flow prior run `run_dir`, checked with messages that say what
// --format weights takes.
void check_weights_source(const std::string& run_dir) {
  const fs::path dir(run_dir);
  const char* how = "give the run directory of a trained flow prior, e.g. runs/prior/flow_tiny-<hash> (`motionctl "
                    "train configs/prior/flow_tiny.yaml` prints it)";
  if (!fs::exists(dir)) fail("export --format weights: '{}' does not exist; {}", run_dir, how);
  if (!fs::is_directory(dir)) fail("export --format weights: '{}' is a file, not a run directory; {}", run_dir, how);
  if (!fs::exists(dir / "config.yaml"))
    fail("export --format weights: '{}' has no config.yaml, so it is not a training run directory; {}", run_dir, how);
  const Component model = read_model_section((dir / "config.yaml").string());
  if (model.type != "flow_prior")
    fail("export --format weights: '{}' is a run of model type '{}'; only flow priors (model.type flow_prior) can be "
         "exported; {}",
         run_dir, model.type, how);
  if (!fs::exists(dir / "DONE") || !fs::exists(dir / "checkpoints" / "final.pt"))
    fail("export --format weights: the run '{}' is not finished ({} missing); finish it with `motionctl train "
         "{}/config.yaml` (training resumes from its last checkpoint), then export again",
         run_dir, fs::exists(dir / "DONE") ? "checkpoints/final.pt is" : "DONE is", run_dir);
}

void export_weights(const std::string& run_dir, const std::string& out, bool probe, const FlowProbeOptions& popt) {
  check_weights_source(run_dir);
  if (fs::is_directory(out))
    fail("--out {}: is a folder; --format weights writes one file, e.g. --out {}/weights.h5", out, out);
  const fs::path parent = fs::path(out).parent_path();
  if (!parent.empty()) {
    std::error_code ec;
    fs::create_directories(parent, ec);
    if (ec || !fs::is_directory(parent))
      fail("--out {}: cannot create its folder '{}' ({})", out, parent.string(), ec ? ec.message() : "not a folder");
  }
  FlowPrior prior = FlowPrior::load(run_dir);
  FlowWeightsSource src;
  src.run_dir = run_dir;
  src.config_yaml = read_file(fs::path(run_dir) / "config.yaml");
  src.config_hash = run_config_hash((fs::path(run_dir) / "config.yaml").string(), {});
  std::vector<FlowWeightsGroup> extra;
  if (probe) extra.push_back(flow_probe(prior, popt));
  write_flow_weights(prior, src, out, extra);
  int64_t count = 0;
  for (const auto& p : prior.net()->parameters()) count += p.numel();
  std::cout << fmt::format("wrote {}: flow prior '{}' (config hash {}), {} parameters in {} tensors{}\n", out, run_dir,
                           src.config_hash, count, flow_weight_tensors(prior).size(),
                           probe ? "; /probe holds the C++ output on a fixed input "
                                   "(check: python3 tools/flow_reference.py check " + out + ")"
                                 : "");
}

}  // namespace

void add_export_command(CLI::App& app) {
  auto* cmd = app.add_subcommand(
      "export", "write clips of a motion file as BVH (one file per clip), or a trained flow prior's weights as HDF5");
  struct Args {
    std::string file, out, ids, format = "bvh";
    BvhOptions bvh;
    bool probe = false;
    FlowProbeOptions probe_opt;
  };
  auto a = std::make_shared<Args>();
  cmd->add_option("input", a->file,
                  "bvh: motion HDF5 file (dataset, sample or generate output); weights: a flow prior's run directory")
      ->required();
  cmd->add_option("--out", a->out, "bvh: output folder (created if missing); weights: output file (.h5)")->required();
  cmd->add_option("--format", a->format, "output format: bvh, or weights (a flow prior for Python, docs/formats.md)")
      ->check(CLI::IsMember({"bvh", "weights"}));
  cmd->add_flag("--probe", a->probe,
                "weights: also store the C++ output on a fixed input (/probe) for checking a reimplementation");
  cmd->add_option("--probe-caption", a->probe_opt.captions, "weights --probe: captions of the probe batch (repeat)");
  cmd->add_option("--probe-seed", a->probe_opt.seed, "weights --probe: seed of the probe's input joints");
  cmd->add_option("--ids", a->ids, "comma-separated clip ids (default: every clip)");
  cmd->add_option("--translations", a->bvh.translations,
                  "root: a rigid BVH (root translation only); all: every joint carries its offset, exact for any "
                  "motion; auto (default): root when it reproduces the input within 1e-4 m, else all")
      ->check(CLI::IsMember({"auto", "root", "all"}));
  cmd->add_option("--scale", a->bvh.scale, "file units per metre (default 1: metres; 100: centimetres)")
      ->check(CLI::PositiveNumber);
  cmd->callback([a, cmd] {
    const std::vector<const char*> bvh_only = {"--ids", "--translations", "--scale"};
    const std::vector<const char*> weights_only = {"--probe", "--probe-caption", "--probe-seed"};
    for (const char* o : a->format == "weights" ? bvh_only : weights_only)
      if (cmd->count(o) > 0)
        fail("{} does not apply to --format {}; it is an option of --format {}", o, a->format,
             a->format == "weights" ? "bvh" : "weights");
    if (a->format == "weights") {
      if (a->probe_opt.captions.empty()) fail("--probe-caption: give at least one caption");
      export_weights(a->file, a->out, a->probe, a->probe_opt);
      return;
    }
    MotionSet m = read_motion_file(a->file);
    // A valid file may hold no clips (an empty set round-trips); there is nothing to
    // export then, and saying so beats exiting 0 with no file written.
    if (m.size() == 0) fail("{}: holds no clips (its dataset 'lengths' is empty); there is nothing to export", a->file);
    std::vector<size_t> chosen = select_clips(m, a->ids, a->file);
    std::error_code ec;
    fs::create_directories(a->out, ec);
    if (ec || !fs::is_directory(a->out))
      fail("--out {}: cannot create the output folder ({})", a->out, ec ? ec.message() : "not a folder");
    for (size_t i : chosen) {
      BvhExport e;
      try {
        e = clip_to_bvh(m.skeleton, m.clip(i), m.lengths[i], m.fps, a->bvh);
      } catch (const UserError& err) {
        fail("{}: clip {} ('{}'): {}", a->file, i, m.ids[i], err.what());
      }
      const fs::path path = fs::path(a->out) / fmt::format("{:04d}_{}.bvh", i, safe_file_name(m.ids[i]));
      write_file_atomic(path, e.text);
      std::cout << fmt::format("wrote {}: {} frames, {} (rigid fit error {:.2e} m); re-read error {:.2e} m\n",
                               path.string(), m.lengths[i],
                               e.all_translations ? "every joint translated" : "root translation only", e.rigid_error,
                               e.written_error);
    }
  });
}

}  // namespace mc
