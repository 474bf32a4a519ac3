// The flow prior's weights file (models/flow_weights.h): every parameter and buffer
// of the loaded bundle under its module path, bit for bit, with the attributes a
// loader needs; sealed; a non-finite weight is refused with no file written.
#include <H5Cpp.h>

#include <catch2/catch.hpp>

#include "core/h5_seal.h"
#include "models/flow_prior_test_util.h"
#include "models/flow_weights.h"
#include "models/kinematic_head.h"
#include "test_util.h"

using namespace mc;
using namespace mc::test;

namespace {

std::string string_attr(const H5::H5Object& o, const std::string& name) {
  H5::Attribute a = o.openAttribute(name);
  std::string s;
  a.read(a.getStrType(), s);
  return s;
}

}  // namespace

TEST_CASE("flow weights: every tensor of the bundle under its module path, bit for bit", "[flow_weights]") {
  TempDir dir("flow_weights");
  const fs::path run = dir.path / "prior";
  write_random_prior_run(run, 40, "flow_prior", kPriorWords, "  temporal_kernel: 3\n");
  FlowPrior prior = FlowPrior::load(run.string());
  const std::string out = (dir.path / "w.h5").string();
  FlowWeightsSource src{run.string(), "model: {}\n", "abc123"};
  FlowWeightsGroup extra;
  extra.name = "probe";
  extra.arrays = {{"mask", torch::tensor({true, false})}, {"ids", torch::tensor({int64_t{3}, int64_t{4}})}};
  write_flow_weights(prior, src, out, {extra});
  CHECK(check_h5_seal(out, "weights") == H5Seal::valid);

  auto tensors = flow_weight_tensors(prior);
  // Parameters, then the normaliser buffers; the temporal kernel's convolutions in place of embed/head.
  std::set<std::string> names;
  for (auto& [n, t] : tensors) names.insert(n);
  CHECK(names.count("transformer.embed_conv.weight") == 1);
  CHECK(names.count("transformer.head.weight") == 0);
  CHECK(names.count("text.encoder.layers.0.self_attn.in_proj_weight") == 1);
  CHECK(names.count("joint_mean") == 1);
  CHECK(names.count("joint_std") == 1);

  H5::H5File f(out, H5F_ACC_RDONLY);
  H5::Group w = f.openGroup("weights");
  CHECK(w.getNumObjs() == tensors.size());
  for (auto& [name, t] : tensors) {
    INFO(name);
    REQUIRE(w.nameExists(name));
    H5::DataSet ds = w.openDataSet(name);
    CHECK(ds.getDataType() == H5::PredType::IEEE_F32LE);
    std::vector<hsize_t> dims(ds.getSpace().getSimpleExtentNdims());
    ds.getSpace().getSimpleExtentDims(dims.data());
    CHECK(std::vector<int64_t>(dims.begin(), dims.end()) == t.sizes().vec());
    auto back = torch::empty(t.sizes(), torch::kFloat32);
    ds.read(back.data_ptr<float>(), H5::PredType::NATIVE_FLOAT);
    CHECK(torch::equal(back, t.contiguous()));
  }
  CHECK(string_attr(f, "format") == kFlowWeightsFormat);
  CHECK(string_attr(f, "config_hash") == "abc123");
  CHECK(string_attr(f, "config") == "model: {}\n");
  CHECK(string_attr(f, "model_config").find("temporal_kernel: 3") != std::string::npos);
  H5::Group m = f.openGroup("model");
  int64_t v = 0;
  m.openAttribute("temporal_kernel").read(H5::PredType::NATIVE_INT64, &v);
  CHECK(v == 3);
  m.openAttribute("mlp_hidden").read(H5::PredType::NATIVE_INT64, &v);
  CHECK(v == prior.net()->transformer->opt.resolved_mlp_hidden());
  CHECK(f.openDataSet("vocab").getSpace().getSimpleExtentNpoints() == static_cast<hssize_t>(kPriorWords.size()));
  CHECK(f.openDataSet("probe/mask").getDataType() == H5::PredType::STD_U8LE);
  CHECK(f.openDataSet("probe/ids").getDataType() == H5::PredType::STD_I64LE);

  SECTION("a non-finite weight is refused, naming it, and nothing is written") {
    {
      torch::NoGradGuard ng;
      prior.net()->transformer->final_ada->bias[0] = std::nanf("");
    }
    const std::string bad = (dir.path / "bad.h5").string();
    expect_user_error([&] { write_flow_weights(prior, src, bad); },
                      {"weight 'transformer.final_ada.bias' is not finite", "retrain"});
    CHECK_FALSE(fs::exists(bad));
  }
}

