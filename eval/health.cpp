// The prior health check: reference and floor clips, samples through the generator
// registry, the text-to-motion and realism metrics beside the ground truth, targets,
// and the health.md / health.json reports.
#include "eval/health.h"

#include <fmt/ranges.h>
#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <cmath>
#include <filesystem>

#include "control/control_task.h"
#include "core/atomic_file.h"
#include "core/error.h"
#include "core/run_dir.h"
#include "data/fixture/fixture_build.h"
#include "data/motion_set.h"
#include "data/skeleton.h"
#include "eval/t2m_evaluator.h"
#include "samplers/motion_generator.h"
#include "train/dependencies.h"
#include "train/dependency_record.h"
#include "train/train_job.h"
#include "train/trainer.h"

namespace mc {
namespace fs = std::filesystem;

void HealthOptions::visit(FieldVisitor& v) {
  v("run_dir", run_dir, "the trained run to check (model.type flow_prior, tmd_prior, masked_prior or vq_tokenizer)");
  v("samples", samples, "N: generated samples = reference clips = held-out floor clips (>= 3)");
  v("seed", seed, "generation seed; evaluation replicate r reshuffles R-precision pools with seed + r");
  v("evaluator", evaluator,
    "evaluator training config ('' = the configs/eval/evaluator_*.yaml whose data.path is the checked data)");
  v("evaluator_overrides", evaluator_overrides, "key=value overrides of the evaluator config");
  v("data", data, "motion file whose reference.split is the reference ('' = data.path of the run's config)");
  v("reference", reference, "the split the samples are compared with (default test)");
  v("ground_truth", ground_truth,
    "self-check: score the reference clips themselves (ground_truth generator) through the same pipeline");
  v("generator", generator,
    "generator file ('' = experiments/generators/<flow|tmd|masked|vq_reconstruction>.yaml by model type)");
  v("generator_overrides", generator_overrides, "key=value overrides of the generator file");
  v("substitutions", substitutions,
    "path=value overrides applied only where the generator file has the path (a reproduce profile's)");
  v("threads", threads, "torch CPU threads (0 = all cores, or $OMP_NUM_THREADS when set)", at_least(0));
  v("device", device, "torch device: cpu, cuda, cuda:N");
  v("protocol", protocol,
    "evaluation protocol (R-precision pools are capped at N; each repeat reshuffles pools and diversity pairs)");
  v("targets", targets, "health targets: pass/fail per row, all must pass for a healthy verdict");
}

// ---------------------------------------------------------------- report

bool HealthReport::healthy() const { return failed().empty(); }

std::vector<std::string> HealthReport::failed() const {
  std::vector<std::string> out;
  for (const auto& m : metrics)
    if (m.pass && !*m.pass) out.push_back(m.label);
  return out;
}

const HealthMetric* HealthReport::find(const std::string& key) const {
  for (const auto& m : metrics)
    if (m.key == key) return &m;
  return nullptr;
}

const std::vector<std::string>& health_model_types() {
  static const std::vector<std::string> types = {"flow_prior", "tmd_prior", "masked_prior", "vq_tokenizer"};
  return types;
}

namespace {

// How each model type is sampled: the generator file and the key naming the run in it.
struct TypeGenerator {
  const char* file;
  const char* run_key;
};
TypeGenerator generator_for(const std::string& type) {
  if (type == "flow_prior") return {"experiments/generators/flow.yaml", "generator.prior.run_dir"};
  if (type == "tmd_prior") return {"experiments/generators/tmd.yaml", "generator.prior_run"};
  if (type == "masked_prior") return {"experiments/generators/masked.yaml", "generator.prior_run"};
  return {"experiments/generators/vq_reconstruction.yaml", "generator.tokenizer_run"};
}

std::string same_path(const std::string& p) { return fs::weakly_canonical(fs::absolute(p)).string(); }

std::vector<JointsView> views(const MotionSet& m) {
  std::vector<JointsView> v;
  for (size_t i = 0; i < m.size(); ++i) v.push_back(joints_view(m, i));
  return v;
}

// Evaluator-free figures of one motion set.
std::map<std::string, double> realism(const MotionSet& m, const EvalProtocol& p) {
  std::map<std::string, double> out;
  out["foot_skating"] = evaluator_free_metrics(m, "health", p, "", nullptr).at("foot_skating");
  auto v = views(m);
  out["acceleration"] = mean_abs_acceleration(v, m.fps);
  out["bone_length_std_mm"] = bone_length_std_mm(v, m.skeleton);
  FloorPenetration fp = toe_floor_penetration(v, m.skeleton);
  out["toe_penetration_m"] = fp.depth;
  out["toe_below_floor_fraction"] = fp.frame_fraction;
  return out;
}

// Mean over `repeats` replicates of the T2M metrics (pools and pairs reshuffled by seed + r).
std::map<std::string, double> mean_t2m(const EvalEmbeddings& e, const EvalProtocol& p, int64_t seed) {
  std::map<std::string, double> sum;
  for (int r = 0; r < p.repeats; ++r)
    for (auto& [k, v] : t2m_metrics(e, p, static_cast<uint64_t>(seed) + r)) sum[k] += v;
  for (auto& [k, v] : sum) v /= p.repeats;
  return sum;
}

std::string range_text(const std::string& split, size_t from, size_t to) {
  return fmt::format("{}[{}:{}]", split, from, to);
}

}  // namespace

std::string default_evaluator_config(const std::string& data_path) {
  const fs::path dir = resolve_data_path("configs/eval");
  std::vector<fs::path> files;
  if (fs::is_directory(dir))
    for (auto& e : fs::directory_iterator(dir)) {
      const std::string name = e.path().filename().string();
      if (e.path().extension() == ".yaml" && name.rfind("evaluator_", 0) == 0) files.push_back(e.path());
    }
  std::sort(files.begin(), files.end());
  const std::string want = same_path(resolve_data_path(data_path));
  // Several evaluators may train on the same data (standard and paper sizes): the
  // one with the fewest training steps is the default (--evaluator picks another).
  std::string best;
  int best_steps = 0;
  for (const auto& f : files) {
    TrainJobConfig job = load_job<TrainJobConfig>(f.string(), {});
    if (same_path(resolve_data_path(job.data.path)) != want) continue;
    if (best.empty() || job.optim.steps < best_steps) {
      best = f.string();
      best_steps = job.optim.steps;
    }
  }
  if (!best.empty()) return best;
  fail("no evaluator config in {} trains on '{}' (the data being checked); pass --evaluator CFG", dir.string(),
       data_path);
}

HealthReport check_health(const HealthOptions& options) {
  HealthOptions opt = options;  // config_hash visits (non-const)
  HealthReport rep;
  rep.options_hash = config_hash(opt);
  rep.run_dir = opt.run_dir;
  rep.ground_truth = opt.ground_truth;
  rep.seed = opt.seed;
  rep.samples = opt.samples;

  // ---- the run and its model type
  if (opt.run_dir.empty()) fail("no run directory given (motionctl health RUN_DIR)");
  const fs::path run(opt.run_dir);
  if (!fs::is_directory(run)) fail("run directory '{}' does not exist", opt.run_dir);
  const fs::path cfg_file = run / "config.yaml";
  if (!fs::exists(cfg_file)) fail("'{}' is not a run directory: it has no config.yaml", opt.run_dir);
  try {
    YAML::Node root = YAML::LoadFile(cfg_file.string());
    if (root["model"] && root["model"]["type"]) rep.model_type = root["model"]["type"].as<std::string>();
  } catch (const YAML::Exception& e) {
    fail("{}: cannot read model.type: {}", cfg_file.string(), e.what());
  }
  const auto& types = health_model_types();
  if (std::find(types.begin(), types.end(), rep.model_type) == types.end())
    fail("run '{}' has model type '{}', which the health check does not cover (it checks {})", opt.run_dir,
         rep.model_type, fmt::format("{}", fmt::join(types, ", ")));
  // FID and KID need 2 samples; R-precision top-3 needs pools of at least 3.
  if (opt.samples < 3)
    fail("samples = {}: the health check needs at least 3 samples (R-precision top-3 ranks pools of >= 3)",
         opt.samples);
  TrainJobConfig job;
  parse_config(compose_config(cfg_file.string()), job);

  // ---- data: reference = the first N clips of reference.split (test); floor = N held-out clips of the other
  std::string data_path = opt.data.empty() ? job.data.path : opt.data;
  if (!fs::exists(resolve_data_path(data_path))) {
    if (!opt.data.empty() || job.data.fixture.empty())
      fail("data file '{}' does not exist{}", data_path,
           opt.data.empty() ? fmt::format(" (data.path of {})", cfg_file.string()) : "");
    build_fixture(resolve_data_path(job.data.fixture), {fmt::format("output={}", job.data.path)}, false);
  }
  data_path = resolve_data_path(data_path);
  rep.data = data_path;
  MotionSet data = read_motion_file(data_path);
  const std::string ref_split = opt.reference.split, other = ref_split == "test" ? "val" : "test";
  const auto ref_all = data.indices_of_split(ref_split), other_all = data.indices_of_split(other);
  const size_t N = static_cast<size_t>(opt.samples);
  if (N > ref_all.size())
    fail("samples = {} is larger than the {} split of {} ({} clips)", opt.samples, ref_split, data_path,
         ref_all.size());
  std::vector<size_t> ref_idx(ref_all.begin(), ref_all.begin() + N), floor_idx;
  rep.reference = range_text(ref_split, 0, N);
  if (other_all.size() >= N) {
    floor_idx.assign(other_all.begin(), other_all.begin() + N);
    rep.floor_reference = range_text(other, 0, N);
  } else if (ref_all.size() >= 2 * N) {
    floor_idx.assign(ref_all.begin() + N, ref_all.begin() + 2 * N);
    rep.floor_reference = range_text(ref_split, N, 2 * N);
  } else {
    fail("samples = {}: the ground-truth floor needs {} held-out clips, but the {} split of {} has {} and its {} "
         "split {} beyond the {} reference clips; lower --samples",
         opt.samples, N, other, data_path, other_all.size(), ref_split, ref_all.size() - N, N);
  }
  const MotionSet reference = data.subset(ref_idx), held_out = data.subset(floor_idx);

  // ---- evaluator (trained on first use, as `motionctl eval` does)
  const std::string ev_cfg = opt.evaluator.empty() ? default_evaluator_config(data_path) : opt.evaluator;
  if (!fs::exists(resolve_data_path(ev_cfg))) fail("evaluator config '{}' does not exist", ev_cfg);
  TrainResult ev_run = run_train(resolve_data_path(ev_cfg), opt.evaluator_overrides);
  rep.evaluator_run = ev_run.run_dir.string();
  rep.evaluator_sha1 = weights_sha1(rep.evaluator_run);
  if (!opt.ground_truth) rep.run_sha1 = weights_sha1(opt.run_dir);
  T2MEvaluator ev = T2MEvaluator::load(rep.evaluator_run);

  // ---- samples: the registry's generator for the model type (or the ground truth)
  RunConfig rc;
  rc.seed = opt.seed;
  rc.threads = opt.threads;
  rc.device = opt.device;
  GeneratorContext ctx;
  ctx.device = setup_torch(rc);
  std::string gen_file;
  std::vector<std::string> gen_ov;
  if (opt.ground_truth) {
    gen_file = "experiments/generators/ground_truth.yaml";
    gen_ov.push_back(fmt::format("generator.joints={}", data.num_joints()));
  } else {
    TypeGenerator tg = generator_for(rep.model_type);
    gen_file = opt.generator.empty() ? tg.file : opt.generator;
    gen_ov.push_back(fmt::format("{}={}", tg.run_key, opt.run_dir));
  }
  gen_ov.insert(gen_ov.end(), opt.generator_overrides.begin(), opt.generator_overrides.end());
  if (!fs::exists(resolve_data_path(gen_file))) fail("generator file '{}' does not exist", gen_file);
  Component gen_cfg("generator");
  parse_component_file(resolve_data_path(gen_file), "generator", opt.substitutions, gen_ov, gen_cfg);
  Component proto("protocol", "text_to_motion");  // first caption and length of each clip
  const std::vector<ControlTask> tasks =
      as_protocol(proto).make_tasks(data, ref_idx, static_cast<uint64_t>(opt.seed));
  resolve_dependencies(gen_cfg);
  auto gen = as_generator(gen_cfg).make(ctx);
  rep.generator = gen->describe();
  GeneratedMotions g = gen->generate(tasks, static_cast<uint64_t>(opt.seed));
  const MotionSet samples = generated_motion_set(g, tasks, data);  // no post-processing

  // ---- evaluator metrics: samples and ground truth against the same reference and texts
  EvalProtocol p = opt.protocol;
  p.r_precision_pool = std::max(3, std::min<int>(p.r_precision_pool, opt.samples));  // top-3 needs 3
  rep.r_precision_pool = p.r_precision_pool;
  rep.repeats = p.repeats;
  const Embeddings ref_emb = ev.embed_motions(reference, rep.reference);
  const Embeddings floor_emb = ev.embed_motions(held_out, rep.floor_reference);
  EvalEmbeddings gen_e, gt_e;
  gen_e.gt_motion = gt_e.gt_motion = ref_emb;
  gen_e.motion = ev.embed_motions(samples, "samples");
  gt_e.motion = ref_emb;
  for (const auto& t : tasks) gen_e.captions.push_back(t.caption);
  gt_e.captions = gen_e.captions;
  gen_e.text = gt_e.text = ev.embed_texts(gen_e.captions);
  auto t2m_gen = mean_t2m(gen_e, p, opt.seed), t2m_gt = mean_t2m(gt_e, p, opt.seed);
  auto real_gen = realism(samples, p), real_gt = realism(reference, p);

  // ---- rows and targets
  const HealthTargets& tg = opt.targets;
  auto add = [&](std::string key, std::string label, double value, std::optional<double> gt, std::string target = "",
                 std::optional<bool> pass = std::nullopt) {
    rep.metrics.push_back({std::move(key), std::move(label), value, gt, std::move(target), pass});
  };
  const double fid_gen = fid(gen_e.motion, ref_emb), fid_floor = fid(floor_emb, ref_emb);
  add("fid", fmt::format("FID (N = {})", N), fid_gen, fid_floor, fmt::format("<= {:g}x GT floor", tg.fid_floor_ratio),
      fid_gen <= tg.fid_floor_ratio * fid_floor);
  add("kid", fmt::format("KID (N = {})", N), kid(gen_e.motion, ref_emb), kid(floor_emb, ref_emb));
  add("r_precision_top1", "R-precision top-1", t2m_gen.at("r_precision_top1"), t2m_gt.at("r_precision_top1"));
  add("r_precision_top2", "R-precision top-2", t2m_gen.at("r_precision_top2"), t2m_gt.at("r_precision_top2"));
  const double r3 = t2m_gen.at("r_precision_top3"), r3_gt = t2m_gt.at("r_precision_top3");
  add("r_precision_top3", "R-precision top-3", r3, r3_gt, fmt::format(">= {:g}x GT", tg.r_precision_top3_ratio),
      r3 >= tg.r_precision_top3_ratio * r3_gt);
  add("matching", "matching score", t2m_gen.at("matching"), t2m_gt.at("matching"));
  add("diversity", "diversity", t2m_gen.at("diversity"), t2m_gt.at("diversity"));
  const double fs_gen = real_gen.at("foot_skating"), fs_gt = real_gt.at("foot_skating");
  add("foot_skating", "foot skating ratio", fs_gen, fs_gt, fmt::format("<= {:g}x GT", tg.foot_skating_ratio),
      fs_gen <= tg.foot_skating_ratio * fs_gt);
  const double acc = real_gen.at("acceleration"), acc_gt = real_gt.at("acceleration");
  add("acceleration", "mean |acceleration| (m/s^2)", acc, acc_gt, fmt::format("<= {:g}x GT", tg.acceleration_ratio),
      acc <= tg.acceleration_ratio * acc_gt);
  const double bone = real_gen.at("bone_length_std_mm");
  add("bone_length_std_mm", "bone-length std (mm)", bone, real_gt.at("bone_length_std_mm"),
      fmt::format("<= {:g} mm", tg.bone_length_std_mm), bone <= tg.bone_length_std_mm);
  add("toe_penetration_m", "toe floor penetration (m)", real_gen.at("toe_penetration_m"),
      real_gt.at("toe_penetration_m"));
  add("toe_below_floor_fraction", "frames with a toe below y = 0", real_gen.at("toe_below_floor_fraction"),
      real_gt.at("toe_below_floor_fraction"));
  if (rep.model_type == "vq_tokenizer")
    add("reconstruction_mpjpe_m", "reconstruction MPJPE (m)", reconstruction_mpjpe(views(samples), views(reference)),
        0.0);
  for (const auto& m : rep.metrics)
    if (!std::isfinite(m.value)) fail("health of '{}': {} is not finite ({})", opt.run_dir, m.label, m.value);

  for (auto& [k, v] : read_summary_csv(run / "summary.csv"))
    if (k.rfind("val_", 0) == 0) rep.validation[k] = v;

  const std::string stem = opt.reference.file_stem();
  write_file_atomic(run / (stem + ".md"), health_markdown(rep));
  write_file_atomic(run / (stem + ".json"), health_json(rep));
  return rep;
}

// ---------------------------------------------------------------- rendering

namespace {

std::string num(double v) {
  if (!std::isfinite(v)) return "–";
  if (v == 0.0) return "0";
  return fmt::format("{:.4g}", v);
}

// A Markdown table cell: a '|' inside (e.g. "mean |acceleration|") would end the cell.
std::string cell(const std::string& s) {
  std::string out;
  for (char c : s) out += c == '|' ? std::string("\\|") : std::string(1, c);
  return out;
}

std::optional<double> ratio_of(const HealthMetric& m) {
  if (!m.ground_truth || !std::isfinite(*m.ground_truth) || *m.ground_truth == 0.0) return std::nullopt;
  return m.value / *m.ground_truth;
}

}  // namespace

std::string json_quote(const std::string& s) {
  std::string out = "\"";
  for (unsigned char c : s) {
    switch (c) {
      case '"': out += "\\\""; break;
      case '\\': out += "\\\\"; break;
      case '\n': out += "\\n"; break;
      case '\t': out += "\\t"; break;
      case '\r': out += "\\r"; break;
      default:
        if (c < 0x20) out += fmt::format("\\u{:04x}", c);
        else out += static_cast<char>(c);
    }
  }
  return out + "\"";
}

namespace {

std::string json_string(const std::string& s) { return json_quote(s); }
// Shortest representation that reads back to the same double: a report re-read from a
// run's cached health.json then gives the same ratios, byte for byte, as a fresh one
// (with 10 digits the ratios moved in their last digit between the two).
std::string json_number(double v) { return std::isfinite(v) ? fmt::format("{}", v) : "null"; }
std::string json_number(const std::optional<double>& v) { return v ? json_number(*v) : "null"; }

}  // namespace

std::string health_markdown(const HealthReport& r) {
  std::string s = fmt::format("# Prior health: `{}`\n\n", r.run_dir);
  const auto failed = r.failed();
  int targets = 0;
  for (const auto& m : r.metrics) targets += m.pass.has_value();
  if (failed.empty())
    s += fmt::format("**Verdict: healthy** ({} of {} targets met)\n\n", targets, targets);
  else
    s += fmt::format("**Verdict: NOT healthy**: {} of {} targets missed ({})\n\n", failed.size(), targets,
                     cell(fmt::format("{}", fmt::join(failed, "; "))));
  s += fmt::format(
      "{} `{}`: {} on the first caption and length of the reference clips {} of `{}`; seed {}. {}Ground truth = the "
      "reference clips themselves, except FID/KID, whose ground-truth figure is the floor: held-out clips {} against "
      "the reference. Evaluator `{}`; R-precision pools of {}, {} replicates.\n\n",
      r.model_type, r.run_dir, r.ground_truth ? "ground-truth self-check (the reference clips scored as samples)"
                                              : fmt::format("{} samples", r.samples),
      r.reference, r.data, r.seed,
      r.ground_truth ? "" : fmt::format("Generator: {}. ", r.generator), r.floor_reference, r.evaluator_run,
      r.r_precision_pool, r.repeats);
  s += fmt::format("| metric | {} | ground truth | ratio | target | pass |\n", r.ground_truth ? "GT as samples"
                                                                                         : r.model_type);
  s += "|---|---:|---:|---:|---|---|\n";
  for (const auto& m : r.metrics) {
    auto ratio = ratio_of(m);
    s += fmt::format("| {} | {} | {} | {} | {} | {} |\n", cell(m.label), num(m.value),
                     m.ground_truth ? num(*m.ground_truth) + (m.key == "fid" || m.key == "kid" ? " (floor)" : "") : "–",
                     ratio ? fmt::format("{:.3g}x", *ratio) : "–", m.target.empty() ? "–" : cell(m.target),
                     m.pass ? (*m.pass ? "pass" : "**FAIL**") : "");
  }
  if (!r.validation.empty()) {
    s += "\nValidation figures of the run (`summary.csv`):\n\n| key | value |\n|---|---:|\n";
    for (const auto& [k, v] : r.validation) s += fmt::format("| {} | {} |\n", k, num(v));
  }
  return s;
}

std::string health_json(const HealthReport& r) {
  std::string s = "{\n";
  auto field = [&](const char* k, const std::string& v) { s += fmt::format("  {}: {},\n", json_string(k), v); };
  field("run_dir", json_string(r.run_dir));
  field("model_type", json_string(r.model_type));
  field("ground_truth_mode", r.ground_truth ? "true" : "false");
  field("healthy", r.healthy() ? "true" : "false");
  std::string failed = "[";
  for (const auto& f : r.failed()) failed += (failed.size() > 1 ? ", " : "") + json_string(f);
  field("failed", failed + "]");
  field("samples", std::to_string(r.samples));
  field("seed", std::to_string(r.seed));
  field("data", json_string(r.data));
  field("reference", json_string(r.reference));
  field("floor_reference", json_string(r.floor_reference));
  field("evaluator_run", json_string(r.evaluator_run));
  field("generator", json_string(r.generator));
  field("r_precision_pool", std::to_string(r.r_precision_pool));
  field("repeats", std::to_string(r.repeats));
  field("options_hash", json_string(r.options_hash));
  field("run_sha1", json_string(r.run_sha1));
  field("evaluator_sha1", json_string(r.evaluator_sha1));
  s += "  \"metrics\": [\n";
  for (size_t i = 0; i < r.metrics.size(); ++i) {
    const auto& m = r.metrics[i];
    s += fmt::format(
        "    {{\"key\": {}, \"label\": {}, \"value\": {}, \"ground_truth\": {}, \"ratio\": {}, \"target\": {}, "
        "\"pass\": {}}}{}\n",
        json_string(m.key), json_string(m.label), json_number(m.value), json_number(m.ground_truth),
        json_number(ratio_of(m)), m.target.empty() ? "null" : json_string(m.target),
        m.pass ? (*m.pass ? "true" : "false") : "null", i + 1 < r.metrics.size() ? "," : "");
  }
  s += "  ],\n  \"validation\": {";
  size_t i = 0;
  for (const auto& [k, v] : r.validation)
    s += fmt::format("{}\n    {}: {}", i++ ? "," : "", json_string(k), json_number(v));
  s += r.validation.empty() ? "}\n}\n" : "\n  }\n}\n";
  return s;
}

HealthReport read_health_json(const std::string& path) {
  HealthReport r;
  try {
    YAML::Node n = YAML::LoadFile(path);  // JSON is YAML
    r.run_dir = n["run_dir"].as<std::string>();
    r.model_type = n["model_type"].as<std::string>();
    r.ground_truth = n["ground_truth_mode"].as<bool>();
    r.samples = n["samples"].as<int>();
    r.seed = n["seed"].as<int64_t>();
    r.data = n["data"].as<std::string>();
    r.reference = n["reference"].as<std::string>();
    r.floor_reference = n["floor_reference"].as<std::string>();
    r.evaluator_run = n["evaluator_run"].as<std::string>();
    r.generator = n["generator"].as<std::string>();
    r.r_precision_pool = n["r_precision_pool"].as<int>();
    r.repeats = n["repeats"].as<int>();
    r.options_hash = n["options_hash"].as<std::string>();
    // Reports written before the fingerprints have none: "" (never reused by reproduce).
    if (n["run_sha1"]) r.run_sha1 = n["run_sha1"].as<std::string>();
    if (n["evaluator_sha1"]) r.evaluator_sha1 = n["evaluator_sha1"].as<std::string>();
    for (const auto& m : n["metrics"]) {
      HealthMetric h;
      h.key = m["key"].as<std::string>();
      h.label = m["label"].as<std::string>();
      h.value = m["value"].IsNull() ? NAN : m["value"].as<double>();
      if (!m["ground_truth"].IsNull()) h.ground_truth = m["ground_truth"].as<double>();
      if (!m["target"].IsNull()) h.target = m["target"].as<std::string>();
      if (!m["pass"].IsNull()) h.pass = m["pass"].as<bool>();
      r.metrics.push_back(h);
    }
    for (const auto& kv : n["validation"])
      r.validation[kv.first.as<std::string>()] = kv.second.IsNull() ? NAN : kv.second.as<double>();
  } catch (const YAML::Exception& e) {
    fail("{}: not a health report ({}); rerun `motionctl health`", path, e.what());
  }
  return r;
}

}  // namespace mc
