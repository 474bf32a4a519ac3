// Prior health inside the table replay: every trained prior or tokenizer that the
// rows of a table used is checked once (eval/health.h) with the profile's data,
// evaluator, sample count and sampling budgets. Each table names the verdict of its
// priors at its top; results/<profile>/health.{md,json} gathers the reports.
#pragma once
#include <filesystem>
#include <map>
#include <optional>
#include <string>
#include <vector>

#include "data/motion_set.h"
#include "eval/health.h"
#include "experiments/experiment.h"
#include "experiments/report.h"

namespace mc {

// A trained control component (flow ControlNet, AnchorRoute adapter) the health check
// does not sample: does it read its control signal? Its run's own validation at t = 0.1,
// on the same draws with the signal and with it removed (summary.csv). No target.
struct ControlUptake {
  std::string run_dir, model_type, figure;  // figure: what is compared (e.g. val_ctrl_t0.10)
  std::optional<double> with_signal, without_signal;  // absent: the run predates the logging
  std::string note;                                    // why absent
};
// Reads the uptake figures of `run_dir` (model type flow_controlnet or anchor_adapter);
// nullopt for other types.
std::optional<ControlUptake> control_uptake(const std::string& run_dir, const std::string& model_type);

struct ComponentHealth {
  std::string run_dir, model_type;
  std::optional<HealthReport> report;  // absent when the check could not run
  std::string error;                   // why it could not
  bool healthy() const { return report && report->healthy(); }
};

class ProfileHealth {
 public:
  // `data` is the profile's ground truth (RowEvaluator::data()): it fixes N, the
  // profile's num_samples capped so that the test split and the floor clips fit.
  ProfileHealth(const ProfileFile& profile, const MotionSet& data);

  // Checks the table's components the health check covers (each run once per replay;
  // a RUN_DIR/health.json with the same options is reused) and returns the Markdown
  // line for the top of the table ('' when its rows used none).
  std::string table_line(const TableResult& table);

  // results/<profile>/health.md and health.json over every component checked so far.
  void write(const std::filesystem::path& out_dir) const;

  const std::vector<ComponentHealth>& components() const { return checked_; }
  int samples() const { return base_.samples; }

 private:
  const ComponentHealth& check(const std::string& run_dir, const std::string& model_type);

  std::string profile_name_;
  HealthOptions base_;
  std::string cap_error_;  // non-empty when no N >= 3 fits the data
  std::vector<ComponentHealth> checked_;
  std::map<std::string, size_t> index_;  // run_dir -> checked_ position
  std::vector<ControlUptake> controls_;  // control components the tables used, in first-use order
};

}  // namespace mc
