// compile(): ConstraintSpec -> LinearObservation rows in world units, with every
// range/shape/source check naming the item; the hard-row rank check; the affine
// map into model units.
#include "control/linear_observation.h"

#include <algorithm>
#include <cmath>
#include <map>
#include <numeric>
#include <set>

#include "control/camera_rows.h"
#include "control/directions.h"
#include "control/projection_solver.h"
#include "core/error.h"
#include "data/skeleton.h"

namespace mc {

namespace {

constexpr double kPi = 3.14159265358979323846;
const char* const kAxisNames = "xyz";

std::string shape_text(const std::vector<int>& shape) {
  std::string s = "[";
  for (size_t i = 0; i < shape.size(); ++i) s += (i ? ", " : "") + std::to_string(shape[i]);
  return s + "]";
}

std::string list_text(const std::vector<int>& v, size_t max_items = 8) {
  std::string s;
  for (size_t i = 0; i < v.size() && i < max_items; ++i) s += (i ? ", " : "") + std::to_string(v[i]);
  if (v.size() > max_items) s += fmt::format(", ... ({} in all)", v.size());
  return s;
}

// Rows under construction: equalities (A, y) and inequalities (G, h).
struct RowSink {
  std::vector<Eigen::Triplet<double>> entries;
  std::vector<double> y, variance;
  std::vector<int> item;
  std::vector<Eigen::Triplet<double>> g_entries;
  std::vector<double> h, g_variance;
  std::vector<int> g_item;
  std::vector<DirectionProbe> directions;
  int row(int item_index, double target, double var) {
    y.push_back(target);
    variance.push_back(var);
    item.push_back(item_index);
    return static_cast<int>(y.size()) - 1;
  }
  void add(int r, int col, double value) { entries.emplace_back(r, col, value); }
  // g x <= bound
  int g_row(int item_index, double bound, double var) {
    h.push_back(bound);
    g_variance.push_back(var);
    g_item.push_back(item_index);
    return static_cast<int>(h.size()) - 1;
  }
  void g_add(int r, int col, double value) { g_entries.emplace_back(r, col, value); }
};

// Compiles one item; every failure names the spec source, the item and the key.
class ItemCompiler {
 public:
  ItemCompiler(const ConstraintSpec& spec, int index, int frames, const Skeleton& skeleton, const float* source,
               RowSink& sink)
      : spec_(spec), index_(index), it_(spec.items[index]), T_(frames), J_(skeleton.num_joints()), sk_(skeleton),
        src_(source), sink_(sink) {}

  void compile() {
    const std::string& type = it_.type;
    if (it_.score_only && !is_direction_type(type))
      fail_key("score_only", fmt::format("only tangent and facing items can be score_only (their angle error is "
                                         "scored without imposing them); {} items always constrain", type));
    if (type == "floor") return floor();
    if (type == "half_space") return half_space();
    if (type == "box") return box();
    if (type == "speed_limit") return speed_limit();
    if (type == "tangent") return tangent();
    if (type == "facing") return facing();
    if (type == "keyframe") return selection(/*frames_required=*/true, /*joints_default_all=*/false);
    if (type == "trajectory") return selection(false, false);
    if (type == "planar_root") return planar_root();
    if (type == "camera_2d") return camera_2d();
    if (type == "relative") return relative();
    if (type == "loop") return loop();
    if (type == "upper_body_edit") return upper_body_edit();
    fail_key("type", fmt::format("unknown constraint type '{}'", type));
  }

 private:
  std::string where() const {
    return (it_.line > 0 ? fmt::format("{}:{}", spec_.source, it_.line) : spec_.source) + ": " +
           spec_.item_label(index_);
  }
  [[noreturn]] void fail_key(const std::string& key, const std::string& problem) const {
    fail("{}: key '{}': {}", where(), key, problem);
  }

  std::vector<int> joints(bool default_all) const {
    if (it_.joints.empty()) {
      if (!default_all) fail_key("joints", fmt::format("{} items need 'joints' (indices or names)", it_.type));
      std::vector<int> all(J_);
      std::iota(all.begin(), all.end(), 0);
      return all;
    }
    std::vector<int> out;
    std::set<int> seen;
    for (const JointRef& r : it_.joints) {
      int j = r.index;
      if (!r.name.empty()) {
        try {
          j = sk_.joint_index(r.name);
        } catch (const UserError& e) {
          fail_key("joints", e.what());
        }
      } else if (j < 0 || j >= J_) {
        fail_key("joints", fmt::format("joint {} is out of range 0..{} (skeleton '{}')", j, J_ - 1, sk_.name));
      }
      if (!seen.insert(j).second)
        fail_key("joints", fmt::format("joint {} ('{}') is listed twice", j, sk_.joint_names[j]));
      out.push_back(j);
    }
    return out;
  }

