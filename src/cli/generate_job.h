// The `motionctl generate` job config (marker key `generator:`): data split,
// generator, protocol, the user's own constraints, output file.
#pragma once
#include <string>

#include "core/config.h"
#include "core/run_dir.h"

namespace mc {

struct GenerateDataConfig : Config {
  std::string path = "data/fixture_smoke.h5";
  std::string fixture = "configs/data/smoke.yaml";
  std::string split = "test";
  int num_samples = 8;
  void visit(FieldVisitor& v) override {
    v("path", path, "motion file the tasks' clips come from");
    v("fixture", fixture, "fixture config that builds `path` when it is missing ('' = must exist)");
    v("split", split, "split of `path` whose clips give the tasks", one_of({"train", "val", "test"}));
    v("num_samples", num_samples, "first N clips of the split (0 = all)", at_least(0));
  }
};

// A user's own control instead of the protocol's (docs/formats.md, "Your own
// constraints for generate"): the protocol still picks the clips (caption, length,
// source motion), these keys replace what the user gives.
struct GenerateCustomConfig : Config {
  std::string constraints;
  std::string caption;
  int length = 0;
  void visit(FieldVisitor& v) override {
    v("constraints", constraints,
      "constraint spec for every task (YAML or HDF5, docs/constraints.md), or a motion file whose /control group "
      "gives one spec per task ('' = the protocol's)");
    v("caption", caption, "text for every task ('' = each clip's)");
    v("length", length, "frames of every task (0 = each clip's, or the /control/frames of a per-task file)",
      at_least(0));
  }
};

struct GenerateJobConfig : Config {
  RunConfig run;
  GenerateDataConfig data;
  Component generator{"generator"};
  Component protocol{"protocol"};
  GenerateCustomConfig custom;
  std::string output = "samples/generated.h5";
  void visit(FieldVisitor& v) override {
    v("run", run, "seed, threads, device (run directories are not used)");
    v("data", data, "where the tasks come from");
    v("generator", generator, "the method (picked by type)");
    v("protocol", protocol, "the control tasks (picked by type)");
    v("custom", custom, "your own constraints, caption or length in place of the protocol's");
    v("output", output, "motion HDF5 file to write (atomically)");
  }
};

}  // namespace mc
