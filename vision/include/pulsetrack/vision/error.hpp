#pragma once
// Errors of the vision module: a message that names the file (or input) and what was wrong.
// Used at the boundaries (loading, calibration); the per-frame path has its own enum codes.

#include <expected>
#include <string>
#include <utility>

namespace pulsetrack::vision {

struct Error {
  std::string message;
  int code = 0;  // a library's own code where the caller may act on it (the DDS layer's), or 0
};

template <class T>
using Result = std::expected<T, Error>;

inline std::unexpected<Error> fail(std::string message) {
  return std::unexpected(Error{std::move(message)});
}

}  // namespace pulsetrack::vision
