#include "pulsetrack/tools/commands.hpp"

#include <fmt/format.h>

namespace pulsetrack::tools {

int commandError(const char* command, const std::string& message) {
  fmt::print(stderr, "pulsetrack {}: error: {}\n", command, message);
  return 1;
}

}  // namespace pulsetrack::tools
