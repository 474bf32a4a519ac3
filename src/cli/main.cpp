// motionctl: the command-line entry point. Subcommands are thin: parse, call, print.
// Exit codes: 0 ok, 2 bad input (config, files, values; also a run directory in
// use or a diverged training), 1 internal error, 128 + signal when SIGINT/SIGTERM
// stopped a training after writing its checkpoint (130 for Ctrl-C).
#include <CLI/CLI.hpp>
#include <unistd.h>

#include <cstdlib>
#include <new>
#include <string>
#include <iostream>

#include "cli/commands.h"
#include "core/error.h"
#include "core/interrupt.h"
#include "core/process_env.h"
#include "core/resources.h"
#include "train/distributed.h"

// OpenMP threads spin while waiting by default; when the cores are shared (CI,
// parallel builds, several runs) that turns a 6 it/s loop into 0.1 it/s, so
// motionctl asks for passive waiting. And Debian's OpenBLAS runs its SSE3 kernels
// on CPU models it does not know (2.5x slower training steps here). Both libraries
// read their settings before main(); core/process_env.h sets them and re-executes
// the binary once (docs/choices.md, "Passive OpenMP waiting, by re-exec",
// "OpenBLAS's Prescott fallback").

int main(int argc, char** argv) {
  mc::reexec_with_runtime_environment(argv);
  mc::set_command_line(argc, argv);  // `train --nproc N` starts its ranks with it
  // A data-parallel rank says which one it is in its errors.
  std::string who = "motionctl";
  if (const char* w = std::getenv("WORLD_SIZE"); w && std::atoi(w) > 1)
    if (const char* r = std::getenv("RANK")) who = std::string("motionctl[rank ") + r + "]";
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
  mc::add_export_command(app);
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    int code = app.exit(e);
    return code == 0 ? 0 : mc::kExitUserError;
  } catch (const mc::UserError& e) {
    std::cerr << who << ": error: " << e.what() << "\n";
    return mc::kExitUserError;
  } catch (const mc::Interrupted& e) {
    std::cerr << who << ": " << e.what() << "\n";
    return 128 + e.signal;
  } catch (const mc::ExitStatus& e) {
    return e.code;
  } catch (const mc::DataParallelError& e) {
    std::cerr << who << ": error: " << e.what() << "\n";
    return 1;
  } catch (const std::bad_alloc&) {
    // Sizes are checked up front (core/resources.h); this is what slips through.
    std::cerr << "motionctl: error: out of memory (" << mc::format_bytes(mc::available_memory_bytes())
              << " available): a size in the config or an input file is too large for this machine; lower it "
                 "(model.width, optim.batch_size, data.window, fixture.num_clips, sampler.batch_size)\n";
    return mc::kExitUserError;
  } catch (const c10::Error& e) {
    if (std::string(e.what()).find("can't allocate memory") != std::string::npos) {
      std::cerr << "motionctl: error: out of memory: " << e.what_without_backtrace() << " ("
                << mc::format_bytes(mc::available_memory_bytes())
                << " available); lower the sizes in the config (model.width, optim.batch_size, data.window, "
                   "sampler.batch_size)\n";
      return mc::kExitUserError;
    }
    std::cerr << "motionctl: internal torch error: " << e.what_without_backtrace() << "\n";
    return 1;
  } catch (const std::exception& e) {
    std::cerr << "motionctl: internal error: " << e.what() << "\n";
    return 1;
  }
  return 0;
}