  int resolve(const JointRef& r, const char* key) const {
    int j = r.index;
    if (!r.name.empty()) {
      try {
        j = sk_.joint_index(r.name);
      } catch (const UserError& e) {
        fail_key(key, e.what());
      }
    } else if (j < 0 || j >= J_) {
      fail_key(key, fmt::format("joint {} is out of range 0..{} (skeleton '{}')", j, J_ - 1, sk_.name));
    }
    return j;
  }

  // The joints of a skeleton role (floor: toes; facing: face), named in messages.
  std::vector<int> role_joints(const std::string& role, const char* why) const {
    try {
      return sk_.role(role);
    } catch (const UserError& e) {
      fail_key("joints", fmt::format("{} items default to the skeleton role '{}' ({}), which skeleton '{}' lacks: "
                                     "name the joints",
                                     it_.type, role, why, sk_.name));
    }
  }

  std::vector<int> frames(bool required) const {
    const FrameSelection& f = it_.frames;
    std::vector<int> out;
    switch (f.kind) {
      case FrameSelection::Kind::unset:
        if (required) fail_key("frames", fmt::format("{} items need 'frames'", it_.type));
        [[fallthrough]];
      case FrameSelection::Kind::all:
        out.resize(T_);
        std::iota(out.begin(), out.end(), 0);
        return out;
      case FrameSelection::Kind::list: {
        std::set<int> seen;
        for (int t : f.list) {
          if (t < 0 || t >= T_)
            fail_key("frames", fmt::format("frame {} is out of range 0..{} (clip of {} frames)", t, T_ - 1, T_));
          if (!seen.insert(t).second) fail_key("frames", fmt::format("frame {} is listed twice", t));
          out.push_back(t);
        }
        return out;
      }
      case FrameSelection::Kind::range: {
        int stop = f.stop < 0 ? T_ : f.stop;
        if (f.start < 0 || f.start >= T_)
          fail_key("frames", fmt::format("range start {} is out of range 0..{} (clip of {} frames)", f.start, T_ - 1, T_));
        if (stop > T_ || stop <= f.start)
          fail_key("frames", fmt::format("range stop {} must be in {}..{} (clip of {} frames)", stop, f.start + 1, T_, T_));
        for (int t = f.start; t < stop; t += f.step) out.push_back(t);
        return out;
      }
    }
    return out;
  }

  std::vector<int> axes() const {
    if (it_.axes.empty()) return {0, 1, 2};
    for (int a : it_.axes)
      if (a < 0 || a > 2) fail_key("axes", fmt::format("axis {} is out of range (use x, y, z or 0, 1, 2)", a));
    return it_.axes;
  }

  // from_source items and upper_body_edit read the source motion; values must be finite.
  double source(int t, int j, int c, const char* key) const {
    if (!src_)
      fail_key(key, fmt::format("the item takes its targets from the source motion, but none was given "
                                "(pass a source motion, or give 'values')"));
    double v = src_[(static_cast<size_t>(t) * J_ + j) * 3 + c];
    if (!std::isfinite(v))
      fail_key(key, fmt::format("the source motion is not finite at frame {}, joint {} ('{}'), axis {}", t, j,
                                sk_.joint_names[j], kAxisNames[c]));
    return v;
  }

  // Either explicit values of one of the accepted shapes, or from_source.
  // Returns the index of the accepted shape matched (or -1 for from_source).
  int targets(const std::vector<std::vector<int>>& accepted, const char* what) const {
    if (it_.from_source) return -1;
    std::string list;
    for (auto& s : accepted) list += (list.empty() ? "" : " or ") + shape_text(s);
    if (!it_.values.given())
      fail_key("values", fmt::format("give 'values' of shape {} ({}) or 'from_source: true'", list, what));
    for (size_t k = 0; k < accepted.size(); ++k)
      if (it_.values.shape == accepted[k]) return static_cast<int>(k);
    fail_key("values", fmt::format("target shape mismatch: got {}, expected {} ({})", shape_text(it_.values.shape),
                                   list, what));
  }

  double value(size_t flat) const { return it_.values.data[flat]; }

  // keyframe and trajectory: unit rows selecting (frame, joint, axis) entries.
  void selection(bool frames_required, bool joints_default_all) {
    auto js = joints(joints_default_all);
    auto fs = frames(frames_required);
    auto as = axes();
    const int F = static_cast<int>(fs.size()), Jk = static_cast<int>(js.size()), Ak = static_cast<int>(as.size());
    std::vector<std::vector<int>> shapes = {{F, Jk, Ak}};
    if (it_.type == "trajectory" && Jk == 1) shapes.push_back({F, Ak});
    int shape = targets(shapes, "frames x joints x axes");
    for (int f = 0; f < F; ++f)
      for (int k = 0; k < Jk; ++k)
        for (int a = 0; a < Ak; ++a) {
          double y = shape < 0 ? source(fs[f], js[k], as[a], "from_source")
                               : value((static_cast<size_t>(f) * Jk + k) * Ak + a);
          int r = sink_.row(index_, y, it_.variance);
          sink_.add(r, LinearObservation::index(fs[f], js[k], as[a], J_), 1.0);
        }
  }

