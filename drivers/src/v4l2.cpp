#include "pulsetrack/drivers/v4l2.hpp"

#include <fcntl.h>
#include <fmt/format.h>
#include <linux/videodev2.h>
#include <sys/ioctl.h>
#include <sys/mman.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>

#include "paired_frames.hpp"
#include "pulsetrack/drivers/trigger_box.hpp"
#include "pulsetrack/rt/heartbeat.hpp"

namespace pulsetrack::drivers {

namespace {

class SystemIo final : public V4l2Io {
 public:
  int open(const char* path, int flags) override { return ::open(path, flags); }
  int close(int fd) override { return ::close(fd); }
  int ioctl(int fd, unsigned long request, void* arg) override {
    int r = 0;
    do {
      r = ::ioctl(fd, request, arg);
    } while (r == -1 && errno == EINTR);
    return r;
  }
  void* mmap(size_t length, int fd, off_t offset) override {
    return ::mmap(nullptr, length, PROT_READ | PROT_WRITE, MAP_SHARED, fd, offset);
  }
  int munmap(void* addr, size_t length) override { return ::munmap(addr, length); }
  int poll(pollfd* fds, nfds_t n, int timeout_ms) override { return ::poll(fds, n, timeout_ms); }
};

uint32_t fourcc(const std::string& name) {
  if (name == "GREY") return V4L2_PIX_FMT_GREY;
  if (name == "Y16") return V4L2_PIX_FMT_Y16;
  if (name == "YUYV") return V4L2_PIX_FMT_YUYV;
  return 0;
}

std::string fourccName(uint32_t f) {
  std::string s(4, ' ');
  for (int i = 0; i < 4; ++i) s[static_cast<size_t>(i)] = static_cast<char>((f >> (8 * i)) & 0xff);
  return s;
}

}  // namespace

V4l2Io& systemV4l2Io() {
  static SystemIo io;
  return io;
}

V4l2Camera::V4l2Camera(V4l2Io& io, V4l2CameraConfig config) : io_(io), config_(std::move(config)) {
  fourcc_ = fourcc(config_.pixel_format);
}

V4l2Camera::~V4l2Camera() { close(); }

vision::Result<void> V4l2Camera::fail(const std::string& step) {
  const int e = errno;
  error_ = fmt::format("{}: {}: {}", config_.device, step, e != 0 ? std::strerror(e) : "failed");
  close();
  return vision::fail(error_);
}

bool V4l2Camera::setControl(uint32_t id, int value) {
  v4l2_control c{};
  c.id = id;
  c.value = value;
  return io_.ioctl(fd_, VIDIOC_S_CTRL, &c) == 0;
}

vision::Result<void> V4l2Camera::open() {
  close();
  if (fourcc_ == 0)
    return vision::fail(fmt::format("{}: pixel format '{}': expected GREY, Y16 or YUYV",
                                    config_.device, config_.pixel_format));
  errno = 0;
  fd_ = io_.open(config_.device.c_str(), O_RDWR | O_NONBLOCK | O_CLOEXEC);
  if (fd_ < 0) return fail("cannot open");
  v4l2_capability cap{};
  if (io_.ioctl(fd_, VIDIOC_QUERYCAP, &cap) != 0)
    return fail("VIDIOC_QUERYCAP (not a V4L2 device?)");
  const uint32_t caps =
      (cap.capabilities & V4L2_CAP_DEVICE_CAPS) != 0 ? cap.device_caps : cap.capabilities;
  if ((caps & V4L2_CAP_VIDEO_CAPTURE) == 0 || (caps & V4L2_CAP_STREAMING) == 0) {
    errno = 0;
    return fail(fmt::format("'{}' ({}) is not a streaming capture device",
                            reinterpret_cast<const char*>(cap.card),
                            reinterpret_cast<const char*>(cap.driver)));
  }
  v4l2_format fmt{};
  fmt.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  fmt.fmt.pix.width = static_cast<uint32_t>(config_.width);
  fmt.fmt.pix.height = static_cast<uint32_t>(config_.height);
  fmt.fmt.pix.pixelformat = fourcc_;
  fmt.fmt.pix.field = V4L2_FIELD_NONE;
  if (io_.ioctl(fd_, VIDIOC_S_FMT, &fmt) != 0) return fail("VIDIOC_S_FMT");
  if (fmt.fmt.pix.pixelformat != fourcc_ ||
      fmt.fmt.pix.width != static_cast<uint32_t>(config_.width) ||
      fmt.fmt.pix.height != static_cast<uint32_t>(config_.height)) {
    errno = 0;
    return fail(fmt::format("the camera offers {}x{} {} where the config asks {}x{} {}",
                            fmt.fmt.pix.width, fmt.fmt.pix.height,
                            fourccName(fmt.fmt.pix.pixelformat), config_.width, config_.height,
                            config_.pixel_format));
  }
  const uint32_t bpp = fourcc_ == V4L2_PIX_FMT_GREY ? 1 : 2;
  bytes_per_line_ = std::max(fmt.fmt.pix.bytesperline, static_cast<uint32_t>(config_.width) * bpp);
  if (config_.exposure_us) {
    (void)setControl(V4L2_CID_EXPOSURE_AUTO, V4L2_EXPOSURE_MANUAL);  // not every camera has it
    if (!setControl(V4L2_CID_EXPOSURE_ABSOLUTE, std::max(1, *config_.exposure_us / 100)))
      return fail(fmt::format("setting the exposure to {} us", *config_.exposure_us));
  }
  if (config_.gain && !setControl(V4L2_CID_GAIN, *config_.gain))
    return fail(fmt::format("setting the gain to {}", *config_.gain));
  if (config_.trigger_control != 0 && !setControl(config_.trigger_control, config_.trigger_value))
    return fail(fmt::format("selecting the external trigger (control 0x{:08x} = {})",
                            config_.trigger_control, config_.trigger_value));
  v4l2_requestbuffers req{};
  req.count = static_cast<uint32_t>(config_.buffers);
  req.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  req.memory = V4L2_MEMORY_MMAP;
  if (io_.ioctl(fd_, VIDIOC_REQBUFS, &req) != 0) return fail("VIDIOC_REQBUFS (memory mapping)");
  if (req.count < 2) {
    errno = 0;
    return fail(fmt::format("the driver gives {} buffer(s), at least 2 are needed", req.count));
  }
  buffers_.assign(req.count, {});
  for (uint32_t i = 0; i < req.count; ++i) {
    v4l2_buffer b{};
    b.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    b.memory = V4L2_MEMORY_MMAP;
    b.index = i;
    if (io_.ioctl(fd_, VIDIOC_QUERYBUF, &b) != 0) return fail(fmt::format("VIDIOC_QUERYBUF {}", i));
    void* p = io_.mmap(b.length, fd_, static_cast<off_t>(b.m.offset));
    if (p == MAP_FAILED) return fail(fmt::format("mmap of buffer {}", i));
    buffers_[i] = {p, b.length};
    if (b.length < bytes_per_line_ * static_cast<uint32_t>(config_.height)) {
      errno = 0;
      return fail(fmt::format("buffer {} holds {} bytes, a frame needs {}", i, b.length,
                              bytes_per_line_ * static_cast<uint32_t>(config_.height)));
    }
    if (io_.ioctl(fd_, VIDIOC_QBUF, &b) != 0) return fail(fmt::format("VIDIOC_QBUF {}", i));
  }
  int type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  if (io_.ioctl(fd_, VIDIOC_STREAMON, &type) != 0) return fail("VIDIOC_STREAMON");
  streaming_ = true;
  error_.clear();
  return {};
}

void V4l2Camera::close() {
  if (fd_ < 0) return;
  if (streaming_) {
    int type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    (void)io_.ioctl(fd_, VIDIOC_STREAMOFF, &type);
    streaming_ = false;
  }
  for (const Buffer& b : buffers_) {
    if (b.data != nullptr) (void)io_.munmap(b.data, b.length);
  }
  if (!buffers_.empty()) {
    v4l2_requestbuffers req{};
    req.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    req.memory = V4L2_MEMORY_MMAP;
    (void)io_.ioctl(fd_, VIDIOC_REQBUFS, &req);  // count 0: free them (fails harmlessly if gone)
  }
  buffers_.clear();
  (void)io_.close(fd_);
  fd_ = -1;
}

V4l2Camera::Dequeue V4l2Camera::dequeue(int& index, CameraStamp& stamp) {
  v4l2_buffer b{};
  b.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  b.memory = V4L2_MEMORY_MMAP;
  if (io_.ioctl(fd_, VIDIOC_DQBUF, &b) != 0) {
    const int e = errno;
    if (e == EAGAIN) return Dequeue::kAgain;
    error_ = fmt::format("{}: VIDIOC_DQBUF: {}{}", config_.device, std::strerror(e),
                         e == ENODEV ? " (the camera went away)" : "");
    return e == ENODEV ? Dequeue::kGone : Dequeue::kError;
  }
  if (b.index >= buffers_.size()) {
    error_ = fmt::format("{}: VIDIOC_DQBUF returned buffer {} of {}", config_.device, b.index,
                         buffers_.size());
    return Dequeue::kError;
  }
  // A frame the driver marks bad, or a short one, is given back and not used.
  if ((b.flags & V4L2_BUF_FLAG_ERROR) != 0 ||
      b.bytesused < bytes_per_line_ * static_cast<uint32_t>(config_.height)) {
    (void)requeue(static_cast<int>(b.index));
    return Dequeue::kAgain;
  }
  index = static_cast<int>(b.index);
  stamp.seq = b.sequence;
  stamp.t_ns = static_cast<int64_t>(b.timestamp.tv_sec) * 1'000'000'000 +
               static_cast<int64_t>(b.timestamp.tv_usec) * 1000;
  stamp.slot = index;
  return Dequeue::kFrame;
}

void V4l2Camera::convert(int index, cv::Mat& out, int x0, int y0) const {
  const auto* data = static_cast<const uint8_t*>(buffers_[static_cast<size_t>(index)].data);
  const auto x = static_cast<size_t>(x0);
  for (int y = 0; y < out.rows; ++y) {
    const uint8_t* row = data + static_cast<size_t>(y + y0) * bytes_per_line_;
    uint8_t* dst = out.ptr<uint8_t>(y);
    if (fourcc_ == V4L2_PIX_FMT_GREY) {
      std::memcpy(dst, row + x, static_cast<size_t>(out.cols));
    } else if (fourcc_ == V4L2_PIX_FMT_Y16) {
      for (int c = 0; c < out.cols; ++c)
        dst[c] = row[2 * (x + static_cast<size_t>(c)) + 1];  // little-endian: the high byte
    } else {
      for (int c = 0; c < out.cols; ++c)
        dst[c] = row[2 * (x + static_cast<size_t>(c))];  // YUYV: the Y bytes
    }
  }
}

bool V4l2Camera::requeue(int index) {
  v4l2_buffer b{};
  b.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  b.memory = V4L2_MEMORY_MMAP;
  b.index = static_cast<uint32_t>(index);
  return io_.ioctl(fd_, VIDIOC_QBUF, &b) == 0;
}

namespace {

// One device after poll(): a frame dequeued (kFrame; the buffer is the caller's until requeue),
// nothing to take (kAgain), or a fault (kGone or kError: the device is closed and `fault` says
// why). Both sources read their devices through it.
V4l2Camera::Dequeue takeReady(V4l2Camera& cam, short revents, int& index, CameraStamp& stamp,
                              std::string& fault) {
  if ((revents & (POLLERR | POLLHUP | POLLNVAL)) != 0 && (revents & POLLIN) == 0) {
    fault = fmt::format("{}: the device reports an error (unplugged?)", cam.device());
    cam.close();
    return V4l2Camera::Dequeue::kError;
  }
  if ((revents & POLLIN) == 0) return V4l2Camera::Dequeue::kAgain;
  const V4l2Camera::Dequeue d = cam.dequeue(index, stamp);
  if (d == V4l2Camera::Dequeue::kFrame || d == V4l2Camera::Dequeue::kAgain) return d;
  fault = cam.lastError();
  cam.close();
  return d;
}

class V4l2StereoSource final : public CameraSource {
 public:
  V4l2StereoSource(V4l2Io& io, const V4l2StereoConfig& c, vision::StereoRig rig,
                   TriggerBox* trigger)
      : io_(io),
        config_(c),
        rig_(std::move(rig)),
        cams_{std::make_unique<V4l2Camera>(io, c.left), std::make_unique<V4l2Camera>(io, c.right)},
        period_ns_(static_cast<int64_t>(1e9 / c.fps)),
        pairs_(period_ns_, trigger) {}

