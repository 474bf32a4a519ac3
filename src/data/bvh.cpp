// BVH export (rotations solved from joint positions), a BVH reader and forward
// kinematics for the round trip. Conventions: docs/formats.md, "BVH export".
#include "data/bvh.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <sstream>

#include <fmt/format.h>

#include "core/error.h"

namespace mc {

namespace {

constexpr double kPi = 3.14159265358979323846;
constexpr double kDegenerate = 1e-9;  // metres: shorter offsets or targets carry no direction

Eigen::Matrix3d axis_rotation(int axis, double angle) {
  return Eigen::AngleAxisd(angle, Eigen::Vector3d::Unit(axis)).toRotationMatrix();
}

// The smallest rotation taking unit vector a to unit vector b (a swing about a x b).
Eigen::Matrix3d minimal_rotation(const Eigen::Vector3d& a, const Eigen::Vector3d& b) {
  const double c = a.dot(b);
  if (c < -1.0 + 1e-12) {
    // Opposite: half a turn about any axis perpendicular to a; the one nearest the
    // axis least aligned with a, so the choice is deterministic.
    Eigen::Index k;
    a.cwiseAbs().minCoeff(&k);
    Eigen::Vector3d axis = a.cross(Eigen::Vector3d::Unit(k)).normalized();
    return 2.0 * axis * axis.transpose() - Eigen::Matrix3d::Identity();
  }
  const Eigen::Vector3d v = a.cross(b);
  Eigen::Matrix3d vx;
  vx << 0, -v.z(), v.y(), v.z(), 0, -v.x(), -v.y(), v.x(), 0;
  return Eigen::Matrix3d::Identity() + vx + vx * vx / (1.0 + c);
}

// The rotation R minimising sum |R a_i - b_i|^2 over unit pairs (Kabsch / Wahba).
Eigen::Matrix3d best_fit_rotation(const std::vector<Eigen::Vector3d>& a, const std::vector<Eigen::Vector3d>& b) {
  Eigen::Matrix3d H = Eigen::Matrix3d::Zero();
  for (size_t i = 0; i < a.size(); ++i) H += a[i] * b[i].transpose();
  Eigen::JacobiSVD<Eigen::Matrix3d> svd(H, Eigen::ComputeFullU | Eigen::ComputeFullV);
  const Eigen::Matrix3d U = svd.matrixU(), V = svd.matrixV();
  Eigen::Matrix3d D = Eigen::Matrix3d::Identity();
  D(2, 2) = (V * U.transpose()).determinant() < 0 ? -1.0 : 1.0;
  return V * D * U.transpose();
}

double wrap_near(double angle, double target) {
  return angle + 2.0 * kPi * std::round((target - angle) / (2.0 * kPi));
}

// How each joint's rotation is fitted: its children with a usable rest offset,
// and whether they span a plane (then a best-fit rotation fixes all three axes;
// otherwise the swing of the first child's bone).
struct JointFit {
  std::vector<int> children;
  std::vector<Eigen::Vector3d> rest_units;
  bool planar = false;
};

std::vector<JointFit> joint_fits(const Skeleton& s) {
  const int J = s.num_joints();
  std::vector<JointFit> fits(J);
  for (int c = 0; c < J; ++c) {
    const int p = s.parents[c];
    if (p < 0) continue;
    const Eigen::Vector3d o = s.rest_directions[c] * s.bone_lengths[c];
    if (o.norm() < kDegenerate) continue;
    fits[p].children.push_back(c);
    fits[p].rest_units.push_back(o.normalized());
  }
  for (auto& f : fits) {
    if (f.children.size() < 2) continue;
    Eigen::MatrixXd A(3, f.children.size());
    for (size_t i = 0; i < f.children.size(); ++i) A.col(i) = f.rest_units[i];
    Eigen::JacobiSVD<Eigen::MatrixXd> svd(A);
    f.planar = svd.singularValues()(1) > 1e-6;
  }
  return fits;
}

// Depth-first order of the hierarchy (the order a BVH lists joints and channels).
std::vector<int> depth_first(const Skeleton& s) {
  std::vector<std::vector<int>> kids(s.num_joints());
  for (int j = 0; j < s.num_joints(); ++j)
    if (s.parents[j] >= 0) kids[s.parents[j]].push_back(j);
  std::vector<int> order, stack = {s.root()};
  while (!stack.empty()) {
    int j = stack.back();
    stack.pop_back();
    order.push_back(j);
    for (auto it = kids[j].rbegin(); it != kids[j].rend(); ++it) stack.push_back(*it);
  }
  return order;
}

std::string bvh_name(const std::string& name) {
  std::string out = name;
  for (char& c : out)
    if (std::isspace(static_cast<unsigned char>(c)) || c == '{' || c == '}') c = '_';
  return out.empty() ? "joint" : out;
}

// Solved pose of one frame: global rotation of every joint and the positions its
// forward kinematics gives.
struct FramePose {
  std::vector<Eigen::Matrix3d> global, local;
  std::vector<Eigen::Vector3d> position, translation;  // translation: local offset actually used
};

// Rotations from positions. `exact_offsets`: every joint's translation is its input
// offset from the parent (the "all" layout); otherwise the skeleton's rest offsets,
// and each rotation aims the bones from the joint's forward-kinematics position at
// the children's input positions, so length errors do not pile up down a chain.
FramePose solve_frame(const Skeleton& s, const std::vector<JointFit>& fits, const std::vector<Eigen::Vector3d>& P,
                      bool exact_offsets) {
  const int J = s.num_joints();
  FramePose f;
  f.global.assign(J, Eigen::Matrix3d::Identity());
  f.local.assign(J, Eigen::Matrix3d::Identity());
  f.position.assign(J, Eigen::Vector3d::Zero());
  f.translation.assign(J, Eigen::Vector3d::Zero());
  for (int j = 0; j < J; ++j) {
    const int p = s.parents[j];
    const Eigen::Matrix3d Gp = p < 0 ? Eigen::Matrix3d::Identity() : f.global[p];
    if (p < 0) {
      f.translation[j] = P[j];
      f.position[j] = P[j];
    } else {
      f.translation[j] = exact_offsets ? Eigen::Vector3d(Gp.transpose() * (P[j] - P[p]))
                                       : Eigen::Vector3d(s.rest_directions[j] * s.bone_lengths[j]);
      f.position[j] = exact_offsets ? P[j] : Eigen::Vector3d(f.position[p] + Gp * f.translation[j]);
    }
    const JointFit& fit = fits[j];
    std::vector<Eigen::Vector3d> rest, target;
    for (size_t i = 0; i < fit.children.size(); ++i) {
      Eigen::Vector3d d = Gp.transpose() * (P[fit.children[i]] - f.position[j]);
      if (d.norm() < kDegenerate) continue;
      rest.push_back(fit.rest_units[i]);
      target.push_back(d.normalized());
    }
    Eigen::Matrix3d L = Eigen::Matrix3d::Identity();
    if (fit.planar && rest.size() >= 2)
      L = best_fit_rotation(rest, target);
    else if (!rest.empty())
      L = minimal_rotation(rest[0], target[0]);
    f.local[j] = L;
    f.global[j] = Gp * L;
  }
  return f;
}

std::string fmt_num(double v) {
  std::string s = fmt::format("{:.6f}", v);
  return s == "-0.000000" ? "0.000000" : s;
}

}  // namespace

Eigen::Matrix3d rotation_zxy(const Eigen::Vector3d& zxy) {
  return axis_rotation(2, zxy[0]) * axis_rotation(0, zxy[1]) * axis_rotation(1, zxy[2]);
}

// R = Rz(a) Rx(b) Ry(c) has R21 = sin b, (R01, R11) = cos b (-sin a, cos a) and
// (R20, R22) = cos b (-sin c, cos c); (a + pi, pi - b, c + pi) is the same rotation.
Eigen::Vector3d euler_zxy_nearest(const Eigen::Matrix3d& R, const Eigen::Vector3d& prev) {
  const double sb = std::clamp(R(2, 1), -1.0, 1.0);
  const double cb = std::sqrt(std::max(0.0, R(0, 1) * R(0, 1) + R(1, 1) * R(1, 1)));
  if (cb < 1e-7) {
    // Gimbal lock: only a + c (b = +90) or c - a (b = -90) is defined; keep a at its
    // previous value so the curve does not jump.
    const double a = prev[0], phi = std::atan2(R(0, 2), R(0, 0));
    const double b = sb > 0 ? kPi / 2 : -kPi / 2;
    const double c = sb > 0 ? phi - a : phi + a;
    return {a, wrap_near(b, prev[1]), wrap_near(c, prev[2])};
  }
  const double b = std::asin(sb), a = std::atan2(-R(0, 1), R(1, 1)), c = std::atan2(-R(2, 0), R(2, 2));
  Eigen::Vector3d best;
  double best_d = std::numeric_limits<double>::infinity();
  for (const Eigen::Vector3d& cand : {Eigen::Vector3d(a, b, c), Eigen::Vector3d(a + kPi, kPi - b, c + kPi)}) {
    Eigen::Vector3d w(wrap_near(cand[0], prev[0]), wrap_near(cand[1], prev[1]), wrap_near(cand[2], prev[2]));
    const double d = (w - prev).squaredNorm();
    if (d < best_d) best_d = d, best = w;
  }
  return best;
}

BvhExport clip_to_bvh(const Skeleton& s, const float* joints, int frames, double fps, const BvhOptions& opt) {
  if (opt.translations != "auto" && opt.translations != "root" && opt.translations != "all")
    fail("BVH translations '{}': expected auto, root or all", opt.translations);
  if (!(opt.scale > 0) || !std::isfinite(opt.scale)) fail("BVH scale {} must be a positive number", opt.scale);
  if (!(opt.tolerance > 0)) fail("BVH tolerance {} must be positive", opt.tolerance);
  if (frames < 1) fail("cannot export a clip of {} frames to BVH", frames);
  if (!(fps > 0)) fail("cannot export to BVH at {} frames per second", fps);
  const int J = s.num_joints();
  std::vector<std::vector<Eigen::Vector3d>> P(frames, std::vector<Eigen::Vector3d>(J));
  for (int t = 0; t < frames; ++t)
    for (int j = 0; j < J; ++j) {
      const float* q = joints + (static_cast<size_t>(t) * J + j) * 3;
      if (!std::isfinite(q[0]) || !std::isfinite(q[1]) || !std::isfinite(q[2]))
        fail("frame {} joint '{}' is not finite; cannot export it to BVH", t, s.joint_names[j]);
      P[t][j] = Eigen::Vector3d(q[0], q[1], q[2]);
    }

  const auto fits = joint_fits(s);
  BvhExport out;
  std::vector<FramePose> poses(frames);
  for (int t = 0; t < frames; ++t) {
    poses[t] = solve_frame(s, fits, P[t], false);
    for (int j = 0; j < J; ++j) out.rigid_error = std::max(out.rigid_error, (poses[t].position[j] - P[t][j]).norm());
  }
  out.all_translations = opt.translations == "all" || (opt.translations == "auto" && out.rigid_error > opt.tolerance);
  if (out.all_translations)
    for (int t = 0; t < frames; ++t) poses[t] = solve_frame(s, fits, P[t], true);

  // Hierarchy, depth first.
  const std::vector<int> order = depth_first(s);
  std::vector<int> kids(J, 0);
  for (int j = 0; j < J; ++j)
    if (s.parents[j] >= 0) ++kids[s.parents[j]];
  const char* rot = "Zrotation Xrotation Yrotation";
  std::string h = "HIERARCHY\n";
  std::vector<int> open;  // joints whose block is open, innermost last
  auto close_to = [&](int parent) {
    while (!open.empty() && open.back() != parent) {
      open.pop_back();
      h += std::string(2 * open.size(), ' ') + "}\n";
    }
  };
  for (int j : order) {
    const int p = s.parents[j];
    close_to(p);
    const std::string pad(2 * open.size(), ' ');
    h += pad + (p < 0 ? "ROOT " : "JOINT ") + bvh_name(s.joint_names[j]) + "\n" + pad + "{\n";
    const Eigen::Vector3d off = p < 0 ? Eigen::Vector3d::Zero() : Eigen::Vector3d(s.rest_directions[j] * s.bone_lengths[j]);
    h += pad + "  OFFSET " + fmt_num(off.x() * opt.scale) + " " + fmt_num(off.y() * opt.scale) + " " +
         fmt_num(off.z() * opt.scale) + "\n";
    const bool pos = p < 0 || out.all_translations;
    h += pad + (pos ? std::string("  CHANNELS 6 Xposition Yposition Zposition ") + rot : std::string("  CHANNELS 3 ") + rot) +
         "\n";
    if (kids[j] == 0) {
      // Leaf: an End Site half the bone's length further along its rest direction
      // gives importers a bone to draw (its roll is not observable).
      Eigen::Vector3d e = s.rest_directions[j] * (0.5 * s.bone_lengths[j]);
      if (e.norm() < kDegenerate) e = Eigen::Vector3d(0, 0.05, 0);
      h += pad + "  End Site\n" + pad + "  {\n" + pad + "    OFFSET " + fmt_num(e.x() * opt.scale) + " " +
           fmt_num(e.y() * opt.scale) + " " + fmt_num(e.z() * opt.scale) + "\n" + pad + "  }\n";
    }
    open.push_back(j);
  }
  close_to(-1);

  std::string m = fmt::format("MOTION\nFrames: {}\nFrame Time: {:.8f}\n", frames, 1.0 / fps);
  std::vector<Eigen::Vector3d> prev(J, Eigen::Vector3d::Zero());
  for (int t = 0; t < frames; ++t) {
    std::string line;
    for (int j : order) {
      if (s.parents[j] < 0 || out.all_translations) {
        const Eigen::Vector3d& tr = poses[t].translation[j];
        line += fmt_num(tr.x() * opt.scale) + " " + fmt_num(tr.y() * opt.scale) + " " + fmt_num(tr.z() * opt.scale) + " ";
      }
      prev[j] = euler_zxy_nearest(poses[t].local[j], prev[j]);
      line += fmt_num(prev[j][0] * 180.0 / kPi) + " " + fmt_num(prev[j][1] * 180.0 / kPi) + " " +
              fmt_num(prev[j][2] * 180.0 / kPi) + " ";
    }
    line.back() = '\n';
    m += line;
  }
  out.text = h + m;

  // Read back what was written (rounded to 6 decimals) and measure it.
  BvhMotion back = parse_bvh(out.text, "BVH export");
  std::vector<double> pos = bvh_positions(back, opt.scale);
  for (int t = 0; t < frames; ++t)
    for (size_t k = 0; k < order.size(); ++k) {
      const double* q = pos.data() + (static_cast<size_t>(t) * J + k) * 3;
      out.written_error = std::max(out.written_error, (Eigen::Vector3d(q[0], q[1], q[2]) - P[t][order[k]]).norm());
    }
  return out;
}

int BvhMotion::num_channels() const {
  int n = 0;
  for (auto& c : channels) n += static_cast<int>(c.size());
  return n;
}

// ---------------------------------------------------------------- reader

namespace {

struct Tokens {
  std::vector<std::pair<std::string, int>> items;  // token, line
  size_t pos = 0;
  std::string source;

