#pragma once
// The ROI pair around the simulated craniotomy: the bounding boxes of the projections of a circle
// of radius r mm around the cortex patch's centre, in both cameras.

#include <cmath>
#include <opencv2/imgproc.hpp>
#include <vector>

#include "pulsetrack/sim/scene.hpp"
#include "pulsetrack/vision/stereo_tracker.hpp"

namespace pulsetrack::test {

inline vision::Roi cortexRoi(const sim::StereoSimulator& s, double r) {
  const sim::CortexScene& c = *s.cortex();
  std::vector<cv::Point2f> l, rr;
  for (int k = 0; k < 36; ++k) {
    const double a = k * CV_PI / 18;
    const cv::Vec3d p = c.position(r * std::cos(a), r * std::sin(a), 0.0);
    const cv::Vec2d pl = s.rig().projectLeft(p), pr = s.rig().projectRight(p);
    l.emplace_back(static_cast<float>(pl[0]), static_cast<float>(pl[1]));
    rr.emplace_back(static_cast<float>(pr[0]), static_cast<float>(pr[1]));
  }
  return {cv::boundingRect(l), cv::boundingRect(rr)};
}

}  // namespace pulsetrack::test
