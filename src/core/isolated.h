// Crash isolation for third-party readers that trust their input (issue 16):
// libhdf5 can segfault on a damaged file it has no checksum for. isolated_probe
// runs a read in a forked child first; a crash or hang there becomes a UserError
// naming the file, and only a read that finished cleanly is repeated in this
// process. Used for HDF5 files without a seal (core/h5_seal.h).
#pragma once
#include <functional>
#include <string>

namespace mc {

// Runs `probe` in a forked child. Returns normally when it returned; rethrows its
// UserError (message kept) when it threw one; throws a UserError that names
// `what` when it crashed (signal), ran out of memory, threw anything else or ran
// longer than `timeout_s` seconds. The child shares nothing with this process after
// the fork, so `probe` should only read (its results are discarded). `fix` ends those
// messages: what the user does about a damaged file (a cache is deleted, not re-created).
inline constexpr double kProbeTimeoutS = 600;
void isolated_probe(const std::string& what, const std::function<void()>& probe, double timeout_s = kProbeTimeoutS,
                    const std::string& fix = "re-create it");

}  // namespace mc