  void planar_root() {
    auto fs = frames(false);
    const int F = static_cast<int>(fs.size()), root = sk_.root();
    int shape = targets({{F, 2}}, "frames x (x, z) of the root");
    for (int f = 0; f < F; ++f)
      for (int k = 0; k < 2; ++k) {
        int axis = k == 0 ? 0 : 2;
        double y = shape < 0 ? source(fs[f], root, axis, "from_source") : value(static_cast<size_t>(f) * 2 + k);
        int r = sink_.row(index_, y, it_.variance);
        sink_.add(r, LinearObservation::index(fs[f], root, axis, J_), 1.0);
      }
  }

  // eq. (19)-(20): two rows per (frame, joint), each coupling the joint's three axes.
  void camera_2d() {
    if (!it_.has_camera) fail_key("camera", "camera_2d items need 'camera: {scale, pitch_deg, yaw_deg, roll_deg}'");
    auto js = joints(true);
    auto fs = frames(false);
    const int F = static_cast<int>(fs.size()), Jk = static_cast<int>(js.size());
    const CameraParams& c = it_.camera;
    Eigen::Matrix<double, 2, 3> C =
        camera_rows(c.scale, c.pitch_deg * kPi / 180.0, c.yaw_deg * kPi / 180.0, c.roll_deg * kPi / 180.0);
    int shape = targets({{F, Jk, 2}}, "frames x joints x (u, v)");
    for (int f = 0; f < F; ++f)
      for (int k = 0; k < Jk; ++k) {
        Eigen::Vector2d uv;
        if (shape < 0) {
          Eigen::Vector3d x(source(fs[f], js[k], 0, "from_source"), source(fs[f], js[k], 1, "from_source"),
                            source(fs[f], js[k], 2, "from_source"));
          uv = C * x;
        } else {
          uv << value((static_cast<size_t>(f) * Jk + k) * 2), value((static_cast<size_t>(f) * Jk + k) * 2 + 1);
        }
        for (int u = 0; u < 2; ++u) {
          int r = sink_.row(index_, uv[u], it_.variance);
          for (int a = 0; a < 3; ++a)
            if (C(u, a) != 0.0) sink_.add(r, LinearObservation::index(fs[f], js[k], a, J_), C(u, a));
        }
      }
  }

  // x_a - x_b = d per frame and axis.
  void relative() {
    auto js = joints(false);
    if (js.size() != 2)
      fail_key("joints", fmt::format("relative items take exactly two joints [a, b] (x_a - x_b = d), got {}",
                                     js.size()));
    auto fs = frames(false);
    auto as = axes();
    const int F = static_cast<int>(fs.size()), Ak = static_cast<int>(as.size());
    int shape = targets({{F, Ak}, {Ak}}, "offset x_a - x_b per frame and axis, or one constant offset per axis");
    for (int f = 0; f < F; ++f)
      for (int k = 0; k < Ak; ++k) {
        double d;
        if (shape < 0)
          d = source(fs[f], js[0], as[k], "from_source") - source(fs[f], js[1], as[k], "from_source");
        else
          d = shape == 0 ? value(static_cast<size_t>(f) * Ak + k) : value(k);
        int r = sink_.row(index_, d, it_.variance);
        sink_.add(r, LinearObservation::index(fs[f], js[0], as[k], J_), 1.0);
        sink_.add(r, LinearObservation::index(fs[f], js[1], as[k], J_), -1.0);
      }
  }

