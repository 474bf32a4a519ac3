// Atomic file output (temp + fsync + rename) and checked whole-file reads.
#include "core/atomic_file.h"

#include <fcntl.h>
#include <unistd.h>

#include <atomic>
#include <cerrno>
#include <cstring>
#include <fstream>
#include <sstream>

#include "core/error.h"

namespace mc {
namespace {

void fsync_path(const fs::path& p, bool directory) {
  int fd = ::open(p.c_str(), directory ? O_RDONLY | O_DIRECTORY : O_RDONLY);
  if (fd < 0) return;  // best effort: some filesystems refuse directory fds
  ::fsync(fd);
  ::close(fd);
}

fs::path make_tmp(const fs::path& target) {
  static std::atomic<unsigned> counter{0};
  return target.parent_path() /
         fmt::format(".{}.tmp.{}.{}", target.filename().string(), ::getpid(), counter++);
}

}  // namespace

AtomicOutput::AtomicOutput(fs::path target) : target_(std::move(target)) {
  if (!target_.parent_path().empty()) {
    std::error_code ec;
    fs::create_directories(target_.parent_path(), ec);
    if (ec) fail("cannot create directory '{}': {}", target_.parent_path().string(), ec.message());
  }
  tmp_ = make_tmp(target_);
}

AtomicOutput::~AtomicOutput() {
  if (!committed_) {
    std::error_code ec;
    fs::remove(tmp_, ec);
  }
}

void AtomicOutput::commit() {
  if (!fs::exists(tmp_)) fail("internal: temporary output '{}' was never written", tmp_.string());
  fsync_path(tmp_, false);
  std::error_code ec;
  fs::rename(tmp_, target_, ec);
  if (ec) fail("cannot move '{}' to '{}': {}", tmp_.string(), target_.string(), ec.message());
  committed_ = true;
  fsync_path(target_.parent_path().empty() ? fs::path(".") : target_.parent_path(), true);
}

void write_file_atomic(const fs::path& path, const std::string& content) {
  AtomicOutput out(path);
  {
    std::ofstream f(out.tmp_path(), std::ios::binary);
    if (!f) fail("cannot write '{}': {}", out.tmp_path().string(), std::strerror(errno));
    f.write(content.data(), static_cast<std::streamsize>(content.size()));
    f.flush();
    if (!f) fail("write to '{}' failed (disk full?)", out.tmp_path().string());
  }
  out.commit();
}

std::string read_file(const fs::path& path) {
  std::ifstream f(path, std::ios::binary);
  if (!f) fail("cannot read '{}': {}", path.string(), fs::exists(path) ? "permission denied" : "no such file");
  std::ostringstream ss;
  ss << f.rdbuf();
  return ss.str();
}

}  // namespace mc
