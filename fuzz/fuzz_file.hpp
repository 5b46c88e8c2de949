#pragma once
// For harnesses whose reader takes a path: the input written to one scratch file per process,
// and the check every reader owes its user (an error names the file).

#include <unistd.h>

#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <string>

namespace pulsetrack::fuzz {

// This process's scratch folder (made once).
inline const std::filesystem::path& scratchDir() {
  static const std::filesystem::path dir = [] {
    auto d =
        std::filesystem::temp_directory_path() / ("pulsetrack-fuzz." + std::to_string(::getpid()));
    std::filesystem::create_directories(d);
    return d;
  }();
  return dir;
}

// Writes the input to `path` (replacing it).
inline void writeFile(const std::filesystem::path& path, const uint8_t* data, size_t size) {
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  out.write(reinterpret_cast<const char*>(data), static_cast<std::streamsize>(size));
}

// The input as the file `name` in the scratch folder.
inline std::filesystem::path writeInput(const char* name, const uint8_t* data, size_t size) {
  const auto path = scratchDir() / name;
  writeFile(path, data, size);
  return path;
}

// An error that does not say which file broke is a finding too.
inline void requireNamed(const std::string& message, const std::filesystem::path& path) {
  if (message.find(path.string()) == std::string::npos) {
    std::fprintf(stderr, "error does not name %s: %s\n", path.c_str(), message.c_str());
    __builtin_trap();
  }
}

// For readers that take the text and the file's name.
inline std::string inputText(const uint8_t* data, size_t size) {
  return {reinterpret_cast<const char*>(data), size};
}

}  // namespace pulsetrack::fuzz
