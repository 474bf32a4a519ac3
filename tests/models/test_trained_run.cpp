// Tests of the run-directory loader's helpers (models/trained_run.*): where a run's
// recorded dependency is found when the run tree sits under another runs root.
#include <catch2/catch.hpp>

#include "models/trained_run.h"
#include "test_util.h"

using namespace mc;
using namespace mc::test;

TEST_CASE("a run's recorded dependency is found beside it under its own runs root", "[trained_run]") {
  TempDir t("trained_run");
  const fs::path root = t.path / "elsewhere";
  fs::create_directories(root / "tmd" / "tmd_tiny-f3f834096820");
  TrainedRun run;
  run.dir = root / "tmd" / "tmd_tiny-f3f834096820";

  // Not installed beside it: the recorded path is kept, so a loader's error names it.
  CHECK(run.dependency("runs/tokenizer/vq_tiny") == "runs/tokenizer/vq_tiny");
  fs::create_directories(root / "tokenizer" / "vq_tiny");
  // Recorded relative to the root it was trained under, with or without a trailing
  // separator or dot segments: the copy beside it is the one used.
  for (std::string rec : {"runs/tokenizer/vq_tiny", "runs/tokenizer/vq_tiny/", "./runs/x/../tokenizer/vq_tiny",
                          "/some/old/root/tokenizer/vq_tiny"}) {
    INFO(rec);
    CHECK(fs::path(run.dependency(rec)) == root / "tokenizer" / "vq_tiny");
  }
  // Another component's name is not redirected.
  CHECK(run.dependency("runs/tokenizer/vq_standard") == "runs/tokenizer/vq_standard");
  // A bare name (no experiment folder) is not guessed at.
  CHECK(run.dependency("vq_tiny") == "vq_tiny");
}

TEST_CASE("half-precision weights load back as float32 holding the rounded values", "[trained_run]") {
  TempDir t("half_weights");
  torch::manual_seed(3);
  torch::nn::Linear a(7, 5);
  torch::nn::BatchNorm1d bn(5);  // parameters, float buffers and an integer one (num_batches_tracked)
  { torch::NoGradGuard ng; bn->running_mean.uniform_(-2, 2); bn->num_batches_tracked.fill_(17); }
  const torch::Tensor w = a->weight.detach().clone();
  const fs::path file = t.path / "w.pt";
  save_module_weights(*a, torch::kFloat16, file);
  CHECK(a->weight.scalar_type() == torch::kFloat32);  // the saved module is unchanged
  CHECK(torch::equal(a->weight, w));

  torch::nn::Linear b(7, 5);
  torch::serialize::InputArchive ar;
  ar.load_from(file.string());
  read_module_weights(ar, *b);
  CHECK(b->weight.scalar_type() == torch::kFloat32);
  CHECK(b->bias.scalar_type() == torch::kFloat32);
  CHECK(torch::equal(b->weight, w.to(torch::kFloat16).to(torch::kFloat32)));
  CHECK_FALSE(torch::equal(b->weight, w));  // rounding did happen (7x5 random floats)
  CHECK(b->weight.requires_grad());

  const fs::path file_bn = t.path / "bn.pt";
  save_module_weights(*bn, torch::kFloat16, file_bn);
  torch::nn::BatchNorm1d bn2(5);
  torch::serialize::InputArchive ar2;
  ar2.load_from(file_bn.string());
  read_module_weights(ar2, *bn2);
  CHECK(bn2->weight.scalar_type() == torch::kFloat32);
  CHECK(bn2->running_mean.scalar_type() == torch::kFloat32);
  CHECK(bn2->num_batches_tracked.scalar_type() == torch::kInt64);
  CHECK(bn2->num_batches_tracked.item<int64_t>() == 17);
  // Buffers are data the run derived, not weights: stored and loaded as they are.
  CHECK(torch::equal(bn2->running_mean, bn->running_mean));
  CHECK_FALSE(torch::equal(bn->running_mean, bn->running_mean.to(torch::kFloat16).to(torch::kFloat32)));
}

TEST_CASE("rounding weights to float16 is exact in place and refuses a weight out of its range", "[trained_run]") {
  torch::manual_seed(5);
  torch::nn::Linear a(4, 3);
  const torch::Tensor w = a->weight.detach().clone();
  round_module_weights(*a, torch::kFloat16, "test");
  CHECK(a->weight.scalar_type() == torch::kFloat32);
  CHECK(torch::equal(a->weight, w.to(torch::kFloat16).to(torch::kFloat32)));
  round_module_weights(*a, torch::kFloat32, "test");  // float32: nothing to do
  CHECK(torch::equal(a->weight, w.to(torch::kFloat16).to(torch::kFloat32)));
  {
    torch::NoGradGuard ng;
    a->bias[1] = 1.0e5;  // beyond float16's 65504
  }
  try {
    round_module_weights(*a, torch::kFloat16, "runs/x");
    FAIL("no error");
  } catch (const UserError& e) {
    const std::string m = e.what();
    CHECK(m.find("runs/x") != std::string::npos);
    CHECK(m.find("bias") != std::string::npos);
    CHECK(m.find("run.final_weights.dtype=float32") != std::string::npos);
  }
  CHECK(weights_dtype("float16") == torch::kFloat16);
  CHECK_THROWS_AS(weights_dtype("bfloat16"), UserError);
}
