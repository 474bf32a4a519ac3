// The VQ motion tokenizer (MoMask-style, reference-facts §6): conv encoder ->
// EMA codebook quantiser -> conv decoder, over either normalised absolute joints
// [B, T, J*3] or HumanML3D-style translation-invariant features (root velocity in
// the heading frame, root height, root-relative joints) from which world joints
// are recovered by integration; plus the soft decode and codebook metric the TMD
// prior and AnchorRoute build on. Whatever the representation, encode() reads and
// decode()/soft_decode()/decode_embeddings() return normalised absolute joints, so
// the anchor losses and RouteSolver's residuals stay in world metres.
#pragma once
#include <functional>
#include <string>

#include <torch/torch.h>

#include "core/config.h"
#include "data/features.h"
#include "data/motion_set.h"
#include "data/skeleton.h"
#include "models/conv_motion.h"
#include "models/geometry_loss.h"

namespace mc {

// ---------------------------------------------------------------- quantiser

struct EmaQuantizerOptions {
  int codebook_size = 512;       // K
  int code_dim = 512;            // D
  double decay = 0.99;           // EMA decay of counts and sums
  double commitment = 0.02;      // beta of ||z - sg(e)||^2
  double reset_threshold = 1.0;  // codes whose EMA count falls below are re-drawn (0 = never)
  double epsilon = 1e-5;         // Laplace smoothing of the cluster sizes
};

struct QuantizerOutput {
  torch::Tensor quantized;    // [..., D] straight-through: forward = code, backward = identity to z
  torch::Tensor ids;          // [...] int64
  torch::Tensor commit_loss;  // scalar, already times beta (0 without valid vectors)
  torch::Tensor perplexity;   // scalar, of the code histogram over the valid vectors
  torch::Tensor resets;       // scalar, codes re-drawn by this call's EMA update (0 in eval)
};

// A data-parallel shard's view of the whole batch for the quantiser (issue 19;
// train/batch_shard.h builds it): this rank, the rank count and the in-place sum of
// a tensor over the ranks. The commitment mean, the code histogram and the EMA step
// then use the whole batch's vectors, and dead codes restart from the whole batch's
// vectors, so every rank keeps the codebook one process would. Default: one process.
struct QuantizerSync {
  int rank = 0, world = 1;
  std::function<void(torch::Tensor&)> sum;
  bool active() const { return world > 1 && static_cast<bool>(sum); }
};

// Nearest-code quantiser whose codebook is not a parameter: it follows the EMA of
// the encoder outputs assigned to each code, so the optimiser never touches it.
struct EmaQuantizerImpl : torch::nn::Module {
  explicit EmaQuantizerImpl(const EmaQuantizerOptions& o);
  // z [..., D]; valid [...] bool (undefined = all valid) marks the vectors that
  // count for the loss, the statistics and (in training mode) the EMA update.
  QuantizerOutput forward(const torch::Tensor& z, const torch::Tensor& valid = {}, const QuantizerSync& sync = {});
  torch::Tensor assign(const torch::Tensor& z) const;    // [..., D] -> nearest ids [...] (no update)
  torch::Tensor lookup(const torch::Tensor& ids) const;  // [...] -> [..., D]
  // One EMA step from flat vectors z [N, D] and their ids [N]; returns the number
  // of codes re-drawn. Random replacements come from torch's CPU generator.
  torch::Tensor ema_update(const torch::Tensor& z, const torch::Tensor& ids);
  // The same step for a shard: z [n, D] are rows [offset, offset + n) of the whole
  // batch's `total` vectors, whose summed one-hot counts [K] and vector sums [K, D]
  // are given.
  torch::Tensor ema_update_shard(const torch::Tensor& z, const torch::Tensor& counts, const torch::Tensor& sums,
                                 int64_t total, int64_t offset, const QuantizerSync& sync);
  // The EMA statistics step both updates share: decays cluster_size and embed_sum
  // towards this batch's counts [K] and sums [K, D]; returns the smoothed code means.
  torch::Tensor ema_means_(const torch::Tensor& counts, const torch::Tensor& sums);

