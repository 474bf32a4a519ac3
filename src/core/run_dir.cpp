// Run directory lifecycle (create, resume, finish, force) and log/metrics files.
#include "core/run_dir.h"

#include <unistd.h>

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
    int64_t s = std::stoll(line.substr(0, line.find(',')));
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

RunDir RunDir::open(const RunConfig& run, const std::string& resolved_yaml, const std::vector<std::string>& overrides,
                    const std::string& default_name) {
  RunDir r;
  r.dir_ = fs::path(run.root) / sanitize_name(run.experiment) / sanitize_name(run.name.empty() ? default_name : run.name);
  fs::path cfg_path = r.dir_ / "config.yaml";
  if (fs::exists(r.dir_) && run.force) fs::remove_all(r.dir_);
  if (fs::exists(cfg_path)) {
    std::string old = read_file(cfg_path);
    // run.force and run.threads are not part of the run's identity: a run
    // trained on one thread is reused by a job that asks for all cores.
    auto strip = [](std::string s) {
      auto p = s.find("force: true");
      if (p != std::string::npos) s.replace(p, 11, "force: false");
      p = s.find("\n  threads: ");
      if (p != std::string::npos) s.erase(p + 1, s.find('\n', p + 1) - p);
      return s;
    };
    if (strip(old) != strip(resolved_yaml))
      fail("run directory '{}' holds a run with a different config; pick another run.name or pass run.force=true "
           "to replace it (see diff against {})",
           r.dir_.string(), cfg_path.string());
  }
  std::error_code ec;
  fs::create_directories(r.checkpoints(), ec);
  fs::create_directories(r.outputs(), ec);
  if (ec) fail("cannot create run directory '{}': {}", r.dir_.string(), ec.message());
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
