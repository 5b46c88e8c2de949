#pragma once
// The trigger box: a small USB HID device that drives both cameras' trigger inputs with the
// same pulse and reports every pulse it sends. Protocol (docs/trigger-box.md), 64-byte
// reports, byte 0 the report id, integers little-endian, the last used byte a CRC-8
// (polynomial 0x07, init 0) over the bytes before it:
//
//   host -> box   0x01 CONFIGURE  u32 period_us, u16 pulse_width_us
//                 0x02 START      (pulse numbers restart at 0)
//                 0x03 STOP
//                 0x04 STATUS?    (the box answers with a STATUS report)
//   box -> host   0x81 PULSE      u32 sequence, u64 device time (us)
//                 0x82 STATUS     u8 state (0 idle, 1 running, 2 fault), u32 period_us,
//                                 u32 last sequence, u16 firmware, u8 fault flags
//                                 (bit 0 output shorted, bit 1 over-temperature, bit 2 power)
//
// The parser and the state machine are byte-level and tested on streams with garbage, short
// reports and lost pulses; the HID access (hidapi) is a thin HidDevice.

#include <array>
#include <atomic>
#include <cstdint>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <thread>

#include "pulsetrack/vision/error.hpp"

namespace pulsetrack::drivers {

inline constexpr size_t kTriggerReportSize = 64;

uint8_t crc8(std::span<const uint8_t> bytes);

struct TriggerReport {
  enum class Kind { kPulse, kStatus } kind = Kind::kPulse;
  uint32_t sequence = 0;
  uint64_t device_us = 0;
  uint8_t state = 0;  // status
  uint32_t period_us = 0;
  uint16_t firmware = 0;
  uint8_t faults = 0;
};

// One input report (as hid_read returns it: report id first). Fails saying what is wrong.
vision::Result<TriggerReport> parseTriggerReport(std::span<const uint8_t> bytes);

// Output reports.
std::array<uint8_t, kTriggerReportSize> encodeConfigure(uint32_t period_us,
                                                        uint16_t pulse_width_us);
std::array<uint8_t, kTriggerReportSize> encodeCommand(uint8_t id);  // START, STOP, STATUS?
// Input reports, as the box sends them (the tests' and a firmware's reference).
std::array<uint8_t, kTriggerReportSize> encodePulse(uint32_t sequence, uint64_t device_us);
std::array<uint8_t, kTriggerReportSize> encodeStatus(uint8_t state, uint32_t period_us,
                                                     uint32_t sequence, uint16_t firmware,
                                                     uint8_t faults);

// What the reports say, kept for the capture thread without a lock: the recent pulses on the
// host's monotonic clock, counts of lost pulses (sequence gaps), garbage and restarts.
class TriggerState {
 public:
  // A report read at host time `host_ns`.
  void onReport(const TriggerReport& r, int64_t host_ns);
  void onGarbage() { garbage_.fetch_add(1, std::memory_order_relaxed); }
  // The pulse whose host time is within `tolerance_ns` of `t_ns` (a camera's exposure time).
  // With `period_ns`, a pulse whose report has not arrived yet (USB latency can exceed the
  // camera's delivery) is numbered from the newest known pulse up to 8 periods before.
  [[nodiscard]] std::optional<uint64_t> pulseNear(int64_t t_ns, int64_t tolerance_ns,
                                                  int64_t period_ns = 0) const;
  [[nodiscard]] uint64_t pulses() const { return pulses_.load(std::memory_order_relaxed); }
  [[nodiscard]] uint64_t lost() const { return lost_.load(std::memory_order_relaxed); }
  [[nodiscard]] uint64_t garbage() const { return garbage_.load(std::memory_order_relaxed); }
  [[nodiscard]] uint64_t restarts() const { return restarts_.load(std::memory_order_relaxed); }
  [[nodiscard]] uint8_t faults() const { return faults_.load(std::memory_order_relaxed); }
  [[nodiscard]] int state() const { return state_.load(std::memory_order_relaxed); }

 private:
  static constexpr size_t kRing = 256;
  struct Entry {
    std::atomic<uint64_t> seq{UINT64_MAX};  // written last (release): the entry is complete
    std::atomic<int64_t> host_ns{0};
  };
  std::array<Entry, kRing> ring_{};
  std::atomic<uint64_t> pulses_{0}, lost_{0}, garbage_{0}, restarts_{0};
  std::atomic<uint8_t> faults_{0};
  std::atomic<int> state_{-1};
  // Reader thread only: the device-to-host clock offset, the smallest seen over a window
  // (the report with the least USB latency).
  bool have_seq_ = false;
  uint64_t last_seq_ = 0, epoch_ = 0;
  std::array<int64_t, 64> offsets_{};
  size_t n_offsets_ = 0;
};

// The HID device: hidapi on a board, a byte-stream emulation in the tests.
class HidDevice {
 public:
  virtual ~HidDevice() = default;
  virtual int write(std::span<const uint8_t> report) = 0;           // bytes written, -1
  virtual int read(std::span<uint8_t> report, int timeout_ms) = 0;  // bytes, 0 timeout, -1
  [[nodiscard]] virtual std::string name() const = 0;
  [[nodiscard]] virtual std::string lastError() const = 0;
};
// hidapi: the first device with this vendor and product id (and serial, when given).
vision::Result<std::unique_ptr<HidDevice>> openHidDevice(uint16_t vendor, uint16_t product,
                                                         const std::string& serial = "");

class TriggerBox {
 public:
  TriggerBox(std::unique_ptr<HidDevice> device, double rate_hz, uint16_t pulse_width_us = 100);
  ~TriggerBox();
  TriggerBox(const TriggerBox&) = delete;
  TriggerBox& operator=(const TriggerBox&) = delete;

  // Configures the rate, starts the pulses and the reading thread.
  vision::Result<void> start();
  void stop();
  [[nodiscard]] std::optional<uint64_t> pulseNear(int64_t t_ns, int64_t tolerance_ns) const {
    return state_.pulseNear(t_ns, tolerance_ns, static_cast<int64_t>(1e9 / rate_hz_));
  }
  // One line for health.
  [[nodiscard]] std::string state() const;
  [[nodiscard]] const TriggerState& counters() const { return state_; }

 private:
  void readLoop();
  std::unique_ptr<HidDevice> device_;
  double rate_hz_;
  uint16_t pulse_width_us_;
  TriggerState state_;
  std::atomic<bool> running_{false}, device_error_{false};
  std::thread reader_;
};

}  // namespace pulsetrack::drivers
