// T2M-style evaluator: networks, contrastive training objective (registered as
// model type `t2m_evaluator`) and the loader that embeds texts and motions.
#include "eval/t2m_evaluator.h"

#include "models/sharded_dropout.h"

#include <yaml-cpp/yaml.h>

#include <filesystem>
#include <fstream>

#include "core/atomic_file.h"
#include "core/error.h"
#include "data/features.h"
#include "data/normalizer.h"
#include "eval/metrics.h"
#include "models/trainable.h"
#include "models/trained_run.h"

namespace mc {
namespace fs = std::filesystem;
namespace nn = torch::nn;

namespace {

nn::Sequential embedding_head(int in, int hidden, int out) {
  return nn::Sequential(nn::Linear(in, hidden), nn::LayerNorm(nn::LayerNormOptions({hidden})),
                        nn::LeakyReLU(nn::LeakyReLUOptions().negative_slope(0.2)), nn::Linear(hidden, out));
}

// Final hidden states of a bidirectional GRU over a padded batch -> [B, 2H].
torch::Tensor bigru_last(nn::GRU& gru, const torch::Tensor& x, const torch::Tensor& lengths) {
  auto packed = nn::utils::rnn::pack_padded_sequence(x, lengths.to(torch::kCPU), /*batch_first=*/true,
                                                      /*enforce_sorted=*/false);
  auto out = gru->forward_with_packed_input(packed);
  auto h = std::get<1>(out);  // [2, B, H]
  return torch::cat({h[0], h[1]}, -1);
}

struct TextEncoderImpl : nn::Module {
  TextEncoderImpl(int vocab, const T2MEvaluatorConfig& c) {
    embedding = register_module("embedding", nn::Embedding(nn::EmbeddingOptions(vocab, c.word_dim).padding_idx(0)));
    gru = register_module("gru", nn::GRU(nn::GRUOptions(c.word_dim, c.text_hidden).batch_first(true).bidirectional(true)));
    head = register_module("head", embedding_head(2 * c.text_hidden, c.text_hidden, c.embed_dim));
  }
  torch::Tensor forward(const torch::Tensor& ids, const torch::Tensor& lengths) {
    return head->forward(bigru_last(gru, embedding(ids), lengths));
  }
  nn::Embedding embedding{nullptr};
  nn::GRU gru{nullptr};
  nn::Sequential head{nullptr};
};
TORCH_MODULE(TextEncoder);

// Movement encoder (two stride-2 convs: time / 4) followed by a BiGRU, as T2M.
struct MotionEncoderImpl : nn::Module {
  MotionEncoderImpl(int feature_dim, const T2MEvaluatorConfig& c) : unit(c.unit_length) {
    movement = register_module(
        "movement",
        nn::Sequential(nn::Conv1d(nn::Conv1dOptions(feature_dim, c.movement_dim, 4).stride(2).padding(1)),
                       ShardedDropout(c.dropout), nn::LeakyReLU(nn::LeakyReLUOptions().negative_slope(0.2)),
                       nn::Conv1d(nn::Conv1dOptions(c.movement_dim, c.movement_dim, 4).stride(2).padding(1)),
                       ShardedDropout(c.dropout), nn::LeakyReLU(nn::LeakyReLUOptions().negative_slope(0.2))));
    gru = register_module("gru",
                          nn::GRU(nn::GRUOptions(c.movement_dim, c.motion_hidden).batch_first(true).bidirectional(true)));
    head = register_module("head", embedding_head(2 * c.motion_hidden, c.motion_hidden, c.embed_dim));
  }
  // feats [B, T, F] normalised, T a multiple of 4; lengths [B] in frames (multiples of unit_length).
  torch::Tensor forward(const torch::Tensor& feats, const torch::Tensor& lengths) {
    auto h = movement->forward(feats.transpose(1, 2)).transpose(1, 2);  // [B, T/4, C]
    auto steps = torch::clamp(torch::div(lengths, 4, "floor"), 1, h.size(1));
    return head->forward(bigru_last(gru, h, steps));
  }
  int unit;
  nn::Sequential movement{nullptr};
  nn::GRU gru{nullptr};
  nn::Sequential head{nullptr};
};
TORCH_MODULE(MotionEncoder);

}  // namespace

struct T2MEvaluatorNetImpl : nn::Module {
  T2MEvaluatorNetImpl(int vocab, int feature_dim, const T2MEvaluatorConfig& c) {
    text = register_module("text", TextEncoder(vocab, c));
    motion = register_module("motion", MotionEncoder(feature_dim, c));
    // The evaluator carries its own feature statistics so that it measures every
    // motion file with the same yardstick, whatever statistics that file holds.
    feature_mean = register_buffer("feature_mean", torch::zeros({feature_dim}));
    feature_std = register_buffer("feature_std", torch::ones({feature_dim}));
  }
  TextEncoder text{nullptr};
  MotionEncoder motion{nullptr};
  torch::Tensor feature_mean, feature_std;
};

namespace {

const char* kFeatureLayout = "mc67";

Eigen::MatrixXd to_eigen(const torch::Tensor& t2d) {
  auto t = t2d.to(torch::kFloat64).contiguous();
  Eigen::MatrixXd out(t.size(0), t.size(1));
  auto acc = t.accessor<double, 2>();
  for (int64_t i = 0; i < t.size(0); ++i)
    for (int64_t k = 0; k < t.size(1); ++k) out(i, k) = acc[i][k];
  return out;
}

struct EncodedTexts {
  torch::Tensor ids, lengths;
};

EncodedTexts encode_texts(const TextVocab& vocab, const std::vector<std::string>& captions, int max_words) {
  const int64_t B = captions.size();
  auto ids = torch::zeros({B, max_words}, torch::kInt64);
  auto lengths = torch::zeros({B}, torch::kInt64);
  for (int64_t b = 0; b < B; ++b) {
    auto e = vocab.encode(captions[b], max_words);
    for (int k = 0; k < max_words; ++k) ids[b][k] = e.ids[k];
    lengths[b] = std::max(1, e.length);
  }
  return {ids, lengths};
}

// Normalised feature windows [B, Tpad, F] of clips: `starts`/`takes` in feature frames.
// Tpad covers the longest take (at least `min_frames`).
torch::Tensor gather_windows(const FeatureSet& fs_, const std::vector<int64_t>& idx, const std::vector<int64_t>& starts,
                             const std::vector<int64_t>& takes, const torch::Tensor& mean, const torch::Tensor& std,
                             int64_t min_frames = 4) {
  int64_t T = min_frames;
  for (auto t : takes) T = std::max(T, (t + 3) / 4 * 4);
  const int64_t F = fs_.dim;
  auto out = torch::zeros({static_cast<int64_t>(idx.size()), T, F});
  for (size_t b = 0; b < idx.size(); ++b) {
    auto clip = torch::from_blob(const_cast<float*>(fs_.clip(idx[b])), {fs_.t_max, F}, torch::kFloat32);
    out[b].narrow(0, 0, takes[b]).copy_((clip.narrow(0, starts[b], takes[b]) - mean) / std);
  }
  return out;
}

class T2MEvaluatorTrainer : public Trainable {
 public:
  T2MEvaluatorTrainer(const T2MEvaluatorConfig& c, const TrainContext& ctx) : cfg_(c), ctx_(ctx) {
    const MotionSet& set = ctx.data->set();
    vocab_ = set.vocab.empty() ? TextVocab::build(set) : TextVocab(set.vocab, ctx.data->source());
    features_ = compute_features(set, kFeatureLayout);
    net_ = std::make_shared<T2MEvaluatorNetImpl>(vocab_.size(), features_.dim, c);
    NormStats stats = set.stats.value_or(NormStats{});
    if (stats.feature_layout != kFeatureLayout || static_cast<int>(stats.feature_mean.size()) != features_.dim)
      stats = compute_norm_stats(set);
    torch::NoGradGuard ng;
    net_->feature_mean.copy_(torch::tensor(stats.feature_mean));
    net_->feature_std.copy_(torch::tensor(stats.feature_std));
  }
  nn::Module& module() override { return *net_; }

