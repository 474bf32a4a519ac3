// SIGINT/SIGTERM during a training loop: instead of dying mid-step, the loop
// notices the request at the end of the step, writes a checkpoint at the step
// reached and unwinds with Interrupted (main() exits 128 + signal: 130 for
// Ctrl-C, 143 for SIGTERM), releasing the run's lock on the way. A second signal
// while the loop is finishing its step kills the process the default way.
// Outside a training loop the handlers are not installed, so Ctrl-C stops any
// other command at once as usual.
#pragma once
#include <stdexcept>
#include <string>

namespace mc {

// Thrown once the interrupted loop has saved its checkpoint. Not a UserError (so
// table replays and sweeps do not record it as a failed row and carry on) and
// caught by main().
struct Interrupted : std::runtime_error {
  int signal;
  Interrupted(int sig, const std::string& what) : std::runtime_error(what), signal(sig) {}
};

// Installs the handlers for its lifetime (nests; the outermost restores the
// previous handlers).
class InterruptScope {
 public:
  InterruptScope();
  ~InterruptScope();
  InterruptScope(const InterruptScope&) = delete;
  InterruptScope& operator=(const InterruptScope&) = delete;
};

// The signal received inside an InterruptScope (0: none).
int interrupt_requested();
// Forgets a received signal: the loop calls it once it has acted on it (an
// unhandled one is delivered when the outermost scope ends).
void clear_interrupt();
// For tests: behave as if `sig` had arrived.
void request_interrupt(int sig);

}  // namespace mc
