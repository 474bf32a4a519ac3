// What this machine can give a command (issue 16): memory and CPU threads.
// Sizes that cannot fit are refused up front with an estimate and the key to
// change, instead of a bad_alloc (exit 1), an OOM kill of a neighbour's job, or a
// machine brought to its knees by thousands of spinning threads.
#pragma once
#include <cstdint>
#include <string>

namespace mc {

// Memory this process can still take: MemAvailable from /proc/meminfo (or total
// physical memory where that file is missing), capped by RLIMIT_AS/RLIMIT_DATA.
uint64_t available_memory_bytes();

// UserError when `bytes` (an estimate, a lower bound) exceeds the available memory:
// "<what> needs at least X GB (<detail>) but N GB are available; <fix>".
void require_memory(long double bytes, const std::string& what, const std::string& detail, const std::string& fix);

// CPUs this process may run on (sched_getaffinity; hardware_concurrency as fallback).
int usable_cpus();

// UserError naming `key` when `threads` exceeds usable_cpus(): more threads than
// cores only slows torch down and thousands of them hang the machine. 0 = all.
void check_thread_count(int threads, const std::string& key);

// "12.3 GB" / "456 MB".
std::string format_bytes(long double bytes);

}  // namespace mc
