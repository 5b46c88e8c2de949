#include "pulsetrack/drivers/trigger_box.hpp"

#include <fmt/format.h>
#include <hidapi/hidapi.h>

#include <algorithm>
#include <cmath>
#include <cstring>

#include "pulsetrack/rt/heartbeat.hpp"

namespace pulsetrack::drivers {

namespace {

constexpr uint8_t kConfigure = 0x01, kPulse = 0x81, kStatus = 0x82;
constexpr size_t kPulseLength = 1 + 4 + 8;  // id, sequence, time; CRC after
constexpr size_t kStatusLength =
    1 + 1 + 4 + 4 + 2 + 1;  // id, state, period, sequence, firmware, faults

template <class T>
void put(uint8_t* p, T v) {
  for (size_t i = 0; i < sizeof(T); ++i)
    p[i] = static_cast<uint8_t>((static_cast<uint64_t>(v) >> (8 * i)) & 0xff);
}

template <class T>
T get(const uint8_t* p) {
  uint64_t v = 0;
  for (size_t i = 0; i < sizeof(T); ++i) v |= static_cast<uint64_t>(p[i]) << (8 * i);
  return static_cast<T>(v);
}

std::array<uint8_t, kTriggerReportSize> sealed(std::array<uint8_t, kTriggerReportSize> r,
                                               size_t used) {
  r[used] = crc8({r.data(), used});
  return r;
}

}  // namespace

uint8_t crc8(std::span<const uint8_t> bytes) {
  uint8_t crc = 0;
  for (const uint8_t b : bytes) {
    crc ^= b;
    for (int i = 0; i < 8; ++i)
      crc = static_cast<uint8_t>((crc & 0x80) != 0 ? (crc << 1) ^ 0x07 : crc << 1);
  }
  return crc;
}

vision::Result<TriggerReport> parseTriggerReport(std::span<const uint8_t> b) {
  if (b.empty()) return vision::fail("an empty report");
  const auto check = [&](size_t used, const char* what) -> vision::Result<void> {
    if (b.size() < used + 1)
      return vision::fail(
          fmt::format("a {} report of {} bytes, {} expected", what, b.size(), used + 1));
    if (crc8(b.first(used)) != b[used])
      return vision::fail(fmt::format("a {} report whose CRC-8 is 0x{:02x}, 0x{:02x} expected",
                                      what, b[used], crc8(b.first(used))));
    return {};
  };
  TriggerReport r;
  if (b[0] == kPulse) {
    if (auto ok = check(kPulseLength, "pulse"); !ok) return std::unexpected(ok.error());
    r.kind = TriggerReport::Kind::kPulse;
    r.sequence = get<uint32_t>(&b[1]);
    r.device_us = get<uint64_t>(&b[5]);
    return r;
  }
  if (b[0] == kStatus) {
    if (auto ok = check(kStatusLength, "status"); !ok) return std::unexpected(ok.error());
    r.kind = TriggerReport::Kind::kStatus;
    r.state = b[1];
    r.period_us = get<uint32_t>(&b[2]);
    r.sequence = get<uint32_t>(&b[6]);
    r.firmware = get<uint16_t>(&b[10]);
    r.faults = b[12];
    if (r.state > 2) return vision::fail(fmt::format("a status report with state {}", r.state));
    return r;
  }
  return vision::fail(fmt::format("an unknown report id 0x{:02x}", b[0]));
}

std::array<uint8_t, kTriggerReportSize> encodeConfigure(uint32_t period_us,
                                                        uint16_t pulse_width_us) {
  std::array<uint8_t, kTriggerReportSize> r{};
  r[0] = kConfigure;
  put(&r[1], period_us);
  put(&r[5], pulse_width_us);
  return sealed(r, 7);
}

std::array<uint8_t, kTriggerReportSize> encodeCommand(uint8_t id) {
  std::array<uint8_t, kTriggerReportSize> r{};
  r[0] = id;
  return sealed(r, 1);
}

std::array<uint8_t, kTriggerReportSize> encodePulse(uint32_t sequence, uint64_t device_us) {
  std::array<uint8_t, kTriggerReportSize> r{};
  r[0] = kPulse;
  put(&r[1], sequence);
  put(&r[5], device_us);
  return sealed(r, kPulseLength);
}

std::array<uint8_t, kTriggerReportSize> encodeStatus(uint8_t state, uint32_t period_us,
                                                     uint32_t sequence, uint16_t firmware,
                                                     uint8_t faults) {
  std::array<uint8_t, kTriggerReportSize> r{};
  r[0] = kStatus;
  r[1] = state;
  put(&r[2], period_us);
  put(&r[6], sequence);
  put(&r[10], firmware);
  r[12] = faults;
  return sealed(r, kStatusLength);
}

void TriggerState::onReport(const TriggerReport& r, int64_t host_ns) {
  if (r.kind == TriggerReport::Kind::kStatus) {
    state_.store(r.state, std::memory_order_relaxed);
    faults_.store(r.faults, std::memory_order_relaxed);
    return;
  }
  if (have_seq_ && r.sequence <= last_seq_) {
    // The numbers went back: the box restarted (START, or a power cycle). A new epoch keeps
    // the pulse numbers the source hands out increasing.
    restarts_.fetch_add(1, std::memory_order_relaxed);
    epoch_ += last_seq_ + 1;
    n_offsets_ = 0;
  } else if (have_seq_ && r.sequence > last_seq_ + 1) {
    lost_.fetch_add(r.sequence - last_seq_ - 1, std::memory_order_relaxed);
  }
  have_seq_ = true;
  last_seq_ = r.sequence;
  pulses_.fetch_add(1, std::memory_order_relaxed);
  // Device time to host time: the report arrives some USB latency after the pulse; the
  // smallest offset over the last 64 reports is the closest to the true one.
  const int64_t device_ns = static_cast<int64_t>(r.device_us) * 1000;
  offsets_[n_offsets_ % offsets_.size()] = host_ns - device_ns;
  ++n_offsets_;
  const size_t n = std::min(n_offsets_, offsets_.size());
  const int64_t offset =
      *std::min_element(offsets_.begin(), offsets_.begin() + static_cast<long>(n));
  const uint64_t seq = epoch_ + r.sequence;
  Entry& e = ring_[seq % kRing];
  // A seqlock without fences (ThreadSanitizer cannot follow std::atomic_thread_fence, and g++
  // refuses to build one under -fsanitize=thread): the time is stored with release, so a reader
  // that sees it (acquire) also sees the UINT64_MAX before it and skips the entry. On x86 these
  // are plain stores and loads, as with the fences; on ARMv8 stlr/ldar instead of dmb.
  e.seq.store(UINT64_MAX, std::memory_order_relaxed);
  e.host_ns.store(device_ns + offset, std::memory_order_release);
  e.seq.store(seq, std::memory_order_release);
}

std::optional<uint64_t> TriggerState::pulseNear(int64_t t_ns, int64_t tolerance_ns,
                                                int64_t period_ns) const {
  std::optional<uint64_t> best;
  int64_t best_d = tolerance_ns + 1;
  uint64_t newest = 0;
  int64_t newest_t = 0;
  bool have_newest = false;
  for (const Entry& e : ring_) {
    const uint64_t s1 = e.seq.load(std::memory_order_acquire);
    if (s1 == UINT64_MAX) continue;
    // Acquire: the check of seq below cannot move before this load, and a time written after
    // s1 brings the writer's UINT64_MAX with it.
    const int64_t t = e.host_ns.load(std::memory_order_acquire);
    if (e.seq.load(std::memory_order_relaxed) != s1) continue;  // being rewritten
    const int64_t d = std::llabs(t - t_ns);
    if (d < best_d) {
      best_d = d;
      best = s1;
    }
    if (!have_newest || s1 > newest) {
      newest = s1;
      newest_t = t;
      have_newest = true;
    }
  }
  if (best || period_ns <= 0 || !have_newest) return best;
  const int64_t ahead = t_ns - newest_t;
  if (ahead <= 0 || ahead > 8 * period_ns) return std::nullopt;
  const int64_t steps = (ahead + period_ns / 2) / period_ns;
  if (std::llabs(ahead - steps * period_ns) > tolerance_ns) return std::nullopt;
  return newest + static_cast<uint64_t>(steps);
}

TriggerBox::TriggerBox(std::unique_ptr<HidDevice> device, double rate_hz, uint16_t pulse_width_us)
    : device_(std::move(device)), rate_hz_(rate_hz), pulse_width_us_(pulse_width_us) {}

TriggerBox::~TriggerBox() { stop(); }

vision::Result<void> TriggerBox::start() {
  const auto period_us = static_cast<uint32_t>(std::lround(1e6 / rate_hz_));
  const auto cfg = encodeConfigure(period_us, pulse_width_us_);
  if (device_->write(cfg) < 0)
    return vision::fail(
        fmt::format("{}: configuring {} Hz: {}", device_->name(), rate_hz_, device_->lastError()));
  if (device_->write(encodeCommand(0x02)) < 0)
    return vision::fail(fmt::format("{}: start: {}", device_->name(), device_->lastError()));
  (void)device_->write(encodeCommand(0x04));
  running_.store(true);
  reader_ = std::thread([this] { readLoop(); });
  return {};
}

void TriggerBox::stop() {
  if (!running_.exchange(false)) return;
  if (reader_.joinable()) reader_.join();
  (void)device_->write(encodeCommand(0x03));
}

void TriggerBox::readLoop() {
  std::array<uint8_t, kTriggerReportSize> buf{};
  while (running_.load()) {
    const int n = device_->read(buf, 100);
    if (n < 0) {
      device_error_.store(true);
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
      continue;
    }
    if (n == 0) continue;
    device_error_.store(false);
    auto r = parseTriggerReport({buf.data(), static_cast<size_t>(n)});
    if (!r) {
      state_.onGarbage();
      continue;
    }
    state_.onReport(*r, rt::monotonicNs());
  }
}

std::string TriggerBox::state() const {
  const int s = state_.state();
  const uint8_t f = state_.faults();
  std::string faults;
  if ((f & 1) != 0) faults += ", output shorted";
  if ((f & 2) != 0) faults += ", over-temperature";
  if ((f & 4) != 0) faults += ", power";
  return fmt::format(
      "trigger box {}: {}{} at {:g} Hz, {} pulses, {} lost, {} bad reports, {} restarts{}",
      device_->name(), device_error_.load() ? "not answering, " : "",
      s == 1   ? "running"
      : s == 2 ? "FAULT"
      : s == 0 ? "idle"
               : "no status yet",
      rate_hz_, state_.pulses(), state_.lost(), state_.garbage(), state_.restarts(), faults);
}

namespace {

class HidapiDevice final : public HidDevice {
 public:
  HidapiDevice(hid_device* d, std::string name) : d_(d), name_(std::move(name)) {}
  ~HidapiDevice() override { hid_close(d_); }
  HidapiDevice(const HidapiDevice&) = delete;
  HidapiDevice& operator=(const HidapiDevice&) = delete;
  int write(std::span<const uint8_t> report) override {
    return hid_write(d_, report.data(), report.size());
  }
  int read(std::span<uint8_t> report, int timeout_ms) override {
    return hid_read_timeout(d_, report.data(), report.size(), timeout_ms);
  }
  std::string name() const override { return name_; }
  std::string lastError() const override {
    const wchar_t* e = hid_error(d_);
    if (e == nullptr) return "unknown error";
    std::string s;
    for (; *e != 0; ++e) s += *e < 128 ? static_cast<char>(*e) : '?';
    return s;
  }

 private:
  hid_device* d_;
  std::string name_;
};

}  // namespace

vision::Result<std::unique_ptr<HidDevice>> openHidDevice(uint16_t vendor, uint16_t product,
                                                         const std::string& serial) {
  if (hid_init() != 0) return vision::fail("hidapi: hid_init failed");
  std::wstring wserial(serial.begin(), serial.end());
  hid_device* d = hid_open(vendor, product, serial.empty() ? nullptr : wserial.c_str());
  const std::string name =
      fmt::format("{:04x}:{:04x}{}", vendor, product, serial.empty() ? "" : " " + serial);
  if (d == nullptr)
    return vision::fail(
        fmt::format("trigger box {}: not found (is it plugged in, and is the udev rule for "
                    "/dev/hidraw* installed?)",
                    name));
  return std::unique_ptr<HidDevice>(std::make_unique<HidapiDevice>(d, name));
}

}  // namespace pulsetrack::drivers