  std::string name() const override {
    return fmt::format("v4l2 {} + {}", config_.left.device, config_.right.device);
  }
  const vision::StereoRig& rig() const override { return rig_; }

  vision::Result<void> start() override {
    for (auto& cam : cams_) {
      if (auto ok = cam->open(); !ok) return ok;
    }
    const int64_t now = rt::monotonicNs();
    last_frame_ns_ = {now, now};
    pairs_.reset();
    return {};
  }

  Next next(StereoFrame& frame, std::chrono::milliseconds timeout) override {
    const int64_t deadline = rt::monotonicNs() + std::chrono::nanoseconds(timeout).count();
    const int64_t silent_after = std::max<int64_t>(1'000'000'000, 5 * period_ns_);
    for (;;) {
      const int64_t now = rt::monotonicNs();
      if (!cams_[0]->isOpen() || !cams_[1]->isOpen()) {
        if (now < next_reopen_ns_) return Next::kFault;
        next_reopen_ns_ = now + int64_t{config_.reopen_ms} * 1'000'000;
        std::array<bool, 2> reopened{};
        for (size_t c = 0; c < 2; ++c) {
          if (cams_[c]->isOpen()) continue;
          if (auto ok = cams_[c]->open(); !ok) {
            fault_ = ok.error().message;
            return Next::kFault;
          }
          reopened[c] = true;
        }
        // Frames waiting for a partner: the reopened camera's buffers were queued afresh by
        // open(), the other camera's are given back.
        const PairEvents dropped = pairs_.reset();
        for (int k = 0; k < dropped.n_released; ++k) {
          const int slot = dropped.released[static_cast<size_t>(k)];
          if (!reopened[static_cast<size_t>(PairedFrames::camera(slot))]) giveBack(slot);
        }
        last_frame_ns_ = {now, now};
      }
      if (now >= deadline) return Next::kTimeout;
      pollfd fds[2] = {{cams_[0]->fd(), POLLIN, 0}, {cams_[1]->fd(), POLLIN, 0}};
      const int wait_ms = static_cast<int>(std::max<int64_t>(1, (deadline - now) / 1'000'000));
      const int r = io_.poll(fds, 2, wait_ms);
      if (r < 0) {
        if (errno == EINTR) continue;
        fault_ = fmt::format("poll: {}", std::strerror(errno));
        return Next::kFault;
      }
      const int64_t t = rt::monotonicNs();
      for (int c = 0; c < 2; ++c) {
        if (t - last_frame_ns_[static_cast<size_t>(c)] > silent_after) {
          fault_ = fmt::format("{}: no frame for {} ms (camera stopped, or trigger cable?)",
                               cams_[static_cast<size_t>(c)]->device(),
                               (t - last_frame_ns_[static_cast<size_t>(c)]) / 1'000'000);
          cams_[static_cast<size_t>(c)]->close();
          return Next::kFault;
        }
      }
      for (int c = 0; c < 2; ++c) {
        int index = 0;
        CameraStamp stamp;
        const V4l2Camera::Dequeue d =
            takeReady(*cams_[static_cast<size_t>(c)], fds[c].revents, index, stamp, fault_);
        if (d == V4l2Camera::Dequeue::kAgain) continue;
        if (d != V4l2Camera::Dequeue::kFrame) return Next::kFault;
        last_frame_ns_[static_cast<size_t>(c)] = t;
        stamp.slot = PairedFrames::slot(c, index);
        const PairEvents ev = pairs_.offer(c, stamp);
        for (int k = 0; k < ev.n_released; ++k) giveBack(ev.released[static_cast<size_t>(k)]);
        if (!ev.paired) continue;
        cams_[0]->convert(PairedFrames::index(ev.left.slot), frame.left);
        cams_[1]->convert(PairedFrames::index(ev.right.slot), frame.right);
        giveBack(ev.left.slot);
        giveBack(ev.right.slot);
        pairs_.emit(ev, frame);
        return Next::kFrame;
      }
    }
  }

  void stop() override {
    for (auto& cam : cams_) cam->close();
  }
  std::string lastFault() const override { return fault_; }
  SourceCounters counters() const override { return pairs_.counters(); }
  std::string triggerState() const override { return pairs_.triggerState(config_.fps); }

 private:
  void giveBack(int slot) {
    V4l2Camera& cam = *cams_[static_cast<size_t>(PairedFrames::camera(slot))];
    if (cam.isOpen()) (void)cam.requeue(PairedFrames::index(slot));
  }

  V4l2Io& io_;
  V4l2StereoConfig config_;
  vision::StereoRig rig_;
  std::array<std::unique_ptr<V4l2Camera>, 2> cams_;
  int64_t period_ns_;
  PairedFrames pairs_;
  std::array<int64_t, 2> last_frame_ns_{};
  int64_t next_reopen_ns_ = 0;
  std::string fault_;
};

// One device carrying both views in each frame (side by side or top-bottom): each frame is a
// pair, split into the caller's two images. The device's sequence numbers the pairs; its gaps
// are frames the driver dropped.
class V4l2SplitSource final : public CameraSource {
 public:
  V4l2SplitSource(V4l2Io& io, const V4l2StereoConfig& c, vision::StereoRig rig)
      : io_(io),
        config_(c),
        rig_(std::move(rig)),
        cam_(io, c.left),
        period_ns_(static_cast<int64_t>(1e9 / c.fps)) {}

