#include "pulsetrack/drivers/libcamera_source.hpp"

#include <atomic_queue/atomic_queue.h>
#include <fmt/format.h>
#include <libcamera/libcamera.h>
#include <poll.h>
#include <sys/eventfd.h>
#include <sys/mman.h>
#include <unistd.h>

#include <array>
#include <cstring>
#include <mutex>

#include "paired_frames.hpp"
#include "pulsetrack/drivers/pairing.hpp"
#include "pulsetrack/drivers/trigger_box.hpp"
#include "pulsetrack/rt/heartbeat.hpp"

namespace pulsetrack::drivers {

namespace lc = libcamera;

namespace {

// One CameraManager per process (libcamera allows one), started on first use.
lc::CameraManager& manager() {
  static std::once_flag once;
  static std::unique_ptr<lc::CameraManager> m;
  std::call_once(once, [] {
    m = std::make_unique<lc::CameraManager>();
    (void)m->start();
  });
  return *m;
}

}  // namespace

vision::Result<std::vector<LibcameraInfo>> listLibcameraCameras() {
  std::vector<LibcameraInfo> out;
  for (const std::shared_ptr<lc::Camera>& c : manager().cameras()) {
    const auto model = c->properties().get(lc::properties::Model);
    out.push_back({c->id(), model ? *model : std::string("unknown model")});
  }
  return out;
}

namespace {

class LibcameraStereoSource final : public CameraSource {
 public:
  LibcameraStereoSource(const LibcameraStereoConfig& c, vision::StereoRig rig, TriggerBox* trigger)
      : config_(c),
        rig_(std::move(rig)),
        pairs_(static_cast<int64_t>(1e9 / c.fps), trigger),
        completed_(256) {
    event_fd_ = eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC);
  }
  ~LibcameraStereoSource() override {
    teardown();
    if (event_fd_ >= 0) ::close(event_fd_);
  }
  LibcameraStereoSource(const LibcameraStereoSource&) = delete;
  LibcameraStereoSource& operator=(const LibcameraStereoSource&) = delete;

  std::string name() const override {
    return fmt::format("libcamera {} + {}", config_.left_id, config_.right_id);
  }
  const vision::StereoRig& rig() const override { return rig_; }
  vision::Result<void> start() override { return setup(); }

  Next next(StereoFrame& frame, std::chrono::milliseconds timeout) override {
    const int64_t deadline = rt::monotonicNs() + std::chrono::nanoseconds(timeout).count();
    for (;;) {
      const int64_t now = rt::monotonicNs();
      if (!running_ || disconnected_.load()) {
        if (now < next_reopen_ns_) return Next::kFault;
        next_reopen_ns_ = now + int64_t{config_.reopen_ms} * 1'000'000;
        if (disconnected_.load()) {
          fault_ = "a camera disconnected";
          teardown();
        }
        if (auto ok = setup(); !ok) {
          fault_ = ok.error().message;
          return Next::kFault;
        }
      }
      Completed c{};
      while (completed_.try_pop(c)) {
        lc::Request* r = c.request;
        if (r->status() == lc::Request::RequestCancelled) continue;
        const auto& buffers = r->buffers();
        if (buffers.empty()) continue;
        const lc::FrameBuffer* fb = buffers.begin()->second;
        CameraStamp s;
        s.seq = fb->metadata().sequence;
        const auto ts = r->metadata().get(lc::controls::SensorTimestamp);
        s.t_ns = ts ? *ts : static_cast<int64_t>(fb->metadata().timestamp);
        s.slot = PairedFrames::slot(c.camera, static_cast<int>(r->cookie()));
        const PairEvents ev = pairs_.offer(c.camera, s);
        for (int k = 0; k < ev.n_released; ++k) requeue(ev.released[static_cast<size_t>(k)]);
        if (!ev.paired) continue;
        copyOut(ev.left.slot, frame.left);
        copyOut(ev.right.slot, frame.right);
        requeue(ev.left.slot);
        requeue(ev.right.slot);
        pairs_.emit(ev, frame);
        return Next::kFrame;
      }
      if (now >= deadline) return Next::kTimeout;
      pollfd pfd{event_fd_, POLLIN, 0};
      (void)::poll(&pfd, 1, static_cast<int>(std::max<int64_t>(1, (deadline - now) / 1'000'000)));
      uint64_t v = 0;
      (void)::read(event_fd_, &v, sizeof v);
    }
  }

