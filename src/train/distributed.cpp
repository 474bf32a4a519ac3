// c10d glue of DataParallel (train/distributed.h) and the local launcher of
// `motionctl train --nproc N`. Only this file sees c10d's headers; Debian's
// libtorch builds Gloo in, but its headers declare it only with USE_C10D_GLOO.
#ifndef USE_C10D_GLOO
#define USE_C10D_GLOO 1
#endif
#include "train/distributed.h"

#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <torch/csrc/distributed/c10d/FileStore.hpp>
#include <torch/csrc/distributed/c10d/PrefixStore.hpp>
#include <torch/csrc/distributed/c10d/ProcessGroupGloo.hpp>
#include <torch/csrc/distributed/c10d/TCPStore.hpp>

#include <cerrno>
#include <chrono>
#include <csignal>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <iostream>
#include <mutex>
#include <sstream>
#include <thread>

#include "core/error.h"

namespace mc {
namespace fs = std::filesystem;
using Clock = std::chrono::steady_clock;

// ---------------------------------------------------------------- environment

namespace {

int env_int(const char* name, int fallback, int min, int max) {
  const char* v = std::getenv(name);
  if (!v || !*v) return fallback;
  char* end = nullptr;
  errno = 0;
  const long x = std::strtol(v, &end, 10);
  if (errno || *end || x < min || x > max)
    fail("environment variable {}='{}' is not an integer in [{}, {}]", name, v, min, max);
  return static_cast<int>(x);
}

std::string env_str(const char* name) {
  const char* v = std::getenv(name);
  return v ? v : "";
}

bool is_loopback(const std::string& host) { return host == "127.0.0.1" || host == "localhost" || host == "::1"; }

}  // namespace

DistEnv dist_env_from_environment() {
  DistEnv e;
  e.world = env_int("WORLD_SIZE", 1, 1, 1 << 16);
  if (e.world == 1) return e;
  if (env_str("RANK").empty())
    fail("WORLD_SIZE={} is set but RANK is not: every rank of a data-parallel job needs its RANK (0 .. {})", e.world,
         e.world - 1);
  e.rank = env_int("RANK", 0, 0, e.world - 1);
  e.store_path = env_str("MOTIONCTL_DIST_STORE");
  e.local_rank = env_int("LOCAL_RANK", e.rank, 0, e.world - 1);
  // Without LOCAL_WORLD_SIZE every rank is taken to share this machine: fewer
  // threads each, never more threads than cores.
  e.local_world = env_int("LOCAL_WORLD_SIZE", e.world, 1, e.world);
  e.master_addr = env_str("MASTER_ADDR");
  e.master_port = env_int("MASTER_PORT", 0, 1, 65535);
  e.agent_store = env_str("TORCHELASTIC_USE_AGENT_STORE") == "True";
  if (e.store_path.empty() && (e.master_addr.empty() || e.master_port == 0))
    fail("WORLD_SIZE={} but MASTER_ADDR and MASTER_PORT are not both set: give every rank the address and a free port "
         "of rank 0's machine (torchrun sets them), or MOTIONCTL_DIST_STORE (a FileStore path, one machine)",
         e.world);
  return e;
}

// ---------------------------------------------------------------- process group

struct DataParallel::Impl {
  DistEnv env;
  DistOptions opt;
  c10::intrusive_ptr<c10d::Store> store;
  c10::intrusive_ptr<c10d::ProcessGroupGloo> pg;
  ReduceTimes times;

  struct Bucket {
    torch::Tensor flat;
    std::vector<size_t> params;
    int64_t pending = 0;
    bool ready = false;
    std::vector<at::Tensor> io;  // {flat}: what the all-reduce works on
    c10::intrusive_ptr<c10d::Work> work;
  };
  std::vector<torch::Tensor> params;
  std::vector<std::pair<size_t, int64_t>> where;  // parameter -> (bucket, offset)
  std::vector<unsigned> hook_ids;
  std::vector<char> seen;
  std::vector<Bucket> buckets;
  size_t next_launch = 0;
  bool armed = false;
  std::exception_ptr hook_error;
  std::mutex mu;

  ~Impl() {
    for (size_t j = 0; j < hook_ids.size(); ++j) params[j].remove_hook(hook_ids[j]);
  }

  std::chrono::milliseconds timeout() const {
    return std::chrono::milliseconds(static_cast<int64_t>(opt.timeout_seconds * 1000));
  }

