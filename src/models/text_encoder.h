// The caption encoder shared by the flow prior and the contrastive text encoder
// (`text_clip`): one module, so a `text_clip` run's weights load one-to-one into a
// prior's `text.*` parameters; plus the config switch that names such a run.
#pragma once
#include <string>
#include <vector>

#include <torch/torch.h>

#include "core/config.h"
#include "core/trained_runs.h"
#include "data/text_vocab.h"

namespace mc {

struct TextEncoderOptions {
  int vocab_size = 4;
  int width = 256;  // also the pooled text vector size
  int layers = 2;
  int heads = 4;
  int ff = 512;
  double dropout = 0.1;
  int max_words = 32;
};

// The text encoder's sizes under the keys every text-conditioned model's config
// declares (text_width ... max_words, in this order): a base of FlowPriorConfig,
// TokenPriorConfig and TextClipConfig, so their keys, defaults, ranges and checks
// are written once, and a text_clip run with the flow prior's values loads
// one-to-one into it.
struct TextEncoderFields {
  int text_width = 256;
  int text_layers = 2;
  int text_heads = 4;
  int text_ff = 512;
  double text_dropout = 0.1;
  int max_words = 32;
  // Visits the six fields (in the owning config's visit(), where they stand in its
  // dump); `width_help` says what text_width sizes in that model.
  void visit_text_fields(FieldVisitor& v, const char* width_help);
  // "" or what is wrong with the sizes, for the owning config's validate().
  std::string text_fields_error() const;
  TextEncoderOptions text_encoder_options(int vocab_size) const;
};

// Word embeddings + learned positions + a transformer encoder, mean-pooled over
// the real tokens (<sos> words <eos>) and projected: one vector per caption.
struct TextEncoderImpl : torch::nn::Module {
  explicit TextEncoderImpl(const TextEncoderOptions& o);
  torch::Tensor forward(const torch::Tensor& ids, const torch::Tensor& lengths);  // [B, L], [B] -> [B, width]
  torch::nn::Embedding embedding{nullptr}, position{nullptr};
  torch::nn::TransformerEncoder encoder{nullptr};
  torch::nn::LayerNorm norm{nullptr};
  torch::nn::Linear out{nullptr};
};
TORCH_MODULE(TextEncoder);

struct EncodedCaptions {
  torch::Tensor ids;      // [B, max_words] int64
  torch::Tensor lengths;  // [B] int64
};
EncodedCaptions encode_captions(const TextVocab& vocab, const std::vector<std::string>& captions, int max_words);

// `model.text_encoder` of a prior: a finished `text_clip` run (or its training
// config, trained on demand) whose text encoder replaces the jointly trained one.
// Off (both empty, the default) it is left out of the dumped config, so every run
// trained before the switch existed keeps its name and hash.
struct TextEncoderSourceConfig : Config, DeclaresDependencies {
  std::string run_dir;                 // a finished text_clip run; wins over `config`
  std::string config;                  // else its training config, trained first when not finished
  std::vector<std::string> overrides;  // overrides for `config`
  bool frozen = true;                  // false: initialised from the run, then trained with the prior
  void visit(FieldVisitor& v) override {
    v("run_dir", run_dir, "finished text_clip run whose text encoder the prior uses (takes precedence over config)");
    v("config", config,
      "training config of that text_clip run (when run_dir is empty), trained like `motionctl train` unless "
      "already finished; '' with run_dir '' = off (the text encoder is trained jointly)");
    v("overrides", overrides, "key=value overrides applied to `config`");
    v("frozen", frozen,
      "true: its weights stay fixed (no gradient, eval mode, not optimised) and a trainable adapter maps its "
      "pooled vector to the condition; false: they initialise the prior's encoder and train with it");
  }
  void dependencies(DependencyVisitor& d) override { d("model.text_encoder", run_dir, config, overrides); }
  bool enabled() const { return !run_dir.empty() || !config.empty(); }
  bool omitted_from_dump() const override { return !enabled(); }
  std::string validate() const override {
    if (!enabled() && (!frozen || !overrides.empty()))
      return "frozen/overrides need text_encoder.config (a text_clip training config) or text_encoder.run_dir";
    return "";
  }
};

}  // namespace mc
