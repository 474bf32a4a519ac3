// `motionctl export --format bvh FILE.h5 --out DIR [--ids a,b] [--translations auto|root|all]`:
// one BVH per clip of any motion file (dataset, `sample`/`generate` output), on the
// file's own skeleton, each re-read after writing to report its round-trip error.
#include <filesystem>
#include <iostream>
#include <map>
#include <sstream>

#include "cli/commands.h"
#include "core/atomic_file.h"
#include "core/error.h"
#include "data/bvh.h"
#include "data/motion_set.h"

namespace mc {
namespace fs = std::filesystem;

namespace {

std::string safe_file_name(const std::string& id) {
  std::string out;
  for (char c : id) out += (std::isalnum(static_cast<unsigned char>(c)) || c == '-' || c == '.' || c == '_') ? c : '_';
  while (!out.empty() && out.front() == '_') out.erase(out.begin());
  while (!out.empty() && out.back() == '_') out.pop_back();
  return out.empty() ? "clip" : out;
}

std::vector<size_t> select_clips(const MotionSet& m, const std::string& ids, const std::string& file) {
  std::vector<size_t> out;
  if (ids.empty()) {
    for (size_t i = 0; i < m.size(); ++i) out.push_back(i);
    return out;
  }
  std::map<std::string, size_t> index;
  for (size_t i = 0; i < m.size(); ++i) index[m.ids[i]] = i;
  std::stringstream ss(ids);
  for (std::string id; std::getline(ss, id, ',');) {
    if (id.empty()) continue;
    auto it = index.find(id);
    if (it == index.end())
      fail("--ids: {} has no clip with id '{}' (its first ids: {}{})", file, id, m.ids[0],
           m.size() > 1 ? ", " + m.ids[1] : "");
    out.push_back(it->second);
  }
  if (out.empty()) fail("--ids '{}' names no clip; give comma-separated clip ids", ids);
  return out;
}

}  // namespace

void add_export_command(CLI::App& app) {
  auto* cmd = app.add_subcommand("export", "write clips of a motion file as BVH (one file per clip)");
  struct Args {
    std::string file, out, ids, format = "bvh";
    BvhOptions bvh;
  };
  auto a = std::make_shared<Args>();
  cmd->add_option("motions", a->file, "motion HDF5 file (dataset, sample or generate output)")->required();
  cmd->add_option("--out", a->out, "output folder (created if missing)")->required();
  cmd->add_option("--format", a->format, "output format (bvh)")->check(CLI::IsMember({"bvh"}));
  cmd->add_option("--ids", a->ids, "comma-separated clip ids (default: every clip)");
  cmd->add_option("--translations", a->bvh.translations,
                  "root: a rigid BVH (root translation only); all: every joint carries its offset, exact for any "
                  "motion; auto (default): root when it reproduces the input within 1e-4 m, else all")
      ->check(CLI::IsMember({"auto", "root", "all"}));
  cmd->add_option("--scale", a->bvh.scale, "file units per metre (default 1: metres; 100: centimetres)")
      ->check(CLI::PositiveNumber);
  cmd->callback([a] {
    MotionSet m = read_motion_file(a->file);
    std::vector<size_t> chosen = select_clips(m, a->ids, a->file);
    std::error_code ec;
    fs::create_directories(a->out, ec);
    if (ec || !fs::is_directory(a->out))
      fail("--out {}: cannot create the output folder ({})", a->out, ec ? ec.message() : "not a folder");
    for (size_t i : chosen) {
      BvhExport e;
      try {
        e = clip_to_bvh(m.skeleton, m.clip(i), m.lengths[i], m.fps, a->bvh);
      } catch (const UserError& err) {
        fail("{}: clip {} ('{}'): {}", a->file, i, m.ids[i], err.what());
      }
      const fs::path path = fs::path(a->out) / fmt::format("{:04d}_{}.bvh", i, safe_file_name(m.ids[i]));
      write_file_atomic(path, e.text);
      std::cout << fmt::format("wrote {}: {} frames, {} (rigid fit error {:.2e} m); re-read error {:.2e} m\n",
                               path.string(), m.lengths[i],
                               e.all_translations ? "every joint translated" : "root translation only", e.rigid_error,
                               e.written_error);
    }
  });
}

}  // namespace mc
