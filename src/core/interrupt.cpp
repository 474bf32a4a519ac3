// Signal handlers of InterruptScope: the first SIGINT/SIGTERM is recorded for the
// training loop to act on; a second one restores the default action and re-raises;
// one left unhandled when the scope ends is delivered then.
#include "core/interrupt.h"

#include <signal.h>

#include <csignal>

#include <atomic>

namespace mc {
namespace {

volatile std::sig_atomic_t g_signal = 0;
std::atomic<int> g_depth{0};
struct sigaction g_old_int, g_old_term;

extern "C" void on_signal(int sig) {
  if (g_signal != 0) {  // asked twice: stop now
    ::signal(sig, SIG_DFL);
    ::raise(sig);
    return;
  }
  g_signal = sig;
}

}  // namespace

InterruptScope::InterruptScope() {
  if (g_depth++ > 0) return;
  g_signal = 0;
  struct sigaction sa {};
  sa.sa_handler = on_signal;
  sigemptyset(&sa.sa_mask);
  sa.sa_flags = SA_RESTART;
  ::sigaction(SIGINT, &sa, &g_old_int);
  ::sigaction(SIGTERM, &sa, &g_old_term);
}

InterruptScope::~InterruptScope() {
  if (--g_depth > 0) return;
  ::sigaction(SIGINT, &g_old_int, nullptr);
  ::sigaction(SIGTERM, &g_old_term, nullptr);
  // A signal that arrived after the loop's last look (final evaluation and
  // writes) was not acted on: deliver it now, the way it would have been.
  const int pending = g_signal;
  g_signal = 0;
  if (pending != 0) ::raise(pending);
}

int interrupt_requested() { return g_signal; }
void clear_interrupt() { g_signal = 0; }
void request_interrupt(int sig) { g_signal = sig; }

}  // namespace mc