  std::string name() const override {
    return fmt::format("v4l2 {} ({})", config_.left.device, layoutName());
  }
  const vision::StereoRig& rig() const override { return rig_; }

  vision::Result<void> start() override {
    const cv::Size view = rig_.left.imageSize();
    const cv::Size whole = layoutFrameSize(config_.layout, view);
    const cv::Size frame(config_.left.width, config_.left.height);
    if (frame != whole) {
      const cv::Size holds = layoutViewSize(config_.layout, frame);
      return vision::fail(fmt::format(
          "{}: a {} frame of {}x{} holds two {}x{} views; the rig's cameras are {}x{} (the frame "
          "must be {}x{})",
          config_.left.device, layoutName(), frame.width, frame.height, holds.width, holds.height,
          view.width, view.height, whole.width, whole.height));
    }
    if (auto ok = cam_.open(); !ok) return ok;
    last_frame_ns_ = rt::monotonicNs();
    have_seq_ = false;
    return {};
  }

  Next next(StereoFrame& frame, std::chrono::milliseconds timeout) override {
    const int64_t deadline = rt::monotonicNs() + std::chrono::nanoseconds(timeout).count();
    const int64_t silent_after = std::max<int64_t>(1'000'000'000, 5 * period_ns_);
    for (;;) {
      const int64_t now = rt::monotonicNs();
      if (!cam_.isOpen()) {
        if (now < next_reopen_ns_) return Next::kFault;
        next_reopen_ns_ = now + int64_t{config_.reopen_ms} * 1'000'000;
        if (auto ok = cam_.open(); !ok) {
          fault_ = ok.error().message;
          return Next::kFault;
        }
        last_frame_ns_ = now;
        have_seq_ = false;  // a reopened device counts from 0 again
      }
      if (now >= deadline) return Next::kTimeout;
      pollfd fd{cam_.fd(), POLLIN, 0};
      const int wait_ms = static_cast<int>(std::max<int64_t>(1, (deadline - now) / 1'000'000));
      const int r = io_.poll(&fd, 1, wait_ms);
      if (r < 0) {
        if (errno == EINTR) continue;
        fault_ = fmt::format("poll: {}", std::strerror(errno));
        return Next::kFault;
      }
      const int64_t t = rt::monotonicNs();
      if (t - last_frame_ns_ > silent_after) {
        fault_ = fmt::format("{}: no frame for {} ms (no video signal, or the cable?)",
                             cam_.device(), (t - last_frame_ns_) / 1'000'000);
        cam_.close();
        return Next::kFault;
      }
      int index = 0;
      CameraStamp stamp;
      const V4l2Camera::Dequeue d = takeReady(cam_, fd.revents, index, stamp, fault_);
      if (d == V4l2Camera::Dequeue::kAgain) continue;
      if (d != V4l2Camera::Dequeue::kFrame) return Next::kFault;
      last_frame_ns_ = t;
      // The pair's number: the device's sequence, continued across a reopen (whose gap is not
      // known: one step).
      if (have_seq_) {
        const uint64_t step = stamp.seq > last_seq_ ? stamp.seq - last_seq_ : 1;
        counters_.dropped += step - 1;
        seq_ += step;
      } else if (counters_.frames > 0) {
        ++seq_;
      }
      last_seq_ = stamp.seq;
      have_seq_ = true;
      const bool sbs = config_.layout == StereoLayout::kSideBySide;
      cam_.convert(index, frame.left, 0, 0);
      cam_.convert(index, frame.right, sbs ? frame.left.cols : 0, sbs ? 0 : frame.left.rows);
      (void)cam_.requeue(index);
      frame.trigger_seq = seq_;
      frame.t_left_ns = stamp.t_ns;
      frame.t_right_ns = stamp.t_ns;
      ++counters_.frames;
      shared_.store(counters_);
      return Next::kFrame;
    }
  }

  void stop() override { cam_.close(); }
  std::string lastFault() const override { return fault_; }
  SourceCounters counters() const override { return shared_.load(); }
  std::string triggerState() const override {
    return fmt::format(
        "one device at {:g} Hz, {}: the two views are exposed together (no pairing, no trigger "
        "box needed)",
        config_.fps, layoutName());
  }

 private:
  [[nodiscard]] const char* layoutName() const {
    return config_.layout == StereoLayout::kSideBySide ? "side by side" : "top-bottom";
  }

  V4l2Io& io_;
  V4l2StereoConfig config_;
  vision::StereoRig rig_;
  V4l2Camera cam_;
  int64_t period_ns_;
  int64_t last_frame_ns_ = 0, next_reopen_ns_ = 0;
  bool have_seq_ = false;
  uint64_t last_seq_ = 0, seq_ = 0;
  SourceCounters counters_;
  SharedCounters shared_;
  std::string fault_;
};

}  // namespace

cv::Size layoutFrameSize(StereoLayout layout, cv::Size view) noexcept {
  switch (layout) {
    case StereoLayout::kSideBySide:
      return {2 * view.width, view.height};
    case StereoLayout::kTopBottom:
      return {view.width, 2 * view.height};
    case StereoLayout::kTwoCameras:
      break;
  }
  return view;
}

cv::Size layoutViewSize(StereoLayout layout, cv::Size frame) noexcept {
  switch (layout) {
    case StereoLayout::kSideBySide:
      return {frame.width / 2, frame.height};
    case StereoLayout::kTopBottom:
      return {frame.width, frame.height / 2};
    case StereoLayout::kTwoCameras:
      break;
  }
  return frame;
}

std::unique_ptr<CameraSource> makeV4l2Source(V4l2Io& io, const V4l2StereoConfig& config,
                                             vision::StereoRig rig, TriggerBox* trigger) {
  if (config.layout != StereoLayout::kTwoCameras)
    return std::make_unique<V4l2SplitSource>(io, config, std::move(rig));
  return std::make_unique<V4l2StereoSource>(io, config, std::move(rig), trigger);
}

}  // namespace pulsetrack::drivers
