// The text-conditioned flow prior (model type `flow_prior`): config, the jointly
// trained text encoder, the network bundle a trained run stores in final.pt, and
// the trained prior loaded from its run directory (FlowPrior: classifier-free-guided
// velocity and the normaliser between world and model units).
#pragma once
#include <memory>
#include <string>
#include <vector>

#include "core/config.h"
#include "data/skeleton.h"
#include "data/text_vocab.h"
#include "models/flow_transformer.h"
#include "models/geometry_loss.h"
#include "models/kinematic_head.h"
#include "models/motion_dataset.h"
#include "models/text_encoder.h"

namespace mc {

// The text encoder's text_* fields (TextEncoderFields) are trained jointly, unless
// text_encoder names a contrastively pretrained `text_clip` run (no CLIP here).
struct FlowPriorConfig : Config, TextEncoderFields {
  // Family rule (reference-facts §2): width = 64 * depth, heads = depth; 0 follows it.
  int depth = 8;
  int width = 0;
  int heads = 0;
  int mlp_hidden = 0;  // 0 = 8/3 * width rounded up to 64 (SwiGLU with the params of a 4x MLP)
  double dropout = 0.0;
  double cond_drop = 0.1;
  std::vector<double> eval_t = {0.1, 0.3, 0.5, 0.7, 0.9};
  // What the network outputs. velocity: v = x1 - x0 (ACMDM). clean: the clean
  // endpoint x1 (x-prediction, as later absolute-coordinate flows use); the
  // velocity is then (x1_hat - x_t) / (1 - t), so every sampler is unchanged and
  // its last step lands on x1_hat. loss: which error is averaged, velocity
  // (eq. (3); a clean network's is its clean error over max(1 - t, clean_eps)) or
  // clean. smooth_weight adds that error's frame-to-frame differences (a
  // frequency-weighted MSE that penalises jitter, like MDM's velocity loss).
  std::string prediction = "velocity";
  std::string loss = "velocity";
  double clean_eps = 0.05;
  double smooth_weight = 0.0;
  int temporal_kernel = 1;
  GeometryLossConfig geometry_loss;  // off by default (and then absent from the dump)
  TextEncoderSourceConfig text_encoder;  // off by default (and then absent from the dump)
  KinematicHeadConfig kinematic_head;    // off by default (and then absent from the dump)
  void visit(FieldVisitor& v) override {
    v("depth", depth, "transformer blocks L", in_range(1, 64));
    v("width", width, "hidden size d (0 = 64 * depth)", at_least(0));
    v("heads", heads, "attention heads (0 = depth); width / heads must be even for RoPE", at_least(0));
    v("mlp_hidden", mlp_hidden, "SwiGLU hidden size (0 = 8/3 * width rounded up to a multiple of 64)", at_least(0));
    v("dropout", dropout, "dropout on attention probabilities and the MLP hidden", in_range(0.0, 0.9));
    v("cond_drop", cond_drop, "probability of replacing the text by the learned null embedding (for CFG)",
      in_range(0.0, 1.0));
    visit_text_fields(v, "text encoder width (also the pooled text vector size)");
    v("eval_t", eval_t, "flow times at which evaluate() reports the validation loss", each(in_range(0.0, 1.0)));
    v("prediction", prediction, "network output: velocity (x1 - x0, ACMDM) or clean (the endpoint x1)",
      one_of({"velocity", "clean"}));
    v("loss", loss, "training error: velocity (eq. (3)) or clean (||x1_hat - x1||^2)", one_of({"velocity", "clean"}));
    v("clean_eps", clean_eps, "clean prediction, velocity loss: floor of 1 - t in the loss weight 1/(1 - t)^2",
      in_range(1e-4, 0.5));
    v("smooth_weight", smooth_weight,
      "weight of the loss on frame-to-frame differences of the error (0 = off, ACMDM)", in_range(0.0, 100.0));
    v("temporal_kernel", temporal_kernel,
      "frames the input embedding and output head see (odd; 1 = ACMDM's per-frame PS22 Linear)", in_range(1, 31));
    v("geometry_loss", geometry_loss,
      "bone-vector and foot-contact terms of the training loss, in metres (off by default)");
    v("text_encoder", text_encoder,
      "a contrastively pretrained text_clip run whose text encoder (same text_* sizes) replaces the jointly "
      "trained one (off by default)");
    v("kinematic_head", kinematic_head,
      "the network states x1_hat in root steps, root height, root position and root-relative joints, with a "
      "loss on those channels (ours; off by default)");
  }
  std::string validate() const override;
  FlowTransformerOptions transformer_options(int num_joints) const;
};

// Everything final.pt holds: text encoder (and its adapter when pretrained), null
// text embedding, velocity network and the dataset's per-axis normalisation
// (buffers, so the weights carry them).
struct FlowPriorNetImpl : torch::nn::Module {
  FlowPriorNetImpl(int vocab_size, int num_joints, const FlowPriorConfig& c);
  // Pooled text vectors [B, text_width].
  torch::Tensor encode_text(const torch::Tensor& ids, const torch::Tensor& lengths);
  // The null condition broadcast to [B, text_width].
  torch::Tensor null_condition(int64_t B) const;
  // The velocity the network's output `out` stands for at (x, t) (t [B]; mask [B, T]
  // bool of valid frames), and the clean endpoint it implies: identity / x + (1 - t) out
  // for velocity networks, (x1_hat - x)/(1 - t) / x1_hat for clean ones (samplers never
  // ask at t = 1), where x1_hat is `out` itself or, with the kinematic head, the
  // normalised joints its channels decode to (decode_head).
  torch::Tensor to_velocity(const torch::Tensor& out, const torch::Tensor& x, const torch::Tensor& t,
                            const torch::Tensor& mask) const;
  torch::Tensor to_clean(const torch::Tensor& out, const torch::Tensor& x, const torch::Tensor& t,
                         const torch::Tensor& mask) const;
  // Kinematic head: its z-scored channels [B, T, C] to normalised joints [B, T, J, 3].
  torch::Tensor decode_head(const torch::Tensor& out, const torch::Tensor& mask) const;
  // Kinematic head: the z-scored channels [B, T, C] of x1_hat that the output `out`
  // stands for at (x, t): `out` itself, or with model.kinematic_head.skip
  // c_skip(t) (channels of x / t) + c_out(t) out (models/kinematic_head.h).
  torch::Tensor head_channels(const torch::Tensor& out, const torch::Tensor& x, const torch::Tensor& t,
                              const torch::Tensor& mask) const;
  // The source noise x0 [B, T, J, 3] (normalised) for clips whose valid frames are
  // `mask` [B, T]: N(0, I) drawn from `gen` (exactly as torch::randn({B, T, J, 3}, gen)),
  // or with model.kinematic_head.noise.enabled, i.i.d. channel draws [B, T, C]
  // decoded by the head's map at the channels' std. nullopt = torch's default generator.
  torch::Tensor draw_noise(const torch::Tensor& mask, int64_t num_joints, c10::optional<at::Generator> gen) const;
  bool clean_prediction = false;
  bool kinematic_head = false;
  bool kinematic_noise = false;
  bool kinematic_skip = false;
  bool kinematic_bones = false;  // model.kinematic_head.bones.enabled
  bool kinematic_rigid = false;  // model.kinematic_head.bones.rigid
  // Kinematic head: the channels [B, T, C] (metres, not z-scored) the head is trained
  // to write for world joints [B, T, J, 3]: kinematic_channels, with the pose block
  // as bone vectors under model.kinematic_head.bones.
  torch::Tensor head_target_channels(const torch::Tensor& world, const torch::Tensor& mask) const;
  // model.text_encoder.frozen with a pretrained encoder: encode_text runs `text`
  // without gradient and in eval mode whatever mode the bundle is in.
  bool text_frozen = false;
  TextEncoder text{nullptr};
  // Only with model.text_encoder: LayerNorm -> Linear -> GELU -> Linear from the
  // pretrained pooled vector to the condition (absent otherwise, so older
  // checkpoints keep their parameter list).
  torch::nn::Sequential text_adapter{nullptr};
  FlowTransformer transformer{nullptr};
  torch::Tensor null_text;             // [text_width] parameter
  torch::Tensor joint_mean, joint_std;  // (3,) buffers
  // With the kinematic head only (registered last, so other checkpoints keep their
  // buffer list): the training split's per-channel mean and std [C].
  torch::Tensor kin_mean, kin_std;
  // With model.kinematic_head.bones only (registered after those): the pose block's
  // maps between bone vectors and root-relative joints [J-1, J-1]
  // (models/kinematic_head.h) and, for `rigid`, the bones' mean lengths [J-1] over
  // the training split, all filled by the trainer and saved with the weights.
  torch::Tensor kin_from_bones, kin_to_bones, kin_bone_length;
};
TORCH_MODULE(FlowPriorNet);

// The inputs of a flow model's validation loss at flow time `t` (evaluate() of the
// prior and of its ControlNet): the chunk's whole clips with their first captions,
// x0 drawn from `gen` (constant-seeded by the caller, so the numbers compare across
// runs and torch's generator is left alone), t for every clip and no text dropped.
struct FlowValidationInputs {
  MotionBatch batch;
  std::vector<std::string> captions;
  torch::Tensor x0, t, drop;
};
FlowValidationInputs flow_validation_inputs(const MotionDataset& data, const std::vector<int64_t>& chunk, double t,
                                            at::Generator& gen, torch::Device device,
                                            const FlowPriorNetImpl* net = nullptr);

// A finished `flow_prior` run: config.yaml, checkpoints/final.pt, outputs/vocab.txt,
// outputs/prior_meta.yaml. All tensors in and out are on device() in normalised
// units [B, T, J, 3] unless a name says world.
class FlowPrior {
 public:
  // UserError naming the missing file, a wrong model type or an unreadable checkpoint.
  static FlowPrior load(const std::string& run_dir, torch::Device device = torch::kCPU);
  // A randomly initialised prior of the given size held in memory (no run
  // directory): for benchmarks, whose timings do not depend on trained weights.
  static FlowPrior untrained(const FlowPriorConfig& cfg, const Skeleton& skeleton, int t_max, uint64_t seed,
                             torch::Device device = torch::kCPU);