  // Random caption and random unit-aligned crop per clip (T2M's loader), both
  // drawn from torch's generator so resume is exact. With a shard: every clip's
  // crop is drawn, the shard's rows are built, padded as the whole batch is.
  std::pair<torch::Tensor, torch::Tensor> sample_motions(const std::vector<int64_t>& idx, bool random_crop,
                                                         const BatchShard& shard = {}) {
    std::vector<int64_t> starts, takes;
    const int64_t unit = cfg_.unit_length;
    for (int64_t i : idx) {
      int64_t len = features_.lengths[i];
      int64_t take = std::max<int64_t>(unit, len / unit * unit);
      if (random_crop && take > 2 * unit && torch::randint(0, 3, {1}).item<int64_t>() == 0) take -= unit;
      take = std::min(take, len);
      int64_t start = random_crop && len > take ? torch::randint(0, len - take + 1, {1}).item<int64_t>() : 0;
      starts.push_back(start);
      takes.push_back(take);
    }
    int64_t T = 4;
    for (auto t : takes) T = std::max(T, (t + 3) / 4 * 4);
    auto x = gather_windows(features_, shard.local(idx), shard.local(starts), shard.local(takes), net_->feature_mean,
                            net_->feature_std, T);
    return {x, torch::tensor(shard.local(takes))};
  }

