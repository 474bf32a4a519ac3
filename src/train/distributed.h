// Data-parallel training beyond one process (issue 19) on PyTorch's c10d: Gloo
// process groups over a FileStore (local launches) or a TCPStore (MASTER_ADDR /
// MASTER_PORT, as torchrun and cluster schedulers set them). What a rank does:
// join (rendezvous; every rank must run the same job, checked by its description),
// take rank 0's starting state, then per step reduce the gradients in buckets
// (launched from gradient hooks while backward runs, or after it) and the step's
// scalars. Rank 0 alone writes the run directory (trainer.cpp). A rank that dies
// makes the others fail within the timeout with an error naming it (DataParallelError),
// never hang. `motionctl train --nproc N` starts N local ranks (launch_local_ranks).
#pragma once
#include <cstdint>
#include <memory>
#include <stdexcept>
#include <string>
#include <vector>

#include "models/batch_shard.h"

namespace mc {

// Where a rank finds its job: the standard variables (RANK, WORLD_SIZE,
// LOCAL_RANK, LOCAL_WORLD_SIZE, MASTER_ADDR, MASTER_PORT) or, for local launches,
// MOTIONCTL_DIST_STORE (a FileStore path, fresh for each job).
struct DistEnv {
  int rank = 0, world = 1;
  int local_rank = 0, local_world = 1;  // ranks on this machine (threads are split among them)
  std::string store_path;               // FileStore (wins over MASTER_ADDR)
  std::string master_addr;
  int master_port = 0;
  bool agent_store = false;  // TORCHELASTIC_USE_AGENT_STORE: torchrun's agent hosts the TCPStore
  bool distributed() const { return world > 1; }
};
// The job this process belongs to, from the environment; world 1 when WORLD_SIZE
// is unset. UserError naming the variable when a value is malformed.
DistEnv dist_env_from_environment();

// How ranks talk; none of it changes what is trained.
struct DistOptions {
  double timeout_seconds = 300;           // any collective or rendezvous wait (a dead rank: fails sooner)
  int64_t bucket_bytes = 25LL << 20;      // gradient bucket size (PyTorch DDP's 25 MiB)
  bool overlap = true;                    // launch a bucket's all-reduce from the backward's gradient hooks
  double start_timeout_seconds = 86400;   // ranks > 0 waiting for rank 0 to start (it may train components first)
};

// A rank lost contact with the others (one died, hung past the timeout or could
// not be reached): exit code 1, the message names the rank(s) that went silent.
struct DataParallelError : std::runtime_error {
  using std::runtime_error::runtime_error;
};

// The exit code of a command whose outcome was reported already (the ranks'
// launcher printed which rank failed): main() exits with it, printing nothing.
struct ExitStatus {
  int code;
  explicit ExitStatus(int c) : code(c) {}
};

// Times of the data-parallel parts of the steps so far (`motionctl bench ddp`).
struct ReduceTimes {
  int64_t steps = 0;
  double wait_seconds = 0;     // blocked after backward, waiting for the gradient all-reduces
  double scalar_seconds = 0;   // the per-step scalar all-reduce (loss, parts, stop flags)
};

class DataParallel : public Collective {
 public:
  // Joins the job (rendezvous and Gloo connections): every rank calls it. UserError
  // for a malformed environment; DataParallelError when ranks do not all arrive.
  static std::unique_ptr<DataParallel> join(const DistEnv& env, const DistOptions& options);
  ~DataParallel() override;

  int rank() const override;
  int world() const override;
  void sum_(torch::Tensor& t) override;
  const DistEnv& env() const;
  const DistOptions& options() const;

  // Every rank gives `fields` (name, value) describing its job (version, config
  // hash, rank count, loop options); a rank whose fields differ from rank 0's is
  // refused on every rank with a UserError naming the rank and the field.
  void check_same_job(const std::vector<std::pair<std::string, std::string>>& fields);

  // Rank 0 tells the others how the start went ("ok", "finished", or an error
  // message that they then fail with); they wait for it (options().start_timeout_seconds).
  void announce_start(const std::string& status);
  std::string await_start();
  // Rank 0's `bytes` reach every rank.
  void broadcast(std::string& bytes);

  // Buckets of `params`' gradients and, with options().overlap, the hooks that
  // launch each bucket's all-reduce as soon as its last gradient is ready.
  void attach(const std::vector<torch::Tensor>& params);
  void begin_backward();
  // After backward: every gradient becomes the sum over ranks (buckets launched in
  // the same order on every rank; a parameter without a gradient counts as zero).
  // `what` names the step in an error.
  void finish_gradients(const std::string& what);
  // Sums a vector of scalars over the ranks (the step's loss, parts and stop flags).
  std::vector<double> sum_scalars(const std::vector<double>& v, const std::string& what);
  const ReduceTimes& times() const;
  // Switches the overlap of the attached parameters (`motionctl bench ddp` times both).
  void set_overlap(bool on);
  size_t bucket_count() const;

 private:
  struct Impl;
  explicit DataParallel(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

// `motionctl train ... --nproc N`: starts N ranks of this binary with `args` (the
// command line without --nproc) over a fresh FileStore and waits for them. When one
// fails, the others get `grace_seconds` to notice and exit with their own message,
// then SIGTERM (SIGKILL 10 s later). Returns the exit code: 0, the first failing
// rank's code, or 1 for a rank killed by a signal; the message names the rank.
// SIGINT/SIGTERM are passed to the ranks (they checkpoint and exit 130/143 together).
int launch_local_ranks(int nproc, const std::vector<std::string>& args, double grace_seconds);

// The command line of this process (set by main), for launch_local_ranks.
void set_command_line(int argc, char** argv);
const std::vector<std::string>& command_line();

}  // namespace mc
