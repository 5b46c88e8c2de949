#include "pulsetrack/sim/paper_rig.hpp"

#include <opencv2/calib3d.hpp>

namespace pulsetrack::sim {

vision::StereoRig paperRig() {
  vision::StereoRig rig;
  const cv::Size size(1360, 1024);
  const double f = 25.0 / 4.65e-3;  // 5376.3 px
  // Two copies of the same lens, as a calibration would find them: slightly different.
  const double d1[5] = {-0.118, 0.42, 0.00061, -0.00043, -0.9};
  const double d2[5] = {-0.109, 0.37, -0.00032, 0.00052, -0.6};
  rig.left =
      vision::CameraModel({f * 1.0004, 0, 683.2, 0, f * 0.9998, 508.9, 0, 0, 1}, d1, 5, size);
  rig.right =
      vision::CameraModel({f * 0.9993, 0, 676.1, 0, f * 0.9996, 514.3, 0, 0, 1}, d2, 5, size);
  // The right camera 60 mm to the right of the left one, turned to look at (0, 0, 450) mm of
  // the left frame, with the small roll and tilt of a real bracket.
  const cv::Vec3d centre(60.0, 0.3, -1.2);
  const cv::Vec3d z = cv::normalize(cv::Vec3d(0, 0, 450) - centre);
  const cv::Vec3d x = cv::normalize(cv::Vec3d(0, 1, 0).cross(z));
  const cv::Vec3d y = z.cross(x);
  const cv::Matx33d r_left_from_right(x[0], y[0], z[0], x[1], y[1], z[1], x[2], y[2], z[2]);
  cv::Matx33d wobble;
  cv::Rodrigues(cv::Vec3d(0.0021, -0.0008, 0.0035), wobble);
  rig.r = wobble * r_left_from_right.t();
  rig.t = -(rig.r * centre);
  rig.rms = 0.0;
  return rig;
}

}  // namespace pulsetrack::sim
