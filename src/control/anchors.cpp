// Anchor sets (AnchorRoute §3.1): conversion from and to constraint specs, benchmark
// draws, the interpolation prior and condition features, and the support assignment.
#include "control/anchors.h"

#include <algorithm>
#include <cmath>
#include <map>
#include <set>
#include <tuple>

#include "core/error.h"
#include "data/skeleton.h"

namespace mc {

namespace {

const char* const kAxisNames = "xyz";

std::string axes_text(const std::array<bool, 3>& a) {
  std::string s;
  for (int c = 0; c < 3; ++c)
    if (a[c]) s += kAxisNames[c];
  return s.empty() ? "none" : s;
}

bool is_xyz(const std::array<bool, 3>& a) { return a[0] && a[1] && a[2]; }
bool is_xz(const std::array<bool, 3>& a) { return a[0] && !a[1] && a[2]; }

// The axes an anchor of `family` on `joint` controls.
std::array<bool, 3> family_axes(AnchorFamily f) {
  return f == AnchorFamily::planar_root ? std::array<bool, 3>{true, false, true}
                                        : std::array<bool, 3>{true, true, true};
}

// Unbiased uniform integer in [0, n) from raw engine output (no std distribution,
// whose algorithm differs between standard libraries).
uint64_t uniform_below(std::mt19937_64& rng, uint64_t n) {
  const uint64_t limit = UINT64_MAX - UINT64_MAX % n;
  uint64_t r;
  do r = rng();
  while (r >= limit);
  return r % n;
}

// Why an anchor does not fit a family ("" if it does).
std::string family_mismatch(AnchorFamily f, const Anchor& a) {
  switch (f) {
    case AnchorFamily::root_3d:
      if (a.joint != 0 || !is_xyz(a.axes)) return "root_3d anchors control x, y, z of the root (joint 0)";
      return "";
    case AnchorFamily::planar_root:
      if (a.joint != 0 || !is_xz(a.axes)) return "planar_root anchors control x and z of the root (joint 0) only";
      return "";
    case AnchorFamily::body_point:
      if (!is_xyz(a.axes)) return "body_point anchors control x, y and z of a joint";
      return "";
  }
  return "";
}

}  // namespace

std::string family_name(AnchorFamily f) {
  switch (f) {
    case AnchorFamily::root_3d: return "root_3d";
    case AnchorFamily::planar_root: return "planar_root";
    case AnchorFamily::body_point: return "body_point";
  }
  return "?";
}

AnchorFamily parse_anchor_family(const std::string& name, const std::string& what) {
  if (name == "root_3d") return AnchorFamily::root_3d;
  if (name == "planar_root") return AnchorFamily::planar_root;
  if (name == "body_point") return AnchorFamily::body_point;
  fail("{}: unknown anchor family '{}' (use root_3d, planar_root or body_point)", what, name);
}

std::vector<int> AnchorSet::times() const {
  std::vector<int> t;
  for (const auto& a : anchors) t.push_back(a.frame);
  std::sort(t.begin(), t.end());
  t.erase(std::unique(t.begin(), t.end()), t.end());
  return t;
}

std::vector<int> AnchorSet::joints() const {
  std::vector<int> j;
  for (const auto& a : anchors) j.push_back(a.joint);
  std::sort(j.begin(), j.end());
  j.erase(std::unique(j.begin(), j.end()), j.end());
  return j;
}

void AnchorSet::normalize_and_check(int num_joints, const std::string& what) {
  std::sort(anchors.begin(), anchors.end(),
            [](const Anchor& a, const Anchor& b) { return std::tie(a.frame, a.joint) < std::tie(b.frame, b.joint); });
  if (frames < 1) fail("{}: anchor set has {} frames; it needs a clip of at least 1 frame", what, frames);
  for (size_t n = 0; n < anchors.size(); ++n) {
    const Anchor& a = anchors[n];
    if (a.frame < 0 || a.frame >= frames)
      fail("{}: anchor at frame {} is outside the clip [0, {})", what, a.frame, frames);
    if (a.joint < 0 || a.joint >= num_joints)
      fail("{}: anchor at frame {} names joint {}, but the skeleton has {} joints", what, a.frame, a.joint,
           num_joints);
    if (n > 0 && anchors[n - 1].frame == a.frame && anchors[n - 1].joint == a.joint)
      fail("{}: two anchors on joint {} at frame {}; merge them into one", what, a.joint, a.frame);
    std::string why = family_mismatch(family, a);
    if (!why.empty())
      fail("{}: anchor at frame {} on joint {} controls axes {}: {}", what, a.frame, a.joint, axes_text(a.axes), why);
    for (int c = 0; c < 3; ++c) {
      if (!std::isfinite(a.value[c])) fail("{}: anchor at frame {} on joint {} has a non-finite value", what, a.frame, a.joint);
      if (!a.axes[c] && a.value[c] != 0.0)
        fail("{}: anchor at frame {} on joint {} has a value on uncontrolled axis {}", what, a.frame, a.joint,
             kAxisNames[c]);
    }
  }
}

// ------------------------------------------------------------------ spec <-> anchors

AnchorSet anchors_from_observation(const LinearObservation& obs, std::optional<AnchorFamily> family) {
  const int J = obs.joints;
  auto label = [&](int r) {
    int it = r < static_cast<int>(obs.item_of_row.size()) ? obs.item_of_row[r] : -1;
    return it >= 0 && it < static_cast<int>(obs.item_labels.size()) ? obs.item_labels[it]
                                                                     : fmt::format("row {}", r);
  };
  struct Slot {
    Anchor anchor;
    int row = 0;  // first row, for messages
  };
  std::map<std::pair<int, int>, Slot> slots;  // (frame, joint)
  for (int r = 0; r < obs.rows(); ++r) {
    if (!obs.is_hard(r))
      fail("{}: {}: row {} is soft (variance {}); anchors are hard targets: set variance 0", obs.source, label(r), r,
           obs.variance[r]);
    int nnz = 0, col = -1;
    double coef = 0;
    for (Eigen::SparseMatrix<double, Eigen::RowMajor>::InnerIterator e(obs.A, r); e; ++e) {
      if (e.value() == 0.0) continue;
      ++nnz;
      col = static_cast<int>(e.col());
      coef = e.value();
    }
    if (nnz != 1 || coef != 1.0)
      fail("{}: {}: row {} combines {} coordinates (coefficient {}); anchors can only select single joint "
           "coordinates (keyframe, trajectory and planar_root items), not camera, relative or loop rows",
           obs.source, label(r), r, nnz, coef);
    const int c = col % 3, j = (col / 3) % J, t = col / (3 * J);
    auto [it, fresh] = slots.try_emplace({t, j});
    Slot& s = it->second;
    if (fresh) {
      s.anchor.frame = t;
      s.anchor.joint = j;
      s.anchor.axes = {false, false, false};
      s.row = r;
    }
    if (s.anchor.axes[c])
      fail("{}: {}: row {} pins axis {} of joint {} at frame {} a second time", obs.source, label(r), r,
           kAxisNames[c], j, t);
    s.anchor.axes[c] = true;
    s.anchor.value[c] = obs.y[r];
  }
  AnchorSet set;
  set.frames = obs.frames;
  for (auto& [key, s] : slots) set.anchors.push_back(s.anchor);

  if (!family) {
    if (set.anchors.empty())
      fail("{}: the constraints give no anchor rows, so the anchor family cannot be inferred; name it", obs.source);
    bool all_root = true, all_xyz = true, all_xz = true;
    for (const auto& a : set.anchors) {
      all_root = all_root && a.joint == 0;
      all_xyz = all_xyz && is_xyz(a.axes);
      all_xz = all_xz && is_xz(a.axes);
    }
    if (all_root && all_xyz) family = AnchorFamily::root_3d;
    else if (all_root && all_xz) family = AnchorFamily::planar_root;
    else if (all_xyz) family = AnchorFamily::body_point;
    else {
      // Name the first anchor that fits no family.
      for (auto& [key, s] : slots)
        if (!is_xyz(s.anchor.axes) && !(s.anchor.joint == 0 && is_xz(s.anchor.axes)))
          fail("{}: {}: joint {} at frame {} is controlled on axes {}; anchors control x, y, z of a joint "
               "(root_3d, body_point) or x, z of the root (planar_root)",
               obs.source, label(s.row), key.second, key.first, axes_text(s.anchor.axes));
      fail("{}: the constraints mix root x, z anchors with x, y, z anchors; one anchor set has one family "
           "(root_3d, planar_root or body_point)",
           obs.source);
    }
  }
  set.family = *family;
  for (auto& [key, s] : slots) {
    std::string why = family_mismatch(set.family, s.anchor);
    if (!why.empty())
      fail("{}: {}: joint {} at frame {} is controlled on axes {}: {}", obs.source, label(s.row), key.second,
           key.first, axes_text(s.anchor.axes), why);
  }
  set.normalize_and_check(J, obs.source);
  return set;
}

AnchorSet anchors_from_spec(const ConstraintSpec& spec, int frames, const Skeleton& skeleton,
                            const float* source_motion, std::optional<AnchorFamily> family) {
  // Inequality and direction items are not anchors: they ride along (RouteSolver's
  // extra residuals, the exact projection) and are left out here.
  ConstraintSpec anchors_only;
  anchors_only.source = spec.source;
  for (size_t i = 0; i < spec.items.size(); ++i) {
    const auto& t = spec.items[i].type;
    if (is_inequality_type(t) || is_direction_type(t)) continue;
    if (t != "keyframe" && t != "trajectory" && t != "planar_root")
      fail("{}: {}: {} items cannot be expressed as anchors (anchors select joint coordinates: use keyframe, "
           "trajectory or planar_root items)",
           spec.source, spec.item_label(static_cast<int>(i)), t);
    anchors_only.items.push_back(spec.items[i]);
  }
  return anchors_from_observation(compile(anchors_only, frames, skeleton, source_motion), family);
}

ConstraintSpec anchors_to_spec(const AnchorSet& set, const std::string& source) {
  ConstraintSpec spec;
  spec.source = source;
  auto item_for = [&](int joint, const std::string& type, const std::string& name) {
    ConstraintItem it;
    it.type = type;
    it.name = name;
    it.frames.kind = FrameSelection::Kind::list;
    if (type != "planar_root") it.joints = {JointRef{joint, ""}};
    for (const auto& a : set.anchors) {
      if (a.joint != joint) continue;
      it.frames.list.push_back(a.frame);
      for (int c = 0; c < 3; ++c)
        if (a.axes[c]) it.values.data.push_back(a.value[c]);
    }
    const int F = static_cast<int>(it.frames.list.size());
    it.values.shape = type == "planar_root" ? std::vector<int>{F, 2} : std::vector<int>{F, 1, 3};
    return it;
  };
  if (set.anchors.empty()) return spec;
  switch (set.family) {
    case AnchorFamily::root_3d: spec.items.push_back(item_for(0, "keyframe", "root anchors")); break;
    case AnchorFamily::planar_root: spec.items.push_back(item_for(0, "planar_root", "planar root anchors")); break;
    case AnchorFamily::body_point:
      for (int j : set.joints()) spec.items.push_back(item_for(j, "keyframe", fmt::format("joint {} anchors", j)));
      break;
  }
  return spec;
}

std::vector<double> anchor_errors(const AnchorSet& set, const float* motion, int num_joints) {
  std::vector<double> e;
  e.reserve(set.anchors.size());
  for (const auto& a : set.anchors) {
    const float* p = motion + (static_cast<size_t>(a.frame) * num_joints + a.joint) * 3;
    double s = 0;
    for (int c = 0; c < 3; ++c)
      if (a.axes[c]) s += (p[c] - a.value[c]) * (p[c] - a.value[c]);
    e.push_back(std::sqrt(s));
  }
  return e;
}

double anchor_loss(const AnchorSet& set, const float* motion, int num_joints) {  // eq. (3)
  double s = 0;
  for (double e : anchor_errors(set, motion, num_joints)) s += e * e;
  return s;
}

// ------------------------------------------------------------------ benchmark draws

std::vector<int> draw_anchor_frames(std::mt19937_64& rng, int frames, int K) {
  if (K < 0 || K > frames) fail("cannot draw {} distinct anchor frames from a clip of {} frames", K, frames);
  std::vector<int> idx(frames);
  for (int i = 0; i < frames; ++i) idx[i] = i;
  for (int i = 0; i < K; ++i)
    std::swap(idx[i], idx[i + static_cast<int>(uniform_below(rng, static_cast<uint64_t>(frames - i)))]);
  idx.resize(K);
  std::sort(idx.begin(), idx.end());
  return idx;
}

AnchorSet draw_anchor_set(AnchorFamily family, int K, const float* motion, int frames, int num_joints,
                          std::mt19937_64& rng, const std::vector<int>& body_joints) {
  AnchorSet set;
  set.family = family;
  set.frames = frames;
  auto times = draw_anchor_frames(rng, frames, K);
  int joint = 0;
  if (family == AnchorFamily::body_point) {
    if (body_joints.empty()) fail("body_point anchors need at least one candidate joint");
    joint = body_joints[uniform_below(rng, body_joints.size())];
  }
  const auto axes = family_axes(family);
  for (int t : times) {
    Anchor a;
    a.frame = t;
    a.joint = joint;
    a.axes = axes;
    for (int c = 0; c < 3; ++c)
      if (axes[c]) a.value[c] = motion[(static_cast<size_t>(t) * num_joints + joint) * 3 + c];
    set.anchors.push_back(a);
  }
  set.normalize_and_check(num_joints, "draw_anchor_set");
  return set;
}

AnchorSet draw_sparse_keyjoint_set(const float* motion, int frames, int num_joints, std::mt19937_64& rng,
                                   double ratio, const std::vector<int>& joints) {
  if (!(ratio > 0 && ratio <= 1)) fail("sparse keyjoint protocol: frame ratio {} must be in (0, 1]", ratio);
  const int K = std::max(1, static_cast<int>(std::lround(ratio * frames)));
  AnchorSet set;
  set.family = AnchorFamily::body_point;
  set.frames = frames;
  for (int t : draw_anchor_frames(rng, frames, K))
    for (int j : joints) {
      Anchor a;
      a.frame = t;
      a.joint = j;
      if (j < 0 || j >= num_joints) fail("sparse keyjoint protocol: joint {} is not in a {}-joint skeleton", j, num_joints);
      for (int c = 0; c < 3; ++c) a.value[c] = motion[(static_cast<size_t>(t) * num_joints + j) * 3 + c];
      set.anchors.push_back(a);
    }
  set.normalize_and_check(num_joints, "sparse keyjoint protocol");
  return set;
}

// ------------------------------------------------------------------ interpolation prior

Eigen::MatrixXd interpolate_anchor_values(const std::vector<int>& times, const Eigen::MatrixXd& values) {
  const int n = static_cast<int>(times.size());
  if (n == 0 || values.rows() != n) fail("interpolation prior: {} times but {} value rows", n, values.rows());
  for (int i = 1; i < n; ++i)
    if (times[i] <= times[i - 1]) fail("interpolation prior: anchor times must be strictly ascending");
  const int t0 = times.front(), span = times.back() - t0 + 1;
  Eigen::MatrixXd out(span, values.cols());
  if (n == 1) {
    out.row(0) = values.row(0);
    return out;
  }
  std::vector<double> h(n - 1);
  for (int i = 0; i + 1 < n; ++i) h[i] = times[i + 1] - times[i];
  // Second derivatives M of the not-a-knot spline (zero for the linear fallback).
  Eigen::MatrixXd M = Eigen::MatrixXd::Zero(n, values.cols());
  if (n >= 4) {
    Eigen::MatrixXd S = Eigen::MatrixXd::Zero(n, n), rhs = Eigen::MatrixXd::Zero(n, values.cols());
    for (int i = 1; i + 1 < n; ++i) {  // C2 continuity at the interior knots
      S(i, i - 1) = h[i - 1];
      S(i, i) = 2 * (h[i - 1] + h[i]);
      S(i, i + 1) = h[i];
      rhs.row(i) = 6 * ((values.row(i + 1) - values.row(i)) / h[i] - (values.row(i) - values.row(i - 1)) / h[i - 1]);
    }
    // Not-a-knot: the third derivative is continuous at the second and the
    // second-to-last knot (the first two and last two pieces are one cubic).
    S(0, 0) = -1 / h[0];
    S(0, 1) = 1 / h[0] + 1 / h[1];
    S(0, 2) = -1 / h[1];
    S(n - 1, n - 3) = -1 / h[n - 3];
    S(n - 1, n - 2) = 1 / h[n - 3] + 1 / h[n - 2];
    S(n - 1, n - 1) = -1 / h[n - 2];
    M = S.partialPivLu().solve(rhs);
  }
  int piece = 0;
  for (int k = 0; k < span; ++k) {
    const double x = t0 + k;
    while (piece + 2 < n && x > times[piece + 1]) ++piece;
    const double hh = h[piece];
    const double A = (times[piece + 1] - x) / hh, B = 1 - A;
    out.row(k) = A * values.row(piece) + B * values.row(piece + 1) +
                 ((A * A * A - A) * M.row(piece) + (B * B * B - B) * M.row(piece + 1)) * (hh * hh / 6);
  }
  // Exactly the anchor values at anchor frames (the spline agrees up to rounding).
  for (int i = 0; i < n; ++i) out.row(times[i] - t0) = values.row(i);
  return out;
}

// ------------------------------------------------------------------ condition features

AnchorFeatureLayout anchor_feature_layout(AnchorFamily family, const std::vector<int>& body_joints) {
  AnchorFeatureLayout L;
  L.family = family;
  if (family == AnchorFamily::body_point) {
    if (body_joints.empty()) fail("body_point anchor features need the list of joints they cover");
    std::set<int> seen;
    for (int j : body_joints)
      if (!seen.insert(j).second) fail("body_point anchor features: joint {} is listed twice", j);
    L.joints = body_joints;
  } else {
    L.joints = {0};
  }
  for (size_t g = 0; g < L.joints.size(); ++g) {
    L.axes.push_back(family_axes(family));
    L.d_f += L.family == AnchorFamily::planar_root ? 2 : 3;
  }
  return L;
}

namespace {

// One group's interpolation prior (eq. (5)): its controlled world axes, anchor frames
// (ascending: sets are sorted by frame), anchor values and the prior on
// [times.front(), times.back()].
struct GroupPrior {
  std::vector<int> chan;
  std::vector<int> times;
  Eigen::MatrixXd V, P;
  bool defined(int t) const { return !times.empty() && t >= times.front() && t <= times.back(); }
  // Axis c (0, 1, 2) of the prior at frame t (defined(t)); 0 for an uncontrolled axis.
  double at(int t, int c) const {
    for (size_t k = 0; k < chan.size(); ++k)
      if (chan[k] == c) return P(t - times.front(), static_cast<Eigen::Index>(k));
    return 0.0;
  }
  double anchor(size_t n, int c) const {
    for (size_t k = 0; k < chan.size(); ++k)
      if (chan[k] == c) return V(static_cast<Eigen::Index>(n), static_cast<Eigen::Index>(k));
    return 0.0;
  }
};

GroupPrior group_prior(const AnchorSet& set, const AnchorFeatureLayout& layout, int g) {
  GroupPrior r;
  for (int c = 0; c < 3; ++c)
    if (layout.axes[g][c]) r.chan.push_back(c);
  std::vector<Eigen::Vector3d> vals;
  for (const auto& a : set.anchors)
    if (a.joint == layout.joints[g]) {
      r.times.push_back(a.frame);
      vals.push_back(a.value);
    }
  if (r.times.empty()) return r;
  r.V.resize(static_cast<Eigen::Index>(r.times.size()), static_cast<Eigen::Index>(r.chan.size()));
  for (size_t n = 0; n < r.times.size(); ++n)
    for (size_t k = 0; k < r.chan.size(); ++k) r.V(n, k) = vals[n][r.chan[k]];
  r.P = interpolate_anchor_values(r.times, r.V);
  return r;
}

void check_features_input(const AnchorSet& set, const AnchorFeatureLayout& layout, const char* what) {
  if (set.family != layout.family)
    fail("{}: a {} anchor set cannot use a {} feature layout", what, family_name(set.family),
         family_name(layout.family));
  for (const auto& a : set.anchors) {
    auto it = std::find(layout.joints.begin(), layout.joints.end(), a.joint);
    if (it == layout.joints.end())
      fail("{}: the anchor at frame {} is on joint {}, which the feature layout does not cover", what, a.frame,
           a.joint);
  }
}

}  // namespace

FeatureMatrix anchor_features(const AnchorSet& set, const AnchorFeatureLayout& layout) {  // eqs. (5)-(6)
  check_features_input(set, layout, "anchor features");
  const int T = set.frames, d = layout.d_f, G = layout.groups();
  FeatureMatrix f = FeatureMatrix::Zero(T, layout.width());
  int col = 0;
  for (int g = 0; g < G; ++g) {
    const GroupPrior gp = group_prior(set, layout, g);
    const int dg = static_cast<int>(gp.chan.size());
    if (!gp.times.empty()) {
      for (size_t n = 0; n < gp.times.size(); ++n) {  // m^a (.) a, m^a
        for (int k = 0; k < dg; ++k) f(gp.times[n], col + k) = static_cast<float>(gp.V(n, k));
        f(gp.times[n], 3 * d + G + g) = 1.f;
      }
      const int t0 = gp.times.front(), t1 = gp.times.back();
      for (int t = t0; t <= t1; ++t) {  // m^p (.) p, m^p, Delta p (eq. (6))
        for (int k = 0; k < dg; ++k) {
          f(t, d + col + k) = static_cast<float>(gp.P(t - t0, k));
          if (t > t0) f(t, 2 * d + col + k) = static_cast<float>(gp.P(t - t0, k) - gp.P(t - t0 - 1, k));
        }
        f(t, 3 * d + g) = 1.f;
      }
    }
    col += dg;
  }
  return f;
}

// ------------------------------------------------------------------ path-frame features

int path_group_width(const AnchorFeatureLayout& layout, int g) {
  const bool y = layout.axes[g][1];
  const int kinematics = y ? 4 : 2, anchor = (y ? 3 : 2) + 1;  // displacement + time
  return kinematics + 2 * anchor + 2 + (layout.family == AnchorFamily::body_point ? 3 : 0);
}

int path_feature_width(const AnchorFeatureLayout& layout) {
  int w = 0;
  for (int g = 0; g < layout.groups(); ++g) w += path_group_width(layout, g);
  return w;
}

namespace {

// The path heading psi_t over a group's prior range (index t - t0); see anchor_path_features.
struct PathKinematics {
  std::vector<double> vx, vz, vy, speed, psi;
};

PathKinematics path_kinematics(const GroupPrior& gp) {
  PathKinematics k;
  const int t0 = gp.times.front(), t1 = gp.times.back(), n = t1 - t0 + 1;
  k.vx.assign(n, 0.0);
  k.vz.assign(n, 0.0);
  k.vy.assign(n, 0.0);
  k.speed.assign(n, 0.0);
  k.psi.assign(n, 0.0);
  for (int i = 0; i < n; ++i) {
    // Backward difference (eq. (6)'s Delta p); the first frame takes the forward one.
    const int a = i > 0 ? i - 1 : 0, b = i > 0 ? i : std::min(1, n - 1);
    k.vx[i] = gp.at(t0 + b, 0) - gp.at(t0 + a, 0);
    k.vy[i] = gp.at(t0 + b, 1) - gp.at(t0 + a, 1);
    k.vz[i] = gp.at(t0 + b, 2) - gp.at(t0 + a, 2);
    k.speed[i] = std::hypot(k.vx[i], k.vz[i]);
  }
  int first = -1, fastest = 0;
  for (int i = 0; i < n; ++i) {
    if (first < 0 && k.speed[i] >= kPathMinSpeed) first = i;
    if (k.speed[i] > k.speed[fastest]) fastest = i;
  }
  const int seed = first >= 0 ? first : fastest;
  double psi = k.speed[seed] > 0 ? std::atan2(k.vx[seed], k.vz[seed]) : 0.0;
  for (int i = 0; i < n; ++i) {
    if (k.speed[i] >= kPathMinSpeed) psi = std::atan2(k.vx[i], k.vz[i]);
    k.psi[i] = psi;
  }
  return k;
}

double wrap_angle(double a) { return std::atan2(std::sin(a), std::cos(a)); }

// World xz (dx, dz) in the frame rotated by -psi: x' lateral, z' along the heading.
void to_path_frame(double psi, double dx, double dz, double& x, double& z) {
  const double c = std::cos(psi), s = std::sin(psi);
  x = c * dx - s * dz;
  z = s * dx + c * dz;
}

}  // namespace

FeatureMatrix anchor_path_features(const AnchorSet& set, const AnchorFeatureLayout& layout) {
  check_features_input(set, layout, "anchor path features");
  const int T = set.frames, G = layout.groups();
  FeatureMatrix f = FeatureMatrix::Zero(T, path_feature_width(layout));
  std::vector<GroupPrior> priors;
  std::vector<PathKinematics> kin(G);
  for (int g = 0; g < G; ++g) {
    priors.push_back(group_prior(set, layout, g));
    if (!priors[g].times.empty()) kin[g] = path_kinematics(priors[g]);
  }
  int root = -1;  // the root group, for body points' root-relative channels
  if (layout.family == AnchorFamily::body_point)
    for (int g = 0; g < G; ++g)
      if (layout.joints[g] == 0) root = g;
  const double rate = kPathFrameRate;
  int col = 0;
  for (int g = 0; g < G; ++g) {
    const GroupPrior& gp = priors[g];
    const bool has_y = layout.axes[g][1];
    const int w = path_group_width(layout, g);
    if (gp.times.empty()) {
      col += w;
      continue;
    }
    const PathKinematics& k = kin[g];
    const int t0 = gp.times.front(), t1 = gp.times.back();
    for (int t = t0; t <= t1; ++t) {
      const int i = t - t0;
      int c = col;
      auto put = [&](double v) { f(t, c++) = static_cast<float>(v); };
      put(k.speed[i] * rate);
      double turn = 0.0;
      if (i > 0) {
        const double gate = std::min(1.0, std::min(k.speed[i], k.speed[i - 1]) / kPathMinSpeed);
        turn = wrap_angle(k.psi[i] - k.psi[i - 1]) * gate * rate;
      }
      put(turn);
      if (has_y) {
        put(k.vy[i] * rate);
        put(gp.at(t, 1));
      }
      // Next (strictly later) and previous (strictly earlier) anchors in the path frame at t.
      auto upper = std::upper_bound(gp.times.begin(), gp.times.end(), t);
      auto lower = std::lower_bound(gp.times.begin(), gp.times.end(), t);
      const int next = upper == gp.times.end() ? -1 : static_cast<int>(upper - gp.times.begin());
      const int prev = lower == gp.times.begin() ? -1 : static_cast<int>(lower - gp.times.begin()) - 1;
      for (int n : {next, prev}) {
        if (n < 0) {
          c += has_y ? 4 : 3;
          continue;
        }
        double x, z;
        to_path_frame(k.psi[i], gp.anchor(n, 0) - gp.at(t, 0), gp.anchor(n, 2) - gp.at(t, 2), x, z);
        put(x);
        if (has_y) put(gp.anchor(n, 1) - gp.at(t, 1));
        put(z);
        put(std::abs(gp.times[n] - t) / rate);
      }
      put(1.0);  // m^p
      put(std::binary_search(gp.times.begin(), gp.times.end(), t) ? 1.0 : 0.0);  // m^a
      if (layout.family == AnchorFamily::body_point && root >= 0 && root != g && priors[root].defined(t)) {
        const GroupPrior& rp = priors[root];
        const double psi = kin[root].psi[t - rp.times.front()];
        double x, z;
        to_path_frame(psi, gp.at(t, 0) - rp.at(t, 0), gp.at(t, 2) - rp.at(t, 2), x, z);
        put(x);
        put(gp.at(t, 1) - rp.at(t, 1));
        put(z);
      }
    }
    col += w;
  }
  return f;
}

// ------------------------------------------------------------------ support (eqs. (7)-(9))

std::vector<int> nearest_anchor_assignment(const std::vector<int>& times, int frames, int delta) {
  if (delta < 0) fail("support radius delta must be >= 0, got {}", delta);
  std::vector<int> n_star(frames, -1);
  for (int t = 0; t < frames; ++t) {
    int best = delta + 1;
    for (size_t n = 0; n < times.size(); ++n) {
      const int dist = std::abs(t - times[n]);
      if (dist < best) {  // strict: ties keep the earlier anchor (eq. (8))
        best = dist;
        n_star[t] = static_cast<int>(n);
      }
    }
  }
  return n_star;
}

std::vector<SupportEntry> support_entries(const AnchorSet& set, int delta) {
  std::vector<SupportEntry> out;
  for (int j : set.joints()) {
    std::vector<int> idx, times;
    for (int n = 0; n < set.size(); ++n)
      if (set.anchors[n].joint == j) {
        idx.push_back(n);
        times.push_back(set.anchors[n].frame);
      }
    auto assign = nearest_anchor_assignment(times, set.frames, delta);
    for (int t = 0; t < set.frames; ++t)
      if (assign[t] >= 0) out.push_back({t, idx[assign[t]]});
  }
  std::sort(out.begin(), out.end(), [&](const SupportEntry& a, const SupportEntry& b) {
    return std::make_pair(a.frame, set.anchors[a.anchor].joint) < std::make_pair(b.frame, set.anchors[b.anchor].joint);
  });
  return out;
}

AnchorSet support_targets(const AnchorSet& set, int delta, const float* gt_motion, int num_joints) {  // eq. (9)
  AnchorSet out;
  out.family = set.family;
  out.frames = set.frames;
  for (const auto& e : support_entries(set, delta)) {
    const Anchor& n = set.anchors[e.anchor];
    Anchor a;
    a.frame = e.frame;
    a.joint = n.joint;
    a.axes = n.axes;
    for (int c = 0; c < 3; ++c)
      if (a.axes[c]) a.value[c] = gt_motion[(static_cast<size_t>(e.frame) * num_joints + a.joint) * 3 + c];
    out.anchors.push_back(a);
  }
  return out;
}

}  // namespace mc
