// Replication summaries: mean, population std and 95% CI half-width over repeated
// evaluations (reference-facts §5: 20 replications, mean +- 1.96 std / sqrt(N)).
#include <cmath>

#include "core/error.h"
#include "eval/metrics.h"

namespace mc {

Replicated summarize(const std::vector<double>& values) {
  if (values.empty()) fail("summarize: no values");
  Replicated r;
  r.n = static_cast<int>(values.size());
  for (double v : values) {
    if (!std::isfinite(v)) fail("summarize: value {} is not finite", v);
    r.mean += v;
  }
  r.mean /= r.n;
  double ss = 0.0;
  for (double v : values) ss += (v - r.mean) * (v - r.mean);
  r.std = std::sqrt(ss / r.n);  // population (ddof = 0), as np.std in the T2M scripts
  r.ci95 = 1.96 * r.std / std::sqrt(static_cast<double>(r.n));
  return r;
}

std::map<std::string, Replicated> replicate(int n, uint64_t seed0,
                                            const std::function<MetricValues(uint64_t seed)>& run) {
  if (n < 1) fail("replicate: need at least 1 replication, got {}", n);
  if (!run) fail("replicate: no function to run");
  std::map<std::string, std::vector<double>> values;
  for (int r = 0; r < n; ++r) {
    const uint64_t seed = seed0 + static_cast<uint64_t>(r);
    const MetricValues m = run(seed);
    if (m.empty()) fail("replicate: run with seed {} reported no metrics", seed);
    if (r == 0) {
      for (const auto& [name, v] : m) values[name].push_back(v);
      continue;
    }
    if (m.size() != values.size())
      fail("replicate: run with seed {} reported {} metrics, the first run {}", seed, m.size(), values.size());
    for (const auto& [name, v] : m) {
      auto it = values.find(name);
      if (it == values.end()) fail("replicate: run with seed {} reported '{}', which the first run did not", seed, name);
      it->second.push_back(v);
    }
  }
  std::map<std::string, Replicated> out;
  for (const auto& [name, v] : values) {
    try {
      out[name] = summarize(v);
    } catch (const UserError& e) {
      fail("replicate: metric '{}': {}", name, e.what());
    }
  }
  return out;
}

}  // namespace mc
