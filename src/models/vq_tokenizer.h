// The VQ motion tokenizer (MoMask-style, reference-facts §6): conv encoder ->
// EMA codebook quantiser -> conv decoder over normalised joints [B, T, J*3], plus
// the soft decode and codebook metric the TMD prior and AnchorRoute build on.
#pragma once
#include <string>

#include <torch/torch.h>

#include "core/config.h"
#include "data/motion_set.h"
#include "data/skeleton.h"
#include "models/conv_motion.h"

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

// Nearest-code quantiser whose codebook is not a parameter: it follows the EMA of
// the encoder outputs assigned to each code, so the optimiser never touches it.
struct EmaQuantizerImpl : torch::nn::Module {
  explicit EmaQuantizerImpl(const EmaQuantizerOptions& o);
  // z [..., D]; valid [...] bool (undefined = all valid) marks the vectors that
  // count for the loss, the statistics and (in training mode) the EMA update.
  QuantizerOutput forward(const torch::Tensor& z, const torch::Tensor& valid = {});
  torch::Tensor assign(const torch::Tensor& z) const;    // [..., D] -> nearest ids [...] (no update)
  torch::Tensor lookup(const torch::Tensor& ids) const;  // [...] -> [..., D]
  // One EMA step from flat vectors z [N, D] and their ids [N]; returns the number
  // of codes re-drawn. Random replacements come from torch's CPU generator.
  torch::Tensor ema_update(const torch::Tensor& z, const torch::Tensor& ids);

  EmaQuantizerOptions opt;
  torch::Tensor codebook;      // [K, D] buffer
  torch::Tensor cluster_size;  // [K] buffer, EMA of assignment counts
  torch::Tensor embed_sum;     // [K, D] buffer, EMA of assigned-vector sums
};
TORCH_MODULE(EmaQuantizer);

// ---------------------------------------------------------------- tokenizer

struct VqTokenizerOptions {
  ConvMotionOptions conv;  // conv.latent must equal quant.code_dim
  EmaQuantizerOptions quant;
};

struct VqOutput {
  torch::Tensor recon;  // [B, T, J*3] normalised
  torch::Tensor ids;    // [B, T / stride]
  torch::Tensor commit_loss, perplexity, resets;  // scalars (see QuantizerOutput)
};

struct VqTokenizerImpl : torch::nn::Module {
  explicit VqTokenizerImpl(const VqTokenizerOptions& o);

  // x [B, T, J*3] normalised, T a multiple of stride(); mask [B, T] bool (undefined
  // = all valid). Padded frames are zeroed (the dataset's padding value) so the
  // tokens of a clip do not depend on what its padding held.
  VqOutput forward(const torch::Tensor& x, const torch::Tensor& mask = {});
  torch::Tensor encode(const torch::Tensor& x, const torch::Tensor& mask = {});  // -> ids [B, T / stride] int64
  torch::Tensor decode(const torch::Tensor& ids);                                // [B, L] -> [B, L * stride, J*3]
  // Decoder on continuous code vectors u [B, L, D] (RouteSolver's soft-token variable).
  torch::Tensor decode_embeddings(const torch::Tensor& u);
  // decoder(probs @ codebook) for probs [B, L, K]: differentiable in probs.
  torch::Tensor soft_decode(const torch::Tensor& probs);

  torch::Tensor codebook() const { return quantizer->codebook; }  // [K, D]
  torch::Tensor normalized_codebook() const;                       // rows scaled to unit L2 norm
  // TMD metric d(i, j) = (2 - 2 cos(e_i, e_j))^2 as a [K, K] table; zero diagonal.
  torch::Tensor token_distance_table() const;
  int64_t codebook_size() const { return options.quant.codebook_size; }
  int64_t code_dim() const { return options.quant.code_dim; }
  int64_t stride() const { return int64_t{1} << options.conv.down_stages; }  // frames per token
  int64_t num_joints() const { return options.conv.in_dim / 3; }

  // World joints [..., 3] <-> the normalised space the tokenizer was trained in.
  torch::Tensor normalize(const torch::Tensor& world) const;
  torch::Tensor denormalize(const torch::Tensor& normed) const;

  VqTokenizerOptions options;
  ConvMotionEncoder encoder{nullptr};
  EmaQuantizer quantizer{nullptr};
  ConvMotionDecoder decoder{nullptr};
  torch::Tensor joint_mean, joint_std;  // (3,) buffers: the training data's per-axis stats
};
TORCH_MODULE(VqTokenizer);

// ---------------------------------------------------------------- config

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
  }
};

VqTokenizerOptions vq_tokenizer_options(const VqTokenizerConfig& c, int num_joints);

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
