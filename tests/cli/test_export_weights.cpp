// `motionctl export --format weights --probe` on flow priors of every architecture
// switch the shipped runs do not cover (tests/tools/test_flow_reference.py checks the
// shipped ones): clean prediction, a temporal kernel, the pretrained text encoder's
// adapter, the kinematic head with and without its source noise. tools/flow_reference.py must reproduce each probe to 1e-4.
#include <catch2/catch.hpp>

#include "core/atomic_file.h"
#include "models/flow_prior_test_util.h"
#include "test_util.h"

using namespace mc;
using namespace mc::test;

TEST_CASE("export --format weights: the numpy reference reproduces every architecture switch",
          "[cli][export_weights]") {
  TempDir dir("export_weights");
  const std::vector<std::pair<std::string, std::string>> variants = {
      {"clean_kernel3", "  prediction: clean\n  loss: clean\n  temporal_kernel: 3\n"},
      {"text_adapter", "  text_encoder:\n    run_dir: runs/text/absent\n"},
      {"kinematic_head", "  prediction: clean\n  kinematic_head:\n    enabled: true\n"},
      {"kinematic_noise", "  prediction: clean\n  kinematic_head:\n    enabled: true\n    noise:\n      enabled: true\n"},
  };
  for (const auto& [name, extra] : variants) {
    INFO(name);
    const fs::path run = dir.path / name;
    write_random_prior_run(run, 40, "flow_prior", kPriorWords, extra);
    write_file_atomic(run / "DONE", "");
    const std::string out = (dir.path / (name + ".h5")).string();
    auto e = run_motionctl(fmt::format("export --format weights '{}' --out '{}' --probe --probe-caption 'a person "
                                       "walks forward' --probe-caption 'jumps' --probe-caption 'an unknown word'",
                                       run.string(), out));
    INFO(e.output);
    REQUIRE(e.exit_code == 0);
    CHECK(e.output.find("/probe holds the C++ output") != std::string::npos);
    auto c = run_shell(fmt::format("cd '{}' && '{}' tools/flow_reference.py check '{}' 2>&1", MOTIONCTL_SOURCE_DIR,
                                     MOTIONCTL_PYTHON, out));
    INFO(c.output);
    CHECK(c.exit_code == 0);
    CHECK(c.output.find("OK: largest difference") != std::string::npos);
    // The reference samples from the file alone (its own noise, with the head's channel noise where set).
    const std::string npy = (dir.path / (name + ".npy")).string();
    auto sm = run_shell(fmt::format("cd '{}' && '{}' tools/flow_reference.py sample '{}' --caption 'a person walks' "
                                    "--length 12 --steps 3 --out '{}' 2>&1",
                                    MOTIONCTL_SOURCE_DIR, MOTIONCTL_PYTHON, out, npy));
    INFO(sm.output);
    CHECK(sm.exit_code == 0);
    CHECK(fs::exists(npy));
  }
}
