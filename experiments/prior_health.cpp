// Prior health of the components a replay used: checked once each, reused from
// RUN_DIR/health.json when the options match, named at the top of every table and
// gathered into results/<profile>/health.{md,json}.
#include "experiments/prior_health.h"

#include <fmt/ranges.h>
#include <yaml-cpp/yaml.h>

#include <algorithm>

#include "core/atomic_file.h"
#include "core/error.h"
#include "core/run_dir.h"
#include "train/dependency_record.h"

namespace mc {
namespace fs = std::filesystem;

namespace {

std::string model_type_of(const std::string& run_dir) {
  try {
    YAML::Node n = YAML::LoadFile((fs::path(run_dir) / "config.yaml").string());
    if (n["model"] && n["model"]["type"]) return n["model"]["type"].as<std::string>();
  } catch (const YAML::Exception&) {
  }
  return "";
}

// A Markdown table cell: labels such as "mean |acceleration|" hold '|'.
std::string cell(const std::string& s) {
  std::string out;
  for (char c : s) out += c == '|' ? std::string("\\|") : std::string(1, c);
  return out;
}

bool covered(const std::string& type) {
  const auto& t = health_model_types();
  return std::find(t.begin(), t.end(), type) != t.end();
}

}  // namespace

std::optional<ControlUptake> control_uptake(const std::string& run_dir, const std::string& model_type) {
  ControlUptake u;
  u.run_dir = run_dir;
  u.model_type = model_type;
  std::string with_key, without_key;
  if (model_type == "flow_controlnet") {
    u.figure = "val_ctrl_t0.10: the controlled entries' velocity error at t = 0.1, branch control on / off";
    with_key = "val_ctrl_t0.10";
    without_key = "val_ctrl_off_t0.10";
  } else if (model_type == "anchor_adapter") {
    u.figure = "val_soft_control_error_t01: soft-decoded anchor error (m) at t = 0.1, real / zeroed features";
    with_key = "val_soft_control_error_t01";
    without_key = "val_soft_control_error_t01_zeroed";
    // Which adapter it is (the run names are hashes): its kind and the switches that
    // tell Table IV's rows apart.
    try {
      YAML::Node m = YAML::LoadFile((fs::path(run_dir) / "config.yaml").string())["model"];
      if (m && m["adapter"]) {
        std::string what = m["adapter"].as<std::string>();
        if (m["dual_context"]) what += m["dual_context"].as<bool>() ? ", dual context" : ", no dual context";
        if (m["lambda_anc"]) what += fmt::format(", lambda_anc {:g}", m["lambda_anc"].as<double>());
        if (m["training"] && m["training"]["zero_features"] && m["training"]["zero_features"].as<bool>())
          what += ", trained on zeroed features (audit twin)";
        if (m["features"] && m["features"]["feedback"] && m["features"]["feedback"]["enabled"] &&
            m["features"]["feedback"]["enabled"].as<bool>())
          what += ", feedback channels";
        if (m["training"] && m["training"]["rollout"] && m["training"]["rollout"]["prob"]) {
          const YAML::Node r = m["training"]["rollout"];
          what += fmt::format(", rollout states in {:g} of batches", r["prob"].as<double>());
          if (r["loss"] && r["loss"]["ce_weight"] && r["loss"]["anchor_weight"])
            what += fmt::format(" (CE {:g}, anchor loss {:g})", r["loss"]["ce_weight"].as<double>(),
                                r["loss"]["anchor_weight"].as<double>());
        }
        u.model_type += " (" + what + ")";
      }
    } catch (const YAML::Exception&) {  // the figures still say what they can
    }
  } else {
    return std::nullopt;
  }
  const auto summary = read_summary_csv(fs::path(run_dir) / "summary.csv");
  if (summary.count(with_key)) u.with_signal = summary.at(with_key);
  if (summary.count(without_key)) u.without_signal = summary.at(without_key);
  if (!u.with_signal || !u.without_signal)
    u.note = fmt::format("not logged: the run has no {} (trained before that validation existed); retrain it to "
                         "measure",
                         !u.with_signal ? with_key : without_key);
  return u;
}

ProfileHealth::ProfileHealth(const ProfileFile& pf, const MotionSet& data) : profile_name_(pf.profile.name) {
  const ProfileConfig& p = pf.profile;
  base_.seed = p.seed;
  base_.evaluator = p.evaluator;
  base_.data = p.data;
  base_.threads = p.threads;
  base_.device = p.device;
  base_.substitutions = p.substitutions;  // the rows' sampling budgets
  base_.protocol = pf.protocol;
  base_.protocol.repeats = p.repeats;
  // N: profile.health_samples, else the rows' sample count, capped so that N test clips
  // and N floor clips exist.
  const int test = static_cast<int>(data.indices_of_split("test").size());
  const int val = static_cast<int>(data.indices_of_split("val").size());
  const int wanted = p.health_samples > 0 ? p.health_samples : p.num_samples > 0 ? p.num_samples : 32;
  // At least 3 (the check's minimum) even when the rows use fewer.
  int n = std::min(std::max(wanted, 3), test);
  while (n >= 3 && !(val >= n || test >= 2 * n)) --n;
  if (n < 3)
    cap_error_ = fmt::format("{}: the test split ({} clips) and val split ({}) leave fewer than 3 samples with "
                             "held-out floor clips",
                             p.data, test, val);
  base_.samples = std::max(n, 3);
}

const ComponentHealth& ProfileHealth::check(const std::string& run_dir, const std::string& model_type) {
  auto it = index_.find(run_dir);
  if (it != index_.end()) return checked_[it->second];
  ComponentHealth c;
  c.run_dir = run_dir;
  c.model_type = model_type;
  HealthOptions o = base_;
  o.run_dir = run_dir;
  const fs::path cached = fs::path(run_dir) / "health.json";
  if (!cap_error_.empty()) {
    c.error = cap_error_;
  } else {
    if (fs::exists(cached)) {
      try {
        HealthReport r = read_health_json(cached.string());
        // Same options, and the same weights of the run and of the evaluator it was scored
        // with (a retrained evaluator keeps its config and path but moves every FID).
        if (r.options_hash == config_hash(o) && !r.evaluator_sha1.empty() &&
            r.evaluator_sha1 == weights_sha1(r.evaluator_run) && r.run_sha1 == weights_sha1(run_dir))
          c.report = r;
      } catch (const UserError&) {  // unreadable: check again
      }
    }
    if (!c.report) {
      try {
        c.report = check_health(o);
      } catch (const UserError& e) {
        c.error = e.what();
      }
    }
  }
  index_[run_dir] = checked_.size();
  checked_.push_back(std::move(c));
  return checked_.back();
}

std::string ProfileHealth::table_line(const TableResult& t) {
  std::vector<std::string> runs;
  for (const auto& row : t.rows)
    for (const auto& c : row.components)
      if (std::find(runs.begin(), runs.end(), c) == runs.end()) runs.push_back(c);
  std::vector<std::string> parts;
  bool all_healthy = true;
  for (const auto& run : runs) {
    const std::string type = model_type_of(run);
    if (!covered(type)) {  // adapters, ControlNets: no sampling check, their signal uptake instead
      const bool seen = std::any_of(controls_.begin(), controls_.end(), [&](auto& c) { return c.run_dir == run; });
      if (!seen)
        if (auto u = control_uptake(run, type)) controls_.push_back(*u);
      continue;
    }
    const ComponentHealth& c = check(run, type);
    all_healthy = all_healthy && c.healthy();
    std::string verdict;
    if (!c.report) verdict = "health check failed: " + c.error;
    else if (c.healthy()) verdict = "healthy";
    else verdict = "**NOT healthy** (misses " + fmt::format("{}", fmt::join(c.report->failed(), "; ")) + ")";
    parts.push_back(fmt::format("`{}` ({}) {}", run, type, verdict));
  }
  if (parts.empty()) return "";
  // Table files sit at <results>/<paper>/<table>.md, health.md at <results>/.
  std::string up;
  for (char ch : t.spec.table.id)
    if (ch == '/') up += "../";
  const std::string link = fmt::format("[health.md]({}health.md)", up);
  std::string joined;
  for (size_t i = 0; i < parts.size(); ++i) joined += (i ? "; " : "") + parts[i];
  if (all_healthy) return fmt::format("Prior health ({}, N = {}): {}.", link, base_.samples, joined);
  return fmt::format("**Prior health: NOT healthy** ({}, N = {}): {}. Claims on these rows rest on a prior that "
                     "is not fit to test them.",
                     link, base_.samples, joined);
}

void ProfileHealth::write(const fs::path& out_dir) const {
  int healthy = 0;
  for (const auto& c : checked_) healthy += c.healthy();
  std::string md = fmt::format("# Prior health — profile {}\n\n", profile_name_);
  md += fmt::format(
      "Every trained prior and tokenizer the tables used, checked by `motionctl health` (docs/metrics.md, "
      "\"Prior health\") on the profile's data and evaluator with its sampling budgets, N = {} samples: {} of {} "
      "healthy.\n\n",
      base_.samples, healthy, checked_.size());
  md += "| component | model type | verdict | targets missed |\n|---|---|---|---|\n";
  for (const auto& c : checked_) {
    std::string verdict = !c.report ? "check failed" : c.healthy() ? "healthy" : "**NOT healthy**";
    std::string missed = !c.report ? c.error
                                   : c.healthy() ? "–" : fmt::format("{}", fmt::join(c.report->failed(), "; "));
    md += fmt::format("| `{}` | {} | {} | {} |\n", c.run_dir, c.model_type, verdict, cell(missed));
  }
  if (!controls_.empty()) {
    md += "\n## Control components: do they read their signal?\n\n"
          "Adapters and ControlNets are not sampled by the check. Each run's own validation at t = 0.1 compares "
          "the same draws with its control signal and with it removed (no target; docs/metrics.md, \"Prior "
          "health\"). A change near 0 means the component learned nothing from its signal.\n\n"
          "| component | model type | figure | with signal | without | change |\n|---|---|---|---:|---:|---:|\n";
    for (const auto& u : controls_) {
      if (u.with_signal && u.without_signal)
        md += fmt::format("| `{}` | {} | {} | {:.4g} | {:.4g} | {:+.1f} % |\n", u.run_dir, u.model_type, cell(u.figure),
                          *u.with_signal, *u.without_signal,
                          100.0 * (*u.with_signal - *u.without_signal) / std::max(std::abs(*u.without_signal), 1e-12));
      else
        md += fmt::format("| `{}` | {} | {} | – | – | {} |\n", u.run_dir, u.model_type, cell(u.figure), cell(u.note));
    }
  }
  std::string json = fmt::format("{{\n\"profile\": {},\n\"samples\": {},\n\"healthy\": {},\n\"components\": [\n",
                                 json_quote(profile_name_), base_.samples,
                                 healthy == static_cast<int>(checked_.size()) ? "true" : "false");
  for (size_t i = 0; i < checked_.size(); ++i) {
    const auto& c = checked_[i];
    if (c.report) {
      std::string r = health_markdown(*c.report);
      md += "\n## `" + c.run_dir + "`\n\n" + r.substr(r.find("\n\n") + 2);  // without the report's own title
      std::string j = health_json(*c.report);
      while (!j.empty() && j.back() == '\n') j.pop_back();
      json += j;
    } else {
      json += fmt::format("{{\"run_dir\": {}, \"model_type\": {}, \"healthy\": false, \"error\": {}}}",
                          json_quote(c.run_dir), json_quote(c.model_type), json_quote(c.error));
    }
    json += i + 1 < checked_.size() ? ",\n" : "\n";
  }
  json += "],\n\"control_components\": [\n";
  auto num = [](const std::optional<double>& v) { return v ? fmt::format("{:.17g}", *v) : std::string("null"); };
  for (size_t i = 0; i < controls_.size(); ++i) {
    const auto& u = controls_[i];
    json += fmt::format("{{\"run_dir\": {}, \"model_type\": {}, \"figure\": {}, \"with_signal\": {}, "
                        "\"without_signal\": {}, \"note\": {}}}{}\n",
                        json_quote(u.run_dir), json_quote(u.model_type), json_quote(u.figure), num(u.with_signal),
                        num(u.without_signal), json_quote(u.note), i + 1 < controls_.size() ? "," : "");
  }
  json += "]\n}\n";
  write_file_atomic(out_dir / "health.md", md);
  write_file_atomic(out_dir / "health.json", json);
}

}  // namespace mc