  [[noreturn]] void bad(const std::string& what) const {
    const int line = pos < items.size() ? items[pos].second : (items.empty() ? 1 : items.back().second);
    fail("{}: line {}: {}; the file is not a BVH this reader understands (one ROOT hierarchy, then MOTION)",
         source, line, what);
  }
  bool done() const { return pos >= items.size(); }
  const std::string& peek() const {
    if (done()) bad("unexpected end of file");
    return items[pos].first;
  }
  std::string next() {
    const std::string& t = peek();
    ++pos;
    return t;
  }
  void expect(const std::string& want) {
    if (peek() != want) bad(fmt::format("expected '{}', found '{}'", want, peek()));
    ++pos;
  }
  double number() {
    const std::string& t = peek();
    char* end = nullptr;
    double v = std::strtod(t.c_str(), &end);
    if (end == t.c_str() || *end != '\0' || !std::isfinite(v)) bad(fmt::format("expected a number, found '{}'", t));
    ++pos;
    return v;
  }
};

void parse_joint(Tokens& tk, BvhMotion& m, int parent, int depth) {
  if (depth > 512) tk.bad("hierarchy nested deeper than 512 joints");
  const int j = static_cast<int>(m.names.size());
  m.names.push_back(tk.next());
  m.parents.push_back(parent);
  m.offsets.emplace_back(0, 0, 0);
  m.channels.emplace_back();
  m.end_sites.emplace_back(Eigen::Vector3d::Constant(std::numeric_limits<double>::quiet_NaN()));
  tk.expect("{");
  tk.expect("OFFSET");
  for (int a = 0; a < 3; ++a) m.offsets[j][a] = tk.number();
  tk.expect("CHANNELS");
  const double n = tk.number();
  if (n < 0 || n > 6 || n != std::floor(n)) tk.bad(fmt::format("CHANNELS count {} (expected 0 to 6)", n));
  static const std::vector<std::string> known = {"Xposition", "Yposition", "Zposition",
                                                 "Xrotation", "Yrotation", "Zrotation"};
  for (int c = 0; c < static_cast<int>(n); ++c) {
    std::string ch = tk.next();
    if (std::find(known.begin(), known.end(), ch) == known.end()) tk.bad(fmt::format("unknown channel '{}'", ch));
    m.channels[j].push_back(ch);
  }
  while (tk.peek() != "}") {
    const std::string kw = tk.next();
    if (kw == "JOINT") {
      parse_joint(tk, m, j, depth + 1);
    } else if (kw == "End") {
      tk.expect("Site");
      tk.expect("{");
      tk.expect("OFFSET");
      Eigen::Vector3d e;
      for (int a = 0; a < 3; ++a) e[a] = tk.number();
      m.end_sites[j] = e;
      tk.expect("}");
    } else {
      --tk.pos;
      tk.bad(fmt::format("expected JOINT, End Site or '}}', found '{}'", kw));
    }
  }
  tk.expect("}");
}

}  // namespace

BvhMotion parse_bvh(const std::string& text, const std::string& source) {
  Tokens tk;
  tk.source = source;
  {
    std::istringstream in(text);
    std::string line;
    int n = 0;
    while (std::getline(in, line)) {
      ++n;
      // "Frames:" and "Frame Time:" may be glued to their values; split on ':' too.
      std::string cur;
      auto push = [&] {
        if (!cur.empty()) tk.items.emplace_back(cur, n);
        cur.clear();
      };
      for (char c : line) {
        if (std::isspace(static_cast<unsigned char>(c))) {
          push();
        } else if (c == ':') {
          cur += c;
          push();
        } else {
          cur += c;
        }
      }
      push();
    }
  }
  BvhMotion m;
  tk.expect("HIERARCHY");
  tk.expect("ROOT");
  parse_joint(tk, m, -1, 0);
  if (tk.peek() == "ROOT") tk.bad("a second ROOT; only files with one hierarchy are read");
  tk.expect("MOTION");
  tk.expect("Frames:");
  const double frames = tk.number();
  if (frames < 0 || frames != std::floor(frames) || frames > 1e7) tk.bad(fmt::format("frame count {}", frames));
  tk.expect("Frame");
  tk.expect("Time:");
  m.frame_time = tk.number();
  if (!(m.frame_time > 0)) tk.bad(fmt::format("Frame Time {} must be positive", m.frame_time));
  m.frames = static_cast<int>(frames);
  const size_t want = static_cast<size_t>(m.frames) * m.num_channels();
  if (tk.items.size() - tk.pos != want)
    tk.bad(fmt::format("the motion block holds {} numbers, expected {} ({} frames x {} channels)",
                       tk.items.size() - tk.pos, want, m.frames, m.num_channels()));
  m.values.reserve(want);
  while (!tk.done()) m.values.push_back(tk.number());
  return m;
}

std::vector<double> bvh_positions(const BvhMotion& m, double scale) {
  const int J = static_cast<int>(m.names.size()), C = m.num_channels();
  std::vector<double> out(static_cast<size_t>(m.frames) * J * 3);
  std::vector<Eigen::Matrix3d> G(J);
  std::vector<Eigen::Vector3d> pos(J);
  for (int t = 0; t < m.frames; ++t) {
    const double* v = m.values.data() + static_cast<size_t>(t) * C;
    for (int j = 0; j < J; ++j) {
      Eigen::Vector3d tr = m.offsets[j];
      bool has_pos = false;
      Eigen::Vector3d channel_pos = Eigen::Vector3d::Zero();
      Eigen::Matrix3d R = Eigen::Matrix3d::Identity();
      for (const auto& ch : m.channels[j]) {
        const double x = *v++;
        const int axis = ch[0] - 'X';
        if (ch.compare(1, std::string::npos, "position") == 0) {
          has_pos = true;
          channel_pos[axis] = x;
        } else {
          R = R * axis_rotation(axis, x * kPi / 180.0);
        }
      }
      if (has_pos) tr = channel_pos;
      const int p = m.parents[j];
      if (p < 0) {
        pos[j] = tr;
        G[j] = R;
      } else {
        pos[j] = pos[p] + G[p] * tr;
        G[j] = G[p] * R;
      }
      for (int a = 0; a < 3; ++a) out[(static_cast<size_t>(t) * J + j) * 3 + a] = pos[j][a] / scale;
    }
  }
  return out;
}

}  // namespace mc
