// The one error type for bad user input (config, files, values); main() maps it
// to exit code 2. Everything else that throws is a bug and exits with 1.
#pragma once
#include <stdexcept>
#include <string>

#include <fmt/format.h>

namespace mc {

struct UserError : std::runtime_error {
  using std::runtime_error::runtime_error;
};

template <class... Args>
[[noreturn]] void fail(fmt::format_string<Args...> f, Args&&... args) {
  throw UserError(fmt::format(f, std::forward<Args>(args)...));
}

inline constexpr int kExitUserError = 2;

}  // namespace mc
