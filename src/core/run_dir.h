// Run directories (runs/<experiment>/<name>/): resolved config, overrides, seed,
// log, metrics.csv, checkpoints/, outputs/, and the DONE marker that makes a
// finished run a no-op. Also the log/progress sink every job writes through.
#pragma once
#include <chrono>
#include <filesystem>
#include <fstream>
#include <map>
#include <string>
#include <vector>

#include "core/config.h"

namespace mc {
namespace fs = std::filesystem;

struct RunConfig : Config {
  std::string experiment = "default";
  std::string name;  // empty: <config file stem>-<config hash>
  std::string root = "runs";
  int64_t seed = 0;
  int threads = 0;  // 0: all cores
  std::string device = "cpu";
  bool force = false;
  int log_every = 50;
  int checkpoint_every = 200;
  void visit(FieldVisitor& v) override {
    v("experiment", experiment, "experiment folder under root");
    v("name", name, "run name (default: <config stem>-<config hash>)");
    v("root", root, "directory holding all runs");
    v("seed", seed, "random seed of the run (stored in the run directory)");
    v("threads", threads, "torch CPU threads; 0 = all cores (or $OMP_NUM_THREADS when set)", at_least(0));
    v("device", device, "torch device: cpu, cuda, cuda:N",
      Check<std::string>{[](const std::string& d) {
                            return d == "cpu" || d.rfind("cuda", 0) == 0 ? std::string()
                                                                         : std::string("must be cpu, cuda or cuda:N");
                          },
                          "cpu|cuda|cuda:N"});
    v("force", force, "redo a finished run from scratch");
    v("log_every", log_every, "steps between log lines and metrics.csv rows", at_least(1));
    v("checkpoint_every", checkpoint_every, "steps between checkpoints", at_least(1));
  }
};

// Log lines go to log.txt and stderr; progress() draws a live line on a
// terminal and is silent otherwise (periodic log lines take its place).
class Logger {
 public:
  Logger() = default;
  explicit Logger(const fs::path& file);
  void info(const std::string& line);
  void progress(const std::string& line);  // live line (terminal only)
  void end_progress();
  static bool interactive();  // stderr is a terminal and CI is unset

 private:
  std::ofstream file_;
  bool live_ = false;
};

// metrics.csv with a fixed header; resumable by truncating rows after a step.
class MetricsCsv {
 public:
  MetricsCsv() = default;
  explicit MetricsCsv(fs::path path) : path_(std::move(path)) {}
  void truncate_after(int64_t step);  // keep rows with step <= `step`
  void append(int64_t step, const std::vector<std::pair<std::string, double>>& values);

 private:
  fs::path path_;
  std::vector<std::string> header_;
};

class RunDir {
 public:
  // Opens (creating or resuming) the run directory. `resolved_yaml` is the dumped
  // config; an existing unfinished run must have the same config.
  static RunDir open(const RunConfig& run, const std::string& resolved_yaml, const std::vector<std::string>& overrides,
                     const std::string& default_name);
  const fs::path& path() const { return dir_; }
  fs::path checkpoints() const { return dir_ / "checkpoints"; }
  fs::path outputs() const { return dir_ / "outputs"; }
  fs::path metrics_path() const { return dir_ / "metrics.csv"; }
  bool finished() const;
  void mark_finished(const std::map<std::string, double>& summary);
  std::map<std::string, double> summary() const;  // from summary.csv of a finished run
  Logger& log() { return *log_; }

 private:
  fs::path dir_;
  std::shared_ptr<Logger> log_;
};

// key -> value of a run's summary.csv (what mark_finished wrote); empty when the file
// is absent, UserError naming it when a row does not parse.
std::map<std::string, double> read_summary_csv(const fs::path& path);

std::string sanitize_name(const std::string& s);  // safe for a directory name
std::string utc_timestamp();

}  // namespace mc
