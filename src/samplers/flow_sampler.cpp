// Loading a trained flow prior, guided velocities and the Euler sampler loop.
#include "samplers/flow_sampler.h"

#include <ATen/CPUGeneratorImpl.h>
#include <yaml-cpp/yaml.h>

#include <fstream>

#include "core/error.h"
#include "train/trainer.h"

namespace mc {

// ---------------------------------------------------------------- loading

FlowPrior FlowPrior::load(const std::string& run_dir, torch::Device device) {
  fs::path dir(run_dir);
  if (!fs::is_directory(dir))
    fail("flow prior run directory '{}' does not exist; train one with `motionctl train configs/prior/flow_tiny.yaml` "
         "or set prior.config to train it on demand",
         run_dir);
  fs::path final_pt = dir / "checkpoints" / "final.pt";
  for (const fs::path& p : {dir / "config.yaml", final_pt, dir / "outputs" / "vocab.txt",
                            dir / "outputs" / "prior_meta.yaml"})
    if (!fs::exists(p))
      fail("flow prior run '{}' is incomplete: '{}' is missing; finish it with `motionctl train "
           "{}/config.yaml` (or point at a finished flow_prior run)",
           run_dir, p.string(), run_dir);
  TrainJobConfig job;
  parse_config(compose_config((dir / "config.yaml").string()), job);
  if (job.model.type != "flow_prior")
    fail("'{}' is a run of model type '{}', not a flow prior (flow_prior)", run_dir, job.model.type);
  FlowPrior p;
  p.run_dir_ = run_dir;
  p.device_ = device;
  p.cfg_ = job.model.as<FlowPriorConfig>();
  std::vector<std::string> words;
  {
    std::ifstream f(dir / "outputs" / "vocab.txt");
    for (std::string w; std::getline(f, w);) words.push_back(w);
  }
  p.vocab_ = std::make_shared<TextVocab>(words, (dir / "outputs" / "vocab.txt").string());
  fs::path meta_path = dir / "outputs" / "prior_meta.yaml";
  try {
    YAML::Node meta = YAML::LoadFile(meta_path.string());
    p.fps_ = meta["fps"].as<double>();
    p.t_max_ = meta["t_max"].as<int>();
    p.data_path_ = meta["data"].as<std::string>("");
    p.skeleton_ = skeleton_from_yaml_text(meta["skeleton"].as<std::string>(), meta_path.string());
  } catch (const YAML::Exception& e) {
    fail("'{}' is corrupt: {}", meta_path.string(), e.what());
  }
  p.net_ = std::make_shared<FlowPriorNet>(p.vocab_->size(), p.skeleton_.num_joints(), p.cfg_);
  try {
    torch::serialize::InputArchive ar;
    ar.load_from(final_pt.string());
    (*p.net_)->load(ar);
  } catch (const std::exception&) {  // c10::Error, or torch::jit::ErrorReport on a damaged file
    fail("flow prior checkpoint '{}' is unreadable or does not match its config.yaml", final_pt.string());
  }
  (*p.net_)->to(device);
  (*p.net_)->eval();
  return p;
}

FlowPrior FlowPrior::untrained(const FlowPriorConfig& cfg, const Skeleton& skeleton, int t_max, uint64_t seed,
                               torch::Device device) {
  FlowPrior p;
  p.run_dir_ = "<untrained>";
  p.device_ = device;
  p.cfg_ = cfg;
  p.skeleton_ = skeleton;
  p.t_max_ = t_max;
  std::vector<std::string> words = TextVocab::special_tokens();
  for (const char* w : {"a", "person", "walks", "runs", "jumps", "forward", "waves", "left", "right", "hand"})
    words.push_back(w);
  p.vocab_ = std::make_shared<TextVocab>(words, "untrained prior");
  torch::manual_seed(seed);
  p.net_ = std::make_shared<FlowPriorNet>(p.vocab_->size(), skeleton.num_joints(), cfg);
  {
    torch::NoGradGuard ng;
    // AdaLN-Zero starts at the identity; small random weights everywhere give a
    // network that costs what a trained one costs and returns non-trivial velocities.
    for (auto& w : (*p.net_)->parameters()) w.normal_(0.0, 0.02);
    (*p.net_)->joint_mean.copy_(torch::tensor({0.0f, 0.9f, 0.0f}));
    (*p.net_)->joint_std.copy_(torch::tensor({0.5f, 0.6f, 0.8f}));
  }
  (*p.net_)->to(device);
  (*p.net_)->eval();
  return p;
}

// ---------------------------------------------------------------- velocity

torch::Tensor FlowPrior::encode_texts(const std::vector<std::string>& captions) const {
  torch::NoGradGuard ng;
  auto enc = encode_captions(*vocab_, captions, cfg_.max_words);
  return (*net_)->encode_text(enc.ids.to(device_), enc.lengths.to(device_));
}

torch::Tensor FlowPrior::null_texts(int64_t B) const { return (*net_)->null_condition(B).detach(); }

torch::Tensor FlowPrior::raw_velocity(const torch::Tensor& x, const torch::Tensor& t, const torch::Tensor& text,
                                      const torch::Tensor& mask) const {
  auto tt = t.to(x.device(), torch::kFloat32).reshape({-1}).expand({x.size(0)});
  return (*net_)->to_velocity((*net_)->transformer->forward(x, tt, text, mask).velocity, x, tt);
}

torch::Tensor FlowPrior::velocity(const torch::Tensor& x, const torch::Tensor& t, const torch::Tensor& text,
                                  const torch::Tensor& mask, double cfg_scale) const {
  torch::NoGradGuard ng;
  const int64_t B = x.size(0);
  auto tt = t.to(x.device(), torch::kFloat32).reshape({-1}).expand({B});
  auto v2 = raw_velocity(torch::cat({x, x}), torch::cat({tt, tt}), torch::cat({text, null_texts(B)}),
                         torch::cat({mask, mask}));
  auto vc = v2.narrow(0, 0, B), vu = v2.narrow(0, B, B);
  auto v = vu + cfg_scale * (vc - vu);
  // Only valid frames matter; padded rows are garbage by design but must not poison the check.
  auto valid = mask.to(torch::kBool).view({B, -1, 1, 1}).expand_as(v);
  if (!torch::isfinite(v.masked_select(valid)).all().item<bool>())
    fail("the flow prior '{}' produced a non-finite velocity (at t = {}); the checkpoint is broken or diverged — "
         "retrain it (lower optim.lr) before sampling",
         run_dir_, tt[0].item<double>());
  return v;
}

torch::Tensor FlowPrior::normalize(const torch::Tensor& world) const {
  auto& n = *net_;
  return (world - n->joint_mean.to(world.device())) / n->joint_std.to(world.device());
}

torch::Tensor FlowPrior::denormalize(const torch::Tensor& normed) const {
  auto& n = *net_;
  return normed * n->joint_std.to(normed.device()) + n->joint_mean.to(normed.device());
}

// ---------------------------------------------------------------- sampling

FlowSampleResult sample_flow(const FlowPrior& prior, const std::vector<std::string>& captions,
                             const std::vector<int>& lengths, const FlowSamplerConfig& cfg, uint64_t seed,
                             FlowStepper* stepper) {
  torch::NoGradGuard ng;
  const int64_t N = captions.size(), J = prior.num_joints();
  if (lengths.size() != captions.size())
    fail("{} captions but {} lengths; give one length per caption", captions.size(), lengths.size());
  int64_t T = 1;
  for (size_t i = 0; i < lengths.size(); ++i) {
    if (lengths[i] < 1 || lengths[i] > prior.t_max())
      fail("sample {} asks for {} frames; the prior '{}' was trained on clips of 1..{} frames", i, lengths[i],
           prior.run_dir(), prior.t_max());
    T = std::max<int64_t>(T, lengths[i]);
  }
  EulerStepper euler;
  FlowStepper& step_rule = stepper ? *stepper : euler;
  auto gen = at::make_generator<at::CPUGeneratorImpl>(seed);
  auto noise = torch::randn({N, T, J, 3}, gen, torch::TensorOptions());
  auto grid = torch::linspace(0.0, 1.0, cfg.steps + 1, torch::kFloat64);
  auto ga = grid.accessor<double, 1>();
  const auto dev = prior.device();

  FlowSampleResult out;
  out.world = torch::zeros({N, T, J, 3});
  out.lengths = lengths;
  for (int64_t s = 0; s < N; s += cfg.batch_size) {
    const int64_t B = std::min<int64_t>(cfg.batch_size, N - s);
    std::vector<std::string> caps(captions.begin() + s, captions.begin() + s + B);
    std::vector<int64_t> ids(B);
    auto mask = torch::zeros({B, T}, torch::kBool);
    for (int64_t b = 0; b < B; ++b) {
      ids[b] = s + b;
      mask[b].narrow(0, 0, lengths[s + b]).fill_(true);
    }
    mask = mask.to(dev);
    auto text = prior.encode_texts(caps);
    auto x = step_rule.begin(noise.narrow(0, s, B).to(dev), mask, ids);
    for (int k = 0; k < cfg.steps; ++k) {
      FlowStep st;
      st.index = k;
      st.steps = cfg.steps;
      st.t = ga[k];
      st.t_next = ga[k + 1];
      st.x = x;
      st.mask = mask;
      st.sample_ids = ids;
      st.generator = &gen;
      st.v = prior.velocity(x, torch::full({B}, st.t, torch::TensorOptions().device(dev)), text, mask, cfg.cfg_scale);
      x = step_rule.step(st);
    }
    auto world = prior.denormalize(x).to(torch::kCPU) * mask.to(torch::kCPU).view({B, T, 1, 1}).to(torch::kFloat32);
    if (!torch::isfinite(world).all().item<bool>())
      fail("sampling from '{}' produced non-finite joints (samples {}..{}); nothing was written", prior.run_dir(), s,
           s + B - 1);
    out.world.narrow(0, s, B).copy_(world);
  }
  return out;
}

MotionSet to_motion_set(const FlowPrior& prior, const FlowSampleResult& r, const std::vector<std::string>& captions,
                        const std::vector<std::string>& ids) {
  MotionSet m;
  m.skeleton = prior.skeleton();
  m.fps = prior.fps();
  m.t_max = prior.t_max();
  const int64_t N = r.lengths.size(), J = prior.num_joints(), T = r.world.size(1);
  auto full = torch::zeros({N, m.t_max, J, 3});
  full.narrow(1, 0, T).copy_(r.world);
  full = full.contiguous();
  m.joints.assign(full.data_ptr<float>(), full.data_ptr<float>() + full.numel());
  m.lengths = r.lengths;
  m.ids = ids;
  m.splits.assign(N, "sample");
  for (auto& c : captions) m.captions.push_back({c});
  NormStats st;
  auto mean = prior.net()->joint_mean.to(torch::kCPU).contiguous();
  auto sd = prior.net()->joint_std.to(torch::kCPU).contiguous();
  st.joint_mean.assign(mean.data_ptr<float>(), mean.data_ptr<float>() + 3);
  st.joint_std.assign(sd.data_ptr<float>(), sd.data_ptr<float>() + 3);
  m.stats = st;
  m.clear_padding();
  return m;
}

}  // namespace mc
