// `motionctl bench anchorroute`: Table VII's costs in one run — AnchorRoute's
// generator-only time per sample, RS100/RS200/RS500 relative to it, and the split of
// the generator into transformer calls (TMD + adapter, CFG) and token decoding, beside a
// RouteSolver step (a decoder forward + backward) in the same units, which is what sets
// the ratios.
#include <chrono>
#include <cmath>
#include <filesystem>
#include <iostream>

#include "bench/bench.h"
#include "control/anchors.h"
#include "control/control_task.h"
#include "core/error.h"
#include "core/trained_runs.h"
#include "data/fixture/fixture_build.h"
#include "data/motion_set.h"
#include "data/skeleton.h"
#include "models/anchor_adapters.h"
#include "models/token_prior.h"
#include "control/anchor_loss.h"
#include "samplers/anchorroute_generator.h"
#include "samplers/motion_generator.h"
#include "samplers/tmd_sampler.h"
#include "train/dependencies.h"

namespace mc {

namespace {
using Clock = std::chrono::steady_clock;
double seconds_since(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }
}  // namespace

void bench_anchorroute(const AnchorrouteBenchOptions& o, std::ostream& out) {
  // Tasks: the main protocol on the first test clips of the smoke fixture.
  std::string data_path = resolve_data_path(o.data);
  if (!std::filesystem::exists(data_path)) {
    build_fixture(resolve_data_path(o.fixture), {fmt::format("output={}", o.data)}, false);
    data_path = resolve_data_path(o.data);
  }
  MotionSet data = read_motion_file(data_path);
  auto clips = data.indices_of_split("test");
  if (clips.empty()) fail("bench anchorroute: '{}' has no test clips", o.data);
  if (static_cast<size_t>(o.samples) < clips.size()) clips.resize(o.samples);
  Component proto("protocol");
  parse_component_file(resolve_data_path(o.protocol), "protocol", {}, {}, proto);
  auto tasks = dynamic_cast<const ControlProtocol&>(*proto.cfg).make_tasks(data, clips, 1);
  const int64_t N = tasks.size();

  // The generator at each RouteSolver step count (the adapter is trained or installed once).
  auto config = [&](int steps) {
    Component g("generator");
    auto ov = o.overrides;
    ov.push_back(fmt::format("generator.route.steps={}", steps));
    parse_component_file(resolve_data_path(o.generator), "generator", {}, ov, g);
    return g;
  };
  Component c0 = config(0);
  const auto* arc = dynamic_cast<const AnchorRouteGeneratorConfig*>(c0.cfg.get());
  if (!arc) fail("bench anchorroute: '{}' is a '{}' generator; give an anchorroute one", o.generator, c0.type);
  resolve_dependencies(c0);
  auto gen0 = as_generator(c0).make({});
  out << fmt::format("AnchorRoute bench: {} tasks ({}), {} torch thread(s)\n  {}\n", N, o.protocol,
                     torch::get_num_threads(), gen0->describe());
  gen0->generate({tasks.front()}, 1);  // warm-up (allocator, threads)

  std::vector<int> counts = {0};
  for (int k : o.route_steps) counts.push_back(k);
  std::vector<double> secs, errs;
  std::vector<AnchorSet> sets;
  for (auto& t : tasks) sets.push_back(anchors_from_spec(t.spec, t.length, data.skeleton, t.source.data()));
  for (int k : counts) {
    std::unique_ptr<MotionGenerator> gen;
    if (k == 0) {
      gen = std::move(gen0);
    } else {
      Component ck = config(k);
      resolve_dependencies(ck);
      gen = as_generator(ck).make({});
    }
    double best = 1e300;
    GeneratedMotions g;
    for (int r = 0; r < o.repeats; ++r) {
      g = gen->generate(tasks, 1);
      best = std::min(best, g.seconds);
    }
    secs.push_back(best);
    errs.push_back(mean_control_error(g.world, make_anchor_batch(sets)).item<double>());
  }

  // The generator's split, timed on its first batch with the same components: one CFG
  // network call (adapter hooks + TMD, both passes) at the sampler's batch, and decoding.
  std::string adapter_run = arc->adapter_run;
  if (adapter_run.empty() && !arc->adapter_config.empty())
    adapter_run = trained_run("adapter", arc->adapter_run, arc->adapter_config, arc->adapter_overrides);
  const TmdSamplerConfig& sc = arc->sampler;
  const int64_t batch = std::min<int64_t>(N, sc.batch_size);
  double net_call = 0, decode = 0;
  if (!adapter_run.empty()) {
    auto a = load_anchor_adapter(adapter_run);
    const int64_t s = a.prior->stride();
    int64_t L = 1;
    std::vector<std::string> caps;
    for (int64_t i = 0; i < batch; ++i) {
      L = std::max<int64_t>(L, (tasks[i].length + s - 1) / s);
      caps.push_back(tasks[i].caption);
    }
    auto feats = torch::zeros({batch, L * s, adapter_feature_width(a.cfg.body_joints, a.cfg.features)});
    auto valid = torch::zeros({batch, L}, torch::kBool);
    for (int64_t i = 0; i < batch; ++i) {
      feats[i].narrow(0, 0, sets[i].frames).copy_(adapter_features(sets[i], a.cfg.body_joints, a.cfg.features));
      valid[i].narrow(0, 0, (tasks[i].length + s - 1) / s).fill_(true);
    }
    torch::NoGradGuard ng;
    auto ids = torch::randint(0, a.prior->codebook_size(), {batch, L}, torch::kInt64);
    auto text = a.prior->encode_texts(caps);
    auto t = torch::full({batch}, 0.5);
    const int reps = 5;
    for (int r = 0; r <= reps; ++r) {
      auto t0 = Clock::now();
      auto f = feats;
      if (a.cfg.features.feedback.enabled) {  // the feedback estimate is part of every call's cost
        f = feats.clone();
        std::vector<AnchorSet> bs(sets.begin(), sets.begin() + batch);
        fill_feedback_features(f, bs, frozen_soft_estimate(*a.prior, ids, t, text, valid), a.prior->skeleton(),
                               a.cfg.body_joints, a.cfg.features);
      }
      AdapterInputs in{ids, t, text, valid, f};
      auto h = a.module->guided_hooks(in, a.prior->null_texts(batch, text.memory.size(1)));
      h.guidance = arc->guidance.hooks();
      a.prior->guided_logits(ids, t, text, valid, sc.cfg_scale, &h);
      if (r > 0) net_call += seconds_since(t0) / reps;  // the first call warms up
    }
    auto t0 = Clock::now();
    for (int64_t i = 0; i < batch; ++i) a.prior->decode_world(ids[i].narrow(0, 0, (tasks[i].length + s - 1) / s));
    decode = seconds_since(t0);
  }

  const double g = secs[0];
  out << fmt::format("  {:<16} {:>10} {:>12} {:>8} {:>14}\n", "", "seconds", "s/sample", "cost", "control error");
  for (size_t i = 0; i < counts.size(); ++i)
    out << fmt::format("  {:<16} {:>10.3f} {:>12.4f} {:>7.2f}x {:>12.4f} m\n",
                       counts[i] == 0 ? std::string("generator only") : fmt::format("RS{}", counts[i]), secs[i],
                       secs[i] / N, secs[i] / g, errs[i]);
  const double batches = std::ceil(static_cast<double>(N) / batch);
  if (net_call > 0) {
    const double net_total = net_call * sc.steps * batches, dec_total = decode * batches;
    out << fmt::format(
        "  generator split: {} batch(es) of {} x {} steps x {:.4f} s per CFG call (adapter + TMD, both passes) = "
        "{:.3f} s network, {:.4f} s token decoding; of the measured {:.3f} s: {:.0f}% network, {:.0f}% decoding, "
        "the rest transitions and bookkeeping\n",
        batches, batch, sc.steps, net_call, net_total, dec_total, g, 100 * net_total / g, 100 * dec_total / g);
  }
  if (counts.size() > 1) {
    const size_t last = counts.size() - 1;
    const double step = (secs[last] - g) / counts[last];
    out << fmt::format("  RouteSolver step (decoder forward + backward over all {} motions): {:.4f} s, so 100 steps "
                       "cost {:.2f}x the generator",
                       N, step, 100 * step / g);
    if (decode > 0) out << fmt::format("; one step = {:.1f}x decoding the tokens", step / (decode * batches));
    if (net_call > 0) out << fmt::format(" = {:.2f}x one CFG network call", step / (net_call * batches));
    out << fmt::format(
        "\n  RSk / generator = 1 + k x step / generator: the ratios follow the price of the decoder against the "
        "{}-step transformer, so a bigger transformer or fewer decoder FLOPs shrink them\n",
        sc.steps);
  }
}

}  // namespace mc
