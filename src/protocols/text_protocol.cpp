// `protocol: {type: text_to_motion}`: one unconstrained task per clip (caption and
// length only): the text-to-motion rows (AnchorRoute Table I, the Real-motion rows).
#include "control/control_task.h"
#include "core/error.h"
#include "data/motion_set.h"

namespace mc {
namespace {

struct TextToMotionProtocol : ControlProtocol {
  int caption = 0;  // which caption of each clip
  void visit(FieldVisitor& v) override {
    v("caption", caption, "index of the caption used as the text condition (clips have >= 1)", at_least(0));
  }
  std::vector<ControlTask> make_tasks(const MotionSet& data, const std::vector<size_t>& clips,
                                      uint64_t) const override {
    std::vector<ControlTask> out;
    const size_t per_frame = static_cast<size_t>(data.num_joints()) * 3;
    for (size_t c : clips) {
      if (c >= data.size()) fail("text_to_motion: clip index {} is outside the data ({} clips)", c, data.size());
      ControlTask t;
      t.id = data.ids[c];
      t.clip_id = data.ids[c];
      const auto& caps = data.captions[c];
      t.caption = caps[std::min<size_t>(caption, caps.size() - 1)];
      t.length = data.lengths[c];
      t.source.assign(data.clip(c), data.clip(c) + t.length * per_frame);
      t.spec.source = "text_to_motion (no constraints)";
      out.push_back(std::move(t));
    }
    return out;
  }
};

MC_REGISTER_PROTOCOL("text_to_motion", TextToMotionProtocol, "caption and length of each clip, no spatial control");

}  // namespace
}  // namespace mc
