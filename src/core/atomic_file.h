// Atomic file output: write to a temporary sibling, fsync, rename. A crash or
// an error leaves either the old file or none, never a partial one.
#pragma once
#include <filesystem>
#include <string>

namespace mc {

namespace fs = std::filesystem;

// Writes `content` to `path` atomically.
void write_file_atomic(const fs::path& path, const std::string& content);

// For writers that need a real path (HDF5, torch::save): write to tmp_path(),
// then commit(). The destructor removes the temporary if commit() never ran.
class AtomicOutput {
 public:
  explicit AtomicOutput(fs::path target);
  ~AtomicOutput();
  AtomicOutput(const AtomicOutput&) = delete;
  AtomicOutput& operator=(const AtomicOutput&) = delete;
  const fs::path& tmp_path() const { return tmp_; }
  const fs::path& target() const { return target_; }
  void commit();  // fsync the temporary, rename it over the target, fsync the directory

 private:
  fs::path target_, tmp_;
  bool committed_ = false;
};

std::string read_file(const fs::path& path);  // UserError naming the file when unreadable

}  // namespace mc
