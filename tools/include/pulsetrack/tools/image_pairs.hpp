#pragma once
// Left/right image lists from two shell globs, paired by the part of the name the wildcards
// match ('left*.jpg' and 'right*.jpg' pair left07.jpg with right07.jpg). Used by calibrate
// and, for image-folder sequences, by track.

#include <string>
#include <utility>
#include <vector>

#include "pulsetrack/vision/error.hpp"

namespace pulsetrack::tools {

// Files matching a shell glob, sorted by name. Fails naming the glob when nothing matches.
vision::Result<std::vector<std::string>> globFiles(const std::string& pattern, const char* what);

// The part of `path`'s file name that the wildcards of `pattern`'s file name stand for.
std::string wildcardKey(const std::string& pattern, const std::string& path);

// Pairs the two globs' files by wildcard key, in the left files' name order. Fails listing the
// unpaired files.
vision::Result<std::vector<std::pair<std::string, std::string>>> pairImages(
    const std::string& left_glob, const std::string& right_glob);

}  // namespace pulsetrack::tools
