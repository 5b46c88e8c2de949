#pragma once
// Small helpers shared by the tests: a temporary folder that cleans up, running the CLI.

#include <unistd.h>

#include <array>
#include <cstdio>
#include <filesystem>
#include <iostream>
#include <random>
#include <string>

#include "data_paths.hpp"

namespace pulsetrack::test {

class TempDir {
 public:
  TempDir() {
    std::random_device rd;
    path_ = std::filesystem::temp_directory_path() /
            ("pulsetrack-test-" + std::to_string(::getpid()) + "-" + std::to_string(rd()));
    std::filesystem::create_directories(path_);
  }
  ~TempDir() {
    std::error_code ec;
    std::filesystem::remove_all(path_, ec);
  }
  TempDir(const TempDir&) = delete;
  TempDir& operator=(const TempDir&) = delete;
  [[nodiscard]] const std::filesystem::path& path() const { return path_; }
  [[nodiscard]] std::string operator/(const std::string& name) const {
    return (path_ / name).string();
  }

 private:
  std::filesystem::path path_;
};

struct CommandResult {
  int exit_code = -1;
  std::string output;  // stdout and stderr together
};

// Runs a shell command line, capturing stdout + stderr.
inline CommandResult run(const std::string& command) {
  CommandResult r;
  FILE* pipe = ::popen((command + " 2>&1").c_str(), "r");
  if (pipe == nullptr) return r;
  std::array<char, 4096> buf{};
  size_t n = 0;
  while ((n = std::fread(buf.data(), 1, buf.size(), pipe)) > 0) r.output.append(buf.data(), n);
  const int status = ::pclose(pipe);
  r.exit_code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  return r;
}

inline std::string sourceDir() { return PULSETRACK_SOURCE_DIR; }
inline std::string cli() { return PULSETRACK_CLI; }

}  // namespace pulsetrack::test

// Skips the test loudly, naming the folder, when a data folder (tests/data_paths.hpp) is absent.
#define PULSETRACK_SKIP_WITHOUT_DATA(dir)                                      \
  if (const std::string why = ::pulsetrack::data::absent(dir); !why.empty()) { \
    std::cerr << "SKIPPED: " << why << "\n";                                   \
    GTEST_SKIP() << why;                                                       \
  }
