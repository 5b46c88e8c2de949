// libFuzzer: the trigger box's HID input reports (drivers/trigger_box), as hid_read hands them
// over: any length, any bytes. A report that parses must say what an encoder would have sent.

#include <span>

#include "pulsetrack/drivers/trigger_box.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace pulsetrack::drivers;
  auto report = parseTriggerReport(std::span<const uint8_t>(data, size));
  if (!report) {
    if (report.error().message.empty()) __builtin_trap();
    return 0;
  }
  if (report->kind == TriggerReport::Kind::kPulse) {
    // A pulse parsed from 64 bytes re-encodes to the same sequence and time.
    auto again = parseTriggerReport(encodePulse(report->sequence, report->device_us));
    if (!again || again->sequence != report->sequence || again->device_us != report->device_us)
      __builtin_trap();
  }
  return 0;
}
