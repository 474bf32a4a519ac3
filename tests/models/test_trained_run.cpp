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