  // Which other ranks went silent: each rank that notices a failure leaves a note in
  // the store and looks, for a few seconds, for the others' notes. A rank that
  // leaves none died or hangs.
  std::string silent_ranks() {
    try {
      store->set(fmt::format("lost/{}", env.rank), std::vector<uint8_t>{'1'});
      std::vector<int> silent;
      for (int r = 0; r < env.world; ++r)
        if (r != env.rank) silent.push_back(r);
      const auto deadline = Clock::now() + std::chrono::seconds(3);
      while (!silent.empty() && Clock::now() < deadline) {
        for (size_t i = 0; i < silent.size();)
          if (store->check({fmt::format("lost/{}", silent[i])}))
            silent.erase(silent.begin() + i);
          else
            ++i;
        if (!silent.empty()) std::this_thread::sleep_for(std::chrono::milliseconds(100));
      }
      std::string out;
      for (int r : silent) out += (out.empty() ? "" : ", ") + std::to_string(r);
      return out;
    } catch (const std::exception&) {
      // The TCPStore lives in rank 0's process: unreachable means rank 0 is gone.
      return env.store_path.empty() && env.rank != 0 && !env.agent_store ? "0" : "";
    }
  }

  [[noreturn]] void lost(const std::string& what, const std::string& detail) {
    std::string d = detail.substr(0, detail.find('\n'));
    if (d.size() > 300) d = d.substr(0, 300) + "...";
    const std::string silent = silent_ranks();
    throw DataParallelError(fmt::format(
        "data-parallel rank {} of {}: {} failed ({}): {}. The run keeps its last checkpoint (rank 0 wrote it); start "
        "the same command again to resume",
        env.rank, env.world, what, d,
        silent.empty() ? std::string("another rank stopped or cannot be reached")
                       : fmt::format("rank {} stopped answering (it died, hung past the {:g} s timeout "
                                     "(--dist-timeout) or cannot be reached)",
                                     silent, opt.timeout_seconds)));
  }

  template <class F>
  auto guarded(const std::string& what, F&& f) {
    try {
      return f();
    } catch (const UserError&) {
      throw;
    } catch (const DataParallelError&) {
      throw;
    } catch (const std::exception& e) {
      lost(what, e.what());
    }
  }

  void wait_key(const std::string& key, std::chrono::milliseconds t, const std::string& what) {
    guarded(what, [&] { store->wait({key}, t); });
  }
  std::string get(const std::string& key, const std::string& what) {
    auto v = guarded(what, [&] { return store->get(key); });
    return std::string(v.begin(), v.end());
  }
  void set(const std::string& key, const std::string& value, const std::string& what) {
    guarded(what, [&] { store->set(key, std::vector<uint8_t>(value.begin(), value.end())); });
  }

  // ---- gradient buckets

  void launch_ready() {
    while (next_launch < buckets.size() && buckets[next_launch].ready) {
      Bucket& b = buckets[next_launch++];
      b.io = {b.flat};
      b.work = pg->allreduce(b.io);
    }
  }

