// `generator: {type: vq_reconstruction}`: each task's ground-truth clip encoded to
// tokens and decoded again by a VQ tokenizer. What the token priors can at best
// produce; the prior health check scores a tokenizer run through it.
#include <chrono>

#include "core/error.h"
#include "core/trained_runs.h"
#include "models/token_prior.h"
#include "models/vq_tokenizer.h"
#include "samplers/motion_generator.h"

namespace mc {
namespace {

class VqReconstructionGenerator : public MotionGenerator {
 public:
  explicit VqReconstructionGenerator(LoadedVqTokenizer tok) : tok_(std::move(tok)) {}

  GeneratedMotions generate(const std::vector<ControlTask>& tasks, uint64_t) override {
    torch::NoGradGuard ng;
    auto t0 = std::chrono::steady_clock::now();
    const int64_t J = tok_.skeleton.num_joints(), stride = tok_.model->stride();
    const torch::Device device = tok_.model->joint_mean.device();
    int T = 0;
    for (const auto& t : tasks) T = std::max(T, t.length);
    GeneratedMotions g;
    g.world = torch::zeros({static_cast<int64_t>(tasks.size()), T, J, 3});
    for (size_t i = 0; i < tasks.size(); ++i) {
      const ControlTask& t = tasks[i];
      if (t.length < 1 || t.source.size() != static_cast<size_t>(t.length) * J * 3)
        fail("task '{}' carries no ground-truth clip of {} frames x {} joints; vq_reconstruction encodes that clip",
             t.id, t.length, J);
      // One clip at a time, padded to whole tokens (padding zeroed as in training):
      // its reconstruction depends on neither the batch nor the other clips.
      const int64_t L = (t.length + stride - 1) / stride, Tp = L * stride;
      auto world = torch::zeros({1, Tp, J, 3});
      world[0].narrow(0, 0, t.length).copy_(
          torch::from_blob(const_cast<float*>(t.source.data()), {t.length, J, 3}, torch::kFloat));
      auto mask = torch::zeros({1, Tp}, torch::kBool);
      mask[0].narrow(0, 0, t.length).fill_(true);
      auto x = tok_.model->normalize(world.to(device)).flatten(2);
      auto ids = tok_.model->encode(x, mask.to(device));
      auto rec = tok_.model->denormalize(tok_.model->decode(ids).view({Tp, J, 3})).to(torch::kCPU, torch::kFloat);
      g.world[static_cast<int64_t>(i)].narrow(0, 0, t.length).copy_(rec.narrow(0, 0, t.length));
      g.lengths.push_back(t.length);
    }
    g.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    return g;
  }
  std::string describe() const override {
    return fmt::format("VQ tokenizer {} reconstructions of the tasks' clips (codebook {}, stride {})", tok_.run_dir,
                       tok_.model->codebook_size(), tok_.model->stride());
  }

 private:
  LoadedVqTokenizer tok_;
};

struct VqReconstructionConfig : GeneratorConfig, DeclaresDependencies {
  std::string tokenizer_run;
  std::string tokenizer_config = "configs/tokenizer/vq_tiny.yaml";
  std::vector<std::string> tokenizer_overrides;
  void visit(FieldVisitor& v) override {
    v("tokenizer_run", tokenizer_run, "finished vq_tokenizer run ('' = train tokenizer_config on demand)");
    v("tokenizer_config", tokenizer_config, "tokenizer training config run on demand when tokenizer_run is ''");
    v("tokenizer_overrides", tokenizer_overrides, "key=value overrides for tokenizer_config");
  }
  void dependencies(DependencyVisitor& d) override {
    d("tokenizer", tokenizer_run, tokenizer_config, tokenizer_overrides);
  }
  std::unique_ptr<MotionGenerator> make(const GeneratorContext& ctx) const override {
    std::string dir = tokenizer_run;
    if (dir.empty()) {
      if (tokenizer_config.empty()) fail("generator vq_reconstruction: set tokenizer_run or tokenizer_config");
      dir = trained_run("tokenizer", tokenizer_run, tokenizer_config, tokenizer_overrides);
    }
    return std::make_unique<VqReconstructionGenerator>(load_vq_tokenizer(dir, ctx.device));
  }
};

}  // namespace

MC_REGISTER_GENERATOR("vq_reconstruction", VqReconstructionConfig,
                      "a VQ tokenizer's reconstruction of each task's ground-truth clip (its quality ceiling)");

}  // namespace mc