  void stop() override { teardown(); }
  std::string lastFault() const override { return fault_; }
  SourceCounters counters() const override { return pairs_.counters(); }
  std::string triggerState() const override { return pairs_.triggerState(config_.fps); }

 private:
  struct Completed {
    lc::Request* request = nullptr;
    int camera = 0;
  };
  struct Mapped {
    void* base = nullptr;  // what mmap returned
    const uint8_t* data = nullptr;
    size_t length = 0;
    size_t stride = 0;
  };
  struct Cam {
    std::shared_ptr<lc::Camera> camera;
    std::unique_ptr<lc::CameraConfiguration> config;
    std::unique_ptr<lc::FrameBufferAllocator> allocator;
    std::vector<std::unique_ptr<lc::Request>> requests;
    std::vector<Mapped> maps;
    lc::Stream* stream = nullptr;
    bool started = false;
  };

  vision::Result<void> setupCamera(int index, const std::string& id) {
    Cam& c = cams_[static_cast<size_t>(index)];
    c.camera = manager().get(id);
    if (!c.camera) return vision::fail(fmt::format("libcamera camera '{}': not found", id));
    if (c.camera->acquire() != 0) {
      c.camera.reset();
      return vision::fail(fmt::format("libcamera camera '{}': in use by another process", id));
    }
    c.config = c.camera->generateConfiguration({lc::StreamRole::Raw});
    if (!c.config || c.config->empty())
      return vision::fail(fmt::format("libcamera camera '{}': no raw stream", id));
    lc::StreamConfiguration& sc = c.config->at(0);
    sc.pixelFormat = lc::formats::R8;
    sc.size = lc::Size(static_cast<unsigned>(config_.width), static_cast<unsigned>(config_.height));
    sc.bufferCount = static_cast<unsigned>(config_.buffers);
    if (c.config->validate() == lc::CameraConfiguration::Invalid ||
        sc.pixelFormat != lc::formats::R8 ||
        sc.size !=
            lc::Size(static_cast<unsigned>(config_.width), static_cast<unsigned>(config_.height)))
      return vision::fail(
          fmt::format("libcamera camera '{}': offers {} where the config asks {}x{} R8", id,
                      sc.toString(), config_.width, config_.height));
    if (c.camera->configure(c.config.get()) != 0)
      return vision::fail(fmt::format("libcamera camera '{}': configure failed", id));
    c.stream = sc.stream();
    c.allocator = std::make_unique<lc::FrameBufferAllocator>(c.camera);
    if (c.allocator->allocate(c.stream) < 2)
      return vision::fail(fmt::format("libcamera camera '{}': could not allocate buffers", id));
    const auto& buffers = c.allocator->buffers(c.stream);
    for (size_t i = 0; i < buffers.size(); ++i) {
      const lc::FrameBuffer::Plane& plane = buffers[i]->planes()[0];
      void* p =
          ::mmap(nullptr, plane.offset + plane.length, PROT_READ, MAP_SHARED, plane.fd.get(), 0);
      if (p == MAP_FAILED)
        return vision::fail(fmt::format("libcamera camera '{}': mmap of buffer {}: {}", id, i,
                                        std::strerror(errno)));
      c.maps.push_back({p, static_cast<const uint8_t*>(p) + plane.offset,
                        plane.offset + plane.length, sc.stride});
      std::unique_ptr<lc::Request> r = c.camera->createRequest(i);
      if (!r || r->addBuffer(c.stream, buffers[i].get()) != 0)
        return vision::fail(
            fmt::format("libcamera camera '{}': request {} could not be made", id, i));
      c.requests.push_back(std::move(r));
    }
    c.camera->requestCompleted.connect(
        this, index == 0 ? &LibcameraStereoSource::onLeft : &LibcameraStereoSource::onRight);
    c.camera->disconnected.connect(this, &LibcameraStereoSource::onDisconnected);
    if (c.camera->start() != 0)
      return vision::fail(fmt::format("libcamera camera '{}': start failed", id));
    c.started = true;
    for (auto& r : c.requests) {
      if (c.camera->queueRequest(r.get()) != 0)
        return vision::fail(fmt::format("libcamera camera '{}': queueing a request failed", id));
    }
    return {};
  }

