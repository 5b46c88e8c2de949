#pragma once
// The OpenIGTLink bridge (`pulsetrack igtl`): a process of its own that subscribes to a rig's
// DDS output and serves it to OpenIGTLink clients (3D Slicer's OpenIGTLinkIF, PLUS, SlicerIGT),
// protocol version 2 as Debian's libopenigtlink (1.11) encodes it. Never inside the real-time
// daemon: a client can only ever slow this process, and each client has a queue and a thread of
// its own, so one that stalls or goes away never slows another (docs/slicer.md).
//
// Device names (docs/slicer.md; at most 20 characters, OpenIGTLink's header), in the camera frame,
// or in the tracker's when a registration (O_T_C) is given; positions and translations in mm:
//   TRANSFORM BrainShiftTo<Frame>         the surface's rigid motion from its reference pair
//   TRANSFORM MeanDispTo<Frame>           the features' mean displacement (a translation)
//   TRANSFORM CameraToTracker             the registration (only with one)
//   POINT     Features                    every feature, named F<id>, grouped by its status
//   POLYDATA  DenseField                  the dense field's surface (triangles), with its
//                                         displacement (vectors) and confidence (scalars)
//   IMAGE     LeftCamera                  the left camera's preview, 8-bit grey, at a low rate
//   STATUS    Health                      the daemon's health (time-out when it is silent)
// Clients may ask with GET_<TYPE> (e.g. GET_STATUS): the newest message of that type answers.

#include <Eigen/Geometry>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "pulsetrack/dds/security.hpp"
#include "pulsetrack/vision/error.hpp"

namespace pulsetrack::igtl {

using vision::Result;

struct BridgeOptions {
  uint32_t domain = 0;
  std::string ros_namespace;                   // the daemon's [dds] namespace
  std::optional<dds::SecurityFiles> security;  // a secured domain (an enclave of role subscriber)
  std::string host = "127.0.0.1";              // the address to listen on
  int port = 18944;                            // OpenIGTLink's (and Slicer's) default; 0: any
  double image_rate_hz = 1.0;                  // IMAGE LeftCamera at most this often (0: never)
  double field_rate_hz = 0.5;  // POLYDATA DenseField at most this often (0: never; docs/slicer.md)
  std::optional<Eigen::Isometry3d> camera_to_tracker;  // O_T_C, mm: the tracker's frame
  int max_clients = 16;
  int queue_messages = 256;       // per client: beyond it the oldest message is dropped (counted)
  double stall_timeout_s = 5.0;   // a client that takes no byte for this long is disconnected
  double health_timeout_s = 3.0;  // no health from the daemon this long: STATUS time-out
};

// What a client got, said when it goes.
struct ClientReport {
  std::string peer;
  uint64_t sent = 0, dropped = 0;
  std::string why;  // "disconnected", "stalled ...", "protocol: ..."
};

class Bridge {
 public:
  static Result<std::unique_ptr<Bridge>> create(const BridgeOptions& options);
  ~Bridge();
  Bridge(const Bridge&) = delete;
  Bridge& operator=(const Bridge&) = delete;
  [[nodiscard]] int port() const;
  [[nodiscard]] std::string frameName() const;  // "Camera" or "Tracker"
  // Serves until stop() (from another thread or a signal's watcher).
  void run();
  void stop();

  struct Impl;

 private:
  explicit Bridge(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace pulsetrack::igtl