  // A data-parallel shard encodes its rows, gathers every rank's embeddings and
  // computes the whole batch's loss (rolled negatives cross shard boundaries;
  // train/batch_shard.h, replicated), so its gradient is the one-process gradient
  // through its own rows.
  LossOutput loss(const std::vector<int64_t>& idx, const BatchShard& shard) override {
    const std::vector<std::string> caps = ctx_.data->drawn_captions(idx);
    auto [x, lengths] = sample_motions(idx, true, shard);
    auto txt = encode_texts(vocab_, shard.local(caps), cfg_.max_words);
    const int64_t n = idx.size();
    auto t = shard.gather(net_->text->forward(txt.ids.to(ctx_.device), txt.lengths), n);
    auto m = shard.gather(net_->motion->forward(x.to(ctx_.device), lengths), n);
    // Margin contrastive loss (T2M): pull pairs together, push rolled pairs past the margin.
    auto d_pos = (t - m).norm(2, 1);
    auto d_neg = (t - m.roll(1, 0)).norm(2, 1);
    // A rolled pair with the same caption is not a negative (template captions repeat).
    auto valid = torch::ones({static_cast<int64_t>(idx.size())});
    for (size_t b = 0; b < idx.size(); ++b)
      if (caps[b] == caps[(b + idx.size() - 1) % idx.size()]) valid[b] = 0;
    valid = valid.to(ctx_.device);
    auto pos = d_pos.pow(2).mean();
    auto neg = (torch::clamp(cfg_.margin - d_neg, 0).pow(2) * valid).sum() / valid.sum().clamp_min(1);
    LossOutput out;
    out.loss = shard.replicated(pos + neg);
    out.parts = {{"pos_dist", shard.replicated(d_pos.mean().detach())},
                 {"neg_dist", shard.replicated(d_neg.mean().detach())}};
    return out;
  }
  bool shards_batches() const override { return true; }

  // Validation retrieval quality with the first caption of each clip (pools of 32).
  std::map<std::string, double> evaluate() override {
    torch::NoGradGuard ng;
    net_->eval();
    auto idx = ctx_.data->split("val");
    Embeddings text(idx.size(), cfg_.embed_dim), motion(idx.size(), cfg_.embed_dim);
    size_t s = 0;  // the chunk's first row
    for (const auto& chunk : chunked(idx, 64)) {
      const std::vector<std::string> caps = ctx_.data->first_captions(chunk);
      auto [x, lengths] = sample_motions(chunk, false);
      auto txt = encode_texts(vocab_, caps, cfg_.max_words);
      auto t = net_->text->forward(txt.ids, txt.lengths).to(torch::kFloat64).contiguous();
      auto m = net_->motion->forward(x, lengths).to(torch::kFloat64).contiguous();
      text.middleRows(s, chunk.size()) = to_eigen(t);
      motion.middleRows(s, chunk.size()) = to_eigen(m);
      s += chunk.size();
    }
    std::map<std::string, double> out{{"val_matching", matching_score(text, motion)}};
    if (idx.size() >= 32) {
      auto r = r_precision(text, motion, 32, 3);
      out["val_r_precision_top1"] = r[0];
      out["val_r_precision_top3"] = r[2];
    }
    return out;
  }

  void save_artifacts(const fs::path& outputs) override {
    std::string words;
    for (auto& w : vocab_.words()) words += w + "\n";
    write_file_atomic(outputs / "vocab.txt", words);
    YAML::Emitter e;
    e << YAML::BeginMap << YAML::Key << "feature_layout" << YAML::Value << kFeatureLayout << YAML::Key
      << "feature_dim" << YAML::Value << features_.dim << YAML::Key << "fps" << YAML::Value << ctx_.data->set().fps
      << YAML::Key << "skeleton" << YAML::Value << YAML::Literal << skeleton_to_yaml(ctx_.data->set().skeleton)
      << YAML::EndMap;
    write_file_atomic(outputs / "evaluator_meta.yaml", std::string(e.c_str()) + "\n");
  }

