// motionctl: the command-line entry point. Subcommands are thin: parse, call, print.
// Exit codes: 0 ok, 2 bad input (config, files, values; also a run directory in
// use or a diverged training), 1 internal error, 128 + signal when SIGINT/SIGTERM
// stopped a training after writing its checkpoint (130 for Ctrl-C).
#include <CLI/CLI.hpp>
#include <cstdlib>
#include <iostream>

#include "cli/commands.h"
#include "core/error.h"
#include "core/interrupt.h"

int main(int argc, char** argv) {
  // OpenMP threads spin while waiting by default; when the cores are shared
  // (CI, parallel builds, several runs) that turns a 6 it/s loop into 0.1 it/s.
  // Must be set before the first parallel region; a user's setting wins.
  ::setenv("OMP_WAIT_POLICY", "PASSIVE", 0);
  CLI::App app{"motionctl: spatially controlled human motion generation (ProjFlow, AnchorRoute)"};
  app.require_subcommand(1);
  mc::add_fixture_command(app);
  mc::add_train_command(app);
  mc::add_reproduce_command(app);
  mc::add_generate_command(app);
  mc::add_sweep_command(app);
  mc::add_ship_command(app);
  mc::add_config_command(app);
  mc::add_bench_command(app);
  mc::add_sample_command(app);
  mc::add_eval_commands(app);
  mc::add_health_command(app);
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    int code = app.exit(e);
    return code == 0 ? 0 : mc::kExitUserError;
  } catch (const mc::UserError& e) {
    std::cerr << "motionctl: error: " << e.what() << "\n";
    return mc::kExitUserError;
  } catch (const mc::Interrupted& e) {
    std::cerr << "motionctl: " << e.what() << "\n";
    return 128 + e.signal;
  } catch (const c10::Error& e) {
    std::cerr << "motionctl: internal torch error: " << e.what_without_backtrace() << "\n";
    return 1;
  } catch (const std::exception& e) {
    std::cerr << "motionctl: internal error: " << e.what() << "\n";
    return 1;
  }
  return 0;
}
