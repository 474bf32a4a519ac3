// `motionctl generate CONFIG [overrides]`: controlled generation from YAML. A
// `generator:` (ProjFlow, a baseline, AnchorRoute, ...) runs on the tasks a
// `protocol:` draws from a data split (or on the user's own constraints, `custom:`);
// writes the motions with each sample's constraint spec (/control) and prints the
// control errors, which `motionctl score FILE` recomputes from the file alone.
#include <algorithm>
#include <chrono>
#include <iostream>
#include <optional>

#include "cli/commands.h"
#include "train/dependencies.h"
#include "train/train_job.h"
#include "cli/generate_job.h"
#include "control/control_task.h"
#include "control/linear_observation.h"
#include "control/sample_constraints.h"
#include "core/error.h"
#include "core/job_memory.h"
#include "core/resources.h"
#include "core/run_dir.h"
#include "data/fixture/fixture_build.h"
#include "data/motion_set.h"
#include "data/motion_file_extra.h"
#include "data/skeleton.h"
#include "eval/metrics.h"
#include "eval/observation_errors.h"
#include "samplers/motion_generator.h"
#include "train/trainer.h"

namespace mc {
namespace {

// Replaces the protocol's constraints, captions or lengths by the user's (`custom:`).
void apply_custom(const GenerateCustomConfig& c, const std::string& file, int num_joints,
                  std::vector<ControlTask>& tasks) {
  std::vector<ConstraintSpec> per_task;
  std::vector<int> per_task_frames;
  std::optional<ConstraintSpec> shared;
  if (!c.constraints.empty()) {
    const std::string path = resolve_data_path(c.constraints);
    if (!fs::exists(path))
      fail("{}: custom.constraints '{}' does not exist; give a constraint spec (YAML or HDF5, docs/constraints.md) "
           "or a motion file with a /control group",
           file, c.constraints);
    const std::string ext = fs::path(path).extension().string();
    if (ext == ".h5" || ext == ".hdf5") {
      SampleConstraints sc = read_sample_constraints(path);
      per_task = std::move(sc.specs);
      per_task_frames = std::move(sc.frames);
    }
    if (per_task.empty()) {
      shared = load_constraint_spec(path);
    } else if (per_task.size() != tasks.size()) {
      fail("{}: custom.constraints '{}' holds {} per-task specs (/control) but the protocol drew {} tasks; set "
           "data.num_samples={} or give a spec file that applies to every task",
           file, c.constraints, per_task.size(), tasks.size(), per_task.size());
    }
  }
  for (size_t i = 0; i < tasks.size(); ++i) {
    ControlTask& t = tasks[i];
    if (shared) t.spec = *shared;
    if (!per_task.empty()) t.spec = per_task[i];
    if (!c.caption.empty()) t.caption = c.caption;
    int length = c.length > 0 ? c.length : (!per_task_frames.empty() ? per_task_frames[i] : t.length);
    if (length != t.length) {
      // The clip stays the source of from_source targets while it is long enough;
      // past its end there is no source, and compile() names the items that need one.
      if (length <= t.length && !t.source.empty())
        t.source.resize(static_cast<size_t>(length) * num_joints * 3);
      else
        t.source.clear();
      t.length = length;
    }
  }
}

// Refuses, before the generator trains or allocates anything, tasks whose generated
// motions cannot fit (core/job_memory.h): the sizes a user sets are the number of
// tasks (data.num_samples, capped by the split) and their frames (custom.length).
void check_generate_memory(const GenerateJobConfig& job, const std::string& file,
                           const std::vector<ControlTask>& tasks, int joints, int data_frames) {
  int frames = 0;
  for (const auto& t : tasks) frames = std::max(frames, t.length);
  const long double bytes = generated_motions_bytes(tasks.size(), frames, joints);
  const bool long_clips = job.custom.length > 0 && job.custom.length > data_frames;
  require_memory(
      bytes, fmt::format("{}: this generate job", file),
      fmt::format("{} tasks ({}) x {} frames ({}) x {} joints: float32 joints held 4 times while sampling",
                  tasks.size(), fmt::format("data.num_samples={}", job.data.num_samples), frames,
                  job.custom.length > 0 ? fmt::format("custom.length={}", job.custom.length) : "the clips' lengths",
                  joints),
      long_clips ? fmt::format("lower custom.length (the data's clips have at most {} frames)", data_frames)
                 : "lower data.num_samples");
}

void run_generate(const std::string& file, const std::vector<std::string>& overrides) {
  auto job = load_job<GenerateJobConfig>(file, overrides);
  RunsRootScope components_root(job.run.root);  // what the generator trains lives under run.root
  std::string data_path = resolve_data_path(job.data.path);
  if (!fs::exists(data_path)) {
    if (job.data.fixture.empty()) fail("{}: data.path '{}' does not exist", file, job.data.path);
    build_fixture(resolve_data_path(job.data.fixture), {fmt::format("output={}", job.data.path)}, false);
    data_path = resolve_data_path(job.data.path);
  }
  MotionSet data = read_motion_file(data_path);
  auto clips = data.indices_of_split(job.data.split);
  if (clips.empty()) fail("{}: split '{}' of '{}' is empty (data.split)", file, job.data.split, job.data.path);
  if (job.data.num_samples > 0 && static_cast<size_t>(job.data.num_samples) < clips.size())
    clips.resize(job.data.num_samples);
  const uint64_t seed = static_cast<uint64_t>(job.run.seed);
  std::vector<ControlTask> tasks = as_protocol(job.protocol).make_tasks(data, clips, seed);
  apply_custom(job.custom, file, data.num_joints(), tasks);
  check_generate_memory(job, file, tasks, data.num_joints(), data.t_max);

  GeneratorContext ctx;
  ctx.device = setup_torch(job.run);
  resolve_dependencies(job.generator);  // trains what the generator needs first
  auto gen = as_generator(job.generator).make(ctx);
  std::cerr << "generator: " << gen->describe() << "\n";
  GeneratedMotions g = gen->generate(tasks, seed);

  torch::Tensor w = g.world.to(torch::kCPU, torch::kFloat).contiguous();
  if (!torch::isfinite(w).all().item<bool>()) fail("the generator produced non-finite joints; nothing was written");
  MotionSet m;
  m.skeleton = data.skeleton;
  m.fps = data.fps;
  m.t_max = data.t_max;
  const int J = data.num_joints();
  m.joints.assign(tasks.size() * m.clip_stride(), 0.0f);
  std::vector<std::vector<double>> errors;
  std::vector<ConstraintSpec> stored;  // each sample's spec with its targets written out (/control)
  std::vector<int> stored_frames;
  double worst_hard = 0, worst_inequality = 0;
  std::vector<double> angles;  // direction items' angle errors, degrees
  bool any_inequality = false;
  for (size_t i = 0; i < tasks.size(); ++i) {
    const int len = std::min<int>(g.lengths.at(i), m.t_max);
    const float* src = w.data_ptr<float>() + i * w.size(1) * J * 3;
    std::copy(src, src + static_cast<size_t>(len) * J * 3, m.clip(i));
    m.lengths.push_back(len);
    m.ids.push_back(tasks[i].id);
    m.splits.push_back("sample");
    m.captions.push_back({tasks[i].caption});
    const float* source = tasks[i].source.empty() ? nullptr : tasks[i].source.data();
    stored.push_back(with_explicit_targets(tasks[i].spec, len, data.skeleton, source));
    stored_frames.push_back(len);
    if (tasks[i].spec.items.empty()) continue;
    LinearObservation obs = compile(tasks[i].spec, len, data.skeleton, source);
    errors.push_back(observation_entry_errors(obs, m.clip(i)));
    Eigen::VectorXd x(obs.dim());
    for (int k = 0; k < obs.dim(); ++k) x[k] = m.clip(i)[k];
    Eigen::VectorXd r = obs.A * x - obs.y;
    for (int k = 0; k < obs.rows(); ++k)
      if (obs.is_hard(k)) worst_hard = std::max(worst_hard, std::abs(r[k]));
    if (obs.inequalities() > 0) {
      any_inequality = true;
      Eigen::VectorXd v = obs.G * x - obs.h;
      for (int k = 0; k < obs.inequalities(); ++k)
        if (obs.is_hard_inequality(k)) worst_inequality = std::max(worst_inequality, v[k]);
    }
    auto a = direction_errors(obs, m.clip(i));
    angles.insert(angles.end(), a.begin(), a.end());
  }
  m.stats = data.stats;
  m.provenance = Provenance{"motionctl generate", MOTIONCTL_VERSION, job.run.seed, dump_config(job), utc_timestamp()};
  write_motion_file(job.output, m, [&](int64_t f) { write_sample_constraints(f, stored, stored_frames, job.output); });
  std::cout << fmt::format("wrote {} motions to {} ({:.2f} s/motion)\n", m.size(), job.output,
                           g.seconds / std::max<size_t>(1, m.size()));
  // Tasks with only inequality or direction items have no control entries.
  if (std::any_of(errors.begin(), errors.end(), [](const auto& e) { return !e.empty(); })) {
    ControlMetrics cm = control_metrics_from_errors(errors);
    std::cout << fmt::format("control: traj_err {:.4f}  loc_err {:.4f}  avg_err {:.6f} m  max hard residual {:.2e}\n",
                             cm.traj_err, cm.loc_err, cm.avg_err, worst_hard);
  }
  if (any_inequality)
    std::cout << fmt::format("inequalities: max hard violation {:.2e} (m, or m/frame for speed limits)\n",
                             worst_inequality);
  if (!angles.empty()) {
    double sum = 0;
    for (double a : angles) sum += a;
    std::cout << fmt::format("directions: mean angle error {:.2f} deg over {} frames\n", sum / angles.size(),
                             angles.size());
  }
}

}  // namespace

void add_generate_command(CLI::App& app) {
  auto* cmd = app.add_subcommand("generate", "controlled generation: a generator on a protocol's tasks");
  struct Args {
    std::string file;
    std::vector<std::string> overrides;
  };
  auto a = std::make_shared<Args>();
  cmd->add_option("config", a->file, "generate config, e.g. configs/control/keyframes_smoke.yaml")->required();
  cmd->add_option("overrides", a->overrides, "key.path=value overrides, e.g. data.num_samples=4 output=x.h5");
  cmd->callback([a] { run_generate(a->file, a->overrides); });
}

}  // namespace mc
