// Shipped trained components: manifest, integrity check and installation into runs/.
#include "train/pretrained.h"

#include <c10/util/hash.h>
#include <yaml-cpp/yaml.h>

#include <unistd.h>

#include <algorithm>
#include <cstdlib>
#include <fstream>
#include <sstream>

#include "core/atomic_file.h"
#include "core/error.h"
#include "core/source_dir.h"

namespace mc {

fs::path pretrained_root() {
  if (const char* env = std::getenv("MOTIONCTL_PRETRAINED")) {
    std::string v = env;
    if (v.empty() || v == "none") return {};
    return v;
  }
  return fs::path(source_dir()) / "pretrained";
}

std::vector<PretrainedEntry> read_pretrained_manifest(const fs::path& root) {
  std::vector<PretrainedEntry> out;
  if (root.empty()) return out;
  const fs::path file = root / "manifest.yaml";
  if (!fs::exists(file)) return out;
  YAML::Node doc;
  try {
    doc = YAML::LoadFile(file.string());
  } catch (const YAML::Exception& e) {
    fail("{}: not valid YAML ({}); restore it with git or delete the folder", file.string(), e.what());
  }
  const YAML::Node list = doc["components"];
  if (!list || !list.IsSequence()) fail("{}: needs a list under 'components'", file.string());
  for (size_t i = 0; i < list.size(); ++i) {
    const YAML::Node n = list[i];
    PretrainedEntry e;
    auto get = [&](const char* key) {
      if (!n.IsMap() || !n[key] || !n[key].IsScalar())
        fail("{}: components[{}] has no '{}' (each entry: experiment, name, config, config_hash, sha1, retrain)",
             file.string(), i, key);
      return n[key].as<std::string>();
    };
    e.experiment = get("experiment");
    e.name = get("name");
    e.config = get("config");
    e.config_hash = get("config_hash");
    if (n["overrides"]) {
      if (!n["overrides"].IsSequence())
        fail("{}: components[{}].overrides must be a list of key=value strings", file.string(), i);
      for (const auto& o : n["overrides"]) e.overrides.push_back(o.as<std::string>());
    }
    e.sha1 = get("sha1");
    e.retrain = get("retrain");
    e.dir = root / e.experiment / e.name;
    out.push_back(e);
  }
  return out;
}

std::optional<PretrainedEntry> find_pretrained(const fs::path& root, const std::string& experiment,
                                               const std::string& name) {
  for (auto& e : read_pretrained_manifest(root))
    if (e.experiment == experiment && e.name == name) return e;
  return std::nullopt;
}

std::string file_sha1(const fs::path& file) {
  std::ifstream f(file, std::ios::binary);
  if (!f) fail("cannot read '{}'", file.string());
  std::stringstream ss;
  ss << f.rdbuf();
  return c10::sha1(ss.str()).str();
}

namespace {

// Copies `from` to `to` through a temporary sibling renamed into place: a reader
// never sees a half-copied run directory.
void copy_tree_atomic(const fs::path& from, const fs::path& to) {
  fs::path tmp = to;
  tmp += fmt::format(".tmp.{}", ::getpid());
  std::error_code ec;
  fs::remove_all(tmp, ec);
  fs::create_directories(tmp.parent_path(), ec);
  fs::copy(from, tmp, fs::copy_options::recursive, ec);
  if (ec) fail("cannot copy '{}' to '{}': {}", from.string(), tmp.string(), ec.message());
  fs::rename(tmp, to, ec);
  if (ec) {
    fs::remove_all(tmp);
    if (!fs::exists(to)) fail("cannot move '{}' into place as '{}': {}", tmp.string(), to.string(), ec.message());
  }
}

}  // namespace

bool install_pretrained(const std::string& experiment, const std::string& name, const std::string& config_hash,
                        const fs::path& run_dir, std::ostream* log) {
  if (fs::exists(run_dir)) return false;
  const fs::path root = pretrained_root();
  auto e = find_pretrained(root, experiment, name);
  if (!e) return false;
  if (e->config_hash != config_hash) {
    if (log)
      *log << fmt::format("the shipped {} was trained from another version of {} (config hash {}, now {}); training "
                          "it instead\n",
                          e->name, e->config, e->config_hash, config_hash);
    return false;
  }
  const fs::path ckpt = e->dir / "checkpoints" / "final.pt";
  if (!fs::exists(ckpt) || !fs::exists(e->dir / "DONE"))
    fail("shipped component '{}' is incomplete ({} or DONE missing); restore pretrained/ with git", e->name,
         ckpt.string());
  const std::string got = file_sha1(ckpt);
  if (got != e->sha1)
    fail("shipped component '{}': {} has SHA-1 {} but the manifest says {}; restore it with git or retrain it "
         "with `{}`",
         e->name, ckpt.string(), got, e->sha1, e->retrain);
  copy_tree_atomic(e->dir, run_dir);
  if (log) *log << fmt::format("using the shipped {} ({}) for {}\n", e->name, e->dir.string(), e->config);
  // The runs it was trained on (a ControlNet's base, a TMD prior's tokenizer, an
  // adapter's TMD prior) come with it: they were shipped under the names it records.
  for (const std::string& dep : run_dependencies(run_dir)) {
    const fs::path d(dep);
    if (fs::exists(d)) continue;
    auto de = find_pretrained(root, d.parent_path().filename().string(), d.filename().string());
    if (de) install_pretrained(de->experiment, de->name, de->config_hash, d, log);
  }
  return true;
}

std::vector<std::string> run_dependencies(const fs::path& run_dir) {
  std::vector<std::string> out;
  if (!fs::is_directory(run_dir / "outputs")) return out;
  for (const auto& f : fs::directory_iterator(run_dir / "outputs")) {
    if (f.path().extension() != ".yaml") continue;
    YAML::Node n;
    try {
      n = YAML::LoadFile(f.path().string());
    } catch (const YAML::Exception& e) {
      fail("'{}' is corrupt: {}", f.path().string(), e.what());
    }
    if (!n.IsMap()) continue;
    for (const auto& kv : n) {
      const std::string key = kv.first.as<std::string>();
      if (key.size() > 4 && key.compare(key.size() - 4, 4, "_run") == 0 && kv.second.IsScalar())
        out.push_back(kv.second.as<std::string>());
    }
  }
  std::sort(out.begin(), out.end());
  return out;
}

PretrainedEntry ship_run(const fs::path& run_dir, const fs::path& root, const std::string& config,
                         const std::vector<std::string>& overrides, const std::string& config_hash,
                         const std::string& retrain) {
  if (!fs::exists(run_dir / "DONE") || !fs::exists(run_dir / "checkpoints" / "final.pt"))
    fail("'{}' is not a finished run (DONE or checkpoints/final.pt missing); finish it before shipping it",
         run_dir.string());
  PretrainedEntry e;
  e.experiment = run_dir.parent_path().filename().string();
  e.name = run_dir.filename().string();
  e.config = config;
  e.overrides = overrides;
  e.config_hash = config_hash;
  e.retrain = retrain;
  e.dir = root / e.experiment / e.name;
  const fs::path staging = root / ".staging" / e.name;
  std::error_code ec;
  fs::remove_all(staging, ec);
  fs::create_directories(staging / "checkpoints");
  for (const char* f : {"config.yaml", "overrides.txt", "seed.txt", "summary.csv", "metrics.csv", "DONE",
                        "health.md", "health.json"})
    if (fs::exists(run_dir / f)) fs::copy_file(run_dir / f, staging / f);
  fs::copy_file(run_dir / "checkpoints" / "final.pt", staging / "checkpoints" / "final.pt");
  if (fs::exists(run_dir / "outputs")) fs::copy(run_dir / "outputs", staging / "outputs", fs::copy_options::recursive);
  e.sha1 = file_sha1(staging / "checkpoints" / "final.pt");
  fs::remove_all(e.dir, ec);
  fs::create_directories(e.dir.parent_path());
  fs::rename(staging, e.dir);
  fs::remove_all(root / ".staging", ec);

  // An entry of the same config and overrides under another name is an older training of
  // this component (its config changed since): it is superseded, so its files go too, and
  // the manifest never ships two versions of one component.
  auto entries = read_pretrained_manifest(root);
  const auto superseded = [&](const PretrainedEntry& x) {
    return x.experiment == e.experiment &&
           (x.name == e.name || (x.config == e.config && x.overrides == e.overrides));
  };
  for (const auto& x : entries)
    if (superseded(x) && x.name != e.name) fs::remove_all(root / x.experiment / x.name, ec);
  entries.erase(std::remove_if(entries.begin(), entries.end(), superseded), entries.end());
  entries.push_back(e);
  YAML::Emitter y;
  y << YAML::Comment("Trained components shipped with motionctl (written by `motionctl ship`). run_train installs "
                     "an entry into runs/ when it is about to train a run of the same experiment, name and config hash.");
  y << YAML::BeginMap << YAML::Key << "components" << YAML::Value << YAML::BeginSeq;
  for (auto& x : entries) {
    y << YAML::BeginMap << YAML::Key << "experiment" << YAML::Value << x.experiment << YAML::Key << "name"
      << YAML::Value << x.name << YAML::Key << "config" << YAML::Value << x.config;
    if (!x.overrides.empty()) y << YAML::Key << "overrides" << YAML::Value << YAML::Flow << x.overrides;
    y << YAML::Key << "config_hash" << YAML::Value << x.config_hash << YAML::Key << "sha1" << YAML::Value << x.sha1
      << YAML::Key << "retrain" << YAML::Value << x.retrain << YAML::EndMap;
  }
  y << YAML::EndSeq << YAML::EndMap;
  write_file_atomic(root / "manifest.yaml", std::string(y.c_str()) + "\n");
  return e;
}

}  // namespace mc