  vision::Result<void> setup() {
    teardown();
    disconnected_.store(false);
    for (int i = 0; i < 2; ++i) {
      if (auto ok = setupCamera(i, i == 0 ? config_.left_id : config_.right_id); !ok) {
        teardown();
        return ok;
      }
    }
    (void)pairs_.reset();
    running_ = true;
    return {};
  }

  void teardown() {
    running_ = false;
    for (Cam& c : cams_) {
      if (c.camera) {
        if (c.started) (void)c.camera->stop();
        c.camera->requestCompleted.disconnect(this);
        c.camera->disconnected.disconnect(this);
        c.requests.clear();
        for (const Mapped& m : c.maps) (void)::munmap(m.base, m.length);
        c.maps.clear();
        if (c.allocator && c.stream != nullptr) (void)c.allocator->free(c.stream);
        c.allocator.reset();
        c.config.reset();
        (void)c.camera->release();
        c.camera.reset();
      }
      c = Cam{};
    }
    Completed drop{};
    while (completed_.try_pop(drop)) {
    }
  }

  void onLeft(lc::Request* r) { onComplete(r, 0); }
  void onRight(lc::Request* r) { onComplete(r, 1); }
  void onComplete(lc::Request* r, int camera) {
    (void)completed_.try_push(Completed{r, camera});
    const uint64_t one = 1;
    (void)::write(event_fd_, &one, sizeof one);
  }
  void onDisconnected() { disconnected_.store(true); }

  void requeue(int slot) {
    Cam& c = cams_[static_cast<size_t>(PairedFrames::camera(slot))];
    const auto i = static_cast<size_t>(PairedFrames::index(slot));
    if (!c.camera || i >= c.requests.size()) return;
    c.requests[i]->reuse(lc::Request::ReuseBuffers);
    (void)c.camera->queueRequest(c.requests[i].get());
  }

  void copyOut(int slot, cv::Mat& out) const {
    const Cam& c = cams_[static_cast<size_t>(PairedFrames::camera(slot))];
    const Mapped& m = c.maps[static_cast<size_t>(PairedFrames::index(slot))];
    for (int y = 0; y < config_.height; ++y)
      std::memcpy(out.ptr<uint8_t>(y), m.data + static_cast<size_t>(y) * m.stride,
                  static_cast<size_t>(config_.width));
  }

  LibcameraStereoConfig config_;
  vision::StereoRig rig_;
  PairedFrames pairs_;
  std::array<Cam, 2> cams_;
  atomic_queue::AtomicQueueB2<Completed> completed_;
  int event_fd_ = -1;
  bool running_ = false;
  std::atomic<bool> disconnected_{false};
  int64_t next_reopen_ns_ = 0;
  std::string fault_;
};

}  // namespace

std::unique_ptr<CameraSource> makeLibcameraSource(const LibcameraStereoConfig& config,
                                                  vision::StereoRig rig, TriggerBox* trigger) {
  return std::make_unique<LibcameraStereoSource>(config, std::move(rig), trigger);
}

}  // namespace pulsetrack::drivers
