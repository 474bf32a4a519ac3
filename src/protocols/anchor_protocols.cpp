// The AnchorRoute protocols: anchor draws per clip turned into control tasks.
#include "protocols/anchor_protocols.h"

#include <random>

#include "control/anchors.h"
#include "core/error.h"
#include "data/motion_set.h"

namespace mc {

namespace {

// A generator per (seed, clip, setting): a task does not depend on which other
// clips or settings are requested. std::seed_seq's mixing is fixed by the standard.
std::mt19937_64 task_rng(uint64_t seed, size_t clip, int setting) {
  std::seed_seq seq{static_cast<uint32_t>(seed), static_cast<uint32_t>(seed >> 32), static_cast<uint32_t>(clip),
                    static_cast<uint32_t>(clip >> 32), static_cast<uint32_t>(setting)};
  return std::mt19937_64(seq);
}

ControlTask base_task(const MotionSet& data, size_t i, const std::string& protocol) {
  if (i >= data.size()) fail("protocol {}: clip index {} is outside the motion set ({} clips)", protocol, i, data.size());
  ControlTask t;
  t.clip_id = data.ids[i];
  t.caption = data.captions[i].empty() ? "" : data.captions[i].front();
  t.length = data.lengths[i];
  const size_t n = static_cast<size_t>(t.length) * data.num_joints() * 3;
  t.source.assign(data.clip(i), data.clip(i) + n);
  return t;
}

void check_joints(const std::vector<int>& joints, const MotionSet& data, const std::string& key) {
  for (int j : joints)
    if (j >= data.num_joints())
      fail("protocol key '{}': joint {} is not in the {}-joint skeleton '{}'", key, j, data.num_joints(),
           data.skeleton.name);
}

}  // namespace

std::vector<ControlTask> AnchorRouteProtocol::make_tasks(const MotionSet& data, const std::vector<size_t>& clips,
                                                         uint64_t seed) const {
  const AnchorFamily fam = parse_anchor_family(family, "protocol key 'family'");
  if (fam == AnchorFamily::body_point) check_joints(body_joints, data, "body_joints");
  std::vector<ControlTask> tasks;
  for (size_t i : clips) {
    for (int K : anchor_counts) {
      ControlTask t = base_task(data, i, "anchor_route");
      if (K > t.length)
        fail("protocol anchor_route: clip '{}' has {} frames, fewer than anchor_counts entry {}", t.clip_id, t.length, K);
      auto rng = task_rng(seed, i, K);
      AnchorSet set = draw_anchor_set(fam, K, t.source.data(), t.length, data.num_joints(), rng, body_joints);
      t.id = fmt::format("{}#K{}", t.clip_id, K);
      t.group = fmt::format("family={}/K={}", family, K);
      t.spec = anchors_to_spec(set, "protocol anchor_route, " + t.id);
      tasks.push_back(std::move(t));
    }
  }
  return tasks;
}

std::vector<ControlTask> AnchorKeyjointProtocol::make_tasks(const MotionSet& data, const std::vector<size_t>& clips,
                                                            uint64_t seed) const {
  check_joints(joints, data, "joints");
  std::vector<ControlTask> tasks;
  for (size_t i : clips) {
    ControlTask t = base_task(data, i, "anchor_keyjoint");
    auto rng = task_rng(seed, i, 0);
    AnchorSet set = draw_sparse_keyjoint_set(t.source.data(), t.length, data.num_joints(), rng, frame_ratio, joints);
    t.id = t.clip_id;
    t.group = fmt::format("keyjoint/r={}", frame_ratio);
    t.spec = anchors_to_spec(set, "protocol anchor_keyjoint, " + t.id);
    tasks.push_back(std::move(t));
  }
  return tasks;
}

MC_REGISTER_PROTOCOL("anchor_route", AnchorRouteProtocol,
                     "AnchorRoute main protocol: K random anchors of one family per clip, K over anchor_counts");
MC_REGISTER_PROTOCOL("anchor_keyjoint", AnchorKeyjointProtocol,
                     "six-point sparse keyjoint protocol (SFControl all6-r30, our reading)");

}  // namespace mc