  EmaQuantizerOptions opt;
  torch::Tensor codebook;      // [K, D] buffer
  torch::Tensor cluster_size;  // [K] buffer, EMA of assignment counts
  torch::Tensor embed_sum;     // [K, D] buffer, EMA of assigned-vector sums
};
TORCH_MODULE(EmaQuantizer);

// ---------------------------------------------------------------- tokenizer

// The representation the conv encoder reads and the decoder writes.
struct VqRepresentation {
  std::string type = "absolute_joints";  // or "invariant"
  std::string layout = "inv67";          // invariant: feature layout (features.h), "inv67" or "inv67+vel+contact"
  FeatureOptions features;
  bool invariant() const { return type == "invariant"; }
};

struct VqTokenizerOptions {
  ConvMotionOptions conv;  // conv.latent must equal quant.code_dim; conv.in_dim = J*3 or the feature size
  EmaQuantizerOptions quant;
  VqRepresentation representation;
  int num_joints = 0;      // 0 = conv.in_dim / 3 (absolute joints)
  Skeleton skeleton;       // invariant: needed to compute features in encode() (facing, feet)
};

// Differentiable recovery of world joints from denormalised invariant features
// f [..., T, F] (F >= 4 + 3(J-1)): heading and root xz integrated from frame -1 =
// (origin, heading 0) by cumulative sums (features.h, invariant_features). -> [..., T, J, 3].
torch::Tensor recover_world_from_invariant(const torch::Tensor& f, int64_t num_joints);

struct VqOutput {
  torch::Tensor recon;  // [B, T, C] in the model representation (normalised joints or normalised features)
  torch::Tensor ids;    // [B, T / stride]
  torch::Tensor commit_loss, perplexity, resets;  // scalars (see QuantizerOutput)
};

struct VqTokenizerImpl : torch::nn::Module {
  explicit VqTokenizerImpl(const VqTokenizerOptions& o);

  // x [B, T, C] in the model representation (model_input), T a multiple of stride();
  // mask [B, T] bool (undefined = all valid). Padded frames are zeroed (the dataset's
  // padding value) so the tokens of a clip do not depend on what its padding held.
  VqOutput forward(const torch::Tensor& x, const torch::Tensor& mask = {}, const QuantizerSync& sync = {});
  // x [B, T, J*3] normalised absolute joints (clips start at frame 0, padded at the
  // end) -> ids [B, T / stride] int64. Invariant: features of each clip's valid frames.
  torch::Tensor encode(const torch::Tensor& x, const torch::Tensor& mask = {});
  // The following return normalised absolute joints [B, L * stride, J*3] (invariant:
  // integrated from frame -1 = origin, heading 0, as the dataset's canonical clips start).
  torch::Tensor decode(const torch::Tensor& ids);  // [B, L]
  // Decoder on continuous code vectors u [B, L, D] (RouteSolver's soft-token variable).
  torch::Tensor decode_embeddings(const torch::Tensor& u);
  // decoder(probs @ codebook) for probs [B, L, K]: differentiable in probs.
  torch::Tensor soft_decode(const torch::Tensor& probs);

  // Normalised absolute joints [B, T, J*3] -> the model representation [B, T, C]
  // (absolute: masked copy; invariant: normalised features, zero on padding).
  torch::Tensor model_input(const torch::Tensor& x, const torch::Tensor& mask = {}) const;
  // Decoder output [B, T, C] -> normalised absolute joints [B, T, J*3] (differentiable).
  torch::Tensor model_output_to_joints(const torch::Tensor& y) const;
  bool invariant() const { return options.representation.invariant(); }
  int64_t input_dim() const { return options.conv.in_dim; }

