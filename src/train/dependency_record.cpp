// A run's record of the trained components it was built on, and the check of a
// finished run against the components its config resolves to now.
#include "train/dependency_record.h"

#include <sys/stat.h>
#include <yaml-cpp/yaml.h>

#include <map>
#include <mutex>

#include <fmt/format.h>
#include <fmt/ranges.h>

#include "core/atomic_file.h"
#include "core/error.h"
#include "train/pretrained.h"

namespace mc {

namespace {

// The SHA-1 of a file version already hashed in this process.
struct HashedFile {
  dev_t dev;
  ino_t ino;
  off_t size;
  int64_t mtime_ns;
  std::string sha1;
};

std::string short_sha(const std::string& sha) { return sha.substr(0, 12); }

// The UTC time a run finished, as its DONE marker holds it ("2026-11-23T14:46:34Z",
// which orders as text); "" when absent or not such a time.
std::string done_time(const fs::path& run_dir) {
  std::error_code ec;
  if (!fs::is_regular_file(run_dir / "DONE", ec)) return "";
  std::string t = read_file(run_dir / "DONE");
  while (!t.empty() && (t.back() == '\n' || t.back() == ' ')) t.pop_back();
  const bool iso = t.size() == 20 && t[4] == '-' && t[7] == '-' && t[10] == 'T' && t[13] == ':' && t[16] == ':' &&
                   t[19] == 'Z';
  return iso ? t : "";
}

}  // namespace

std::string weights_sha1(const fs::path& run_dir) {
  static std::map<std::string, HashedFile> cache;
  static std::mutex cache_mutex;
  const fs::path file = run_dir / "checkpoints" / "final.pt";
  struct stat st {};
  if (::stat(file.c_str(), &st) != 0) return "";
  const int64_t mtime_ns = static_cast<int64_t>(st.st_mtim.tv_sec) * 1000000000 + st.st_mtim.tv_nsec;
  const std::string key = fs::weakly_canonical(file).string();
  {
    std::lock_guard<std::mutex> lock(cache_mutex);
    auto it = cache.find(key);
    if (it != cache.end() && it->second.dev == st.st_dev && it->second.ino == st.st_ino &&
        it->second.size == st.st_size && it->second.mtime_ns == mtime_ns)
      return it->second.sha1;
  }
  // final.pt is replaced by an atomic rename, never rewritten in place: a new
  // version is a new inode, so a file that kept (device, inode, size, mtime) kept
  // its bytes.
  const std::string sha = file_sha1(file);
  std::lock_guard<std::mutex> lock(cache_mutex);
  cache[key] = HashedFile{st.st_dev, st.st_ino, st.st_size, mtime_ns, sha};
  return sha;
}

std::string run_key(const std::string& run_dir) {
  fs::path p = fs::path(run_dir).lexically_normal();
  if (p.filename().empty()) p = p.parent_path();  // a trailing separator
  return (p.parent_path().filename() / p.filename()).generic_string();
}

void write_dependency_record(const fs::path& run_dir, const std::vector<ResolvedDependency>& deps,
                             const std::string& note) {
  YAML::Emitter y;
  y << YAML::Comment(
      "The trained components this run was built on, as resolved when it started training (SHA-1 of each one's "
      "checkpoints/final.pt). A later reuse of the run compares them with what its config resolves to then and "
      "trains it again on a mismatch (docs/choices.md, \"Stale dependents\").");
  y << YAML::BeginMap;
  if (!note.empty()) y << YAML::Key << "note" << YAML::Value << note;
  y << YAML::Key << "dependencies" << YAML::Value << YAML::BeginSeq;
  for (const auto& d : deps) {
    y << YAML::BeginMap << YAML::Key << "what" << YAML::Value << d.what << YAML::Key << "run" << YAML::Value << d.run
      << YAML::Key << "config" << YAML::Value << d.config << YAML::Key << "overrides" << YAML::Value << YAML::Flow
      << d.overrides << YAML::Key << "sha1" << YAML::Value << d.sha1 << YAML::EndMap;
  }
  y << YAML::EndSeq << YAML::EndMap;
  write_file_atomic(run_dir / kDependencyRecord, std::string(y.c_str()) + "\n");
}

std::optional<std::vector<ResolvedDependency>> read_dependency_record(const fs::path& run_dir) {
  const fs::path file = run_dir / kDependencyRecord;
  if (!fs::exists(file)) return std::nullopt;
  const std::string fix =
      "delete it (the run is then taken as built on the components its config names today, with a warning) or "
      "retrain the run with run.force=true";
  std::vector<ResolvedDependency> out;
  try {
    const YAML::Node doc = YAML::LoadFile(file.string());
    const YAML::Node list = doc.IsMap() ? doc["dependencies"] : YAML::Node();
    if (!list || !list.IsSequence()) fail("'{}' is corrupt: it has no list under 'dependencies'; {}", file.string(), fix);
    for (size_t i = 0; i < list.size(); ++i) {
      const YAML::Node n = list[i];
      auto get = [&](const char* key) {
        if (!n.IsMap() || !n[key] || !n[key].IsScalar())
          fail("'{}' is corrupt: dependencies[{}] has no '{}'; {}", file.string(), i, key, fix);
        return n[key].as<std::string>();
      };
      ResolvedDependency d;
      d.what = get("what");
      d.run = get("run");
      d.sha1 = get("sha1");
      if (n["config"] && n["config"].IsScalar()) d.config = n["config"].as<std::string>();
      if (n["overrides"] && n["overrides"].IsSequence())
        for (const auto& o : n["overrides"]) d.overrides.push_back(o.as<std::string>());
      out.push_back(d);
    }
  } catch (const YAML::Exception& e) {
    fail("'{}' is corrupt ({}); {}", file.string(), e.what(), fix);
  }
  return out;
}

std::vector<std::string> changed_dependencies(const std::vector<ResolvedDependency>& recorded,
                                              const std::vector<ResolvedDependency>& now) {
  std::vector<std::string> out;
  for (const auto& n : now) {
    const ResolvedDependency* same_run = nullptr;
    const ResolvedDependency* same_what = nullptr;
    for (const auto& r : recorded) {
      if (!same_run && run_key(r.run) == run_key(n.run)) same_run = &r;
      if (!same_what && r.what == n.what) same_what = &r;
    }
    if (same_run) {
      if (same_run->sha1 != n.sha1)
        out.push_back(fmt::format("{} {} {}, which is now {}", n.what, n.run, short_sha(same_run->sha1),
                                  short_sha(n.sha1)));
    } else if (same_what) {
      out.push_back(fmt::format("{} {} {}, which is now {} {}", n.what, same_what->run, short_sha(same_what->sha1),
                                n.run, short_sha(n.sha1)));
    } else {
      std::vector<std::string> runs;
      for (const auto& r : recorded) runs.push_back(run_key(r.run));
      out.push_back(fmt::format("[{}], not on {} {} {}", fmt::join(runs, ", "), n.what, n.run, short_sha(n.sha1)));
    }
  }
  return out;
}

DependencyCheck check_dependencies(const fs::path& run_dir, const std::vector<ResolvedDependency>& now) {
  DependencyCheck c;
  if (auto recorded = read_dependency_record(run_dir)) {
    c.reasons = changed_dependencies(*recorded, now);
    c.state = c.reasons.empty() ? DependencyCheck::State::fresh : DependencyCheck::State::stale;
    return c;
  }
  if (now.empty()) return c;  // nothing it could be stale against
  // A legacy run: the run directories its outputs name, and when runs finished, are
  // all there is. Another run of the same experiment as a dependency resolved now
  // (e.g. prior/flow_standard-<old hash> for prior/flow_standard-<new hash>) means its
  // config changed since; a dependency that finished after this run did (DONE holds
  // the UTC time a run finished, and travels with a copied or shipped run) was trained
  // again since: make's rule, on the recorded times rather than file times.
  const std::string own_done = done_time(run_dir);
  const std::vector<std::string> named = run_dependencies(run_dir);
  for (const auto& n : now) {
    const std::string dep_done = done_time(n.run);
    if (!own_done.empty() && !dep_done.empty() && dep_done > own_done) {
      c.reasons.push_back(fmt::format("{} {} as it was before {}, which was trained again at {}", n.what, n.run,
                                      own_done, dep_done));
      continue;
    }
    const std::string key = run_key(n.run);
    const std::string experiment = fs::path(key).parent_path().string();
    bool same = false;
    std::string other;
    for (const auto& m : named) {
      const std::string mk = run_key(m);
      if (mk == key) same = true;
      else if (fs::path(mk).parent_path().string() == experiment && other.empty()) other = m;
    }
    if (!same && !other.empty())
      c.reasons.push_back(fmt::format("{} {}, which is now {} {}", n.what, other, n.run, short_sha(n.sha1)));
  }
  c.state = c.reasons.empty() ? DependencyCheck::State::unrecorded : DependencyCheck::State::stale;
  return c;
}

std::string describe_dependencies(const std::vector<ResolvedDependency>& deps) {
  std::vector<std::string> parts;
  for (const auto& d : deps) parts.push_back(fmt::format("{} {} (sha1 {})", d.what, d.run, short_sha(d.sha1)));
  return fmt::format("{}", fmt::join(parts, ", "));
}

}  // namespace mc
