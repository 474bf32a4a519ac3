// Memory and thread budgets (core/resources.h).
#include "core/resources.h"

#include <sched.h>
#include <sys/resource.h>
#include <unistd.h>

#include <algorithm>
#include <fstream>
#include <sstream>
#include <thread>

#include "core/error.h"

namespace mc {

uint64_t available_memory_bytes() {
  uint64_t avail = 0;
  std::ifstream in("/proc/meminfo");
  std::string key;
  uint64_t kb = 0;
  std::string unit;
  while (in >> key >> kb) {
    std::getline(in, unit);
    if (key == "MemAvailable:") {
      avail = kb * 1024;
      break;
    }
  }
  if (avail == 0) {
    long pages = ::sysconf(_SC_PHYS_PAGES), page = ::sysconf(_SC_PAGE_SIZE);
    if (pages > 0 && page > 0) avail = static_cast<uint64_t>(pages) * static_cast<uint64_t>(page);
  }
  for (int res : {RLIMIT_AS, RLIMIT_DATA}) {
    rlimit r{};
    if (::getrlimit(res, &r) == 0 && r.rlim_cur != RLIM_INFINITY) avail = std::min<uint64_t>(avail, r.rlim_cur);
  }
  return avail;
}

std::string format_bytes(long double bytes) {
  if (bytes >= 1e9L) return fmt::format("{:.3g} GB", static_cast<double>(bytes / 1e9L));
  return fmt::format("{:.3g} MB", static_cast<double>(bytes / 1e6L));
}

void require_memory(long double bytes, const std::string& what, const std::string& detail, const std::string& fix) {
  const uint64_t avail = available_memory_bytes();
  if (avail == 0 || bytes <= static_cast<long double>(avail)) return;
  fail("{} needs at least {} of memory ({}) but this machine has {} available; {}", what, format_bytes(bytes), detail,
       format_bytes(avail), fix);
}

int usable_cpus() {
  cpu_set_t set;
  CPU_ZERO(&set);
  if (::sched_getaffinity(0, sizeof set, &set) == 0) {
    int n = CPU_COUNT(&set);
    if (n > 0) return n;
  }
  return static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
}

void check_thread_count(int threads, const std::string& key) {
  const int cpus = usable_cpus();
  if (threads > cpus)
    fail("{}={} exceeds the {} CPU(s) this process may use; more threads than cores only slow torch down (and "
         "thousands of them stall the machine): use 0 for all cores or a number up to {}",
         key, threads, cpus, cpus);
}

}  // namespace mc