TEST_CASE("flow weights: a prior with the kinematic head describes it in /model and ships its statistics",
          "[flow_weights][kinematic]") {
  TempDir dir("flow_weights_kin");
  for (const bool noise : {false, true}) {
    INFO("kinematic noise " << noise);
    const fs::path run = dir.path / (noise ? "noise" : "head");
    write_random_prior_run(run, 40, "flow_prior", kPriorWords,
                           std::string("  prediction: clean\n  kinematic_head:\n    enabled: true\n") +
                               (noise ? "    noise:\n      enabled: true\n" : ""));
    FlowPrior prior = FlowPrior::load(run.string());
    const std::string out = (dir.path / (run.filename().string() + ".h5")).string();
    write_flow_weights(prior, {run.string(), "model: {}\n", "abc123"}, out);
    H5::H5File f(out, H5F_ACC_RDONLY);
    int64_t version = 0, head = -1, nz = -1, channels = 0;
    f.openAttribute("format_version").read(H5::PredType::NATIVE_INT64, &version);
    H5::Group m = f.openGroup("model");
    m.openAttribute("kinematic_head").read(H5::PredType::NATIVE_INT64, &head);
    m.openAttribute("kinematic_noise").read(H5::PredType::NATIVE_INT64, &nz);
    m.openAttribute("out_channels").read(H5::PredType::NATIVE_INT64, &channels);
    CHECK(version == 2);
    CHECK(head == 1);
    CHECK(nz == (noise ? 1 : 0));
    CHECK(channels == kinematic_channel_count(22));  // 5 + 3 * 21, not 22 * 3
    // The head's output layer has that many rows, and its de-z-scoring statistics are weights.
    H5::Group w = f.openGroup("weights");
    for (const char* name : {"transformer.head.weight", "kin_mean", "kin_std"}) {
      INFO(name);
      REQUIRE(w.nameExists(name));
      std::vector<hsize_t> dims(w.openDataSet(name).getSpace().getSimpleExtentNdims());
      w.openDataSet(name).getSpace().getSimpleExtentDims(dims.data());
      CHECK(dims[0] == static_cast<hsize_t>(channels));
    }
  }
  // A prior without the head says so too.
  const fs::path plain = dir.path / "plain";
  write_random_prior_run(plain, 40);
  const std::string out = (dir.path / "plain.h5").string();
  write_flow_weights(FlowPrior::load(plain.string()), {plain.string(), "model: {}\n", "abc123"}, out);
  H5::H5File f(out, H5F_ACC_RDONLY);
  int64_t head = -1, channels = 0;
  f.openGroup("model").openAttribute("kinematic_head").read(H5::PredType::NATIVE_INT64, &head);
  f.openGroup("model").openAttribute("out_channels").read(H5::PredType::NATIVE_INT64, &channels);
  CHECK(head == 0);
  CHECK(channels == 22 * 3);
  CHECK_FALSE(f.openGroup("weights").nameExists("kin_mean"));
}

TEST_CASE("flow weights: a prior with the head's skip or bones is refused, naming the key, and no file is left",
          "[flow_weights][kinematic]") {
  TempDir dir("flow_weights_skip");
  const std::vector<std::pair<std::string, std::string>> cases = {
      {"    skip:\n      enabled: true\n", "model.kinematic_head.skip.enabled"},
      {"    bones:\n      enabled: true\n      rigid: true\n", "model.kinematic_head.bones"}};
  for (size_t i = 0; i < cases.size(); ++i) {
    INFO(cases[i].second);
    const fs::path run = dir.path / ("run" + std::to_string(i));
    write_random_prior_run(run, 40, "flow_prior", kPriorWords,
                           "  prediction: clean\n  kinematic_head:\n    enabled: true\n" + cases[i].first);
    FlowPrior prior = FlowPrior::load(run.string());
    const std::string out = (dir.path / ("out" + std::to_string(i) + ".h5")).string();
    CHECK_THROWS_WITH(write_flow_weights(prior, {run.string(), "model: {}\n", "abc123"}, out),
                      Catch::Contains(cases[i].second));
    CHECK_FALSE(fs::exists(out));
  }
}
