// The V4L2 driver through its syscall seam (tests/drivers/fake_v4l2.hpp emulates the kernel's
// streaming state machine): the documented call sequence, the pixel formats, errors that name
// the device and the step, and the stereo source with its faults: missed pulses, dropped
// frames, spurious EAGAIN, a camera unplugged and plugged back, a camera that stops sending,
// and the trigger box's pulse numbers on the pairs. Plus a test on a real /dev/video device,
// skipped loudly when there is none.

#include "pulsetrack/drivers/v4l2.hpp"

#include <fcntl.h>
#include <gtest/gtest.h>
#include <linux/videodev2.h>
#include <sys/ioctl.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <deque>
#include <filesystem>
#include <mutex>

#include "fake_v4l2.hpp"
#include "pulsetrack/drivers/trigger_box.hpp"
#include "pulsetrack/sim/paper_rig.hpp"

namespace pulsetrack::drivers {
namespace {

V4l2CameraConfig small(const std::string& dev, const std::string& fmt = "GREY") {
  V4l2CameraConfig c;
  c.device = dev;
  c.width = 64;
  c.height = 48;
  c.pixel_format = fmt;
  c.buffers = 6;
  return c;
}

TEST(V4l2Camera, OpensWithTheDocumentedSequenceAndClosesCleanly) {
  test::FakeV4l2 io;
  io.add("/dev/video0");
  V4l2CameraConfig c = small("/dev/video0");
  c.exposure_us = 5000;
  c.gain = 3;
  V4l2Camera cam(io, c);
  ASSERT_TRUE(cam.open()) << cam.lastError();
  std::vector<std::string> expected = {
      "open /dev/video0",
      "VIDIOC_QUERYCAP",
      "VIDIOC_S_FMT",
      "VIDIOC_S_CTRL " + std::to_string(V4L2_CID_EXPOSURE_AUTO),
      "VIDIOC_S_CTRL " + std::to_string(V4L2_CID_EXPOSURE_ABSOLUTE),
      "VIDIOC_S_CTRL " + std::to_string(V4L2_CID_GAIN),
      "VIDIOC_REQBUFS 6"};
  for (int i = 0; i < 6; ++i) {
    expected.push_back("VIDIOC_QUERYBUF " + std::to_string(i));
    expected.push_back("mmap " + std::to_string(i));
    expected.push_back("VIDIOC_QBUF " + std::to_string(i));
  }
  expected.emplace_back("VIDIOC_STREAMON");
  EXPECT_EQ(io.calls, expected);
  EXPECT_EQ(io.device("/dev/video0").control_values[V4L2_CID_EXPOSURE_ABSOLUTE],
            50);  // 100 us units
  io.calls.clear();
  cam.close();
  EXPECT_FALSE(cam.isOpen());
  ASSERT_GE(io.calls.size(), 9U);
  EXPECT_EQ(io.calls.front(), "VIDIOC_STREAMOFF");
  EXPECT_EQ(std::count(io.calls.begin(), io.calls.end(), "munmap"), 6);
  EXPECT_EQ(io.calls[io.calls.size() - 2], "VIDIOC_REQBUFS 0");
  EXPECT_EQ(io.calls.back(), "close");
}

TEST(V4l2Camera, GreyY16AndYuyvBecomeTheSameGreyImage) {
  for (const std::string fmt : {"GREY", "Y16", "YUYV"}) {
    test::FakeV4l2 io;
    io.add("/dev/video0");
    V4l2Camera cam(io, small("/dev/video0", fmt));
    ASSERT_TRUE(cam.open()) << cam.lastError();
    pollfd p{cam.fd(), POLLIN, 0};
    for (int k = 0; k < 3; ++k) ASSERT_EQ(io.poll(&p, 1, 1000), 1);  // frame 0 (k=0) is there
    int index = -1;
    CameraStamp s;
    ASSERT_EQ(cam.dequeue(index, s), V4l2Camera::Dequeue::kFrame) << fmt;
    cv::Mat out(48, 64, CV_8UC1, cv::Scalar(255));
    cam.convert(index, out);
    EXPECT_EQ(cv::countNonZero(out != 0), 0) << fmt << ": trigger 0's pixels are 0";
    EXPECT_TRUE(cam.requeue(index));
    EXPECT_EQ(s.seq, 0U);
    // The next one holds trigger 1.
    ASSERT_EQ(io.poll(&p, 1, 1000), 1);
    ASSERT_EQ(cam.dequeue(index, s), V4l2Camera::Dequeue::kFrame);
    cam.convert(index, out);
    EXPECT_EQ(cv::countNonZero(out != 1), 0) << fmt;
    EXPECT_EQ(s.seq, 1U);
  }
}

TEST(V4l2Camera, ErrorsNameTheDeviceAndTheStep) {
  test::FakeV4l2 io;
  io.add("/dev/video0").caps = V4L2_CAP_VIDEO_OUTPUT;
  io.add("/dev/video1").width = 640;
  io.add("/dev/video2").formats = {V4L2_PIX_FMT_YUYV};
  io.add("/dev/video3").max_buffers = 1;
  const auto err = [&](const V4l2CameraConfig& c) {
    V4l2Camera cam(io, c);
    auto r = cam.open();
    EXPECT_FALSE(r);
    EXPECT_FALSE(cam.isOpen());
    return r ? std::string() : r.error().message;
  };
  EXPECT_NE(err(small("/dev/video0"))
                .find("/dev/video0: 'fake camera' (fake) is not a streaming capture device"),
            std::string::npos);
  EXPECT_NE(
      err(small("/dev/video1"))
          .find("/dev/video1: the camera offers 640x48 GREY where the config asks 64x48 GREY"),
      std::string::npos);
  EXPECT_NE(err(small("/dev/video2")).find("offers 64x48 YUYV where the config asks 64x48 GREY"),
            std::string::npos);
  EXPECT_NE(err(small("/dev/video3")).find("/dev/video3: the driver gives 1 buffer(s), at least 2"),
            std::string::npos);
  EXPECT_NE(err(small("/dev/video9")).find("/dev/video9: cannot open: No such file or directory"),
            std::string::npos);
  V4l2CameraConfig trig = small("/dev/video1");
  trig.width = 640;
  trig.trigger_control = 0x0098f901;  // a vendor control this camera lacks
  EXPECT_NE(err(trig).find("selecting the external trigger (control 0x0098f901 = 1)"),
            std::string::npos);
  EXPECT_NE(
      err(small("/dev/video1", "RGB3")).find("pixel format 'RGB3': expected GREY, Y16 or YUYV"),
      std::string::npos);
}

struct StereoRigFake {
  test::FakeV4l2 io;
  V4l2StereoConfig config;
  std::unique_ptr<CameraSource> source;
  StereoFrame frame;
  explicit StereoRigFake(TriggerBox* box = nullptr, double fps = 100.0) {
    io.period_ns = static_cast<int64_t>(1e9 / fps);
    io.add("/dev/video0");
    io.add("/dev/video1").value_offset = 0;
    config.left = small("/dev/video0");
    config.right = small("/dev/video1");
    config.fps = fps;
    config.reopen_ms = 50;
    frame.left.create(48, 64, CV_8UC1);
    frame.right.create(48, 64, CV_8UC1);
    source = makeV4l2Source(io, config, sim::paperRig(), box);
  }
  // The trigger number the pixels carry (mod 251), checked equal in both images.
  int value() const {
    const int l = frame.left.at<uint8_t>(10, 10), r = frame.right.at<uint8_t>(10, 10);
    EXPECT_EQ(l, r) << "a pair of two triggers' frames";
    EXPECT_EQ(cv::countNonZero(frame.left != l), 0);
    return l;
  }
};

TEST(V4l2Source, PairsEveryTriggerAndCountsMissedPulsesAndDroppedFrames) {
  StereoRigFake rig;
  rig.io.device("/dev/video1").misses = [](uint64_t k) {
    return k % 7 == 3;
  };  // the pulse never reached it
  rig.io.device("/dev/video0").drops = [](uint64_t k) {
    return k % 11 == 5;
  };  // the driver dropped it
  rig.io.device("/dev/video0").spurious_eagain = [](uint64_t k) { return k % 13 == 0; };
  ASSERT_TRUE(rig.source->start());
  EXPECT_NE(rig.source->triggerState().find("free-running"), std::string::npos);
  int pairs = 0;
  uint64_t last_seq = 0;
  for (int i = 0; i < 120; ++i) {
    ASSERT_EQ(rig.source->next(rig.frame, std::chrono::milliseconds(1000)), Next::kFrame)
        << rig.source->lastFault();
    const int v = rig.value();
    const uint64_t k = rig.frame.trigger_seq;  // pulses since the first pair (trigger 0)
    EXPECT_EQ(static_cast<uint64_t>(v), k % 251);
    EXPECT_FALSE(k % 7 == 3 || k % 11 == 5) << "trigger " << k << " was incomplete";
    if (pairs > 0) {
      EXPECT_GT(k, last_seq);
    }
    last_seq = k;
    ++pairs;
  }
  const SourceCounters c = rig.source->counters();
  EXPECT_EQ(c.frames, 120U);
  // Of the triggers up to the last pair: one camera's frame alone is unpaired; neither camera's
  // (both faults on one pulse) is a missing trigger.
  uint64_t one = 0, none = 0;
  for (uint64_t k = 0; k < last_seq; ++k) {
    const bool a = k % 7 == 3, b = k % 11 == 5;
    one += a != b ? 1 : 0;
    none += a && b ? 1 : 0;
  }
  EXPECT_EQ(c.unpaired, one);
  EXPECT_EQ(c.missing_triggers, none);
  EXPECT_GE(c.dropped, last_seq / 11);  // the left counter's gaps
  rig.source->stop();
}

TEST(V4l2Source, UnpluggedMidStreamIsAFaultThenItComesBack) {
  StereoRigFake rig;
  ASSERT_TRUE(rig.source->start());
  for (int i = 0; i < 10; ++i)
    ASSERT_EQ(rig.source->next(rig.frame, std::chrono::milliseconds(1000)), Next::kFrame);
  rig.io.unplug("/dev/video1");
  ASSERT_EQ(rig.source->next(rig.frame, std::chrono::milliseconds(1000)), Next::kFault);
  EXPECT_NE(rig.source->lastFault().find("/dev/video1"), std::string::npos)
      << rig.source->lastFault();
  // Still away: reopening fails and says why.
  std::this_thread::sleep_for(std::chrono::milliseconds(60));
  ASSERT_EQ(rig.source->next(rig.frame, std::chrono::milliseconds(100)), Next::kFault);
  EXPECT_NE(rig.source->lastFault().find("/dev/video1: cannot open: No such file"),
            std::string::npos)
      << rig.source->lastFault();
  rig.io.plug("/dev/video1");
  Next n = Next::kFault;
  for (int i = 0; i < 50 && n != Next::kFrame; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
    n = rig.source->next(rig.frame, std::chrono::milliseconds(200));
  }
  ASSERT_EQ(n, Next::kFrame) << rig.source->lastFault();
  for (int i = 0; i < 10; ++i) {
    ASSERT_EQ(rig.source->next(rig.frame, std::chrono::milliseconds(1000)), Next::kFrame);
    (void)rig.value();
  }
}

TEST(V4l2Source, ACameraThatStopsSendingIsAFaultNamingIt) {
  StereoRigFake rig;
  bool silent = false;
  rig.io.device("/dev/video0").misses = [&](uint64_t) { return silent; };
  ASSERT_TRUE(rig.source->start());
  for (int i = 0; i < 5; ++i)
    ASSERT_EQ(rig.source->next(rig.frame, std::chrono::milliseconds(1000)), Next::kFrame);
  silent = true;
  Next n = Next::kTimeout;
  for (int i = 0; i < 40 && n != Next::kFault; ++i)
    n = rig.source->next(rig.frame, std::chrono::milliseconds(100));
  ASSERT_EQ(n, Next::kFault);
  EXPECT_NE(rig.source->lastFault().find("/dev/video0: no frame for"), std::string::npos)
      << rig.source->lastFault();
  silent = false;
  for (int i = 0; i < 50 && n != Next::kFrame; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
    n = rig.source->next(rig.frame, std::chrono::milliseconds(200));
  }
  ASSERT_EQ(n, Next::kFrame) << rig.source->lastFault();
  (void)rig.value();
}

// A trigger box that hears every pulse (and loses some reports): the pairs carry its numbers.
class FakeHid final : public HidDevice {
 public:
  std::mutex m;
  std::deque<std::array<uint8_t, kTriggerReportSize>> in;
  std::vector<std::array<uint8_t, kTriggerReportSize>> out;
  int write(std::span<const uint8_t> r) override {
    std::lock_guard<std::mutex> l(m);
    out.emplace_back();
    std::copy(r.begin(), r.end(), out.back().begin());
    return static_cast<int>(r.size());
  }
  int read(std::span<uint8_t> r, int timeout_ms) override {
    for (int waited = 0;; waited += 1) {
      {
        std::lock_guard<std::mutex> l(m);
        if (!in.empty()) {
          std::copy(in.front().begin(), in.front().end(), r.begin());
          in.pop_front();
          return static_cast<int>(kTriggerReportSize);
        }
      }
      if (waited >= timeout_ms) return 0;
      std::this_thread::sleep_for(std::chrono::milliseconds(1));
    }
  }
  std::string name() const override { return "fake box"; }
  std::string lastError() const override { return {}; }
};

TEST(V4l2Source, PairsCarryTheTriggerBoxsPulseNumbers) {
  auto hid = std::make_unique<FakeHid>();
  FakeHid* h = hid.get();
  // 25 Hz: a pair takes its number from the report whose host time (the box's clock mapped by
  // the smallest report delay seen) is within half a period. Under qemu on a loaded CI machine
  // every early report was read more than 5 ms late, so 100 Hz numbered a pair one pulse off;
  // a real box's USB reports arrive within a millisecond or two.
  TriggerBox box(std::move(hid), 25.0);
  StereoRigFake rig(&box, 25.0);
  const uint64_t first = 1000;  // the box was already counting
  rig.io.on_pulse = [&](uint64_t k, int64_t t) {
    if (k % 13 == 6) return;  // a report lost on the bus: the pulse still fired
    std::lock_guard<std::mutex> l(h->m);
    h->in.push_back(
        encodePulse(static_cast<uint32_t>(first + k), static_cast<uint64_t>(t / 1000) + 777));
  };
  rig.io.device("/dev/video1").misses = [](uint64_t k) { return k % 9 == 4; };
  ASSERT_TRUE(box.start());
  ASSERT_TRUE(rig.source->start());
  int with_box = 0;
  for (int i = 0; i < 60; ++i) {
    ASSERT_EQ(rig.source->next(rig.frame, std::chrono::milliseconds(1000)), Next::kFrame);
    const int v = rig.value();
    if (rig.frame.trigger_seq >= first) {
      EXPECT_EQ((rig.frame.trigger_seq - first) % 251, static_cast<uint64_t>(v));
      ++with_box;
    }
  }
  std::cout << box.state() << ", last pair " << rig.frame.trigger_seq << "\n";
  EXPECT_GT(with_box, 50);  // the first pairs may come before the box's first reports
  EXPECT_GT(box.counters().lost(), 2U);
  EXPECT_NE(rig.source->triggerState().find("trigger box fake box: "), std::string::npos)
      << rig.source->triggerState();
  box.stop();
}

// On a real device (vivid, or a camera) when there is one.
// One device carrying both views (a stereo microscope's side-by-side or top-bottom output through
// a capture card): each frame is a pair, split into the two images; the device's sequence numbers
// the pairs and its gaps count as dropped frames; a frame of the wrong size for the rig is a
// named error; an unplugged device is a fault and comes back.
TEST(V4l2Source, OneDeviceSideBySideOrTopBottomIsAStereoSource) {
  EXPECT_EQ(layoutFrameSize(StereoLayout::kTwoCameras, {64, 48}), cv::Size(64, 48));
  EXPECT_EQ(layoutViewSize(StereoLayout::kTwoCameras, {64, 48}), cv::Size(64, 48));
  for (const StereoLayout layout : {StereoLayout::kSideBySide, StereoLayout::kTopBottom}) {
    const bool sbs = layout == StereoLayout::kSideBySide;
    SCOPED_TRACE(sbs ? "side by side" : "top-bottom");
    EXPECT_EQ(layoutFrameSize(layout, {64, 48}), cv::Size(sbs ? 128 : 64, sbs ? 48 : 96));
    EXPECT_EQ(layoutViewSize(layout, {sbs ? 129 : 64, sbs ? 48 : 97}), cv::Size(64, 48));
    test::FakeV4l2 io;
    io.period_ns = 10'000'000;
    auto& dev = io.add("/dev/video2");
    dev.width = sbs ? 128 : 64;
    dev.height = sbs ? 48 : 96;
    // The left view holds the trigger number, the right one 100 more (mod 251).
    dev.paint = [&dev, sbs](uint64_t k, uint8_t* data, uint32_t stride) {
      for (int y = 0; y < dev.height; ++y) {
        for (int x = 0; x < dev.width; ++x) {
          const bool right = sbs ? x >= dev.width / 2 : y >= dev.height / 2;
          data[static_cast<size_t>(y) * stride + static_cast<size_t>(x)] =
              static_cast<uint8_t>((k + (right ? 100 : 0)) % 251);
        }
      }
    };
    dev.drops = [](uint64_t k) { return k % 9 == 4; };
    V4l2StereoConfig config;
    config.layout = layout;
    config.left = small("/dev/video2");
    config.left.width = dev.width;
    config.left.height = dev.height;
    config.fps = 100.0;
    config.reopen_ms = 50;
    auto rig = vision::rectifiedRig(100.0, {32, 24}, 5.0, {64, 48}, "test rig");
    ASSERT_TRUE(rig) << rig.error().message;
    auto source = makeV4l2Source(io, config, *rig);
    ASSERT_TRUE(source->start());
    EXPECT_NE(source->triggerState().find("the two views are exposed together"), std::string::npos);
    EXPECT_NE(source->name().find("/dev/video2"), std::string::npos);
    StereoFrame frame;
    frame.left.create(48, 64, CV_8UC1);
    frame.right.create(48, 64, CV_8UC1);
    uint64_t first = 0, last = 0;
    for (int i = 0; i < 40; ++i) {
      ASSERT_EQ(source->next(frame, std::chrono::milliseconds(1000)), Next::kFrame)
          << source->lastFault();
      const int l = frame.left.at<uint8_t>(0, 0);
      EXPECT_EQ(cv::countNonZero(frame.left != l), 0) << "a view mixes the two halves";
      EXPECT_EQ(cv::countNonZero(frame.right != (l + 100) % 251), 0);
      EXPECT_EQ(frame.t_left_ns, frame.t_right_ns);
      if (i == 0) first = frame.trigger_seq;
      EXPECT_TRUE(i == 0 || frame.trigger_seq > last);
      last = frame.trigger_seq;
    }
    const SourceCounters c = source->counters();
    EXPECT_EQ(c.frames, 40U);
    EXPECT_EQ(c.dropped, last - first - 39);  // every gap in the sequence is a dropped frame
    EXPECT_GE(c.dropped, 3U);
    // Unplugged: a fault naming the device; plugged back: frames again.
    io.unplug("/dev/video2");
    ASSERT_EQ(source->next(frame, std::chrono::milliseconds(1000)), Next::kFault);
    EXPECT_NE(source->lastFault().find("/dev/video2"), std::string::npos) << source->lastFault();
    io.plug("/dev/video2");
    Next n = Next::kFault;
    for (int i = 0; i < 50 && n != Next::kFrame; ++i) {
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
      n = source->next(frame, std::chrono::milliseconds(200));
    }
    ASSERT_EQ(n, Next::kFrame) << source->lastFault();
    EXPECT_GT(frame.trigger_seq, last);
    source->stop();

    // A frame that is not two of the rig's views: named, with both sizes.
    config.left.width = sbs ? 100 : 64;
    config.left.height = sbs ? 48 : 90;
    auto wrong = makeV4l2Source(io, config, *rig);
    auto ok = wrong->start();
    ASSERT_FALSE(ok);
    EXPECT_NE(ok.error().message.find(sbs ? "/dev/video2: a side by side frame of 100x48 holds two "
                                            "50x48 views; the rig's cameras are 64x48"
                                          : "/dev/video2: a top-bottom frame of 64x90 holds two "
                                            "64x45 views; the rig's cameras are 64x48"),
              std::string::npos)
        << ok.error().message;
  }
}

TEST(V4l2Device, RealDeviceStreamsWhenPresent) {
  std::string dev;
  for (int i = 0; i < 8 && dev.empty(); ++i) {
    const std::string p = "/dev/video" + std::to_string(i);
    if (std::filesystem::exists(p)) dev = p;
  }
  if (dev.empty())
    GTEST_SKIP()
        << "SKIP: no /dev/video* on this machine: the V4L2 driver ran only through its seam";
  // What the device offers, asked of the kernel directly (not through the code under test): a
  // device that offers one of the driver's formats must stream through it, else the test fails.
  const int fd = ::open(dev.c_str(), O_RDWR | O_NONBLOCK);
  ASSERT_GE(fd, 0) << dev << ": " << std::strerror(errno);
  std::string format;
  uint32_t width = 0, height = 0;
  for (uint32_t i = 0; format.empty(); ++i) {
    v4l2_fmtdesc fd_desc{};
    fd_desc.index = i;
    fd_desc.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    if (::ioctl(fd, VIDIOC_ENUM_FMT, &fd_desc) != 0) break;
    const uint32_t f = fd_desc.pixelformat;
    const char* name = f == V4L2_PIX_FMT_GREY   ? "GREY"
                       : f == V4L2_PIX_FMT_Y16  ? "Y16"
                       : f == V4L2_PIX_FMT_YUYV ? "YUYV"
                                                : nullptr;
    if (name == nullptr) continue;
    v4l2_frmsizeenum size{};
    size.index = 0;
    size.pixel_format = f;
    if (::ioctl(fd, VIDIOC_ENUM_FRAMESIZES, &size) != 0) continue;
    width = size.type == V4L2_FRMSIZE_TYPE_DISCRETE ? size.discrete.width : size.stepwise.max_width;
    height =
        size.type == V4L2_FRMSIZE_TYPE_DISCRETE ? size.discrete.height : size.stepwise.max_height;
    format = name;
  }
  ::close(fd);
  if (format.empty())
    GTEST_SKIP() << "SKIP: " << dev
                 << " offers none of GREY, Y16, YUYV (not a camera for this rig)";
  std::cout << dev << ": " << format << " " << width << "x" << height << "\n";
  V4l2CameraConfig c;
  c.device = dev;
  c.width = static_cast<int>(width);
  c.height = static_cast<int>(height);
  c.pixel_format = format;
  V4l2Camera cam(systemV4l2Io(), c);
  auto ok = cam.open();
  ASSERT_TRUE(ok) << dev << " offers " << format << " " << width << "x" << height
                  << " but the driver failed: " << ok.error().message;
  pollfd p{cam.fd(), POLLIN, 0};
  ASSERT_EQ(systemV4l2Io().poll(&p, 1, 2000), 1);
  int index = -1;
  CameraStamp s;
  ASSERT_EQ(cam.dequeue(index, s), V4l2Camera::Dequeue::kFrame) << cam.lastError();
  EXPECT_GT(s.t_ns, 0);
  cv::Mat out(static_cast<int>(height), static_cast<int>(width), CV_8UC1);
  cam.convert(index, out);
  EXPECT_TRUE(cam.requeue(index));
}

}  // namespace
}  // namespace pulsetrack::drivers