  torch::Tensor codebook() const { return quantizer->codebook; }  // [K, D]
  torch::Tensor normalized_codebook() const;                       // rows scaled to unit L2 norm
  // TMD metric d(i, j) = (2 - 2 cos(e_i, e_j))^2 as a [K, K] table; zero diagonal.
  torch::Tensor token_distance_table() const;
  int64_t codebook_size() const { return options.quant.codebook_size; }
  int64_t code_dim() const { return options.quant.code_dim; }
  int64_t stride() const { return int64_t{1} << options.conv.down_stages; }  // frames per token
  int64_t num_joints() const { return options.num_joints > 0 ? options.num_joints : options.conv.in_dim / 3; }

  // World joints [..., 3] <-> the normalised space the tokenizer was trained in.
  torch::Tensor normalize(const torch::Tensor& world) const;
  torch::Tensor denormalize(const torch::Tensor& normed) const;

  VqTokenizerOptions options;
  ConvMotionEncoder encoder{nullptr};
  EmaQuantizer quantizer{nullptr};
  ConvMotionDecoder decoder{nullptr};
  torch::Tensor joint_mean, joint_std;  // (3,) buffers: the training data's per-axis stats
  // Invariant only (absent from absolute tokenizers' checkpoints): per-dimension
  // feature stats of the train split (compute_norm_stats with the layout).
  torch::Tensor feature_mean, feature_std;  // (C,) buffers
};
TORCH_MODULE(VqTokenizer);

// ---------------------------------------------------------------- config

// `model.representation`: absent from the dump when absolute (so tokenizers trained
// before it keep their config hash).
struct VqRepresentationConfig : Config {
  std::string type = "absolute_joints";
  std::string layout = "inv67";
  double facing_smooth_sigma = 20.0;
  double world_weight = 0.0;
  double root_weight = 1.0;
  void visit(FieldVisitor& v) override {
    v("type", type,
      "absolute_joints: per-axis normalised world joints (ACMDM); invariant: HumanML3D-style root heading change, "
      "root xz velocity in the heading frame, root height, root-relative joints; world joints recovered by "
      "integration in every decode",
      one_of({"absolute_joints", "invariant"}));
    v("layout", layout, "invariant feature layout: inv67, or inv67+vel+contact (local velocities and foot contacts "
      "as auxiliary targets)", one_of({"inv67", "inv67+vel+contact"}));
    v("facing_smooth_sigma", facing_smooth_sigma, "Gaussian std (frames) smoothing the heading (HumanML3D: 20)",
      at_least(0.0));
    v("world_weight", world_weight,
      "invariant: weight of the reconstruction loss on joints recovered by integration over the training window "
      "(in joint-std units; penalises root drift)",
      at_least(0.0));
    v("root_weight", root_weight,
      "invariant: weight of the 4 root channels (heading change, xz velocity, height) in the feature losses, "
      "relative to each other channel's 1 (their errors integrate into the trajectory)",
      at_least(0.0));
  }
  bool omitted_from_dump() const override {
    return type == "absolute_joints" && layout == "inv67" && facing_smooth_sigma == 20.0 && world_weight == 0.0 &&
           root_weight == 1.0;
  }
  std::string validate() const override {
    if (type == "absolute_joints" && !omitted_from_dump())
      return "layout, facing_smooth_sigma, world_weight and root_weight apply to representation.type invariant only";
    return "";
  }
};

// `model.clip_world_loss` (issue 15): the invariant tokenizer's world loss on whole
// clips beside the window's losses. The window's world loss sees only the drift of
// the integrated root inside a 64-frame crop, while the decode that AnchorRoute's
// anchors and the oracle control error read integrates over the whole clip (up to
// 196 frames); training on whole clips instead halved that drift but cost the poses
// (docs/choices.md, "Whole clips instead of 64-frame windows"). So each step also
// decodes `clips` whole clips of the batch (padded to the longest of them, with the
// quantiser's codebook held: no EMA step) and adds `weight` x their world MPJPE (m).
// Off by default and then absent from the dump (every tokenizer run keeps its name).
struct ClipWorldLossConfig : Config {
  double weight = 0.0;
  int clips = 16;
  void visit(FieldVisitor& v) override {
    v("weight", weight,
      "invariant: weight of the MPJPE (m) of the joints integrated over whole clips (0 = off)", in_range(0.0, 1e6));
    v("clips", clips, "whole clips per step: the first ones of the batch (fewer if the batch is smaller)",
      in_range(1, 4096));
  }
  bool enabled() const { return weight > 0; }
  bool omitted_from_dump() const override { return !enabled() && clips == 16; }
};

// `model:` section of a tokenizer run (model.type = vq_tokenizer).
struct VqTokenizerConfig : Config {
  int width = 512;
  int code_dim = 512;
  int codebook_size = 512;
  int down_stages = 2;
  int res_depth = 3;
  int dilation_growth = 3;
  double ema_decay = 0.99;
  double commitment = 0.02;
  double reset_threshold = 1.0;
  std::string recon_loss = "smooth_l1";
  double velocity_weight = 0.5;
  VqRepresentationConfig representation;
  GeometryLossConfig geometry_loss;  // off by default (and then absent from the dump)
  ClipWorldLossConfig clip_world_loss;  // off by default (and then absent from the dump)
  void visit(FieldVisitor& v) override {
    v("width", width, "conv channels", at_least(8));
    v("code_dim", code_dim, "codebook vector size D", at_least(1));
    v("codebook_size", codebook_size, "number of codes K", at_least(2));
    v("down_stages", down_stages, "stride-2 stages (2 = x4 in time)", in_range(0, 4));
    v("res_depth", res_depth, "dilated residual blocks per stage", in_range(0, 6));
    v("dilation_growth", dilation_growth, "dilation factor between residual blocks", in_range(1, 9));
    v("ema_decay", ema_decay, "codebook EMA decay", in_range(0.0, 0.99999));
    v("commitment", commitment, "commitment loss weight beta", at_least(0.0));
    v("reset_threshold", reset_threshold, "re-draw codes whose EMA count falls below this (0 = never)",
      at_least(0.0));
    v("recon_loss", recon_loss, "reconstruction loss on normalised joints: smooth_l1 or mse",
      one_of({"smooth_l1", "mse"}));
    v("velocity_weight", velocity_weight, "weight of the frame-difference reconstruction loss", at_least(0.0));
    v("representation", representation, "what the tokenizer reads and writes (absolute_joints by default)");
    v("geometry_loss", geometry_loss,
      "bone-vector and toe-slip terms on the reconstructed world joints (issue 13; off by default): for the "
      "invariant representation on the joints integrated over the training window");
    v("clip_world_loss", clip_world_loss,
      "invariant: the world MPJPE on whole clips beside the window's losses (issue 15; off by default)");
  }
  std::string validate() const override {
    if (clip_world_loss.enabled() && representation.type != "invariant")
      return "clip_world_loss applies to representation.type invariant only (absolute joints do not drift)";
    return "";
  }
};

// Absolute joints need only the joint count; the invariant representation needs the
// skeleton (facing and feet roles) and its feature size.
VqTokenizerOptions vq_tokenizer_options(const VqTokenizerConfig& c, const Skeleton& skeleton);

// ---------------------------------------------------------------- loading

// A finished tokenizer run (config.yaml, checkpoints/final.pt, outputs/tokenizer_meta.yaml),
// in eval mode on `device`, with what its users need to stay consistent with it.
struct LoadedVqTokenizer {
  VqTokenizer model{nullptr};
  VqTokenizerConfig cfg;
  Skeleton skeleton;
  double fps = 20.0;
  std::string run_dir;
  // UserError unless `m` has the tokenizer's skeleton (same joints) and fps.
  void check_compatible(const MotionSet& m, const std::string& source) const;
};

// UserError when a file is missing, the run is not a vq_tokenizer, or the
// checkpoint does not match its config.
LoadedVqTokenizer load_vq_tokenizer(const std::string& run_dir, torch::Device device = torch::kCPU);

}  // namespace mc