  // Pooled text vectors [B, text_width] of captions (the conditional input of velocity()).
  torch::Tensor encode_texts(const std::vector<std::string>& captions) const;
  // The null (unconditional) text vectors [B, text_width].
  torch::Tensor null_texts(int64_t B) const;

  // One network call: x [B, T, J, 3], t scalar or [B] in [0, 1], text [B, text_width]
  // (from encode_texts or null_texts), mask [B, T] bool of valid frames.
  torch::Tensor raw_velocity(const torch::Tensor& x, const torch::Tensor& t, const torch::Tensor& text,
                             const torch::Tensor& mask) const;
  // Classifier-free guided velocity v_u + s (v_c - v_u), conditional and unconditional
  // halves in one forward of the doubled batch (s = 1: the conditional batch alone).
  // UserError when the network output is not finite.
  torch::Tensor velocity(const torch::Tensor& x, const torch::Tensor& t, const torch::Tensor& text,
                         const torch::Tensor& mask, double cfg_scale) const;

  // The flow's source noise x0 [N, T, J, 3] (normalised, on the CPU) for clips of
  // `lengths` frames padded to T, drawn from `gen` (FlowPriorNetImpl::draw_noise).
  torch::Tensor draw_noise(const std::vector<int64_t>& lengths, int64_t T, at::Generator& gen) const;
  torch::Tensor normalize(const torch::Tensor& world) const;    // per-axis z-score, [..., 3]
  torch::Tensor denormalize(const torch::Tensor& normed) const;  // back to world metres

  const FlowPriorConfig& config() const { return cfg_; }
  const Skeleton& skeleton() const { return skeleton_; }
  const TextVocab& vocab() const { return *vocab_; }
  double fps() const { return fps_; }
  int t_max() const { return t_max_; }
  int num_joints() const { return skeleton_.num_joints(); }
  const std::string& run_dir() const { return run_dir_; }
  const std::string& data_path() const { return data_path_; }  // the motion file it was trained on
  torch::Device device() const { return device_; }
  FlowPriorNet& net() const { return *net_; }

 private:
  std::shared_ptr<FlowPriorNet> net_;
  std::shared_ptr<TextVocab> vocab_;
  FlowPriorConfig cfg_;
  Skeleton skeleton_;
  double fps_ = 20;
  int t_max_ = 196;
  std::string run_dir_, data_path_;
  torch::Device device_ = torch::kCPU;
};

}  // namespace mc
