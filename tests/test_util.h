// Shared helpers for tests: temp dirs, running the motionctl binary, reading files,
// catching UserErrors. Helpers of one layer live beside its tests
// (tests/<layer>/*_test_util.h) and are shared from there, never copied.
#pragma once
#include <sys/wait.h>
#include <unistd.h>

#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include <fmt/format.h>

#include <catch2/catch.hpp>

#include "core/error.h"

namespace mc::test {

namespace fs = std::filesystem;

struct TempDir {
  fs::path path;
  explicit TempDir(const std::string& tag = "t") {
    path = fs::temp_directory_path() / fmt::format("mc_{}_{}_{}", tag, ::getpid(), std::rand());
    fs::create_directories(path);
  }
  ~TempDir() {
    std::error_code ec;
    fs::remove_all(path, ec);
  }
};

struct CommandResult {
  int exit_code = -1;
  std::string output;  // stdout + stderr
};

// Runs `motionctl <args>` from the source tree; captures output and exit code.
inline CommandResult run_motionctl(const std::string& args) {
  std::string cmd = fmt::format("cd '{}' && CI=1 '{}' {} 2>&1", MOTIONCTL_SOURCE_DIR, MOTIONCTL_BINARY, args);
  CommandResult r;
  FILE* p = ::popen(cmd.c_str(), "r");
  char buf[4096];
  size_t n;
  while ((n = fread(buf, 1, sizeof buf, p)) > 0) r.output.append(buf, n);
  int status = ::pclose(p);
  r.exit_code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  return r;
}

inline std::string slurp(const fs::path& p) {
  std::ifstream f(p);
  std::stringstream ss;
  ss << f.rdbuf();
  return ss.str();
}

// A run's metrics.csv without its wall_time column (the only column allowed to differ
// between a resumed and an uninterrupted run).
inline std::string metrics_without_wall(const fs::path& p) {
  std::stringstream in(slurp(p)), out;
  std::string line;
  int wall_col = -1;
  bool header = true;
  while (std::getline(in, line)) {
    std::stringstream ls(line);
    std::string cell, kept;
    int col = 0;
    while (std::getline(ls, cell, ',')) {
      if (header && cell == "wall_time") wall_col = col;
      if (col != wall_col) kept += cell + ",";
      ++col;
    }
    header = false;
    out << kept << "\n";
  }
  return out.str();
}

// The message of the UserError `f` throws; "" when it throws nothing, and
// "<not a UserError: ...>" for any other exception (so a Contains check fails).
template <class F>
std::string user_error_of(F&& f) {
  try {
    f();
  } catch (const mc::UserError& e) {
    return e.what();
  } catch (const std::exception& e) {
    return std::string("<not a UserError: ") + e.what() + ">";
  } catch (...) {
    return "<not a UserError>";
  }
  return "";
}

// Runs `f`, expecting a UserError whose message contains every fragment.
template <class F>
void expect_user_error(F&& f, const std::vector<std::string>& fragments) {
  const std::string msg = user_error_of(std::forward<F>(f));
  INFO("message: " << msg);
  REQUIRE_FALSE(msg.empty());
  for (const auto& frag : fragments) CHECK(msg.find(frag) != std::string::npos);
}

}  // namespace mc::test
