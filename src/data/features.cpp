// Joint-derived features (HumanML3D's process_file, positions only): facing from
// hips and shoulders, root velocities in the facing frame, root-relative positions.
#include "data/features.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>

#include "core/config.h"
#include "core/error.h"

namespace mc {
namespace {

constexpr double kPi = 3.14159265358979323846;
// Below this the hips and shoulders give no usable direction (e.g. all joints at one point).
constexpr double kDegenerateNorm = 1e-9;

double wrap_angle(double a) {
  a = std::fmod(a + kPi, 2 * kPi);
  if (a < 0) a += 2 * kPi;
  return a - kPi;
}

void require_clip(const float* joints, int frames, const char* fn) {
  if (frames < 1 || joints == nullptr)
    throw std::invalid_argument(fmt::format("{}: a clip needs at least one frame (got {})", fn, frames));
}

struct FaceJoints {
  int r_hip, l_hip, r_shoulder, l_shoulder;
};

FaceJoints face_joints(const Skeleton& sk) {
  const auto& f = sk.role("face");
  if (f.size() != 4)
    fail("skeleton '{}': role 'face' must list 4 joints (r_hip, l_hip, r_shoulder, l_shoulder), it lists {}", sk.name,
         f.size());
  return {f[0], f[1], f[2], f[3]};
}

// scipy.ndimage.gaussian_filter1d(x, sigma, mode='nearest', truncate=4.0), which
// HumanML3D applies to the forward direction; reproduced for comparable features.
std::vector<double> gaussian_smooth(const std::vector<double>& x, double sigma) {
  if (sigma <= 0 || x.size() < 2) return x;
  const int radius = static_cast<int>(4.0 * sigma + 0.5);
  std::vector<double> w(2 * radius + 1);
  double sum = 0;
  for (int k = -radius; k <= radius; ++k) sum += w[k + radius] = std::exp(-0.5 * (k / sigma) * (k / sigma));
  for (auto& v : w) v /= sum;
  const int n = static_cast<int>(x.size());
  std::vector<double> y(n, 0.0);
  for (int i = 0; i < n; ++i)
    for (int k = -radius; k <= radius; ++k) y[i] += w[k + radius] * x[std::clamp(i + k, 0, n - 1)];
  return y;
}

inline const float* joint_at(const float* joints, int J, int t, int j) {
  return joints + (static_cast<size_t>(t) * J + j) * 3;
}

}  // namespace

std::vector<double> facing_angles(const float* joints, int frames, const Skeleton& sk, const FeatureOptions& opt) {
  require_clip(joints, frames, "facing_angles");
  const FaceJoints f = face_joints(sk);
  const int J = sk.num_joints();
  // forward = cross(up, across) / |across| = (across_z, 0, -across_x) / |across|.
  std::vector<double> fx(frames), fz(frames);
  std::vector<bool> valid(frames);
  for (int t = 0; t < frames; ++t) {
    double across[3];
    for (int a = 0; a < 3; ++a)
      across[a] = (joint_at(joints, J, t, f.r_hip)[a] - joint_at(joints, J, t, f.l_hip)[a]) +
                  (joint_at(joints, J, t, f.r_shoulder)[a] - joint_at(joints, J, t, f.l_shoulder)[a]);
    const double norm = std::sqrt(across[0] * across[0] + across[1] * across[1] + across[2] * across[2]);
    const double horizontal = std::hypot(across[0], across[2]);
    valid[t] = norm > kDegenerateNorm && horizontal > kDegenerateNorm;
    fx[t] = valid[t] ? across[2] / norm : 0.0;
    fz[t] = valid[t] ? -across[0] / norm : 0.0;
  }
  // Degenerate frames borrow the nearest earlier valid direction (the first valid
  // one at the start), so features stay finite; a clip with none faces +Z.
  int first_valid = -1;
  for (int t = 0; t < frames && first_valid < 0; ++t)
    if (valid[t]) first_valid = t;
  for (int t = 0; t < frames; ++t) {
    if (valid[t]) continue;
    const int src = first_valid < 0 ? -1 : (t < first_valid ? first_valid : t - 1);
    fx[t] = src < 0 ? 0.0 : fx[src];
    fz[t] = src < 0 ? 1.0 : fz[src];
  }
  const std::vector<double> sx = gaussian_smooth(fx, opt.facing_smooth_sigma);
  const std::vector<double> sz = gaussian_smooth(fz, opt.facing_smooth_sigma);
  std::vector<double> theta(frames);
  for (int t = 0; t < frames; ++t) {
    // Smoothing a half-turn within the kernel can cancel the direction; keep the raw one then.
    const bool smooth_ok = std::hypot(sx[t], sz[t]) > kDegenerateNorm;
    theta[t] = smooth_ok ? std::atan2(sx[t], sz[t]) : std::atan2(fx[t], fz[t]);
  }
  return theta;
}

std::vector<float> local_positions(const float* joints, int frames, const Skeleton& sk, const FeatureOptions& opt) {
  const std::vector<double> theta = facing_angles(joints, frames, sk, opt);
  const int J = sk.num_joints();
  std::vector<float> out(static_cast<size_t>(frames) * (J - 1) * 3);
  for (int t = 0; t < frames; ++t) {
    const float* root = joint_at(joints, J, t, 0);
    for (int j = 1; j < J; ++j) {
      const float* p = joint_at(joints, J, t, j);
      double x, z;
      to_facing_frame(theta[t], double(p[0]) - root[0], double(p[2]) - root[2], x, z);
      float* o = out.data() + (static_cast<size_t>(t) * (J - 1) + (j - 1)) * 3;
      o[0] = static_cast<float>(x);
      o[1] = p[1];
      o[2] = static_cast<float>(z);
    }
  }
  return out;
}

std::vector<float> joint_velocities(const float* joints, int frames, const Skeleton& sk, const FeatureOptions& opt) {
  const std::vector<double> theta = facing_angles(joints, frames, sk, opt);
  const int J = sk.num_joints();
  std::vector<float> out(static_cast<size_t>(frames - 1) * J * 3);
  for (int t = 0; t + 1 < frames; ++t)
    for (int j = 0; j < J; ++j) {
      const float* p0 = joint_at(joints, J, t, j);
      const float* p1 = joint_at(joints, J, t + 1, j);
      double x, z;
      to_facing_frame(theta[t], double(p1[0]) - p0[0], double(p1[2]) - p0[2], x, z);
      float* o = out.data() + (static_cast<size_t>(t) * J + j) * 3;
      o[0] = static_cast<float>(x);
      o[1] = p1[1] - p0[1];
      o[2] = static_cast<float>(z);
    }
  return out;
}

std::vector<float> foot_contacts(const float* joints, int frames, const Skeleton& sk, const FeatureOptions& opt) {
  require_clip(joints, frames, "foot_contacts");
  std::vector<int> feet = sk.role("left_foot");
  for (int j : sk.role("right_foot")) feet.push_back(j);
  const int J = sk.num_joints(), C = static_cast<int>(feet.size());
  std::vector<float> out(static_cast<size_t>(frames - 1) * C);
  for (int t = 0; t + 1 < frames; ++t)
    for (int c = 0; c < C; ++c) {
      const float* p0 = joint_at(joints, J, t, feet[c]);
      const float* p1 = joint_at(joints, J, t + 1, feet[c]);
      double d2 = 0;
      for (int a = 0; a < 3; ++a) d2 += (double(p1[a]) - p0[a]) * (double(p1[a]) - p0[a]);
      out[static_cast<size_t>(t) * C + c] = d2 < opt.contact_threshold ? 1.0f : 0.0f;
    }
  return out;
}

std::vector<float> mc67_features(const float* joints, int frames, const Skeleton& sk, const FeatureOptions& opt) {
  const std::vector<double> theta = facing_angles(joints, frames, sk, opt);
  const int J = sk.num_joints(), D = 4 + 3 * (J - 1);
  const std::vector<float> local = local_positions(joints, frames, sk, opt);
  std::vector<float> out(static_cast<size_t>(frames - 1) * D);
  for (int t = 0; t + 1 < frames; ++t) {
    float* o = out.data() + static_cast<size_t>(t) * D;
    const float* r0 = joint_at(joints, J, t, 0);
    const float* r1 = joint_at(joints, J, t + 1, 0);
    // HumanML3D: arcsin of the y component of the quaternion r_rot[t+1] * r_rot[t]^-1
    // with r_rot[t] = R_y(-theta[t]): half the heading change, opposite sign.
    o[0] = static_cast<float>(wrap_angle(theta[t] - theta[t + 1]) / 2);
    double vx, vz;
    to_facing_frame(theta[t + 1], double(r1[0]) - r0[0], double(r1[2]) - r0[2], vx, vz);
    o[1] = static_cast<float>(vx);
    o[2] = static_cast<float>(vz);
    o[3] = r0[1];
    std::copy_n(local.data() + static_cast<size_t>(t) * (J - 1) * 3, (J - 1) * 3, o + 4);
  }
  return out;
}
// One frame's world joints from its features (f[3] root height, then J-1 root-relative
// joints in the facing frame) given the integrated heading and root position; shared by
// both layouts' recovery.
static void write_world_frame(const float* f, double heading, double root_x, double root_z, int J, float* o) {
  o[0] = static_cast<float>(root_x);
  o[1] = f[3];
  o[2] = static_cast<float>(root_z);
  for (int j = 1; j < J; ++j) {
    const float* l = f + 4 + (j - 1) * 3;
    double x, z;
    to_facing_frame(-heading, l[0], l[2], x, z);
    o[j * 3 + 0] = static_cast<float>(x + root_x);
    o[j * 3 + 1] = l[1];
    o[j * 3 + 2] = static_cast<float>(z + root_z);
  }
}


std::vector<float> recover_joints_from_mc67(const float* features, int feature_frames, int num_joints) {
  const int J = num_joints, D = 4 + 3 * (J - 1);
  std::vector<float> out(static_cast<size_t>(feature_frames) * J * 3);
  double heading = 0, root_x = 0, root_z = 0;  // heading relative to frame 0
  for (int t = 0; t < feature_frames; ++t) {
    const float* f = features + static_cast<size_t>(t) * D;
    if (t > 0) {
      const float* prev = features + static_cast<size_t>(t - 1) * D;
      heading -= 2.0 * prev[0];
      // The displacement t-1 -> t is stored in the facing frame of t: rotate it back.
      double dx, dz;
      to_facing_frame(-heading, prev[1], prev[2], dx, dz);
      root_x += dx;
      root_z += dz;
    }
    write_world_frame(f, heading, root_x, root_z, J, out.data() + static_cast<size_t>(t) * J * 3);
  }
  return out;
}

std::vector<float> invariant_features(const float* joints, int frames, const Skeleton& sk, bool extras,
                                      const FeatureOptions& opt) {
  const std::vector<double> theta = facing_angles(joints, frames, sk, opt);
  const std::vector<float> local = local_positions(joints, frames, sk, opt);
  const int J = sk.num_joints(), D0 = 4 + 3 * (J - 1);
  std::vector<int> feet = sk.role("left_foot");
  for (int j : sk.role("right_foot")) feet.push_back(j);
  const int C = static_cast<int>(feet.size()), D = extras ? D0 + 3 * J + C : D0;
  std::vector<float> out(static_cast<size_t>(frames) * D, 0.0f);
  for (int t = 0; t < frames; ++t) {
    float* o = out.data() + static_cast<size_t>(t) * D;
    const float* r1 = joint_at(joints, J, t, 0);
    // Frame -1 is the canonical frame: root at the origin, heading 0.
    const double theta0 = t > 0 ? theta[t - 1] : 0.0;
    const double px = t > 0 ? joint_at(joints, J, t - 1, 0)[0] : 0.0, pz = t > 0 ? joint_at(joints, J, t - 1, 0)[2] : 0.0;
    o[0] = static_cast<float>(wrap_angle(theta[t] - theta0));
    double vx, vz;
    to_facing_frame(theta[t], double(r1[0]) - px, double(r1[2]) - pz, vx, vz);
    o[1] = static_cast<float>(vx);
    o[2] = static_cast<float>(vz);
    o[3] = r1[1];
    std::copy_n(local.data() + static_cast<size_t>(t) * (J - 1) * 3, (J - 1) * 3, o + 4);
    if (!extras || t == 0) continue;
    for (int j = 0; j < J; ++j) {
      const float* p0 = joint_at(joints, J, t - 1, j);
      const float* p1 = joint_at(joints, J, t, j);
      double x, z;
      to_facing_frame(theta[t], double(p1[0]) - p0[0], double(p1[2]) - p0[2], x, z);
      o[D0 + 3 * j + 0] = static_cast<float>(x);
      o[D0 + 3 * j + 1] = p1[1] - p0[1];
      o[D0 + 3 * j + 2] = static_cast<float>(z);
    }
    for (int c = 0; c < C; ++c) {
      const float* p0 = joint_at(joints, J, t - 1, feet[c]);
      const float* p1 = joint_at(joints, J, t, feet[c]);
      double d2 = 0;
      for (int a = 0; a < 3; ++a) d2 += (double(p1[a]) - p0[a]) * (double(p1[a]) - p0[a]);
      o[D0 + 3 * J + c] = d2 < opt.contact_threshold ? 1.0f : 0.0f;
    }
  }
  if (extras && frames > 1)
    for (int c = 0; c < C; ++c) out[D0 + 3 * J + c] = out[static_cast<size_t>(D) + D0 + 3 * J + c];
  return out;
}

std::vector<float> recover_joints_from_invariant(const float* features, int frames, int num_joints, int dim) {
  const int J = num_joints;
  if (dim < 4 + 3 * (J - 1))
    throw std::invalid_argument(fmt::format("recover_joints_from_invariant: {} columns < 4 + 3(J-1) for {} joints",
                                            dim, J));
  std::vector<float> out(static_cast<size_t>(frames) * J * 3);
  double heading = 0, root_x = 0, root_z = 0;
  for (int t = 0; t < frames; ++t) {
    const float* f = features + static_cast<size_t>(t) * dim;
    heading += f[0];
    double dx, dz;
    to_facing_frame(-heading, f[1], f[2], dx, dz);  // facing frame of t -> world
    root_x += dx;
    root_z += dz;
    write_world_frame(f, heading, root_x, root_z, J, out.data() + static_cast<size_t>(t) * J * 3);
  }
  return out;
}

std::vector<std::string> feature_layouts() { return {"mc67", "mc67+vel+contact", "inv67", "inv67+vel+contact"}; }

int feature_dim(const std::string& layout, const Skeleton& sk) {
  const int J = sk.num_joints();
  const auto contacts = static_cast<int>(sk.role("left_foot").size() + sk.role("right_foot").size());
  if (layout == "mc67" || layout == "inv67") return 4 + 3 * (J - 1);
  if (layout == "mc67+vel+contact" || layout == "inv67+vel+contact") return 4 + 3 * (J - 1) + 3 * J + contacts;
  const std::string hint = did_you_mean(layout, feature_layouts());
  fail("unknown feature layout '{}'{}; known layouts: mc67, mc67+vel+contact, inv67, inv67+vel+contact", layout,
       hint.empty() ? "" : " (did you mean '" + hint + "'?)");
}

int feature_frames(const std::string& layout, int frames) {
  return layout.rfind("inv67", 0) == 0 ? frames : std::max(frames - 1, 0);
}

std::vector<float> compute_features(const std::string& layout, const float* joints, int frames, const Skeleton& sk,
                                    const FeatureOptions& opt) {
  const int D = feature_dim(layout, sk);
  if (layout == "inv67" || layout == "inv67+vel+contact")
    return invariant_features(joints, frames, sk, layout != "inv67", opt);
  if (layout == "mc67") return mc67_features(joints, frames, sk, opt);
  // mc67+vel+contact: concatenated per frame.
  const std::vector<float> base = mc67_features(joints, frames, sk, opt);
  const std::vector<float> vel = joint_velocities(joints, frames, sk, opt);
  const std::vector<float> contact = foot_contacts(joints, frames, sk, opt);
  const int J = sk.num_joints(), D0 = 4 + 3 * (J - 1), DV = 3 * J, DC = D - D0 - DV;
  std::vector<float> out(static_cast<size_t>(frames - 1) * D);
  for (int t = 0; t + 1 < frames; ++t) {
    float* o = out.data() + static_cast<size_t>(t) * D;
    std::copy_n(base.data() + static_cast<size_t>(t) * D0, D0, o);
    std::copy_n(vel.data() + static_cast<size_t>(t) * DV, DV, o + D0);
    std::copy_n(contact.data() + static_cast<size_t>(t) * DC, DC, o + D0 + DV);
  }
  return out;
}

FeatureSet compute_features(const MotionSet& m, const std::string& layout, const FeatureOptions& opt) {
  FeatureSet fs;
  fs.layout = layout;
  fs.dim = feature_dim(layout, m.skeleton);
  fs.t_max = feature_frames(layout, m.t_max);
  fs.values.assign(m.size() * static_cast<size_t>(fs.t_max) * fs.dim, 0.0f);
  for (size_t i = 0; i < m.size(); ++i) {
    const std::vector<float> f = compute_features(layout, m.clip(i), m.lengths[i], m.skeleton, opt);
    fs.lengths.push_back(feature_frames(layout, m.lengths[i]));
    std::copy(f.begin(), f.end(), fs.values.begin() + i * static_cast<size_t>(fs.t_max) * fs.dim);
  }
  return fs;
}

}  // namespace mc