  // x_j(first) - x_j(last) = 0; with up_to_root_translation the x and z rows
  // compare positions relative to the root, so the character may end elsewhere.
  void loop() {
    auto js = joints(true);
    auto as = axes();
    int first = 0, last = T_ - 1;
    if (it_.frames.kind == FrameSelection::Kind::list) {
      if (it_.frames.list.size() != 2)
        fail_key("frames", fmt::format("a loop takes two frames [first, last], got {}", it_.frames.list.size()));
      first = it_.frames.list[0];
      last = it_.frames.list[1];
      for (int t : {first, last})
        if (t < 0 || t >= T_)
          fail_key("frames", fmt::format("frame {} is out of range 0..{} (clip of {} frames)", t, T_ - 1, T_));
      if (first == last) fail_key("frames", fmt::format("the loop's first and last frame are both {}", first));
    } else if (it_.frames.kind != FrameSelection::Kind::unset) {
      fail_key("frames", "a loop takes a list of two frames [first, last] (default [0, T-1])");
    }
    if (T_ < 2) fail_key("type", fmt::format("a loop needs at least 2 frames, the clip has {}", T_));
    const int root = sk_.root();
    for (int j : js)
      for (int a : as) {
        const bool relative_to_root = it_.up_to_root_translation && a != 1;
        if (relative_to_root && j == root) continue;  // the row would be identically zero
        int r = sink_.row(index_, 0.0, it_.variance);
        sink_.add(r, LinearObservation::index(first, j, a, J_), 1.0);
        sink_.add(r, LinearObservation::index(last, j, a, J_), -1.0);
        if (relative_to_root) {
          sink_.add(r, LinearObservation::index(first, root, a, J_), -1.0);
          sink_.add(r, LinearObservation::index(last, root, a, J_), 1.0);
        }
      }
  }

  void upper_body_edit() {
    const std::string role = it_.role.empty() ? "lower_body" : it_.role;
    std::vector<int> js;
    try {
      js = sk_.role(role);
    } catch (const UserError& e) {
      fail_key("role", e.what());
    }
    auto fs = frames(false);
    auto as = axes();
    for (int t : fs)
      for (int j : js)
        for (int a : as) {
          int r = sink_.row(index_, source(t, j, a, "role"), it_.variance);
          sink_.add(r, LinearObservation::index(t, j, a, J_), 1.0);
        }
  }

  // ------------------------------------------------------------ inequalities

  // Per-axis bounds: one number for every axis, or one per axis.
  std::vector<double> per_axis(const std::vector<double>& v, int A, const char* key) const {
    if (v.size() == 1) return std::vector<double>(A, v[0]);
    if (static_cast<int>(v.size()) != A)
      fail_key(key, fmt::format("expected one number or one per axis ({} axes), got {}", A, v.size()));
    return v;
  }

  // y >= height for the item's joints (default the toes): -y <= -height.
  void floor() {
    auto js = it_.joints.empty() ? role_joints("toes", "the joints that touch the floor") : joints(false);
    for (int t : frames(false))
      for (int j : js) {
        int r = sink_.g_row(index_, -it_.height, it_.variance);
        sink_.g_add(r, LinearObservation::index(t, j, 1, J_), -1.0);
      }
  }

  // n . (x_j - x_ref) >= offset with n the unit normal: -n . x_j (+ n . x_ref) <= -offset.
  void half_space() {
    auto js = joints(false);
    Eigen::Vector3d n(it_.normal[0], it_.normal[1], it_.normal[2]);
    n.normalize();
    const int ref = it_.relative_to.set() ? resolve(it_.relative_to, "relative_to") : -1;
    for (int j : js)
      if (j == ref)
        fail_key("relative_to", fmt::format("joint {} ('{}') is both constrained and the reference; the row would be "
                                            "0 >= offset", j, sk_.joint_names[j]));
    for (int t : frames(false))
      for (int j : js) {
        int r = sink_.g_row(index_, -it_.offset, it_.variance);
        for (int c = 0; c < 3; ++c) {
          if (n[c] == 0.0) continue;
          sink_.g_add(r, LinearObservation::index(t, j, c, J_), -n[c]);
          if (ref >= 0) sink_.g_add(r, LinearObservation::index(t, ref, c, J_), n[c]);
        }
      }
  }

  // min <= x <= max per axis: -x <= -min, x <= max.
  void box() {
    auto js = joints(false);
    auto as = axes();
    const int A = static_cast<int>(as.size());
    std::vector<double> lo = it_.lower.empty() ? std::vector<double>{} : per_axis(it_.lower, A, "min");
    std::vector<double> hi = it_.upper.empty() ? std::vector<double>{} : per_axis(it_.upper, A, "max");
    for (int a = 0; a < A && !lo.empty() && !hi.empty(); ++a)
      if (lo[a] > hi[a])
        fail_key("min", fmt::format("min {} is above max {} on axis {}: the box is empty", lo[a], hi[a],
                                    kAxisNames[as[a]]));
    for (int t : frames(false))
      for (int j : js)
        for (int a = 0; a < A; ++a) {
          const int col = LinearObservation::index(t, j, as[a], J_);
          if (!lo.empty()) sink_.g_add(sink_.g_row(index_, -lo[a], it_.variance), col, -1.0);
          if (!hi.empty()) sink_.g_add(sink_.g_row(index_, hi[a], it_.variance), col, 1.0);
        }
  }

