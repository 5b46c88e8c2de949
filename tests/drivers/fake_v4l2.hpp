#pragma once
// An emulation of the kernel's V4L2 streaming state machine behind the driver's syscall seam
// (docs.kernel.org/userspace-api/media/v4l/mmap.html, vidioc-qbuf.html, func-poll.html):
// buffers are idle, queued (QBUF), filled by the device when a trigger pulse comes (oldest
// queued first; with none queued the frame is dropped and the sequence number still advances),
// and done until DQBUF; DQBUF on a non-blocking fd with nothing done is EAGAIN; poll is POLLIN
// when a buffer is done and POLLERR when not streaming; an unplugged device makes every call
// ENODEV and poll POLLERR | POLLHUP, and open ENOENT until it is plugged back.
//
// Trigger pulses come from a schedule on the real monotonic clock (poll sleeps until the next
// one), so the driver runs as it would on a board. Each image's pixels hold the trigger number
// (mod 251) so a test can check the pairs; faults are injected per camera.

#include <fcntl.h>
#include <linux/videodev2.h>
#include <sys/mman.h>
#include <time.h>

#include <atomic>
#include <cerrno>
#include <cstring>
#include <functional>
#include <map>
#include <mutex>
#include <set>
#include <string>
#include <vector>

#include "pulsetrack/drivers/v4l2.hpp"
#include "pulsetrack/rt/heartbeat.hpp"

namespace pulsetrack::test {

class FakeV4l2 final : public drivers::V4l2Io {
 public:
  struct Device {
    std::string path;
    std::atomic<bool> present{true};  // a test thread may pull the plug while the driver runs
    uint32_t caps = V4L2_CAP_VIDEO_CAPTURE | V4L2_CAP_STREAMING;
    int width = 64, height = 48;
    std::set<uint32_t> formats = {V4L2_PIX_FMT_GREY, V4L2_PIX_FMT_Y16, V4L2_PIX_FMT_YUYV};
    std::set<uint32_t> controls = {V4L2_CID_EXPOSURE_AUTO, V4L2_CID_EXPOSURE_ABSOLUTE,
                                   V4L2_CID_GAIN};
    std::map<uint32_t, int> control_values;
    int max_buffers = 8;
    int value_offset = 0;  // added to the trigger number in the pixels (tells the cameras apart)
    // Faults: the camera misses pulse k (no frame, no sequence step); the driver drops frame k
    // (the sequence still advances); DQBUF says EAGAIN once before frame k is given.
    std::function<bool(uint64_t)> misses, drops, spurious_eagain;
    // The image of trigger k (GREY): rows of `width` bytes, `bytesperline` apart. Default: every
    // pixel the trigger number.
    std::function<void(uint64_t, uint8_t*, uint32_t)> paint;
    // State.
    uint32_t format = 0, bytesperline = 0;
    bool streaming = false;
    struct Buffer {
      std::vector<uint8_t> data;
      enum State { kIdle, kQueued, kDone } state = kIdle;
      uint32_t sequence = 0, bytesused = 0;
      int64_t t_ns = 0;
      bool mapped = false;
    };
    std::vector<Buffer> buffers;
    std::vector<int> done;  // indices, oldest first
    uint32_t sequence = 0;
    bool eagain_pending = false;
  };

  std::vector<std::string> calls;  // "VIDIOC_QBUF 3", ... for call-order checks
  int64_t period_ns = 10'000'000;  // the trigger: 100 Hz
  int64_t t0_ns = 0;
  uint64_t next_trigger = 0;
  std::function<void(uint64_t, int64_t)> on_pulse;  // a trigger box hears every pulse

  Device& add(const std::string& path) {
    devices_[path].path = path;
    return devices_[path];
  }
  Device& device(const std::string& path) { return devices_.at(path); }
  void unplug(const std::string& path) { devices_.at(path).present = false; }
  void plug(const std::string& path) { devices_.at(path).present = true; }

  int open(const char* path, int) override {
    const auto it = devices_.find(path);
    if (it == devices_.end() || !it->second.present) return fail(ENOENT);
    const int fd = next_fd_++;
    fds_[fd] = &it->second;
    it->second.buffers.clear();
    it->second.done.clear();
    it->second.streaming = false;
    queue_order_[&it->second].clear();
    calls.push_back(std::string("open ") + path);
    return fd;
  }
  int close(int fd) override {
    calls.push_back("close");
    return fds_.erase(fd) == 1 ? 0 : fail(EBADF);
  }
  void* mmap(size_t length, int fd, off_t offset) override {
    Device* d = dev(fd);
    if (d == nullptr || !d->present) return errno = ENODEV, MAP_FAILED;
    const auto i = static_cast<size_t>(offset / kOffsetStep);
    if (i >= d->buffers.size() || d->buffers[i].data.size() != length)
      return errno = EINVAL, MAP_FAILED;
    d->buffers[i].mapped = true;
    calls.push_back("mmap " + std::to_string(i));
    return d->buffers[i].data.data();
  }
  int munmap(void*, size_t) override {
    calls.push_back("munmap");
    return 0;
  }

