// `motionctl bench blas [--threads N]`: speed checks (more benchmarks join as the systems land).
#include <fstream>
#include <iostream>

#include "bench/bench.h"
#include "cli/commands.h"
#include "train/train_job.h"
#include "core/error.h"
#include "core/resources.h"
#include "data/skeleton.h"
#include "eval/evaluation.h"

#include <chrono>
#include <thread>

namespace mc {

void add_bench_command(CLI::App& app) {
  auto* cmd = app.add_subcommand("bench", "benchmarks");
  cmd->require_subcommand(1);
  auto* blas = cmd->add_subcommand("blas", "sgemm GFLOP/s of torch::mm (12544x256x256) at the configured threads");
  auto threads = std::make_shared<int>(0);
  blas->add_option("--threads", *threads, "torch threads (0 = all cores)")->check(CLI::NonNegativeNumber);
  blas->callback([threads] {
    check_thread_count(*threads, "--threads");
    BlasBenchResult r = bench_sgemm(*threads);
    LinkedBlas blas = linked_blas();
    double load = 0;
    std::ifstream("/proc/loadavg") >> load;
    std::cout << fmt::format("sgemm 12544x256x256: {:.1f} GFLOP/s at {} thread(s) ({:.2f} ms per call, {:.0f}% of "
                             "the CPU time those threads could use)\n",
                             r.gflops, r.threads, r.seconds_per_call * 1e3, 100 * r.cpu_share);
    for (auto& lib : blas.libraries) std::cout << "BLAS library: " << lib << "\n";
    if (!blas.openblas_config.empty()) std::cout << "OpenBLAS: " << blas.openblas_config << "\n";
    std::cout << fmt::format("load average {:.2f} on {} CPU(s)\n", load, usable_cpus());
    const std::string verdict = blas_verdict(r, blas, load, usable_cpus());
    std::cout << (verdict == "ok" ? std::string("verdict: ok") : "WARNING: " + verdict) << "\n";
  });

  auto* pf = cmd->add_subcommand("projflow", "ProjFlow vs unconstrained sampling time; structured vs dense solver");
  auto po = std::make_shared<ProjflowBenchOptions>();
  auto pthreads = std::make_shared<int>(0);
  pf->add_option("--depth", po->depth, "prior depth L (width 64 L; 8 = the paper's S)")->check(CLI::Range(1, 32));
  pf->add_option("--frames", po->frames, "frames per sample")->check(CLI::Range(8, 1000));
  pf->add_option("--samples", po->samples, "samples (one batch)")->check(CLI::Range(1, 256));
  pf->add_option("--steps", po->steps, "Euler steps")->check(CLI::Range(1, 1000));
  pf->add_option("--keyframe-every", po->keyframe_every, "hard keyframes on all joints every N frames")
      ->check(CLI::Range(1, 1000));
  pf->add_option("--dense-frames", po->dense_frames, "clip lengths of the dense-vs-structured solver comparison");
  pf->add_option("--dno-steps", po->dno_steps, "DNO optimisation steps to time (0 = skip)")->check(CLI::Range(0, 10000));
  pf->add_option("--threads", *pthreads, "torch threads (0 = all cores)")->check(CLI::NonNegativeNumber);
  auto no_inequalities = std::make_shared<bool>(false);
  pf->add_flag("--no-inequalities", *no_inequalities, "skip the inequality-projection timings");
  pf->add_flag("--inequalities-only", po->inequalities_only,
               "only the inequality-projection timings (floor under the toes, pelvis speed limit)");
  pf->callback([po, pthreads, no_inequalities] {
    po->inequalities = !*no_inequalities;
    torch::set_num_threads(*pthreads > 0 ? *pthreads : static_cast<int>(std::max(1u, std::thread::hardware_concurrency())));
    bench_projflow(*po, std::cout);
  });

  auto* ar = cmd->add_subcommand("anchorroute", "AnchorRoute (Table VII): generator-only time per sample, "
                                                "RS100/RS200/RS500 cost ratios, generator vs decoder split");
  auto ao = std::make_shared<AnchorrouteBenchOptions>();
  auto athreads = std::make_shared<int>(1);
  ar->add_option("--generator", ao->generator, "anchorroute generator file (its adapter is trained or installed "
                                               "from pretrained/ on first use)");
  ar->add_option("--set", ao->overrides, "generator.* overrides, e.g. generator.sampler.steps=20");
  ar->add_option("--protocol", ao->protocol, "protocol file of the tasks");
  ar->add_option("--data", ao->data, "motion file whose first test clips give the tasks");
  ar->add_option("--samples", ao->samples, "tasks (first test clips)")->check(CLI::Range(1, 10000));
  ar->add_option("--route-steps", ao->route_steps, "RouteSolver step counts")->check(CLI::Range(1, 100000));
  ar->add_option("--repeats", ao->repeats, "runs per row; the fastest counts")->check(CLI::Range(1, 100));
  ar->add_option("--threads", *athreads, "torch threads (0 = all cores; default 1 as the tables)")
      ->check(CLI::NonNegativeNumber);
  ar->callback([ao, athreads] {
    torch::set_num_threads(*athreads > 0 ? *athreads
                                         : static_cast<int>(std::max(1u, std::thread::hardware_concurrency())));
    bench_anchorroute(*ao, std::cout);
  });

  auto* tr = cmd->add_subcommand("train", "one training step: time, FLOPs, FLOP rate as a fraction of sgemm's; "
                                          "whole-clip configs also padded to t_max (the cost of padding)");
  auto to = std::make_shared<TrainBenchOptions>();
  tr->add_option("config", to->config, "training config, e.g. configs/prior/flow_standard.yaml")->required();
  tr->add_option("overrides", to->overrides, "key=value overrides of the config");
  tr->add_option("--steps", to->steps, "timed steps")->check(CLI::Range(1, 100000));
  tr->add_option("--warmup", to->warmup, "untimed steps first")->check(CLI::Range(0, 100000));
  tr->add_option("--threads", to->threads, "torch threads (0 = the config's run.threads)")->check(CLI::NonNegativeNumber);
  tr->add_flag("!--no-padded", to->compare_padded, "skip the padded comparison");
  tr->callback([to] { bench_train(*to, std::cout); });

  auto* dd = cmd->add_subcommand("ddp", "data-parallel scaling: 1 process x all threads vs N processes x threads / N "
                                        "on the same global batch (all-reduce overlapped with backward and after "
                                        "it), and the all-reduce of every gradient alone");
  auto dopt = std::make_shared<DdpBenchOptions>();
  dd->add_option("config", dopt->config, "training config, e.g. configs/prior/flow_s.yaml")->required();
  dd->add_option("overrides", dopt->overrides, "key=value overrides of the config");
  dd->add_option("--nproc", dopt->nproc, "data-parallel processes")->check(CLI::Range(2, 64));
  dd->add_option("--threads", dopt->threads, "threads in all (0 = the config's run.threads)")
      ->check(CLI::NonNegativeNumber);
  dd->add_option("--steps", dopt->steps, "timed steps per setup")->check(CLI::Range(1, 100000));
  dd->add_option("--warmup", dopt->warmup, "untimed steps first")->check(CLI::Range(0, 100000));
  dd->add_option("--bucket-mb", dopt->bucket_mb, "gradient bucket size in MiB")->check(CLI::Range(0.001, 1e5));
  dd->add_flag("--worker", dopt->worker)->group("");  // internal: one of the ranks
  dd->add_option("--report", dopt->report)->group("");
  dd->callback([dopt] { bench_ddp(*dopt, std::cout); });

  auto* ev = cmd->add_subcommand("eval", "time to evaluate N motions (embedding + every metric, one replication)");
  struct EvalArgs {
    std::string evaluator = "configs/eval/evaluator_smoke.yaml";
    std::string data = "data/fixture_smoke.h5";
    int count = 1000;
    int threads = 0;
  };
  auto ea = std::make_shared<EvalArgs>();
  ev->add_option("--evaluator", ea->evaluator, "evaluator training config (trained if missing)");
  ev->add_option("--data", ea->data, "motion file whose clips are tiled up to --count motions");
  ev->add_option("--count", ea->count, "motions to evaluate")->check(CLI::PositiveNumber);
  ev->add_option("--threads", ea->threads, "torch threads (0 = all cores)")->check(CLI::NonNegativeNumber);
  ev->callback([ea] {
    TrainResult r = run_train(resolve_data_path(ea->evaluator), {});
    T2MEvaluator evaluator = T2MEvaluator::load(r.run_dir.string());
    torch::set_num_threads(ea->threads > 0 ? ea->threads : static_cast<int>(std::max(1u, std::thread::hardware_concurrency())));
    MotionSet all = read_motion_file(resolve_data_path(ea->data));
    std::vector<size_t> idx;
    for (int i = 0; i < ea->count; ++i) idx.push_back(i % all.size());
    MotionSet motions = all.subset(idx);
    MotionSet reference = all.subset(all.indices_of_split("test"));
    auto t0 = std::chrono::steady_clock::now();
    EvalEmbeddings e = embed_for_eval(evaluator, reference, ea->data, motions, ea->data);
    auto t1 = std::chrono::steady_clock::now();
    EvalProtocol p;
    auto m = t2m_metrics(e, p, 0);
    auto free = evaluator_free_metrics(motions, ea->data, p, "", nullptr);
    auto t2 = std::chrono::steady_clock::now();
    double embed_s = std::chrono::duration<double>(t1 - t0).count();
    double metric_s = std::chrono::duration<double>(t2 - t1).count();
    std::cout << fmt::format(
        "evaluate {} motions (+{} reference) at {} thread(s): {:.2f} s total = {:.2f} s embedding + {:.3f} s metrics\n",
        ea->count, reference.size(), torch::get_num_threads(), embed_s + metric_s, embed_s, metric_s);
  });
}

}  // namespace mc
