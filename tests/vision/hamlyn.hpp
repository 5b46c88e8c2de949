#pragma once
// The Hamlyn Centre's beating heart (../shared/data/hamlyn-invivo-tpsnet: 300 rectified da Vinci
// pairs, 360x288, its assumed rig), as the real-tissue tests read it.

#include <gtest/gtest.h>

#include <cstdio>
#include <filesystem>
#include <opencv2/imgcodecs.hpp>
#include <optional>
#include <string>
#include <utility>

#include "data_paths.hpp"
#include "pulsetrack/vision/stereo_rig.hpp"
#include "test_util.hpp"

namespace pulsetrack::vision::hamlyn {

inline std::filesystem::path dir() { return data::shared("hamlyn-invivo-tpsnet"); }

// The left ROI over the heart that the issue and the docs use.
inline const cv::Rect kRoi(120, 60, 200, 180);

// Pair k (1..300) as grey images; empty where a file is missing.
inline void readPair(int k, cv::Mat& left, cv::Mat& right) {
  char name[32];
  std::snprintf(name, sizeof name, "left_%04d.png", k);
  left = cv::imread((dir() / name).string(), cv::IMREAD_GRAYSCALE);
  std::snprintf(name, sizeof name, "right_%04d.png", k);
  right = cv::imread((dir() / name).string(), cv::IMREAD_GRAYSCALE);
}

struct FirstPair {
  StereoRig rig;
  cv::Mat left, right;
};

// The rig and pair 1; a test failure (and nullopt) when either cannot be read.
inline std::optional<FirstPair> firstPair() {
  auto rig = loadRig(dir() / "rig.yaml");
  if (!rig) {
    ADD_FAILURE() << rig.error().message;
    return std::nullopt;
  }
  FirstPair p{*rig, {}, {}};
  readPair(1, p.left, p.right);
  if (p.left.empty() || p.right.empty()) {
    ADD_FAILURE() << "cannot read pair 1 in " << dir();
    return std::nullopt;
  }
  return p;
}

// A test on pair 1: skipped (loudly) without the data set, a failure when it cannot be read.
class PairOne : public ::testing::Test {
 protected:
  void SetUp() override {
    PULSETRACK_SKIP_WITHOUT_DATA(dir());
    auto loaded = firstPair();
    if (!loaded) GTEST_FAIL() << "pair 1 of " << dir() << " unreadable";
    pair_ = std::move(*loaded);
  }
  FirstPair pair_;
};

}  // namespace pulsetrack::vision::hamlyn
