// A contrastively pretrained text encoder for the priors (model type `text_clip`):
// a dual encoder, the priors' own text encoder architecture against a small motion
// encoder, trained CLIP-style with symmetric InfoNCE on the training split's
// caption/motion pairs. A prior's model.text_encoder loads its text half, frozen,
// in place of the jointly trained one. It is not the evaluator: separate code,
// weights and seeds (docs/choices.md, "Training on 2 cores").
#pragma once
#include <iosfwd>
#include <string>
#include <vector>

#include <torch/torch.h>

#include "core/config.h"
#include "models/text_encoder.h"

namespace mc {

// Text side: the flow prior's text_* fields (TextEncoderFields: same names, same
// defaults), so a prior with the same values loads these weights one-to-one.
struct TextClipConfig : Config, TextEncoderFields {
  // Motion side: only here to train the text side; never used by a prior.
  int motion_stride = 4;  // frames per motion token (a strided patch, as T2M's movement encoder's /4)
  int motion_width = 128;
  int motion_layers = 2;
  int motion_heads = 4;
  int motion_ff = 256;
  double motion_dropout = 0.1;
  double init_temperature = 0.07;  // CLIP's initial softmax temperature
  double max_logit_scale = 100.0;  // CLIP's clamp of 1 / temperature
  int eval_pool = 32;              // retrieval pool of evaluate() (R-precision's 32)
  void visit(FieldVisitor& v) override {
    visit_text_fields(v, "text encoder width = the pooled vector and the contrastive embedding size");
    v("motion_stride", motion_stride,
      "frames per motion token: the per-frame features of this many frames enter one Linear (cost / stride)",
      in_range(1, 16));
    v("motion_width", motion_width, "motion encoder width", at_least(8));
    v("motion_layers", motion_layers, "motion transformer encoder layers", in_range(1, 12));
    v("motion_heads", motion_heads, "motion encoder attention heads", at_least(1));
    v("motion_ff", motion_ff, "motion encoder feed-forward size", at_least(8));
    v("motion_dropout", motion_dropout, "motion encoder dropout", in_range(0.0, 0.9));
    v("init_temperature", init_temperature, "initial InfoNCE temperature (learned from there, CLIP-style)",
      in_range(1e-3, 1.0));
    v("max_logit_scale", max_logit_scale, "upper clamp of the learned 1 / temperature", in_range(1.0, 1000.0));
    v("eval_pool", eval_pool, "validation retrieval pool size (T2M's R-precision uses 32)", in_range(2, 1024));
  }
  std::string validate() const override;
};

// Per-frame features [x, x - root, x_t - x_{t-1}] of the normalised joints, those of
// motion_stride consecutive frames through one Linear (a strided patch embedding),
// sinusoidal token positions, a transformer encoder with key padding, masked mean,
// LayerNorm and a Linear to the text width: one vector per clip.
struct ClipMotionEncoderImpl : torch::nn::Module {
  ClipMotionEncoderImpl(int num_joints, const TextClipConfig& c);
  torch::Tensor forward(const torch::Tensor& joints, const torch::Tensor& mask);  // [B, T, J, 3], [B, T] -> [B, text_width]
  torch::nn::Linear input{nullptr};
  torch::nn::TransformerEncoder encoder{nullptr};
  torch::nn::LayerNorm norm{nullptr};
  torch::nn::Linear out{nullptr};
  int64_t width, stride;
};
TORCH_MODULE(ClipMotionEncoder);

// final.pt of a text_clip run: `text` (the module a prior loads), `motion` and the
// learned log inverse temperature.
struct TextClipNetImpl : torch::nn::Module {
  TextClipNetImpl(int vocab_size, int num_joints, const TextClipConfig& c);
  TextEncoder text{nullptr};
  ClipMotionEncoder motion{nullptr};
  torch::Tensor logit_scale;  // log(1 / temperature), scalar parameter
  double max_logit_scale = 100.0;
  torch::Tensor scale() const;  // exp(logit_scale) clamped to max_logit_scale
};
TORCH_MODULE(TextClipNet);

// Symmetric InfoNCE (CLIP): logits = scale * cos(text_i, motion_j) over a batch of
// pairs [B, D] x [B, D]; the mean of the text->motion and motion->text cross
// entropies. `same` [B, B] bool (optional) marks pairs whose captions are the same
// string: those are all positives, with equal target weight (the fixture's
// captions repeat, and a repeated caption is a true match for both clips).
torch::Tensor clip_infonce(const torch::Tensor& text, const torch::Tensor& motion, const torch::Tensor& scale,
                           const torch::Tensor& same = {});

// [B, B] bool: captions[i] == captions[j].
torch::Tensor same_caption_matrix(const std::vector<std::string>& captions);

// Text->motion retrieval in consecutive pools of `pool` pairs (the last partial
// pool dropped, as T2M's R-precision): fraction of texts whose own motion ranks
// within the top k by cosine similarity, for k = 1..top_k (cumulative). Ties rank
// the lower index first, as eval's r_precision does.
std::vector<double> clip_retrieval(const torch::Tensor& text, const torch::Tensor& motion, int pool, int top_k);

// A finished text_clip run as a prior needs it.
struct TextClipRun {
  std::string run_dir;
  TextClipConfig cfg;
  std::vector<std::string> vocab;  // outputs/vocab.txt
};
// UserError naming the missing file or a wrong model type.
TextClipRun read_text_clip_run(const std::string& run_dir);

// The run `src` names: run_dir, or the run of its config the job resolved
// (train/dependencies.h trains it first). `log` (may be null) gets one line.
std::string resolve_text_clip_run(const TextEncoderSourceConfig& src, std::ostream* log);

// Loads the run's text encoder weights into `enc` (a TextEncoder, or any module with
// its parameter names and shapes, such as the token priors' TokenTextEncoder), built
// with `want` (the caller's sizes). UserError naming the first size that differs
// (`what` names the caller's config, e.g. "model.text_encoder").
void load_text_clip_encoder(const TextClipRun& run, torch::nn::Module& enc, const TextEncoderOptions& want,
                            const std::string& what);

}  // namespace mc