  void on_grad(size_t j, const torch::Tensor& g) {
    std::lock_guard<std::mutex> lock(mu);
    if (!armed) return;
    try {
      auto [b, off] = where[j];
      Bucket& bk = buckets[b];
      auto slot = bk.flat.narrow(0, off, params[j].numel());
      if (seen[j]) {  // a second gradient for one leaf (not expected): accumulate
        slot.add_(g.reshape({-1}));
        return;
      }
      slot.copy_(g.reshape({-1}));
      seen[j] = 1;
      if (--bk.pending == 0) {
        bk.ready = true;
        launch_ready();
      }
    } catch (...) {
      // Never throw through autograd: finish_gradients() reports it.
      if (!hook_error) hook_error = std::current_exception();
    }
  }
};

DataParallel::DataParallel(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
DataParallel::~DataParallel() = default;

namespace {

std::shared_ptr<::gloo::transport::Device> gloo_device(const DistEnv& e) {
  const std::string ifname = env_str("GLOO_SOCKET_IFNAME");
  if (!ifname.empty()) return c10d::ProcessGroupGloo::createDeviceForInterface(ifname);
  if (!e.store_path.empty() || is_loopback(e.master_addr))
    return c10d::ProcessGroupGloo::createDeviceForHostname("127.0.0.1");
  return c10d::ProcessGroupGloo::createDefaultDevice();
}

}  // namespace

std::unique_ptr<DataParallel> DataParallel::join(const DistEnv& env, const DistOptions& o) {
  if (!env.distributed()) fail("DataParallel::join needs WORLD_SIZE > 1");
  auto d = std::make_unique<Impl>();
  d->env = env;
  d->opt = o;
  const std::string where = env.store_path.empty()
                                ? fmt::format("TCPStore {}:{}", env.master_addr, env.master_port)
                                : fmt::format("FileStore {}", env.store_path);
  try {
    c10::intrusive_ptr<c10d::Store> base;
    if (!env.store_path.empty()) {
      base = c10::make_intrusive<c10d::FileStore>(env.store_path, env.world);
    } else {
      c10d::TCPStoreOptions so;
      so.port = static_cast<std::uint16_t>(env.master_port);
      so.isServer = env.rank == 0 && !env.agent_store;
      so.numWorkers = env.world;
      so.timeout = d->timeout();
      base = c10::make_intrusive<c10d::TCPStore>(env.master_addr, so);
    }
    base->setTimeout(d->timeout());
    // Our keys (and Gloo's) under one prefix: a torchrun agent's store holds its own.
    d->store = c10::make_intrusive<c10d::PrefixStore>("motionctl", base);
    auto po = c10d::ProcessGroupGloo::Options::create(d->timeout());
    po->devices.push_back(gloo_device(env));
    po->threads = 1;  // one communication thread: the cores are for compute
    d->pg = c10::make_intrusive<c10d::ProcessGroupGloo>(d->store, env.rank, env.world, po);
  } catch (const std::exception& e) {
    std::string msg = e.what();
    msg = msg.substr(0, std::min<size_t>(msg.find('\n'), 300));
    throw DataParallelError(fmt::format(
        "data-parallel rank {} of {} could not join the job through the {} within {:g} s ({}): every rank must "
        "start with the same WORLD_SIZE and store, and rank 0 must be reachable",
        env.rank, env.world, where, o.timeout_seconds, msg));
  }
  return std::unique_ptr<DataParallel>(new DataParallel(std::move(d)));
}

int DataParallel::rank() const { return impl_->env.rank; }
int DataParallel::world() const { return impl_->env.world; }
const DistEnv& DataParallel::env() const { return impl_->env; }
const DistOptions& DataParallel::options() const { return impl_->opt; }
const ReduceTimes& DataParallel::times() const { return impl_->times; }

void DataParallel::sum_(torch::Tensor& t) {
  impl_->guarded("an all-reduce", [&] {
    torch::Tensor c = t.is_contiguous() ? t : t.contiguous();
    std::vector<at::Tensor> v{c};
    impl_->pg->allreduce(v)->wait();
    if (!c.is_same(t)) t.copy_(c);
  });
}

void DataParallel::check_same_job(const std::vector<std::pair<std::string, std::string>>& fields) {
  auto& d = *impl_;
  std::string mine;
  for (auto& [k, v] : fields) mine += k + "=" + v + "\n";
  const std::string what = "the rendezvous";
  d.set(fmt::format("job/{}", d.env.rank), mine, what);
  if (d.env.rank != 0) {
    d.wait_key("job/verdict", d.timeout(), what);
    const std::string verdict = d.get("job/verdict", what);
    if (verdict != "ok") throw UserError(verdict);
    return;
  }
  auto parse = [](const std::string& s) {
    std::vector<std::pair<std::string, std::string>> out;
    std::istringstream in(s);
    for (std::string line; std::getline(in, line);) {
      const auto eq = line.find('=');
      out.emplace_back(line.substr(0, eq), eq == std::string::npos ? "" : line.substr(eq + 1));
    }
    return out;
  };
  std::string refusal;
  for (int r = 1; r < d.env.world && refusal.empty(); ++r) {
    const std::string key = fmt::format("job/{}", r);
    d.wait_key(key, d.timeout(), what);
    const auto theirs = parse(d.get(key, what));
    for (size_t i = 0; i < std::max(theirs.size(), fields.size()) && refusal.empty(); ++i) {
      const std::string name = i < fields.size() ? fields[i].first : theirs[i].first;
      const std::string a = i < fields.size() ? fields[i].second : "(none)";
      const std::string b = i < theirs.size() ? theirs[i].second : "(none)";
      if (i >= theirs.size() || i >= fields.size() || theirs[i].first != fields[i].first || a != b)
        refusal = fmt::format(
            "data-parallel job refused: rank {} runs another job than rank 0: its {} is '{}', rank 0's is '{}'. "
            "Every rank must run the same motionctl build, config, overrides and options (start them all with the "
            "same command)",
            r, name, b, a);
    }
  }
  d.set("job/verdict", refusal.empty() ? "ok" : refusal, what);
  if (!refusal.empty()) throw UserError(refusal);
}

void DataParallel::announce_start(const std::string& status) {
  impl_->set("start", status, "announcing the start");
}

std::string DataParallel::await_start() {
  auto& d = *impl_;
  const auto t = std::chrono::milliseconds(static_cast<int64_t>(d.opt.start_timeout_seconds * 1000));
  d.wait_key("start", t, "waiting for rank 0 to start");
  return d.get("start", "waiting for rank 0 to start");
}

void DataParallel::broadcast(std::string& bytes) {
  auto& d = *impl_;
  d.guarded("broadcasting rank 0's training state", [&] {
    std::vector<at::Tensor> n{torch::tensor({static_cast<int64_t>(bytes.size())}, torch::kInt64)};
    d.pg->broadcast(n)->wait();
    const int64_t size = n[0].item<int64_t>();
    std::vector<at::Tensor> buf;
    if (d.env.rank == 0)
      buf.push_back(torch::from_blob(bytes.data(), {size}, torch::kUInt8).clone());
    else
      buf.push_back(torch::empty({size}, torch::kUInt8));
    d.pg->broadcast(buf)->wait();
    if (d.env.rank != 0) bytes.assign(reinterpret_cast<const char*>(buf[0].data_ptr<uint8_t>()), size);
  });
}

void DataParallel::attach(const std::vector<torch::Tensor>& params) {
  auto& d = *impl_;
  for (size_t j = 0; j < d.hook_ids.size(); ++j) d.params[j].remove_hook(d.hook_ids[j]);
  d.hook_ids.clear();
  d.params.clear();
  for (const auto& p : params)
    if (p.defined() && p.requires_grad()) d.params.push_back(p);
  d.where.assign(d.params.size(), {0, 0});
  d.seen.assign(d.params.size(), 0);
  d.buckets.clear();
  // Buckets in reverse parameter order, the order backward mostly produces them (as
  // PyTorch's DDP does); one dtype per bucket; a bucket closes at bucket_bytes.
  std::vector<int64_t> numel;
  for (size_t k = d.params.size(); k-- > 0;) {
    const auto& p = d.params[k];
    const int64_t size = static_cast<int64_t>(p.element_size());
    const bool open = !d.buckets.empty() && d.buckets.back().flat.scalar_type() == p.scalar_type() &&
                      (numel.back() + p.numel()) * size <= d.opt.bucket_bytes;
    if (!open) {
      d.buckets.emplace_back();
      d.buckets.back().flat = torch::empty({0}, p.options().requires_grad(false));  // holds the dtype until sized
      numel.push_back(0);
    }
    d.where[k] = {d.buckets.size() - 1, numel.back()};
    d.buckets.back().params.push_back(k);
    numel.back() += p.numel();
  }
  for (size_t b = 0; b < d.buckets.size(); ++b)
    d.buckets[b].flat = torch::zeros({numel[b]}, d.buckets[b].flat.options());
  if (d.opt.overlap) {
    Impl* self = &d;
    for (size_t j = 0; j < d.params.size(); ++j)
      d.hook_ids.push_back(d.params[j].register_hook([self, j](const torch::Tensor& g) { self->on_grad(j, g); }));
  }
}

void DataParallel::begin_backward() {
  auto& d = *impl_;
  std::lock_guard<std::mutex> lock(d.mu);
  for (auto& b : d.buckets) {
    b.pending = static_cast<int64_t>(b.params.size());
    b.ready = false;
    b.work.reset();
  }
  std::fill(d.seen.begin(), d.seen.end(), 0);
  d.next_launch = 0;
  d.hook_error = nullptr;
  d.armed = d.opt.overlap;
}

void DataParallel::finish_gradients(const std::string& what) {
  auto& d = *impl_;
  const auto t0 = Clock::now();
  {
    std::lock_guard<std::mutex> lock(d.mu);
    d.armed = false;
    if (d.hook_error) {
      try {
        std::rethrow_exception(d.hook_error);
      } catch (const std::exception& e) {
        d.lost(fmt::format("the gradient all-reduce of {}", what), e.what());
      }
    }
    // Gradients the hooks did not see (no overlap, or a parameter this step did not
    // reach: its gradient is what zero_grad left, zero), then every bucket in order.
    d.guarded(fmt::format("the gradient all-reduce of {}", what), [&] {
      for (auto& b : d.buckets) {
        if (b.ready) continue;
        for (size_t j : b.params) {
          if (d.seen[j]) continue;
          auto slot = b.flat.narrow(0, d.where[j].second, d.params[j].numel());
          const auto& g = d.params[j].grad();
          if (g.defined())
            slot.copy_(g.reshape({-1}));
          else
            slot.zero_();
        }
        b.ready = true;
      }
      d.launch_ready();
      for (auto& b : d.buckets) b.work->wait();
    });
  }
  for (size_t j = 0; j < d.params.size(); ++j) {
    auto src = d.buckets[d.where[j].first].flat.narrow(0, d.where[j].second, d.params[j].numel()).view(
        d.params[j].sizes());
    auto& g = d.params[j].mutable_grad();
    if (g.defined())
      g.copy_(src);
    else
      g = src.clone();
  }
  d.times.wait_seconds += std::chrono::duration<double>(Clock::now() - t0).count();
  ++d.times.steps;
}

void DataParallel::set_overlap(bool on) {
  impl_->opt.overlap = on;
  std::vector<torch::Tensor> params = impl_->params;
  attach(params);
}

size_t DataParallel::bucket_count() const { return impl_->buckets.size(); }

std::vector<double> DataParallel::sum_scalars(const std::vector<double>& v, const std::string& what) {
  auto& d = *impl_;
  const auto t0 = Clock::now();
  auto t = torch::tensor(v, torch::kFloat64);
  d.guarded(what, [&] {
    std::vector<at::Tensor> io{t};
    d.pg->allreduce(io)->wait();
  });
  d.times.scalar_seconds += std::chrono::duration<double>(Clock::now() - t0).count();
  return std::vector<double>(t.data_ptr<double>(), t.data_ptr<double>() + t.numel());
}

// ---------------------------------------------------------------- launcher

namespace {

std::vector<std::string>& command_line_slot() {
  static std::vector<std::string> args;
  return args;
}

volatile std::sig_atomic_t g_launcher_signal = 0;
extern "C" void on_launcher_signal(int sig) { g_launcher_signal = sig; }

std::string describe_status(int status) {
  if (WIFEXITED(status)) return fmt::format("exited with code {}", WEXITSTATUS(status));
  if (WIFSIGNALED(status)) {
    const int s = WTERMSIG(status);
    return fmt::format("was killed by signal {} ({})", s, ::strsignal(s));
  }
  return "stopped";
}

}  // namespace

void set_command_line(int argc, char** argv) {
  command_line_slot().assign(argv, argv + argc);
}
const std::vector<std::string>& command_line() { return command_line_slot(); }

int launch_local_ranks(int nproc, const std::vector<std::string>& args, double grace_seconds) {
  std::string tmpl = (fs::temp_directory_path() / "motionctl-ddp-XXXXXX").string();
  std::vector<char> buf(tmpl.begin(), tmpl.end());
  buf.push_back('\0');
  if (!::mkdtemp(buf.data()))
    fail("--nproc: cannot create a rendezvous directory under {} ({}); set TMPDIR to a writable directory",
         fs::temp_directory_path().string(), std::strerror(errno));
  const fs::path dir = buf.data();
  const std::string store = (dir / "store").string();

  // The parent records SIGINT/SIGTERM instead of dying. A terminal's Ctrl-C reaches
  // every rank itself (one process group); a signal sent to the parent alone is
  // passed on, so the ranks stop together at a checkpoint.
  struct sigaction sa {}, old_int {}, old_term {};
  sa.sa_handler = on_launcher_signal;
  sigemptyset(&sa.sa_mask);
  ::sigaction(SIGINT, &sa, &old_int);
  ::sigaction(SIGTERM, &sa, &old_term);
  g_launcher_signal = 0;
  const bool terminal_group = ::isatty(STDIN_FILENO) && ::tcgetpgrp(STDIN_FILENO) == ::getpgrp();

  std::vector<pid_t> pids(nproc, -1);
  std::vector<int> status(nproc, 0);
  std::vector<bool> done(nproc, false);
  auto kill_all = [&](int sig) {
    for (int r = 0; r < nproc; ++r)
      if (pids[r] > 0 && !done[r]) ::kill(pids[r], sig);
  };
  for (int r = 0; r < nproc; ++r) {
    const pid_t pid = ::fork();
    if (pid < 0) {
      kill_all(SIGKILL);
      fail("--nproc: cannot start rank {} ({})", r, std::strerror(errno));
    }
    if (pid == 0) {
      ::signal(SIGINT, SIG_DFL);
      ::signal(SIGTERM, SIG_DFL);
      ::setenv("RANK", std::to_string(r).c_str(), 1);
      ::setenv("LOCAL_RANK", std::to_string(r).c_str(), 1);
      ::setenv("WORLD_SIZE", std::to_string(nproc).c_str(), 1);
      ::setenv("LOCAL_WORLD_SIZE", std::to_string(nproc).c_str(), 1);
      ::setenv("MOTIONCTL_DIST_STORE", store.c_str(), 1);
      std::vector<char*> argv;
      for (const auto& a : args) argv.push_back(const_cast<char*>(a.c_str()));
      argv.push_back(nullptr);
      ::execv("/proc/self/exe", argv.data());
      std::fprintf(stderr, "motionctl: cannot start rank %d: %s\n", r, std::strerror(errno));
      ::_exit(127);
    }
    pids[r] = pid;
  }

  // After a failure the other ranks get `grace_seconds` to notice it and exit with
  // their own message (a dead peer is seen at once, a hung one after the
  // collective timeout); then SIGTERM, and SIGKILL 10 s later.
  int first_failure = -1, alive = nproc;
  auto term_at = Clock::time_point::max(), kill_at = Clock::time_point::max();
  while (alive > 0) {
    if (const int sig = g_launcher_signal) {
      g_launcher_signal = 0;
      if (sig == SIGTERM || !terminal_group) kill_all(sig);
    }
    int st = 0;
    const pid_t p = ::waitpid(-1, &st, WNOHANG);
    if (p > 0) {
      int r = 0;
      while (r < nproc && pids[r] != p) ++r;
      if (r == nproc) continue;
      done[r] = true;
      status[r] = st;
      --alive;
      const bool clean = WIFEXITED(st) && (WEXITSTATUS(st) == 0 || WEXITSTATUS(st) == 130 || WEXITSTATUS(st) == 143);
      if (!clean && first_failure < 0) {
        first_failure = r;
        if (alive > 0) {
          std::cerr << fmt::format("motionctl: rank {} (pid {}) {}; the other ranks stop\n", r, p,
                                   describe_status(st));
          term_at = Clock::now() + std::chrono::milliseconds(static_cast<int64_t>(grace_seconds * 1000));
        }
      }
      continue;
    }
    if (p < 0 && errno != EINTR && errno != ECHILD) break;
    if (Clock::now() > term_at) {
      kill_all(SIGTERM);
      term_at = Clock::time_point::max();
      kill_at = Clock::now() + std::chrono::seconds(10);
    }
    if (Clock::now() > kill_at) {
      kill_all(SIGKILL);
      kill_at = Clock::time_point::max();
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  ::sigaction(SIGINT, &old_int, nullptr);
  ::sigaction(SIGTERM, &old_term, nullptr);
  std::error_code ec;
  fs::remove_all(dir, ec);

  if (first_failure >= 0) {
    const int st = status[first_failure];
    if (WIFEXITED(st) && WEXITSTATUS(st) == kExitUserError)
      std::cerr << fmt::format("motionctl: rank {} of {} refused the job (exit code 2; the reason is above)\n",
                               first_failure, nproc);
    else
      std::cerr << fmt::format(
          "motionctl: error: data-parallel training failed: rank {} of {} {} (the first to fail). The run keeps its "
          "last checkpoint: run the same command again to resume\n",
          first_failure, nproc, describe_status(st));
    return WIFEXITED(st) ? WEXITSTATUS(st) : 1;
  }
  for (int r = 0; r < nproc; ++r)
    if (WIFEXITED(status[r]) && WEXITSTATUS(status[r]) != 0) return WEXITSTATUS(status[r]);
  return 0;
}

}  // namespace mc
