// Run directory lifecycle (lock, create, resume, finish, force) and log/metrics files.
#include "core/run_dir.h"

#include <fcntl.h>
#include <sys/file.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <mutex>

#include <cstdlib>
#include <ctime>
#include <iostream>
#include <sstream>

#include "core/atomic_file.h"
#include "core/error.h"

namespace mc {

Logger::Logger(const fs::path& file) : file_(file, std::ios::app) {
  if (!file_) fail("cannot open log file '{}'", file.string());
}

bool Logger::interactive() {
  static const bool v = ::isatty(STDERR_FILENO) && std::getenv("CI") == nullptr;
  return v;
}

void Logger::info(const std::string& line) {
  end_progress();
  std::string stamped = fmt::format("[{}] {}", utc_timestamp(), line);
  std::cerr << stamped << "\n";
  if (file_) file_ << stamped << "\n" << std::flush;
}

void Logger::progress(const std::string& line) {
  if (!interactive()) return;
  std::cerr << "\r\033[K" << line << std::flush;
  live_ = true;
}

void Logger::end_progress() {
  if (live_) std::cerr << "\r\033[K" << std::flush;
  live_ = false;
}

void MetricsCsv::truncate_after(int64_t step) {
  if (!fs::exists(path_)) return;
  std::istringstream in(read_file(path_));
  std::string line, out;
  bool header = true;
  while (std::getline(in, line)) {
    if (header) {
      out += line + "\n";
      header = false;
      std::stringstream ss(line);
      header_.clear();
      for (std::string c; std::getline(ss, c, ',');) header_.push_back(c);
      continue;
    }
    if (line.empty()) continue;
    int64_t s = 0;
    try {
      s = std::stoll(line.substr(0, line.find(',')));
    } catch (const std::exception&) {
      fail("{}: row '{}' does not start with a step number; delete the run directory (or run.force=true) to "
           "train it again",
           path_.string(), line.substr(0, 80));
    }
    if (s <= step) out += line + "\n";
  }
  write_file_atomic(path_, out);
}

void MetricsCsv::append(int64_t step, const std::vector<std::pair<std::string, double>>& values) {
  bool fresh = !fs::exists(path_);
  std::ofstream f(path_, std::ios::app);
  if (!f) fail("cannot append to '{}'", path_.string());
  if (fresh) {
    header_ = {"step"};
    for (auto& [k, _] : values) header_.push_back(k);
    f << fmt::format("{}\n", fmt::join(header_, ","));
  }
  f << step;
  for (size_t i = 1; i < header_.size(); ++i) {
    double v = std::numeric_limits<double>::quiet_NaN();
    for (auto& [k, x] : values)
      if (k == header_[i]) v = x;
    f << "," << fmt::format("{:.8g}", v);
  }
  f << "\n" << std::flush;
}

std::string sanitize_name(const std::string& s) {
  std::string out;
  for (char c : s) out += (std::isalnum(static_cast<unsigned char>(c)) || c == '-' || c == '_' || c == '.' || c == '=') ? c : '_';
  return out.empty() ? "run" : out;
}

std::string utc_timestamp() {
  std::time_t t = std::time(nullptr);
  std::tm tm{};
  gmtime_r(&t, &tm);
  char buf[32];
  std::strftime(buf, sizeof buf, "%Y-%m-%dT%H:%M:%SZ", &tm);
  return buf;
}

// ---------------------------------------------------------------- lock

namespace {

// Locks this process holds, by directory: a nested open of a run it already
// holds shares the lock (flock on a second descriptor would refuse ourselves).
std::map<std::string, std::weak_ptr<RunLock>>& held_locks() {
  static std::map<std::string, std::weak_ptr<RunLock>> m;
  return m;
}
std::mutex& held_mutex() {
  static std::mutex m;
  return m;
}

// Files an AtomicOutput writes before its rename: .<name>.tmp.<pid>.<n>.
bool is_atomic_temp(const fs::path& p) {
  const std::string f = p.filename().string();
  return f.size() > 1 && f[0] == '.' && f.find(".tmp.") != std::string::npos;
}

}  // namespace

std::shared_ptr<RunLock> RunLock::acquire(const fs::path& run_dir) {
  std::error_code ec;
  fs::create_directories(run_dir, ec);
  if (ec) fail("cannot create run directory '{}': {}", run_dir.string(), ec.message());
  const std::string key = fs::weakly_canonical(run_dir).string();
  std::lock_guard<std::mutex> g(held_mutex());
  if (auto held = held_locks()[key].lock()) return held;
  const fs::path file = run_dir / ".lock";
  int fd = ::open(file.c_str(), O_RDWR | O_CREAT | O_CLOEXEC, 0644);
  if (fd < 0) fail("cannot open the lock file '{}': {}", file.string(), std::strerror(errno));
  if (::flock(fd, LOCK_EX | LOCK_NB) != 0) {
    const int err = errno;
    ::close(fd);
    if (err != EWOULDBLOCK)
      fail("cannot lock '{}': {} (run directories need a filesystem with flock)", file.string(), std::strerror(err));
    std::string holder;
    try {
      holder = read_file(file);
    } catch (const UserError&) {
    }
    while (!holder.empty() && (holder.back() == '\n' || holder.back() == ' ')) holder.pop_back();
    fail("run directory '{}' is in use by another motionctl process (pid {}); wait for it to finish or stop it "
         "(kill {}), or pick another run.name / run.root. run.force=true does not take over a run in use",
         run_dir.string(), holder.empty() ? "unknown" : holder, holder.empty() ? "<pid>" : holder);
  }
  // Ours now; whatever the file held came from a process that is gone (the kernel
  // drops a flock when its holder exits), so it is overwritten.
  const std::string pid = fmt::format("{}\n", ::getpid());
  if (::ftruncate(fd, 0) != 0 || ::pwrite(fd, pid.data(), pid.size(), 0) != static_cast<ssize_t>(pid.size())) {
    // The pid is for messages only; the lock itself holds.
  }
  std::shared_ptr<RunLock> lock(new RunLock(run_dir, fd));
  held_locks()[key] = lock;
  return lock;
}

RunLock::~RunLock() {
  if (fd_ >= 0) {
    // Leave the file (removing it would race with a process opening it); an
    // empty file says nobody holds it.
    if (::ftruncate(fd_, 0) != 0) {
    }
    ::flock(fd_, LOCK_UN);
    ::close(fd_);
  }
}

// ---------------------------------------------------------------- run directory

fs::path RunDir::path_of(const RunConfig& run, const std::string& default_name) {
  return fs::path(run.root) / sanitize_name(run.experiment) / sanitize_name(run.name.empty() ? default_name : run.name);
}

RunDir RunDir::open(const RunConfig& run, const std::string& resolved_yaml, const std::vector<std::string>& overrides,
                    const std::string& default_name, const SameRun& same) {
  RunDir r;
  r.dir_ = path_of(run, default_name);
  r.lock_ = RunLock::acquire(r.dir_);
  fs::path cfg_path = r.dir_ / "config.yaml";
  std::error_code ec;
  if (run.force) {
    // Redo the run where it is: everything but the lock we hold goes.
    for (const auto& e : fs::directory_iterator(r.dir_, ec))
      if (e.path().filename() != ".lock") fs::remove_all(e.path(), ec);
    if (ec) fail("run.force=true: cannot clear '{}': {}", r.dir_.string(), ec.message());
  }
  if (fs::exists(cfg_path)) {
    const std::string old = read_file(cfg_path);
    const bool same_run = same ? same(old) : old == resolved_yaml;
    if (!same_run)
      fail("run directory '{}' holds a run with a different config; pick another run.name or pass run.force=true "
           "to replace it (see diff against {})",
           r.dir_.string(), cfg_path.string());
  }
  fs::create_directories(r.checkpoints(), ec);
  fs::create_directories(r.outputs(), ec);
  if (ec) fail("cannot create run directory '{}': {}", r.dir_.string(), ec.message());
  // Temporaries of atomic writes killed before their rename: nobody else writes
  // here while we hold the lock, so every one of them is stale.
  std::vector<fs::path> stale;
  for (auto it = fs::recursive_directory_iterator(r.dir_, ec); !ec && it != fs::recursive_directory_iterator();
       it.increment(ec))
    if (it->is_regular_file() && is_atomic_temp(it->path())) stale.push_back(it->path());
  for (const auto& p : stale) fs::remove(p, ec);
  ec.clear();
  if (!fs::exists(cfg_path)) {
    write_file_atomic(cfg_path, resolved_yaml);
    std::string ov;
    for (auto& o : overrides) ov += o + "\n";
    write_file_atomic(r.dir_ / "overrides.txt", ov);
    write_file_atomic(r.dir_ / "seed.txt", fmt::format("{}\n", run.seed));
  }
  r.log_ = std::make_shared<Logger>(r.dir_ / "log.txt");
  return r;
}

bool RunDir::finished() const { return fs::exists(dir_ / "DONE"); }

void RunDir::mark_finished(const std::map<std::string, double>& summary) {
  std::string csv = "key,value\n";
  for (auto& [k, v] : summary) csv += fmt::format("{},{:.10g}\n", k, v);
  write_file_atomic(dir_ / "summary.csv", csv);
  write_file_atomic(dir_ / "DONE", utc_timestamp() + "\n");
}

std::map<std::string, double> RunDir::summary() const { return read_summary_csv(dir_ / "summary.csv"); }

std::map<std::string, double> read_summary_csv(const fs::path& path) {
  std::map<std::string, double> out;
  if (!fs::exists(path)) return out;
  std::istringstream in(read_file(path));
  std::string line;
  std::getline(in, line);
  while (std::getline(in, line)) {
    auto c = line.find(',');
    if (c == std::string::npos) continue;
    try {
      out[line.substr(0, c)] = std::stod(line.substr(c + 1));
    } catch (const std::exception&) {
      fail("{}: row '{}' does not hold a number", path.string(), line);
    }
  }
  return out;
}

}  // namespace mc
