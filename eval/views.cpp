// Checked constructor of the read-only mask views the metrics take (joint views:
// data/joints_view.cpp).
#include "core/error.h"
#include "eval/metrics.h"

namespace mc {

MaskView mask_view(const std::vector<uint8_t>& data, int frames, int joints, int channels, const std::string& what) {
  if (frames < 0 || joints < 1 || channels < 1) fail("{}: invalid shape [{}, {}, {}]", what, frames, joints, channels);
  const size_t expected = static_cast<size_t>(frames) * joints * channels;
  if (data.size() != expected)
    fail("{}: {} values do not form [{}, {}, {}] (expected {})", what, data.size(), frames, joints, channels,
         expected);
  return MaskView{data.data(), frames, joints, channels};
}

}  // namespace mc
