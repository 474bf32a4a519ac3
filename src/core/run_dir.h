// Run directories (runs/<experiment>/<name>/): resolved config, overrides, seed,
// log, metrics.csv, checkpoints/, outputs/, and the DONE marker that makes a
// finished run a no-op; the lock that makes one process the only writer of a run.
// Also the log/progress sink every job writes through.
#pragma once
#include <chrono>
#include <filesystem>
#include <fstream>
#include <functional>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "core/config.h"

namespace mc {
namespace fs = std::filesystem;

// How checkpoints/final.pt stores the weights (run.final_weights). float16 halves
// the file (the repo ships no checkpoint over 5 MiB) at no cost to what the run
// means: the trainer rounds the final parameters to half precision *before* it
// evaluates and saves them (buffers, such as normaliser statistics and a TMD's
// distance table, stay float32), so the run's summary, its health and every
// consumer (which loads them back as float32) see the same weights. Off (float32)
// it is left out of dumps and hashes, so runs trained before it keep their names.
struct FinalWeightsConfig : Config {
  std::string dtype = "float32";
  void visit(FieldVisitor& v) override {
    v("dtype", dtype,
      "float32, or float16: round the final parameters (not buffers) to half precision at the end of training, "
      "then evaluate and store them so (half the file; loaded back as float32)",
      one_of({"float32", "float16"}));
  }
  bool omitted_from_dump() const override { return dtype == "float32"; }
};

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
  FinalWeightsConfig final_weights;
  void visit(FieldVisitor& v) override {
    v("experiment", experiment, "experiment folder under root");
    v("name", name, "run name (default: <config stem>-<config hash>)");
    v("root", root,
      "directory holding all runs, relative to the working directory; also where the components this job trains go; "
      "not part of a run's identity (a moved run tree is found under its new root)");
    v("seed", seed, "random seed of the run (stored in the run directory)");
    v("threads", threads, "torch CPU threads; 0 = all cores (or $OMP_NUM_THREADS when set)", at_least(0));
    v("device", device, "torch device: cpu, cuda, cuda:N",
      Check<std::string>{[](const std::string& d) {
                            return d == "cpu" || d.rfind("cuda", 0) == 0 ? std::string()
                                                                         : std::string("must be cpu, cuda or cuda:N");
                          },
                          "cpu|cuda|cuda:N"});
    v("force", force, "redo the run from scratch in its own directory (refused while another process uses it)");
    v("log_every", log_every, "steps between log lines and metrics.csv rows", at_least(1));
    v("checkpoint_every", checkpoint_every, "steps between checkpoints", at_least(1));
    v("final_weights", final_weights, "how checkpoints/final.pt stores the weights");
  }

  // The fields that say how or where a run is executed, never what it trains:
  // they are left out of a run's identity (its hash, its default name and the
  // "same config" check of an existing run directory), so a run trained on one
  // thread is the run a two-thread job asks for, run.force=true redoes the run in
  // its own directory, and a run tree moved under another run.root is found
  // there. clear_non_identity() sets exactly these to their defaults (so configs
  // that never set them hash as they always did); tests/core/test_run_dir.cpp
  // checks that this list and clear_non_identity() agree with every field.
  static const std::vector<std::string>& non_identity_fields() {
    static const std::vector<std::string> f = {"threads", "force", "root"};
    return f;
  }
  void clear_non_identity() {
    const RunConfig d;
    threads = d.threads;
    force = d.force;
    root = d.root;
  }
};

// The identity of a job with a `run:` section: its dumped config with the
// non-identity run fields at their defaults. Equal identities = the same run.
template <class Job>
std::string identity_yaml(Job job) {
  job.run.clear_non_identity();
  return dump_config(job);
}
template <class Job>
std::string identity_hash(Job job) {
  job.run.clear_non_identity();
  return config_hash(job);
}

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

// An advisory lock (flock) on <run dir>/.lock, which holds the holder's pid: one
// process writes a run at a time. The kernel releases it when the process exits
// in any way (kill -9 included), so a lock file left by a dead process is stale
// and simply taken over. Re-acquiring a run this process already holds shares
// the lock. Child processes do not inherit it (O_CLOEXEC).
class RunLock {
 public:
  // UserError (exit 2) naming the holder's pid when another process holds it.
  static std::shared_ptr<RunLock> acquire(const fs::path& run_dir);
  ~RunLock();
  RunLock(const RunLock&) = delete;
  RunLock& operator=(const RunLock&) = delete;
  const fs::path& dir() const { return dir_; }

 private:
  RunLock(fs::path dir, int fd) : dir_(std::move(dir)), fd_(fd) {}
  fs::path dir_;
  int fd_ = -1;
};

class RunDir {
 public:
  // Decides whether the config found in an existing run directory (its
  // config.yaml text) is the config of the run being opened.
  using SameRun = std::function<bool(const std::string& existing_config_yaml)>;

  // The directory open() would use (nothing is created).
  static fs::path path_of(const RunConfig& run, const std::string& default_name);

  // Opens (creating or resuming) the run directory and locks it for this
  // object's life (RunLock; a run held by another process is refused). With
  // run.force the directory's contents are removed, once locked, and the run
  // starts again in the same directory. Stale temporaries of atomic writes
  // (.<file>.tmp.<pid>.<n>, left by a kill) are removed. `resolved_yaml` is
  // written as config.yaml; an existing run must be the same run (`same`, by
  // default: the same config.yaml text). Call it only once the job is validated,
  // so a failed start does not claim the directory.
  static RunDir open(const RunConfig& run, const std::string& resolved_yaml, const std::vector<std::string>& overrides,
                     const std::string& default_name, const SameRun& same = {});
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
  std::shared_ptr<RunLock> lock_;
};

// key -> value of a run's summary.csv (what mark_finished wrote); empty when the file
// is absent, UserError naming it when a row does not parse.
std::map<std::string, double> read_summary_csv(const fs::path& path);

std::string sanitize_name(const std::string& s);  // safe for a directory name
std::string utc_timestamp();

}  // namespace mc