 private:
  T2MEvaluatorConfig cfg_;
  TrainContext ctx_;
  TextVocab vocab_{TextVocab::special_tokens()};
  FeatureSet features_;
  std::shared_ptr<T2MEvaluatorNetImpl> net_;
};

}  // namespace

MC_REGISTER_MODEL("t2m_evaluator", T2MEvaluatorConfig,
                  [](const Config& c, const TrainContext& ctx) -> std::unique_ptr<Trainable> {
                    return std::make_unique<T2MEvaluatorTrainer>(dynamic_cast<const T2MEvaluatorConfig&>(c), ctx);
                  },
                  "T2M-style text/motion evaluator (BiGRU encoders, margin contrastive loss)");

// ---------------------------------------------------------------- loading

T2MEvaluator T2MEvaluator::load(const std::string& run_dir) {
  TrainedRun run = open_trained_run(
      run_dir, {"evaluator", {"t2m_evaluator"}, {"vocab.txt", "evaluator_meta.yaml"},
                "train one with `motionctl train configs/eval/evaluator_smoke.yaml` (or point eval.evaluator at its "
                "training config)"});
  T2MEvaluator ev;
  ev.run_dir_ = run_dir;
  ev.cfg_ = run.model.as<T2MEvaluatorConfig>();
  ev.vocab_ = std::make_shared<TextVocab>(run.vocab_words(), run.output("vocab.txt").string());
  int feature_dim = 0;
  run.read_meta("evaluator_meta.yaml", [&](const YAML::Node& meta) {
    ev.fps_ = meta["fps"].as<double>();
    ev.skeleton_ = skeleton_from_yaml_text(meta["skeleton"].as<std::string>(), run_dir + "/outputs/evaluator_meta.yaml");
    feature_dim = meta["feature_dim"].as<int>();
  });
  ev.net_ = std::make_shared<T2MEvaluatorNetImpl>(ev.vocab_->size(), feature_dim, ev.cfg_);
  run.load_weights(*ev.net_);
  ev.net_->eval();
  return ev;
}

Eigen::MatrixXd T2MEvaluator::embed_texts(const std::vector<std::string>& captions) const {
  torch::NoGradGuard ng;
  Eigen::MatrixXd out(captions.size(), cfg_.embed_dim);
  for (size_t s = 0; s < captions.size(); s += 256) {
    std::vector<std::string> chunk(captions.begin() + s, captions.begin() + std::min(captions.size(), s + 256));
    auto txt = encode_texts(*vocab_, chunk, cfg_.max_words);
    out.middleRows(s, chunk.size()) = to_eigen(net_->text->forward(txt.ids, txt.lengths));
  }
  return out;
}

Eigen::MatrixXd T2MEvaluator::embed_motions(const MotionSet& m, const std::string& source) const {
  if (!(m.skeleton == skeleton_))
    fail("{}: skeleton '{}' differs from the evaluator's '{}' ({}); evaluate motions of the skeleton the evaluator "
         "was trained on",
         source, m.skeleton.name, skeleton_.name, run_dir_);
  if (std::abs(m.fps - fps_) > 1e-9)
    fail("{}: fps {} differs from the evaluator's {}; resample the motions to {} fps", source, m.fps, fps_, fps_);
  for (size_t i = 0; i < m.size(); ++i)
    if (m.lengths[i] < 2 * cfg_.unit_length + 1)
      fail("{}: clip {} ('{}') has {} frames; the evaluator needs at least {}", source, i, m.ids[i], m.lengths[i],
           2 * cfg_.unit_length + 1);
  torch::NoGradGuard ng;
  FeatureSet feats = compute_features(m, kFeatureLayout);
  Eigen::MatrixXd out(m.size(), cfg_.embed_dim);
  for (size_t s = 0; s < m.size(); s += 128) {
    std::vector<int64_t> idx, starts, takes;
    for (size_t i = s; i < std::min(m.size(), s + 128); ++i) {
      idx.push_back(i);
      starts.push_back(0);
      int64_t len = feats.lengths[i];
      takes.push_back(std::max<int64_t>(cfg_.unit_length, len / cfg_.unit_length * cfg_.unit_length));
    }
    auto x = gather_windows(feats, idx, starts, takes, net_->feature_mean, net_->feature_std);
    out.middleRows(s, idx.size()) = to_eigen(net_->motion->forward(x, torch::tensor(takes)));
  }
  return out;
}

}  // namespace mc
