// Control accuracy: OmniControl's Traj./Loc./Avg. err and AnchorRoute's control
// error over masked (frame, joint, axis) entries (reference-facts §5).
#include <cmath>

#include "core/error.h"
#include "eval/metrics.h"

namespace mc {

namespace {

void check_sample(const ControlSample& s, size_t i) {
  const JointsView& g = s.generated;
  const JointsView& y = s.target;
  const MaskView& m = s.mask;
  if (!g.data || !y.data || !m.data) fail("control sample {}: missing generated, target or mask data", i);
  if (y.frames != g.frames || y.joints != g.joints)
    fail("control sample {}: generated is [{}, {}, 3] but target is [{}, {}, 3]", i, g.frames, g.joints, y.frames,
         y.joints);
  if (m.frames != g.frames || m.joints != g.joints || m.channels != 3)
    fail("control sample {}: generated is [{}, {}, 3] but the mask is [{}, {}, {}] (need one flag per axis)", i,
         g.frames, g.joints, m.frames, m.joints, m.channels);
}

}  // namespace

std::vector<double> controlled_entry_errors(const ControlSample& s) {
  check_sample(s, 0);
  std::vector<double> errors;
  for (int t = 0; t < s.generated.frames; ++t) {
    for (int j = 0; j < s.generated.joints; ++j) {
      if (!s.mask.any(t, j)) continue;
      if (t >= s.generated.length)
        fail("control mask selects frame {} but the generated motion has only {} valid frames", t,
             s.generated.length);
      const Eigen::Vector3d d = s.generated.at(t, j) - s.target.at(t, j);
      double sq = 0.0;
      for (int a = 0; a < 3; ++a)
        if (s.mask.at(t, j, a)) sq += d[a] * d[a];  // only the controlled axes: e.g. xz for planar root
      errors.push_back(std::sqrt(sq));
    }
  }
  return errors;
}

ControlMetrics control_metrics(const std::vector<ControlSample>& samples, const ControlOptions& opt) {
  if (samples.empty()) fail("control_metrics: no samples");
  std::vector<std::vector<double>> errors;
  for (size_t i = 0; i < samples.size(); ++i) {
    check_sample(samples[i], i);
    errors.push_back(controlled_entry_errors(samples[i]));
  }
  return control_metrics_from_errors(errors, opt);
}

ControlMetrics control_metrics_from_errors(const std::vector<std::vector<double>>& errors, const ControlOptions& opt) {
  if (errors.empty()) fail("control_metrics: no samples");
  if (opt.thresholds.empty()) fail("control_metrics: no thresholds");
  for (double th : opt.thresholds)
    if (!(th >= 0.0) || !std::isfinite(th)) fail("control_metrics: threshold {} is not a finite value >= 0", th);

  ControlMetrics r;
  r.rates.resize(opt.thresholds.size());
  for (size_t k = 0; k < opt.thresholds.size(); ++k) r.rates[k].threshold = opt.thresholds[k];
  double avg_sum = 0.0, pooled_sum = 0.0;
  for (size_t i = 0; i < errors.size(); ++i) {
    const std::vector<double>& err = errors[i];
    if (err.empty()) {  // nothing to score: excluded from every average, counted
      ++r.samples_without_control;
      continue;
    }
    ++r.samples;
    r.controlled_entries += static_cast<int64_t>(err.size());
    double sum = 0.0;
    for (double e : err) {
      if (!std::isfinite(e)) fail("control_metrics: sample {} has a non-finite error", i);
      sum += e;
    }
    pooled_sum += sum;
    avg_sum += sum / err.size();
    for (size_t k = 0; k < opt.thresholds.size(); ++k) {
      size_t over = 0;
      for (double e : err) over += e > opt.thresholds[k];
      r.rates[k].traj_err += over > 0 ? 1.0 : 0.0;                        // any entry fails
      r.rates[k].loc_err += static_cast<double>(over) / err.size();  // per sample ...
    }
  }
  if (r.samples == 0) fail("control_metrics: none of the {} samples has a controlled entry", errors.size());
  for (auto& rate : r.rates) {  // ... then the mean over samples
    rate.traj_err /= r.samples;
    rate.loc_err /= r.samples;
  }
  r.traj_err = r.rates[0].traj_err;
  r.loc_err = r.rates[0].loc_err;
  r.avg_err = avg_sum / r.samples;
  r.control_error = pooled_sum / static_cast<double>(r.controlled_entries);
  return r;
}

}  // namespace mc