  // |x[t+1] - x[t]| <= max per axis, for every listed transition t -> t+1.
  void speed_limit() {
    if (T_ < 2) fail_key("type", fmt::format("a speed limit needs at least 2 frames, the clip has {}", T_));
    auto js = joints(false);
    auto as = axes();
    const int A = static_cast<int>(as.size());
    auto vmax = per_axis(it_.upper, A, "max");
    std::vector<int> fs;
    if (it_.frames.kind == FrameSelection::Kind::unset) {
      for (int t = 0; t + 1 < T_; ++t) fs.push_back(t);
    } else {
      fs = frames(false);
      if (it_.frames.kind == FrameSelection::Kind::all) fs.pop_back();  // transitions t -> t+1
      for (int t : fs)
        if (t + 1 >= T_)
          fail_key("frames", fmt::format("frame {} starts no transition: speed frames are t of x[t+1] - x[t], "
                                         "at most {}", t, T_ - 2));
    }
    for (int t : fs)
      for (int j : js)
        for (int a = 0; a < A; ++a)
          for (double sign : {1.0, -1.0}) {
            int r = sink_.g_row(index_, vmax[a], it_.variance);
            sink_.g_add(r, LinearObservation::index(t + 1, j, as[a], J_), sign);
            sink_.g_add(r, LinearObservation::index(t, j, as[a], J_), -sign);
          }
  }

  // ------------------------------------------------------------ directions

  // Unit directions of a tangent/facing item per frame: from `values` ([F, A] or [A])
  // or from the source motion through `measure(frame)`.
  template <class Measure>
  std::vector<Eigen::VectorXd> directions(const std::vector<int>& fs, int A, const char* what, Measure measure) const {
    const int F = static_cast<int>(fs.size());
    int shape = targets({{F, A}, {A}}, what);
    std::vector<Eigen::VectorXd> out;
    for (int f = 0; f < F; ++f) {
      Eigen::VectorXd u(A);
      if (shape < 0) {
        u = measure(fs[f]);
        if (u.norm() < 1e-6)
          fail_key("from_source", fmt::format("the source motion has no {} at frame {} (length {:.2e}); give "
                                              "'values' or pick frames where it is defined", what, fs[f], u.norm()));
      } else {
        for (int a = 0; a < A; ++a) u[a] = value(shape == 0 ? static_cast<size_t>(f) * A + a : static_cast<size_t>(a));
        if (u.norm() < 1e-9)
          fail_key("values", fmt::format("the direction at frame {} is zero; give a non-zero vector", fs[f]));
      }
      out.push_back(u.normalized());
    }
    return out;
  }

  // The joint's velocity (tangent_stencil) is parallel to u: e . v = 0 for every e
  // orthogonal to u (equality rows), and u . v >= min_speed (one inequality row),
  // which fixes the sense and keeps the direction defined.
  void tangent() {
    if (T_ < 2) fail_key("type", fmt::format("a tangent needs at least 2 frames, the clip has {}", T_));
    std::vector<int> js = it_.joints.empty() ? std::vector<int>{sk_.root()} : joints(false);
    if (js.size() != 1)
      fail_key("joints", fmt::format("a tangent item controls one joint's velocity, got {} joints; use one item per joint",
                                     js.size()));
    const int j = js[0];
    auto fs = frames(true);
    std::vector<int> as = it_.axes.empty() ? std::vector<int>{0, 2} : axes();
    const int A = static_cast<int>(as.size());
    auto us = directions(fs, A, "velocity direction", [&](int t) {
      Eigen::VectorXd v = Eigen::VectorXd::Zero(A);
      for (auto [f, w] : tangent_stencil(t, T_))
        for (int a = 0; a < A; ++a) v[a] += w * source(f, j, as[a], "from_source");
      return v;
    });
    for (size_t k = 0; k < fs.size(); ++k) {
      const int t = fs[k];
      const Eigen::VectorXd& u = us[k];
      const auto stencil = tangent_stencil(t, T_);
      Eigen::MatrixXd E = orthogonal_complement(u);
      for (Eigen::Index e = 0; e < E.cols(); ++e) {
        int r = sink_.row(index_, 0.0, it_.variance);
        for (auto [f, w] : stencil)
          for (int a = 0; a < A; ++a)
            if (E(a, e) != 0.0) sink_.add(r, LinearObservation::index(f, j, as[a], J_), w * E(a, e));
      }
      int r = sink_.g_row(index_, -it_.min_speed, it_.variance);
      for (auto [f, w] : stencil)
        for (int a = 0; a < A; ++a)
          if (u[a] != 0.0) sink_.g_add(r, LinearObservation::index(f, j, as[a], J_), -w * u[a]);
      sink_.directions.push_back({index_, false, t, j, -1, as, u});
    }
  }

