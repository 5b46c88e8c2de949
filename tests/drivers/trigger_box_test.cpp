// The trigger box's protocol on byte streams: round trips, CRC, garbage, short reports, unknown
// ids; the state machine's lost pulses, restarts and clock mapping; the box driven through a
// HID device emulation; hidapi itself on this machine (a device that is not there).

#include "pulsetrack/drivers/trigger_box.hpp"

#include <gtest/gtest.h>
#include <hidapi/hidapi.h>

#include <deque>
#include <mutex>
#include <random>

namespace pulsetrack::drivers {
namespace {

TEST(TriggerProtocol, ReportsRoundTripAndTheCrcCatchesEveryFlippedBit) {
  const auto p = encodePulse(123456, 987654321012ULL);
  auto r = parseTriggerReport(p);
  ASSERT_TRUE(r) << r.error().message;
  EXPECT_EQ(r->kind, TriggerReport::Kind::kPulse);
  EXPECT_EQ(r->sequence, 123456U);
  EXPECT_EQ(r->device_us, 987654321012ULL);
  const auto s = encodeStatus(1, 33333, 99, 0x0102, 0x2);
  auto st = parseTriggerReport(s);
  ASSERT_TRUE(st);
  EXPECT_EQ(st->kind, TriggerReport::Kind::kStatus);
  EXPECT_EQ(st->period_us, 33333U);
  EXPECT_EQ(st->firmware, 0x0102);
  EXPECT_EQ(st->faults, 2);
  for (size_t byte = 1; byte < 14; ++byte) {
    for (int bit = 0; bit < 8; ++bit) {
      auto flipped = p;
      flipped[byte] ^= static_cast<uint8_t>(1 << bit);
      EXPECT_FALSE(parseTriggerReport(flipped)) << byte << ":" << bit;
    }
  }
  const auto cfg = encodeConfigure(33333, 100);
  EXPECT_EQ(cfg[0], 0x01);
  EXPECT_EQ(cfg[1] | (cfg[2] << 8) | (cfg[3] << 16), 33333);
  EXPECT_EQ(cfg[7], crc8({cfg.data(), 7}));
  EXPECT_EQ(crc8(std::span<const uint8_t>(reinterpret_cast<const uint8_t*>("123456789"), 9)),
            0xF4);  // CRC-8/SMBUS check value
}

TEST(TriggerProtocol, GarbageShortAndUnknownReportsAreRefusedWithAReason) {
  const auto p = encodePulse(1, 2);
  auto short_r = parseTriggerReport({p.data(), 10});
  ASSERT_FALSE(short_r);
  EXPECT_NE(short_r.error().message.find("a pulse report of 10 bytes, 14 expected"),
            std::string::npos);
  auto crc = p;
  crc[13] ^= 1;
  EXPECT_NE(parseTriggerReport(crc).error().message.find("CRC-8"), std::string::npos);
  std::array<uint8_t, 64> unknown{};
  unknown[0] = 0x42;
  EXPECT_NE(parseTriggerReport(unknown).error().message.find("unknown report id 0x42"),
            std::string::npos);
  EXPECT_FALSE(parseTriggerReport({}));
  auto bad_state = encodeStatus(7, 1, 1, 1, 0);
  EXPECT_NE(parseTriggerReport(bad_state).error().message.find("state 7"), std::string::npos);
  // Random bytes: never a crash, almost never a report (a CRC-8 lets 1 in 256 through at most).
  std::mt19937 rng(1);
  int accepted = 0;
  for (int i = 0; i < 20000; ++i) {
    std::array<uint8_t, 64> junk{};
    for (auto& b : junk) b = static_cast<uint8_t>(rng());
    const size_t n = rng() % 65;
    accepted += parseTriggerReport({junk.data(), n}) ? 1 : 0;
  }
  EXPECT_LT(accepted, 20);
}

TEST(TriggerState, LostPulsesRestartsAndTheHostClock) {
  TriggerState s;
  std::mt19937 rng(2);
  std::uniform_int_distribution<int64_t> latency(50'000, 400'000);  // USB: 50-400 us late
  const int64_t offset = 5'000'000'000;                             // host = device + 5 s
  std::vector<int64_t> pulse_host(300);
  for (uint32_t k = 0; k < 300; ++k) {
    const uint64_t dev_us = 1'000'000 + uint64_t{k} * 10'000;  // 100 Hz
    pulse_host[k] = static_cast<int64_t>(dev_us) * 1000 + offset;
    if (k % 50 == 17) continue;  // a report lost on the bus
    s.onReport({TriggerReport::Kind::kPulse, k, dev_us}, pulse_host[k] + latency(rng));
  }
  EXPECT_EQ(s.lost(), 6U);
  EXPECT_EQ(s.pulses(), 294U);
  // A camera frame exposed 20 us after pulse 250: found, within the USB latency's spread.
  const auto seq = s.pulseNear(pulse_host[250] + 20'000, 2'500'000);
  EXPECT_EQ(seq.value_or(0), 250U);
  EXPECT_FALSE(s.pulseNear(pulse_host[299] + 1'000'000'000, 2'500'000));  // no pulse then
  // The box restarts: the numbers it reports start at 0 again, the source's keep increasing.
  s.onReport({TriggerReport::Kind::kPulse, 0, 9'000'000}, 9'000'000'000 + offset + 100'000);
  EXPECT_EQ(s.restarts(), 1U);
  const auto after = s.pulseNear(9'000'000'000 + offset, 2'500'000);
  EXPECT_EQ(after.value_or(0), 300U);
  s.onReport({TriggerReport::Kind::kStatus, 0, 0, 2, 10000, 0, 1}, 0);
  EXPECT_EQ(s.state(), 2);
  EXPECT_EQ(s.faults(), 1);
}

class ScriptedHid final : public HidDevice {
 public:
  std::mutex m;
  std::deque<std::vector<uint8_t>> in;
  std::vector<std::vector<uint8_t>> out;
  int write(std::span<const uint8_t> r) override {
    std::lock_guard<std::mutex> l(m);
    out.emplace_back(r.begin(), r.end());
    return static_cast<int>(r.size());
  }
  int read(std::span<uint8_t> r, int) override {
    std::lock_guard<std::mutex> l(m);
    if (in.empty()) return 0;
    const auto v = in.front();
    in.pop_front();
    std::copy(v.begin(), v.end(), r.begin());
    return static_cast<int>(v.size());
  }
  std::string name() const override { return "scripted"; }
  std::string lastError() const override { return {}; }
};

TEST(TriggerBox, ConfiguresStartsReadsAndStops) {
  auto dev = std::make_unique<ScriptedHid>();
  ScriptedHid* d = dev.get();
  for (uint32_t k = 0; k < 40; ++k) {
    if (k == 20 || k == 21) continue;  // two pulses the host never heard of
    const auto p = encodePulse(k, 1000 + 33'333ULL * k);
    d->in.emplace_back(p.begin(), p.end());
    if (k == 10) d->in.push_back({0x81, 1, 2, 3});                 // a short report
    if (k == 30) d->in.push_back(std::vector<uint8_t>(64, 0xAA));  // line noise
  }
  const auto st = encodeStatus(1, 33333, 39, 0x0100, 0);
  d->in.emplace_back(st.begin(), st.end());
  TriggerBox box(std::move(dev), 30.0, 200);
  ASSERT_TRUE(box.start());
  for (int i = 0; i < 200 && box.counters().state() != 1; ++i)
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  box.stop();
  ASSERT_GE(d->out.size(), 4U);
  auto cfg = d->out[0];
  EXPECT_EQ(cfg[0], 0x01);
  EXPECT_EQ(cfg[1] | (cfg[2] << 8) | (cfg[3] << 16), 33333);
  EXPECT_EQ(cfg[5] | (cfg[6] << 8), 200);
  EXPECT_EQ(d->out[1][0], 0x02);      // START
  EXPECT_EQ(d->out[2][0], 0x04);      // STATUS?
  EXPECT_EQ(d->out.back()[0], 0x03);  // STOP
  EXPECT_EQ(box.counters().pulses(), 38U);
  EXPECT_EQ(box.counters().lost(), 2U);
  EXPECT_EQ(box.counters().garbage(), 2U);
  const std::string line = box.state();
  EXPECT_NE(line.find("running at 30 Hz, 38 pulses, 2 lost, 2 bad reports"), std::string::npos)
      << line;
}

TEST(TriggerBox, HidapiSaysWhenTheBoxIsNotThere) {
  auto d = openHidDevice(0xfffe, 0x0001);
  ASSERT_FALSE(d);
  EXPECT_NE(d.error().message.find("trigger box fffe:0001: not found"), std::string::npos)
      << d.error().message;
  hid_device_info* all = hid_enumerate(0, 0);
  int n = 0;
  for (hid_device_info* i = all; i != nullptr; i = i->next) ++n;
  hid_free_enumeration(all);
  if (n == 0)
    GTEST_SKIP()
        << "SKIP: no HID device on this machine: the trigger box ran only through its seam";
  std::cout << n << " HID device(s) present\n";
}

}  // namespace
}  // namespace pulsetrack::drivers
