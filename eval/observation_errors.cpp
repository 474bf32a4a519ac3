// Residual-based control errors of a compiled constraint spec (see observation_errors.h).
#include "eval/observation_errors.h"

#include <cmath>
#include <map>
#include <set>
#include <tuple>

#include "control/directions.h"

namespace mc {

std::vector<double> observation_entry_errors(const LinearObservation& obs, const float* motion) {
  const int d = obs.dim();
  Eigen::VectorXd x(d);
  for (int i = 0; i < d; ++i) x[i] = motion[i];
  Eigen::VectorXd r = obs.y - obs.A * x;
  // (item, first column / 3) -> squared residual; ordered so the output order is stable.
  std::map<std::pair<int, int>, double> entries;
  std::set<int> direction_items;
  for (const auto& p : obs.directions) direction_items.insert(p.item);
  for (int row = 0; row < obs.rows(); ++row) {
    if (direction_items.count(obs.item_of_row[row])) continue;
    int first = d;
    for (Eigen::SparseMatrix<double, Eigen::RowMajor>::InnerIterator it(obs.A, row); it; ++it)
      if (it.value() != 0.0) first = std::min<int>(first, it.col());
    if (first == d) continue;  // an empty row observes nothing
    entries[{obs.item_of_row[row], first / 3}] += r[row] * r[row];
  }
  std::vector<double> out;
  out.reserve(entries.size());
  for (auto& [_, sq] : entries) out.push_back(std::sqrt(sq));
  return out;
}

double max_inequality_violation(const LinearObservation& obs, const float* motion) {
  if (obs.inequalities() == 0) return 0.0;
  const int d = obs.dim();
  Eigen::VectorXd x(d);
  for (int i = 0; i < d; ++i) x[i] = motion[i];
  Eigen::VectorXd v = obs.G * x - obs.h;
  return std::max(0.0, v.maxCoeff());
}

std::vector<double> direction_errors(const LinearObservation& obs, const float* motion) {
  std::vector<double> out;
  out.reserve(obs.directions.size());
  for (const auto& p : obs.directions) {
    Eigen::VectorXd dir = p.facing ? Eigen::VectorXd(body_forward(motion, obs.joints, p.joint, p.other, p.frame))
                                   : joint_velocity(motion, obs.frames, obs.joints, p.joint, p.frame, p.axes);
    out.push_back(angle_degrees(dir, p.target));
  }
  return out;
}

}  // namespace mc