  // The body faces f (x, z): with a = x_right - x_left and forward = (a_z, -a_x)
  // (directions.h), forward is parallel to f when a . f = 0 (equality row) and
  // forward . f = a_z f_x - a_x f_z >= min_width (inequality row) fixes its sense.
  void facing() {
    std::vector<int> js;
    if (it_.joints.empty()) {
      auto face = role_joints("face", "right hip, left hip, ...");
      if (face.size() < 2) fail_key("joints", "the skeleton role 'face' needs at least the two hips [right, left]");
      js = {face[0], face[1]};
    } else {
      js = joints(false);
    }
    if (js.size() != 2)
      fail_key("joints", fmt::format("a facing item takes two joints [right, left] (the hips), got {}", js.size()));
    const int right = js[0], left = js[1];
    auto fs = frames(true);
    auto fw = directions(fs, 2, "facing direction", [&](int t) {
      Eigen::VectorXd v(2);
      const double ax = source(t, right, 0, "from_source") - source(t, left, 0, "from_source");
      const double az = source(t, right, 2, "from_source") - source(t, left, 2, "from_source");
      v << az, -ax;
      return v;
    });
    for (size_t k = 0; k < fs.size(); ++k) {
      const int t = fs[k];
      const double fx = fw[k][0], fz = fw[k][1];
      int r = sink_.row(index_, 0.0, it_.variance);  // a . f = 0
      auto both = [&](auto&& add, int row, int c, double coef) {
        if (coef == 0.0) return;
        add(row, LinearObservation::index(t, right, c, J_), coef);
        add(row, LinearObservation::index(t, left, c, J_), -coef);
      };
      auto eq = [&](int row, int col, double v) { sink_.add(row, col, v); };
      auto ineq = [&](int row, int col, double v) { sink_.g_add(row, col, v); };
      both(eq, r, 0, fx);
      both(eq, r, 2, fz);
      int g = sink_.g_row(index_, -it_.min_width, it_.variance);  // a_x f_z - a_z f_x <= -min_width
      both(ineq, g, 0, fz);
      both(ineq, g, 2, -fx);
      sink_.directions.push_back({index_, true, t, right, left, {0, 2}, fw[k]});
    }
  }

