#include "pulsetrack/tools/image_pairs.hpp"

#include <fmt/format.h>
#include <glob.h>

#include <algorithm>
#include <filesystem>
#include <map>
#include <set>

namespace pulsetrack::tools {

using vision::fail;

vision::Result<std::vector<std::string>> globFiles(const std::string& pattern, const char* what) {
  glob_t g{};
  const int rc = ::glob(pattern.c_str(), GLOB_ERR, nullptr, &g);
  std::vector<std::string> files;
  if (rc == 0) {
    for (size_t i = 0; i < g.gl_pathc; ++i) {
      if (std::filesystem::is_regular_file(g.gl_pathv[i])) files.emplace_back(g.gl_pathv[i]);
    }
  }
  globfree(&g);
  if (rc == GLOB_ABORTED)
    return fail(fmt::format("{} '{}': cannot read the folder", what, pattern));
  if (files.empty()) return fail(fmt::format("{} '{}': no file matches", what, pattern));
  std::sort(files.begin(), files.end());
  return files;
}

std::string wildcardKey(const std::string& pattern, const std::string& path) {
  const std::string pat = std::filesystem::path(pattern).filename().string();
  std::string name = std::filesystem::path(path).filename().string();
  const size_t first = pat.find_first_of("*?[");
  if (first == std::string::npos) return {};
  // The suffix starts after the last wildcard (a bracket expression ends at its ']').
  const size_t last = pat.find_last_of("*?]");
  const size_t prefix_len = first;
  const size_t suffix_len = pat.size() - last - 1;
  if (name.size() < prefix_len + suffix_len) return name;
  std::string key = name.substr(prefix_len, name.size() - prefix_len - suffix_len);
  // Frame numbers pair by value: 'left0*.jpg' and 'right*.jpg' pair left01 with right01.
  if (!key.empty() &&
      std::all_of(key.begin(), key.end(), [](char c) { return c >= '0' && c <= '9'; })) {
    const size_t nz = key.find_first_not_of('0');
    key = nz == std::string::npos ? "0" : key.substr(nz);
  }
  return key;
}

vision::Result<std::vector<std::pair<std::string, std::string>>> pairImages(
    const std::string& left_glob, const std::string& right_glob) {
  auto left = globFiles(left_glob, "--left");
  if (!left) return std::unexpected(left.error());
  auto right = globFiles(right_glob, "--right");
  if (!right) return std::unexpected(right.error());
  std::set<std::string> l;
  std::map<std::string, std::string> r;
  for (const auto& f : *left) l.insert(wildcardKey(left_glob, f));
  for (const auto& f : *right) r[wildcardKey(right_glob, f)] = f;
  std::vector<std::string> unpaired;
  std::vector<std::pair<std::string, std::string>> pairs;
  for (const auto& file : *left) {  // in file-name order
    const auto it = r.find(wildcardKey(left_glob, file));
    if (it == r.end()) {
      unpaired.push_back(fmt::format("{} has no right image", file));
    } else {
      pairs.emplace_back(file, it->second);
    }
  }
  for (const auto& [key, file] : r) {
    if (!l.contains(key)) unpaired.push_back(fmt::format("{} has no left image", file));
  }
  if (!unpaired.empty()) {
    std::string list;
    for (size_t i = 0; i < unpaired.size() && i < 8; ++i) list += "\n  " + unpaired[i];
    if (unpaired.size() > 8) list += fmt::format("\n  ... and {} more", unpaired.size() - 8);
    return fail(
        fmt::format("{} unpaired image(s) (left and right are paired by the part of the "
                    "name the wildcards match):{}",
                    unpaired.size(), list));
  }
  return pairs;
}

}  // namespace pulsetrack::tools
