#include "pulsetrack/tools/commands.hpp"

#include <fmt/format.h>

#include <charconv>

namespace pulsetrack::tools {

int commandError(const char* command, const std::string& message) {
  fmt::print(stderr, "pulsetrack {}: error: {}\n", command, message);
  return 1;
}

vision::Result<cv::Rect> parseRect(const std::string& text, const char* option) {
  int v[4] = {0, 0, 0, 0};
  const char* p = text.data();
  const char* end = text.data() + text.size();
  for (int i = 0; i < 4; ++i) {
    const auto [ptr, ec] = std::from_chars(p, end, v[i]);
    if (ec != std::errc() || (i < 3 && (ptr == end || *ptr != ',')) || (i == 3 && ptr != end)) {
      return vision::fail(
          fmt::format("{} '{}': expected x,y,w,h (four integers, pixels)", option, text));
    }
    p = ptr + 1;
  }
  if (v[2] <= 0 || v[3] <= 0)
    return vision::fail(fmt::format("{} '{}': width and height must be positive", option, text));
  return cv::Rect(v[0], v[1], v[2], v[3]);
}

}  // namespace pulsetrack::tools
