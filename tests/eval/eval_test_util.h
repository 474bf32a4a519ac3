// Helpers shared by the eval metric tests: deterministic Gaussian embeddings,
// motion buffers and a UserError-with-message assertion.
#pragma once
#include <catch2/catch.hpp>

#include <cmath>
#include <random>
#include <vector>

#include "core/error.h"
#include "eval/metrics.h"

// Asserts that `expr` throws mc::UserError whose message contains `substr`.
#define REQUIRE_USER_ERROR(expr, substr)                   \
  do {                                                     \
    REQUIRE_THROWS_AS(expr, mc::UserError);                \
    REQUIRE_THROWS_WITH(expr, Catch::Contains(substr));    \
  } while (0)

namespace mc::test {

// Standard normal draws by Box-Muller on explicit 53-bit uniforms (portable).
inline double normal(std::mt19937_64& rng) {
  auto u = [&] { return (static_cast<double>(rng() >> 11) + 0.5) * 0x1.0p-53; };  // (0, 1)
  return std::sqrt(-2.0 * std::log(u())) * std::cos(2.0 * M_PI * u());
}

inline Eigen::MatrixXd gaussian_matrix(int rows, int cols, uint64_t seed) {
  std::mt19937_64 rng(seed);
  Eigen::MatrixXd m(rows, cols);
  for (int i = 0; i < rows; ++i)
    for (int j = 0; j < cols; ++j) m(i, j) = normal(rng);
  return m;
}

// An owned [frames, joints, 3] float buffer with a setter, for building clips.
struct Clip {
  int frames, joints, length;
  std::vector<float> data;
  Clip(int frames_, int joints_, int length_ = -1)
      : frames(frames_), joints(joints_), length(length_ < 0 ? frames_ : length_),
        data(static_cast<size_t>(frames_) * joints_ * 3, 0.0f) {}
  float* at(int t, int j) { return data.data() + (static_cast<size_t>(t) * joints + j) * 3; }
  void set(int t, int j, double x, double y, double z) {
    float* p = at(t, j);
    p[0] = static_cast<float>(x);
    p[1] = static_cast<float>(y);
    p[2] = static_cast<float>(z);
  }
  mc::JointsView view() const { return mc::joints_view(data, frames, joints, length); }
};

}  // namespace mc::test
