// Subcommand registration: one function per `motionctl <command>`.
#pragma once
#include <CLI/CLI.hpp>

namespace mc {
void add_fixture_command(CLI::App& app);
void add_train_command(CLI::App& app);
void add_sweep_command(CLI::App& app);
void add_ship_command(CLI::App& app);
void add_config_command(CLI::App& app);
void add_bench_command(CLI::App& app);
void add_sample_command(CLI::App& app);
void add_eval_commands(CLI::App& app);  // eval, score
void add_reproduce_command(CLI::App& app);
void add_generate_command(CLI::App& app);
void add_health_command(CLI::App& app);
void add_export_command(CLI::App& app);  // export --format bvh
}  // namespace mc
