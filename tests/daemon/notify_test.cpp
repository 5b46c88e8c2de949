// The sd_notify protocol on a real AF_UNIX datagram socket the test binds: READY=1, STATUS=,
// the watchdog interval from WATCHDOG_USEC, and WATCHDOG=1 only while every stage beats.

#include "pulsetrack/daemon/notify.hpp"

#include <gtest/gtest.h>
#include <sys/socket.h>
#include <sys/un.h>
#include <unistd.h>

#include <array>
#include <string>

#include "test_util.hpp"

namespace pulsetrack::daemon {
namespace {

class NotifySocket {
 public:
  explicit NotifySocket(const std::string& path) : path_(path) {
    fd_ = socket(AF_UNIX, SOCK_DGRAM | SOCK_CLOEXEC, 0);
    sockaddr_un a{};
    a.sun_family = AF_UNIX;
    path.copy(a.sun_path, sizeof a.sun_path - 1);
    ok_ = fd_ >= 0 && bind(fd_, reinterpret_cast<sockaddr*>(&a), sizeof a) == 0;
    timeval tv{0, 200000};
    setsockopt(fd_, SOL_SOCKET, SO_RCVTIMEO, &tv, sizeof tv);
  }
  ~NotifySocket() {
    if (fd_ >= 0) close(fd_);
    unlink(path_.c_str());
  }
  NotifySocket(const NotifySocket&) = delete;
  NotifySocket& operator=(const NotifySocket&) = delete;
  [[nodiscard]] bool ok() const { return ok_; }
  // The next datagram, or "" after 200 ms.
  std::string next() const {
    std::array<char, 4096> buf{};
    const ssize_t n = recv(fd_, buf.data(), buf.size(), 0);
    return n > 0 ? std::string(buf.data(), static_cast<size_t>(n)) : std::string();
  }

 private:
  std::string path_;
  int fd_ = -1;
  bool ok_ = false;
};

TEST(Notify, ReadyStatusAndAWatchdogGatedByTheHeartbeats) {
  test::TempDir dir;
  const std::string path = (dir.path() / "notify").string();
  NotifySocket sock(path);
  ASSERT_TRUE(sock.ok());
  setenv("NOTIFY_SOCKET", path.c_str(), 1);
  setenv("WATCHDOG_USEC", "2000000", 1);
  setenv("WATCHDOG_PID", std::to_string(getpid()).c_str(), 1);
  const Notifier n;
  EXPECT_EQ(n.watchdogInterval(), std::chrono::microseconds(1000000));
  n.ready();
  EXPECT_EQ(sock.next(), "READY=1");
  n.status("tracking 92/100 features, 30.0 fps");
  EXPECT_EQ(sock.next(), "STATUS=tracking 92/100 features, 30.0 fps");

  rt::Heartbeat capture, track, publish;
  const rt::Heartbeat* stages[] = {&capture, &track, &publish};
  EXPECT_FALSE(n.pingIfHealthy(stages, std::chrono::milliseconds(100)));  // never beat
  EXPECT_EQ(sock.next(), "");
  capture.beat();
  track.beat();
  publish.beat();
  EXPECT_TRUE(n.pingIfHealthy(stages, std::chrono::milliseconds(100)));
  EXPECT_EQ(sock.next(), "WATCHDOG=1");
  // The track stage stalls: the pings stop.
  track.beat(rt::monotonicNs() - 1'000'000'000);
  capture.beat();
  publish.beat();
  EXPECT_FALSE(n.pingIfHealthy(stages, std::chrono::milliseconds(100)));
  EXPECT_EQ(sock.next(), "");  // (waits 200 ms: beat all three again)
  capture.beat();
  track.beat();
  publish.beat();
  EXPECT_TRUE(n.pingIfHealthy(stages, std::chrono::milliseconds(100)));
  EXPECT_EQ(sock.next(), "WATCHDOG=1");

  // Another process's watchdog (WATCHDOG_PID not ours): off.
  setenv("WATCHDOG_PID", "1", 1);
  EXPECT_EQ(Notifier().watchdogInterval(), std::chrono::microseconds(0));
  unsetenv("NOTIFY_SOCKET");
  unsetenv("WATCHDOG_USEC");
  unsetenv("WATCHDOG_PID");
}

}  // namespace
}  // namespace pulsetrack::daemon
