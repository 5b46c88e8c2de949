#pragma once
// pulsetrack console: the operating-room console, a process of its own (the daemon stays lean).
//
//   DDS (a participant of its own, DDS Security's "controller" role when the domain is secured):
//     reads features, deformation, health, field and the cameras' preview; writes commands.
//   HTTPS (cpp-httplib over OpenSSL): the page (console/www), a login, and
//     GET  /api/events            Server-Sent Events: link, health, image, features, roi,
//                                 deformation, spectrum, field, command (docs/console.md)
//     GET  /api/image/{left,right} the latest preview JPEG
//     GET  /api/roi_right         the right ROI derived from a left one (the rig, the depth)
//     POST /api/command           start, stop, redetect, set_roi, record_start, record_stop
//     POST /api/login, /api/logout
//   Every request but the login page's is authenticated by a session cookie (HttpOnly, Secure,
//   SameSite=Strict); commands need the operator role.
//
// Why cpp-httplib: one Debian-packaged library that does HTTPS with OpenSSL, keep-alive and
// chunked streaming (Server-Sent Events) in a few lines; the console's traffic is one OR's few
// browsers. Server-Sent Events instead of WebSocket: the page only listens (commands are plain
// POSTs that get a status code), EventSource reconnects by itself, and it passes any proxy.

#include <cstdint>
#include <filesystem>
#include <memory>
#include <optional>
#include <string>

#include "pulsetrack/dds/security.hpp"
#include "pulsetrack/vision/error.hpp"

namespace pulsetrack::console {

struct ConsoleOptions {
  std::string host = "127.0.0.1";   // localhost unless configured
  int port = 8443;                  // 0: any free port (tests)
  std::filesystem::path cert, key;  // the TLS certificate (PEM) and its private key
  std::filesystem::path users;      // the users file (credentials.hpp)
  std::filesystem::path www;        // the page's files
  std::filesystem::path rig;        // the rig file: the right ROI from a drawn left one
  uint32_t domain = 0;
  std::string ros_namespace;
  std::optional<dds::SecurityFiles> security;  // this console's enclave; none: unsecured
  double working_distance_mm = 450.0;          // the right ROI's depth before any feature is seen
  double session_hours = 12.0;                 // a login lasts this long (an operation's length)
  double daemon_timeout_s = 3.0;               // no health for this long: "no pulsetrackd"
};

class Console {
 public:
  // Checks every file (each error names it), joins DDS, binds the port.
  static vision::Result<std::unique_ptr<Console>> create(const ConsoleOptions& options);
  ~Console();
  Console(const Console&) = delete;
  Console& operator=(const Console&) = delete;

  [[nodiscard]] int port() const;
  // Serves until stop() (another thread, or a signal handler's flag polled by the caller).
  void run();
  void stop();
  // Said once at start: where it listens and as whom on DDS.
  [[nodiscard]] std::string banner() const;

  struct Impl;

 private:
  explicit Console(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace pulsetrack::console