  int ioctl(int fd, unsigned long request, void* arg) override {
    Device* d = dev(fd);
    if (d == nullptr) return fail(EBADF);
    if (!d->present) return fail(ENODEV);
    switch (request) {
      case VIDIOC_QUERYCAP: {
        calls.emplace_back("VIDIOC_QUERYCAP");
        auto* c = static_cast<v4l2_capability*>(arg);
        *c = {};
        std::strcpy(reinterpret_cast<char*>(c->driver), "fake");
        std::strcpy(reinterpret_cast<char*>(c->card), "fake camera");
        c->capabilities = d->caps | V4L2_CAP_DEVICE_CAPS;
        c->device_caps = d->caps;
        return 0;
      }
      case VIDIOC_S_FMT: {
        calls.emplace_back("VIDIOC_S_FMT");
        auto* f = static_cast<v4l2_format*>(arg);
        if (f->type != V4L2_BUF_TYPE_VIDEO_CAPTURE) return fail(EINVAL);
        if (d->streaming) return fail(EBUSY);
        // As drivers do: the nearest supported format and size, never an error.
        if (!d->formats.contains(f->fmt.pix.pixelformat))
          f->fmt.pix.pixelformat = *d->formats.begin();
        f->fmt.pix.width = static_cast<uint32_t>(d->width);
        f->fmt.pix.height = static_cast<uint32_t>(d->height);
        const uint32_t bpp = f->fmt.pix.pixelformat == V4L2_PIX_FMT_GREY ? 1 : 2;
        f->fmt.pix.bytesperline = static_cast<uint32_t>(d->width) * bpp + 16;  // padded rows
        f->fmt.pix.sizeimage = f->fmt.pix.bytesperline * f->fmt.pix.height;
        d->format = f->fmt.pix.pixelformat;
        d->bytesperline = f->fmt.pix.bytesperline;
        return 0;
      }
      case VIDIOC_S_CTRL: {
        auto* c = static_cast<v4l2_control*>(arg);
        calls.push_back("VIDIOC_S_CTRL " + std::to_string(c->id));
        if (!d->controls.contains(c->id)) return fail(EINVAL);
        d->control_values[c->id] = c->value;
        return 0;
      }
      case VIDIOC_REQBUFS: {
        auto* r = static_cast<v4l2_requestbuffers*>(arg);
        calls.push_back("VIDIOC_REQBUFS " + std::to_string(r->count));
        if (r->memory != V4L2_MEMORY_MMAP || r->type != V4L2_BUF_TYPE_VIDEO_CAPTURE)
          return fail(EINVAL);
        if (d->streaming) return fail(EBUSY);
        r->count = std::min<uint32_t>(r->count, static_cast<uint32_t>(d->max_buffers));
        d->buffers.assign(r->count, {});
        for (auto& b : d->buffers)
          b.data.assign(static_cast<size_t>(d->bytesperline) * static_cast<size_t>(d->height), 0);
        d->done.clear();
        queue_order_[d].clear();
        return 0;
      }
      case VIDIOC_QUERYBUF: {
        auto* b = static_cast<v4l2_buffer*>(arg);
        calls.push_back("VIDIOC_QUERYBUF " + std::to_string(b->index));
        if (b->index >= d->buffers.size()) return fail(EINVAL);
        b->length = static_cast<uint32_t>(d->buffers[b->index].data.size());
        b->m.offset = b->index * static_cast<uint32_t>(kOffsetStep);
        return 0;
      }
      case VIDIOC_QBUF: {
        auto* b = static_cast<v4l2_buffer*>(arg);
        calls.push_back("VIDIOC_QBUF " + std::to_string(b->index));
        if (b->index >= d->buffers.size() || d->buffers[b->index].state != Device::Buffer::kIdle)
          return fail(EINVAL);
        d->buffers[b->index].state = Device::Buffer::kQueued;
        queue_order_[d].push_back(static_cast<int>(b->index));
        return 0;
      }
      case VIDIOC_STREAMON:
        calls.emplace_back("VIDIOC_STREAMON");
        if (d->buffers.empty()) return fail(EINVAL);
        d->streaming = true;
        return 0;
      case VIDIOC_STREAMOFF:
        calls.emplace_back("VIDIOC_STREAMOFF");
        d->streaming = false;
        for (auto& b : d->buffers)
          b.state = Device::Buffer::kIdle;  // all buffers return to the user
        d->done.clear();
        queue_order_[d].clear();
        return 0;
      case VIDIOC_DQBUF: {
        auto* b = static_cast<v4l2_buffer*>(arg);
        if (!d->streaming) return fail(EINVAL);
        if (d->done.empty()) return fail(EAGAIN);
        const int i = d->done.front();
        Device::Buffer& buf = d->buffers[static_cast<size_t>(i)];
        if (d->eagain_pending) {
          d->eagain_pending = false;
          return fail(EAGAIN);
        }
        d->done.erase(d->done.begin());
        buf.state = Device::Buffer::kIdle;
        b->index = static_cast<uint32_t>(i);
        b->sequence = buf.sequence;
        b->bytesused = buf.bytesused;
        b->flags = V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC;
        b->timestamp.tv_sec = buf.t_ns / 1'000'000'000;
        b->timestamp.tv_usec = (buf.t_ns % 1'000'000'000) / 1000;
        return 0;
      }
      default:
        return fail(ENOTTY);
    }
  }

  int poll(pollfd* fds, nfds_t n, int timeout_ms) override {
    const int64_t until = rt::monotonicNs() + int64_t{timeout_ms} * 1'000'000;
    for (;;) {
      int ready = 0;
      for (nfds_t i = 0; i < n; ++i) {
        fds[i].revents = 0;
        Device* d = dev(fds[i].fd);
        if (d == nullptr) {
          fds[i].revents = POLLNVAL;
        } else if (!d->present) {
          fds[i].revents = POLLERR | POLLHUP;
        } else if (!d->streaming) {
          fds[i].revents = POLLERR;
        } else if (!d->done.empty()) {
          fds[i].revents = POLLIN;
        }
        ready += fds[i].revents != 0 ? 1 : 0;
      }
      if (ready > 0) return ready;
      if (t0_ns == 0) t0_ns = rt::monotonicNs();
      const int64_t due = t0_ns + static_cast<int64_t>(next_trigger) * period_ns;
      if (due > until) {
        sleepUntil(until);
        return 0;
      }
      sleepUntil(due);
      fire(next_trigger++, due);
    }
  }

 private:
  static constexpr off_t kOffsetStep = 1 << 24;
  static int fail(int e) {
    errno = e;
    return -1;
  }
  static void sleepUntil(int64_t t) {
    timespec ts{static_cast<time_t>(t / 1'000'000'000), static_cast<long>(t % 1'000'000'000)};
    while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, nullptr) == EINTR) {
    }
  }
  Device* dev(int fd) {
    const auto it = fds_.find(fd);
    return it == fds_.end() ? nullptr : it->second;
  }
  void fire(uint64_t k, int64_t t) {
    if (on_pulse) on_pulse(k, t);
    for (auto& [path, d] : devices_) {
      if (!d.present || !d.streaming) continue;
      if (d.misses && d.misses(k)) continue;
      const uint32_t seq = d.sequence++;
      auto& order = queue_order_[&d];
      if ((d.drops && d.drops(k)) || order.empty()) continue;  // dropped: the sequence advanced
      const int i = order.front();
      order.erase(order.begin());
      Device::Buffer& b = d.buffers[static_cast<size_t>(i)];
      const auto value = static_cast<uint8_t>((k + static_cast<uint64_t>(d.value_offset)) % 251);
      if (d.paint) d.paint(k, b.data.data(), d.bytesperline);
      for (int y = 0; y < d.height && !d.paint; ++y) {
        uint8_t* row = b.data.data() + static_cast<size_t>(y) * d.bytesperline;
        for (int x = 0; x < d.width; ++x) {
          if (d.format == V4L2_PIX_FMT_GREY) {
            row[x] = value;
          } else if (d.format == V4L2_PIX_FMT_Y16) {
            row[2 * x] = static_cast<uint8_t>(x);  // low byte: dropped by the conversion
            row[2 * x + 1] = value;
          } else {
            row[2 * x] = value;
            row[2 * x + 1] = 128;  // chroma
          }
        }
      }
      b.state = Device::Buffer::kDone;
      b.sequence = seq;
      b.bytesused = static_cast<uint32_t>(b.data.size());
      b.t_ns = t + 3000;  // exposure a few us after the pulse
      d.done.push_back(i);
      if (d.spurious_eagain && d.spurious_eagain(k)) d.eagain_pending = true;
    }
  }

  std::map<std::string, Device> devices_;
  std::map<int, Device*> fds_;
  std::map<Device*, std::vector<int>> queue_order_;
  int next_fd_ = 100;
};

}  // namespace pulsetrack::test
