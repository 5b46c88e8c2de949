#pragma once
// Where the left ROI's surface is in the right image, from the rig and the pair alone: a
// surgeon's team gives a left ROI, never a right one or a depth.
//
// A grid of patches over the left ROI; each textured one (no highlight, not flat) is matched
// by NCC along its epipolar curve in the right image, from the near to the far end of a depth
// range (the band a few px wide: a real rig's lines are off by a pixel or so). The matches that
// are clear (NCC above min_ncc) give the depths of the surface there; their median depth and
// spread set the right ROI and the depth tolerance of the tracker's stereo search box, and
// their vertical offset from the epipolar lines is the rig's residual on this data.

#include <opencv2/core.hpp>
#include <optional>
#include <string>

#include "pulsetrack/vision/error.hpp"
#include "pulsetrack/vision/stereo_rig.hpp"

namespace pulsetrack::vision {

struct StereoSearchConfig {
  double near_mm = 20.0;     // the depth range searched (a stereo endoscope at 20 mm ...
  double far_mm = 1000.0;    // ... to a microscope or exoscope at up to 1 m)
  int grid = 10;             // patches per ROI side, at most
  double min_ncc = 0.85;     // a clear match
  double min_texture = 3.0;  // grey levels: a patch's standard deviation below is flat
  int highlight = 250;       // a patch with a pixel at or over this is on a highlight
  double band_px = 3.0;      // half width of the epipolar band searched
  // Without a left ROI (findTissueRegion): the image in cells of about 1/20 of its smaller side
  // (16 px at least); a cell is tissue to track when its grey levels' standard deviation is at
  // least region_texture, under a tenth of it is highlight (>= highlight) and its mean is above
  // region_dark (not the black beyond an endoscope's field stop or a vignetted corner).
  double region_texture = 4.0;
  double region_dark = 25.0;
};

// The left ROI found in an image when none is given: the largest rectangle of tissue cells.
struct TissueRegion {
  cv::Rect found;  // the best region of tissue cells
  cv::Rect roi;    // ... narrowed to what the right camera sees too (findStereoRoi)
  int cells = 0, tissue = 0, flat = 0, highlights = 0, dark = 0;
  // "left ROI 4,32,304,256 found: the best well-textured region (...), narrowed to ...".
  [[nodiscard]] std::string summary() const;
};

struct StereoRange {
  cv::Rect right;             // the right ROI: the left ROI's surface, at the median depth
  cv::Rect2d right_outline;   // ... before it was cut to the right image (its float extent)
  double depth_mm = 0.0;      // median depth of the matches
  double tolerance_mm = 0.0;  // the tracker's depth tolerance: covers their spread
  double depth_lo_mm = 0.0;   // 5th and 95th percentiles of the matches' depths
  double depth_hi_mm = 0.0;
  double disparity_lo_px = 0.0;  // ... and of their left-to-right offsets (px, along x)
  double disparity_hi_px = 0.0;
  double vertical_px = 0.0;  // median signed distance of the matches from their epipolar lines
  double vertical_spread_px = 0.0;  // 1.4826 MAD of those distances
  int patches = 0, flat = 0, highlights = 0, matched = 0;
  cv::Rect left;                       // the left ROI searched (given, or found: region)
  std::optional<TissueRegion> region;  // findStereoRoi without a left ROI: how it was found
  // "disparity 74-102 px, depth 36-45 mm (61 of 100 patches; the rig is off by 0.4 px ...)".
  [[nodiscard]] std::string summary() const;
};

// Fails, saying why, when too few patches match: the ROI is flat, on highlights, or its
// surface is not within the depth range (or not in the right view).
[[nodiscard]] Result<StereoRange> findStereoRange(const StereoRig& rig, const cv::Mat& left,
                                                  const cv::Mat& right, const cv::Rect& roi_left,
                                                  const StereoSearchConfig& config = {});

// The best well-textured region, glare and dark borders left out (the config's region_* keys),
// for a user who gives no ROI: the rectangle of cells, at least min_side px a side, with the most
// tissue cells less 3 per other cell (glare or flat; a dark cell is never inside). Fails, saying
// what the image is made of, when there is none. Instruments are not recognized as such (only
// their glare and flat metal count against a cell).
[[nodiscard]] Result<TissueRegion> findTissueRegion(const cv::Mat& left, int min_side,
                                                    const StereoSearchConfig& config = {});

// The ROI pair from a left ROI, or from none (roi_left empty: findTissueRegion first, then the
// found ROI is narrowed to what the right camera sees too): findStereoRange on it.
[[nodiscard]] Result<StereoRange> findStereoRoi(const StereoRig& rig, const cv::Mat& left,
                                                const cv::Mat& right, const cv::Rect& roi_left,
                                                int min_side,
                                                const StereoSearchConfig& config = {});

// Parses "near,far" in mm (the --depth-range option).
[[nodiscard]] Result<StereoSearchConfig> parseDepthRange(const std::string& text);

}  // namespace pulsetrack::vision
