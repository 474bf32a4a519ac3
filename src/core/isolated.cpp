// isolated_probe (core/isolated.h): fork, run, report through a pipe.
#include "core/isolated.h"

#include <poll.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cstring>
#include <new>

#include "core/error.h"

namespace mc {
namespace {

void write_all(int fd, const std::string& s) {
  size_t done = 0;
  while (done < s.size()) {
    ssize_t n = ::write(fd, s.data() + done, s.size() - done);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) return;
    done += static_cast<size_t>(n);
  }
}

}  // namespace

void isolated_probe(const std::string& what, const std::function<void()>& probe, double timeout_s,
                    const std::string& fix) {
  int fds[2];
  if (::pipe(fds) != 0) {
    probe();  // no pipe (fd limit): read unprotected rather than refuse a good file
    return;
  }
  ::fflush(nullptr);  // the child must not flush this process's buffered output again
  pid_t pid = ::fork();
  if (pid < 0) {
    ::close(fds[0]);
    ::close(fds[1]);
    probe();
    return;
  }
  if (pid == 0) {
    ::close(fds[0]);
    // Crash handlers inherited from the parent (a test framework's, torch's) would
    // report the child's crash as the parent's: let the signal end the child.
    for (int sig : {SIGSEGV, SIGBUS, SIGFPE, SIGILL, SIGABRT}) ::signal(sig, SIG_DFL);
    // Status letter, then the message: 'k' ok, 'u' UserError, 'm' out of memory, 'x' other.
    std::string report = "k";
    try {
      probe();
    } catch (const UserError& e) {
      report = std::string("u") + e.what();
    } catch (const std::bad_alloc&) {
      report = "m";
    } catch (const std::exception& e) {
      report = std::string("x") + e.what();
    } catch (...) {
      report = "x";
    }
    write_all(fds[1], report);
    ::_exit(0);  // no atexit handlers or static destructors: they belong to the parent
  }
  ::close(fds[1]);
  std::string report;
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::duration<double>(timeout_s);
  bool timed_out = false;
  char buf[4096];
  while (true) {
    const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(deadline - std::chrono::steady_clock::now());
    if (left.count() <= 0) {
      timed_out = true;
      break;
    }
    pollfd p{fds[0], POLLIN, 0};
    int r = ::poll(&p, 1, static_cast<int>(std::min<long long>(left.count(), 1000)));
    if (r < 0 && errno == EINTR) continue;
    if (r <= 0) continue;
    ssize_t n = ::read(fds[0], buf, sizeof buf);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) break;  // EOF: the child exited (or closed the pipe)
    report.append(buf, static_cast<size_t>(n));
  }
  ::close(fds[0]);
  if (timed_out) ::kill(pid, SIGKILL);
  int status = 0;
  while (::waitpid(pid, &status, 0) < 0 && errno == EINTR) {
  }
  if (timed_out)
    fail("reading {} did not finish within {} s (the file is probably damaged so that the reader loops); {}", what,
         timeout_s, fix);
  if (WIFSIGNALED(status))
    fail("reading {} crashed the HDF5 library ({}): the file is damaged; {}", what, ::strsignal(WTERMSIG(status)), fix);
  if (report.empty())
    fail("reading {} stopped without a result (exit status {}): the file is damaged; {}", what,
         WIFEXITED(status) ? WEXITSTATUS(status) : -1, fix);
  switch (report[0]) {
    case 'k': return;
    case 'u': throw UserError(report.substr(1));
    case 'm':
      fail("reading {} needs more memory than this machine has: the sizes in the file are damaged or too large; {}",
           what, fix);
    default:
      fail("reading {} failed: {}; the file is damaged, {}", what, report.substr(1), fix);
  }
}

}  // namespace mc
