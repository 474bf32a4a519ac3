// Residual-based control errors of a compiled constraint spec (see observation_errors.h).
#include "eval/observation_errors.h"

#include <cmath>
#include <map>
#include <tuple>

namespace mc {

std::vector<double> observation_entry_errors(const LinearObservation& obs, const float* motion) {
  const int d = obs.dim();
  Eigen::VectorXd x(d);
  for (int i = 0; i < d; ++i) x[i] = motion[i];
  Eigen::VectorXd r = obs.y - obs.A * x;
  // (item, first column / 3) -> squared residual; ordered so the output order is stable.
  std::map<std::pair<int, int>, double> entries;
  for (int row = 0; row < obs.rows(); ++row) {
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

}  // namespace mc
