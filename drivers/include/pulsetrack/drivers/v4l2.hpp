#pragma once
// V4L2 cameras: streaming I/O with mmap buffers, as the kernel documents it
// (https://docs.kernel.org/userspace-api/media/v4l/mmap.html): QUERYCAP, S_FMT (GREY, Y16 or
// YUYV, converted to 8-bit grey), exposure / gain / trigger controls, REQBUFS + QUERYBUF + mmap,
// QBUF all, STREAMON; then poll, DQBUF (monotonic timestamps, sequence numbers), QBUF again.
//
// Every system call goes through V4l2Io, the seam the tests replace with an emulation of the
// kernel's streaming state machine (EAGAIN, ENODEV mid-stream, sequence gaps) and which is the
// plain syscall on a board.

#include <poll.h>
#include <sys/types.h>

#include <array>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "pulsetrack/drivers/pairing.hpp"
#include "pulsetrack/drivers/source.hpp"

namespace pulsetrack::drivers {

// The system calls the driver makes; -1 and errno on failure, as the syscalls.
class V4l2Io {
 public:
  virtual ~V4l2Io() = default;
  virtual int open(const char* path, int flags) = 0;
  virtual int close(int fd) = 0;
  virtual int ioctl(int fd, unsigned long request, void* arg) = 0;
  virtual void* mmap(size_t length, int fd, off_t offset) = 0;  // PROT_READ|WRITE, MAP_SHARED
  virtual int munmap(void* addr, size_t length) = 0;
  virtual int poll(pollfd* fds, nfds_t n, int timeout_ms) = 0;
};
// The real system calls.
V4l2Io& systemV4l2Io();

struct V4l2CameraConfig {
  std::string device = "/dev/video0";
  int width = 1360, height = 1024;
  std::string pixel_format = "GREY";  // GREY | Y16 | YUYV
  int buffers = 6;
  std::optional<int> exposure_us;  // V4L2_CID_EXPOSURE_ABSOLUTE (in 100 us units)
  std::optional<int> gain;         // V4L2_CID_GAIN
  // External trigger: V4L2 has no standard control; cameras expose a vendor control. Its id
  // and the value that selects the external trigger (0: leave the camera as it is).
  uint32_t trigger_control = 0;
  int trigger_value = 1;
};

// One camera. Not thread-safe: the capture stage owns it.
class V4l2Camera {
 public:
  V4l2Camera(V4l2Io& io, V4l2CameraConfig config);
  ~V4l2Camera();
  V4l2Camera(const V4l2Camera&) = delete;
  V4l2Camera& operator=(const V4l2Camera&) = delete;

  // Opens, configures and starts streaming; fails naming the device and the step.
  vision::Result<void> open();
  void close();
  [[nodiscard]] bool isOpen() const { return fd_ >= 0; }
  [[nodiscard]] int fd() const { return fd_; }
  [[nodiscard]] const std::string& device() const { return config_.device; }

  enum class Dequeue { kFrame, kAgain, kGone, kError };
  // One filled buffer, without waiting (call after poll says readable). The buffer stays the
  // caller's until requeue(index).
  Dequeue dequeue(int& index, CameraStamp& stamp);
  // The buffer's image as 8-bit grey into `out` (CV_8UC1): the region of out's size at (x0, y0)
  // of the frame, which must lie inside it (the whole image, or one view of a side-by-side or
  // top-bottom frame).
  void convert(int index, cv::Mat& out, int x0 = 0, int y0 = 0) const;
  bool requeue(int index);
  [[nodiscard]] const std::string& lastError() const { return error_; }

 private:
  vision::Result<void> fail(const std::string& step);
  bool setControl(uint32_t id, int value);

  V4l2Io& io_;
  V4l2CameraConfig config_;
  uint32_t fourcc_ = 0;
  int fd_ = -1;
  uint32_t bytes_per_line_ = 0;
  struct Buffer {
    void* data = nullptr;
    size_t length = 0;
  };
  std::vector<Buffer> buffers_;
  bool streaming_ = false;
  std::string error_;
};

// Two V4L2 cameras triggered together, behind the daemon's source interface. Frames are paired
// by timestamp (FramePairer); with a trigger box the pairs carry the box's pulse numbers (see
// trigger_box.hpp); without one the source is free-running and says so in triggerState().
// A camera that goes away (ENODEV, or no frame within the timeout) is a fault; it is reopened
// every `reopen_ms` until it answers, and tracking resumes.
// How the two views arrive: from two cameras, or in each frame of one device (a stereo
// microscope's or exoscope's video output through a capture card: the views side by side, left
// view on the left, or top-bottom, left view on top). One device needs no pairing and no
// trigger: its two views are exposed together.
enum class StereoLayout { kTwoCameras, kSideBySide, kTopBottom };
// One device's whole frame for two views of `view` in `layout` (twice the width side by side,
// twice the height top-bottom; kTwoCameras: `view`), and the view in a whole frame (the inverse,
// an odd size rounded down).
cv::Size layoutFrameSize(StereoLayout layout, cv::Size view) noexcept;
cv::Size layoutViewSize(StereoLayout layout, cv::Size frame) noexcept;

struct V4l2StereoConfig {
  // kTwoCameras: the two cameras. One device: `left` is it, its width and height the whole
  // frame's (twice the rig's image width side by side, twice its height top-bottom).
  V4l2CameraConfig left, right;
  StereoLayout layout = StereoLayout::kTwoCameras;
  double fps = 30.0;  // the trigger's rate: pairing tolerance, frame timeout
  int reopen_ms = 500;
};

class TriggerBox;  // trigger_box.hpp

// The source for config.layout (one device: `trigger` must be null; its frames are numbered by
// the device's sequence, its gaps counted as dropped). One device's frame size must be the
// layout's of the rig's image size: start() fails naming the device and both sizes otherwise.
std::unique_ptr<CameraSource> makeV4l2Source(V4l2Io& io, const V4l2StereoConfig& config,
                                             vision::StereoRig rig, TriggerBox* trigger = nullptr);

}  // namespace pulsetrack::drivers