  const ConstraintSpec& spec_;
  int index_;
  const ConstraintItem& it_;
  int T_, J_;
  const Skeleton& sk_;
  const float* src_;
  RowSink& sink_;
};

struct UnionFind {
  std::vector<int> parent;
  explicit UnionFind(int n) : parent(n) { std::iota(parent.begin(), parent.end(), 0); }
  int find(int a) {
    while (parent[a] != a) a = parent[a] = parent[parent[a]];
    return a;
  }
  void unite(int a, int b) {
    a = find(a), b = find(b);
    if (a != b) parent[std::max(a, b)] = std::min(a, b);
  }
};

}  // namespace

LinearObservation compile(const ConstraintSpec& spec, int frames, const Skeleton& skeleton,
                          const float* source_motion) {
  if (frames < 1) fail("{}: cannot compile constraints for a clip of {} frames", spec.source, frames);
  RowSink sink;
  for (int i = 0; i < static_cast<int>(spec.items.size()); ++i) {
    if (!spec.items[i].score_only) {
      ItemCompiler(spec, i, frames, skeleton, source_motion, sink).compile();
      continue;
    }
    // Checked and compiled like any item, but only its direction probes are kept.
    RowSink scratch;
    ItemCompiler(spec, i, frames, skeleton, source_motion, scratch).compile();
    sink.directions.insert(sink.directions.end(), scratch.directions.begin(), scratch.directions.end());
  }

  LinearObservation obs;
  obs.frames = frames;
  obs.joints = skeleton.num_joints();
  obs.source = spec.source;
  const int m = static_cast<int>(sink.y.size());
  obs.A.resize(m, obs.dim());
  obs.A.setFromTriplets(sink.entries.begin(), sink.entries.end());
  obs.A.makeCompressed();
  obs.y = Eigen::Map<Eigen::VectorXd>(sink.y.data(), m);
  obs.variance = Eigen::Map<Eigen::VectorXd>(sink.variance.data(), m);
  obs.item_of_row = std::move(sink.item);
  const int p = static_cast<int>(sink.h.size());
  obs.G.resize(p, obs.dim());
  obs.G.setFromTriplets(sink.g_entries.begin(), sink.g_entries.end());
  obs.G.makeCompressed();
  obs.h = Eigen::Map<Eigen::VectorXd>(sink.h.data(), p);
  obs.g_variance = Eigen::Map<Eigen::VectorXd>(sink.g_variance.data(), p);
  obs.item_of_g_row = std::move(sink.g_item);
  obs.directions = std::move(sink.directions);
  for (int i = 0; i < static_cast<int>(spec.items.size()); ++i) obs.item_labels.push_back(spec.item_label(i));
  check_hard_rows(obs);
  if (p > 0) check_feasible(obs);
  return obs;
}

void check_feasible(const LinearObservation& obs) {
  if (obs.inequalities() == 0) return;
  // Feasibility does not depend on the metric; the Euclidean one is the cheapest.
  // Soft rows cannot make a set infeasible, so only the hard ones are solved.
  LinearObservation hard = obs;
  std::vector<int> keep_a, keep_g;
  for (int r = 0; r < obs.rows(); ++r)
    if (obs.is_hard(r)) keep_a.push_back(r);
  for (int r = 0; r < obs.inequalities(); ++r)
    if (obs.is_hard_inequality(r)) keep_g.push_back(r);
  if (keep_g.empty()) return;
  auto select = [](const Eigen::SparseMatrix<double, Eigen::RowMajor>& M, const std::vector<int>& rows, int cols) {
    std::vector<Eigen::Triplet<double>> t;
    for (size_t k = 0; k < rows.size(); ++k)
      for (Eigen::SparseMatrix<double, Eigen::RowMajor>::InnerIterator it(M, rows[k]); it; ++it)
        t.emplace_back(static_cast<int>(k), static_cast<int>(it.col()), it.value());
    Eigen::SparseMatrix<double, Eigen::RowMajor> out(static_cast<int>(rows.size()), cols);
    out.setFromTriplets(t.begin(), t.end());
    out.makeCompressed();
    return out;
  };
  hard.A = select(obs.A, keep_a, obs.dim());
  hard.G = select(obs.G, keep_g, obs.dim());
  hard.y.resize(keep_a.size());
  hard.variance = Eigen::VectorXd::Zero(keep_a.size());
  hard.item_of_row.clear();
  for (size_t k = 0; k < keep_a.size(); ++k)
    hard.y[k] = obs.y[keep_a[k]], hard.item_of_row.push_back(obs.item_of_row[keep_a[k]]);
  hard.h.resize(keep_g.size());
  hard.g_variance = Eigen::VectorXd::Zero(keep_g.size());
  hard.item_of_g_row.clear();
  for (size_t k = 0; k < keep_g.size(); ++k)
    hard.h[k] = obs.h[keep_g[k]], hard.item_of_g_row.push_back(obs.item_of_g_row[keep_g[k]]);
  ProjectionSolver solver(KinematicMetric::euclidean(obs.joints));
  solver.set_observation(hard);
  solver.project(Eigen::MatrixXd::Zero(obs.dim(), 1));  // throws UserError naming the items when infeasible
}

LinearObservation inequality_rows(const LinearObservation& obs) {
  LinearObservation out;
  out.frames = obs.frames;
  out.joints = obs.joints;
  out.source = obs.source;
  out.item_labels = obs.item_labels;
  out.A = obs.G;
  out.y = obs.h;
  out.variance = obs.g_variance;
  out.item_of_row = obs.item_of_g_row;
  out.G.resize(0, obs.dim());
  return out;
}

LinearObservation without_inequalities(const LinearObservation& obs) {
  LinearObservation out = obs;
  out.G.resize(0, obs.dim());
  out.h.resize(0);
  out.g_variance.resize(0);
  out.item_of_g_row.clear();
  return out;
}

std::vector<std::vector<int>> coupled_row_groups(const LinearObservation& obs, bool only_hard) {
  const int blocks = 3 * obs.frames, J = obs.joints;
  auto block_of = [&](int col) { return (col / (3 * J)) * 3 + col % 3; };
  UnionFind uf(blocks);
  for (int r = 0; r < obs.A.rows(); ++r) {
    if (only_hard && !obs.is_hard(r)) continue;
    Eigen::SparseMatrix<double, Eigen::RowMajor>::InnerIterator it(obs.A, r);
    if (!it) continue;
    int first = block_of(it.col());
    for (++it; it; ++it) uf.unite(first, block_of(it.col()));
  }
  std::map<int, std::vector<int>> by_root;
  std::vector<std::vector<int>> groups;
  for (int r = 0; r < obs.A.rows(); ++r) {
    if (only_hard && !obs.is_hard(r)) continue;
    Eigen::SparseMatrix<double, Eigen::RowMajor>::InnerIterator it(obs.A, r);
    if (!it) groups.push_back({r});
    else by_root[uf.find(block_of(it.col()))].push_back(r);
  }
  for (auto& [root, rows] : by_root) groups.push_back(std::move(rows));
  std::sort(groups.begin(), groups.end(), [](auto& a, auto& b) { return a.front() < b.front(); });
  return groups;
}

void check_hard_rows(const LinearObservation& obs) {
  const int J = obs.joints;
  for (const auto& rows : coupled_row_groups(obs, /*only_hard=*/true)) {
    // Dense copy of the group's rows over the columns they touch, each row scaled
    // to unit norm so the rank tolerance does not depend on units or camera scale.
    std::map<int, int> col_index;
    for (int r : rows)
      for (Eigen::SparseMatrix<double, Eigen::RowMajor>::InnerIterator it(obs.A, r); it; ++it)
        col_index.emplace(it.col(), 0);
    int n = 0;
    for (auto& [col, k] : col_index) k = n++;
    const int m = static_cast<int>(rows.size());
    Eigen::MatrixXd a = Eigen::MatrixXd::Zero(m, std::max(n, 1));
    Eigen::VectorXd y(m);
    for (int k = 0; k < m; ++k) {
      for (Eigen::SparseMatrix<double, Eigen::RowMajor>::InnerIterator it(obs.A, rows[k]); it; ++it)
        a(k, col_index[it.col()]) = it.value();
      double norm = a.row(k).norm();
      y[k] = norm > 0 ? obs.y[rows[k]] / norm : obs.y[rows[k]];
      if (norm > 0) a.row(k) /= norm;
    }
    Eigen::MatrixXd gram = a * a.transpose();
    Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> es(gram);
    const Eigen::VectorXd& ev = es.eigenvalues();  // ascending
    const double tol = 1e-10 * std::max(1.0, ev[m - 1]);
    if (ev[0] > tol) continue;

    std::set<int> items, frames;
    bool contradictory = false;
    for (int e = 0; e < m && ev[e] <= tol; ++e) {
      Eigen::VectorXd u = es.eigenvectors().col(e);
      // A left null vector u has u^T A = 0, so consistent targets need u^T y = 0.
      double scale = 1.0 + (u.cwiseAbs().array() * y.cwiseAbs().array()).sum();
      if (std::abs(u.dot(y)) > 1e-9 * scale) contradictory = true;
      for (int k = 0; k < m; ++k)
        if (std::abs(u[k]) > 1e-6) {
          items.insert(obs.item_of_row[rows[k]]);
          for (Eigen::SparseMatrix<double, Eigen::RowMajor>::InnerIterator it(obs.A, rows[k]); it; ++it)
            frames.insert(static_cast<int>(it.col() / (3 * J)));
        }
    }
    std::string names;
    int count = 0;
    for (int i : items) {
      ++count;
      names += (names.empty() ? "" : count == static_cast<int>(items.size()) ? " and " : ", ") +
               (i < static_cast<int>(obs.item_labels.size()) ? obs.item_labels[i] : fmt::format("item {}", i));
    }
    std::vector<int> frame_list(frames.begin(), frames.end());
    if (contradictory)
      fail("{}: contradictory hard constraints: the rows of {} pin the same coordinates to different targets "
           "(at frame{} {}); make one of them soft (variance > 0) or remove the overlap",
           obs.source, names, frame_list.size() > 1 ? "s" : "", list_text(frame_list));
    fail("{}: redundant hard constraints: the rows of {} constrain the same coordinates more than once "
         "(at frame{} {}), so A R^-1 A^T is singular; remove the duplicate rows or make one of the items soft "
         "(variance > 0)",
         obs.source, names, frame_list.size() > 1 ? "s" : "", list_text(frame_list));
  }
}

LinearObservation affine_to_model(const LinearObservation& obs, const std::array<double, 3>& axis_scale,
                                  const std::array<double, 3>& axis_offset) {
  for (int c = 0; c < 3; ++c)
    if (!std::isfinite(axis_scale[c]) || axis_scale[c] == 0.0 || !std::isfinite(axis_offset[c]))
      fail("affine_to_model: axis {} needs a finite non-zero scale and a finite offset, got scale {} offset {}",
           kAxisNames[c], axis_scale[c], axis_offset[c]);
  LinearObservation out = obs;
  // y_m = y - A offset: accumulate row by row while scaling the entries (A_m = A diag(scale)).
  auto move_inside = [&](Eigen::SparseMatrix<double, Eigen::RowMajor>& M, Eigen::VectorXd& b) {
    for (int r = 0; r < M.outerSize(); ++r)
      for (Eigen::SparseMatrix<double, Eigen::RowMajor>::InnerIterator it(M, r); it; ++it) {
        const int c = static_cast<int>(it.col() % 3);
        b[r] -= it.value() * axis_offset[c];
        it.valueRef() *= axis_scale[c];
      }
  };
  move_inside(out.A, out.y);
  if (out.inequalities() > 0) move_inside(out.G, out.h);  // G_m = G diag(scale), h_m = h - G offset
  return out;
}

}  // namespace mc
