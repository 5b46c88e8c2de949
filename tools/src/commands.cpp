#include "pulsetrack/tools/commands.hpp"

#include <fmt/format.h>

#include <atomic>
#include <charconv>
#include <chrono>
#include <csignal>
#include <thread>

namespace pulsetrack::tools {

namespace {
std::atomic<bool> g_stop{false};
void onSignal(int /*sig*/) { g_stop.store(true); }
}  // namespace

void catchStopSignals() {
  g_stop.store(false);
  std::signal(SIGINT, onSignal);
  std::signal(SIGTERM, onSignal);
}

bool stopRequested() noexcept { return g_stop.load(); }

void serveUntilSignal(const std::function<void()>& run, const std::function<void()>& stop) {
  catchStopSignals();
  std::signal(SIGPIPE, SIG_IGN);
  std::thread watch([&] {
    while (!stopRequested()) std::this_thread::sleep_for(std::chrono::milliseconds(100));
    stop();
  });
  run();
  g_stop.store(true);
  watch.join();
}

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
