#include "pulsetrack/sim/planar_render.hpp"

#include <algorithm>
#include <opencv2/imgproc.hpp>

namespace pulsetrack::sim {

CameraRays::CameraRays(const vision::CameraModel& camera, int supersample)
    : supersample_(std::max(1, supersample)), image_size_(camera.imageSize()) {
  const int s = supersample_;
  normalized_.create(image_size_.height * s, image_size_.width * s, CV_32FC2);
  const double step = 1.0 / s;
  const double first = -0.5 + 0.5 * step;  // centre of the first sub-pixel of pixel 0
  cv::parallel_for_(cv::Range(0, normalized_.rows), [&](const cv::Range& rows) {
    for (int yi = rows.start; yi < rows.end; ++yi) {
      auto* out = normalized_.ptr<cv::Vec2f>(yi);
      const int pixel_y = yi / s;  // the output pixel, then the sub-pixel within it
      const double v = pixel_y + first + (yi % s) * step;
      for (int xi = 0; xi < normalized_.cols; ++xi) {
        const int pixel_x = xi / s;
        const double u = pixel_x + first + (xi % s) * step;
        const cv::Vec2d n = camera.undistortToNormalized({u, v});
        out[xi] = cv::Vec2f(static_cast<float>(n[0]), static_cast<float>(n[1]));
      }
    }
  });
}

cv::Mat renderPlane(const CameraRays& rays, const PlaneView& view, const cv::Mat& texture,
                    const cv::Matx33d& texture_from_plane, double background) {
  const cv::Mat& normalized = rays.normalized();
  cv::Mat map_x(normalized.size(), CV_32FC1);
  cv::Mat map_y(normalized.size(), CV_32FC1);
  const cv::Vec3d normal = view.rotation * cv::Vec3d(0, 0, 1);
  const double plane_d = normal.dot(view.translation);  // n . x = d on the plane
  // Camera ray (x, y, 1) scaled by lambda -> plane coordinates -> texture: one homography.
  const cv::Matx33d rt = view.rotation.t();
  cv::parallel_for_(cv::Range(0, normalized.rows), [&](const cv::Range& rows) {
    for (int yi = rows.start; yi < rows.end; ++yi) {
      const auto* in = normalized.ptr<cv::Vec2f>(yi);
      auto* mx = map_x.ptr<float>(yi);
      auto* my = map_y.ptr<float>(yi);
      for (int xi = 0; xi < normalized.cols; ++xi) {
        const cv::Vec3d ray(in[xi][0], in[xi][1], 1.0);
        const double denom = normal.dot(ray);
        const double lambda = denom != 0.0 ? plane_d / denom : -1.0;
        if (!(lambda > 0.0)) {
          mx[xi] = -1e6F;
          my[xi] = -1e6F;
          continue;
        }
        const cv::Vec3d p = rt * (lambda * ray - view.translation);
        const cv::Vec3d t = texture_from_plane * cv::Vec3d(p[0], p[1], 1.0);
        mx[xi] = static_cast<float>(t[0] / t[2]);
        my[xi] = static_cast<float>(t[1] / t[2]);
      }
    }
  });
  cv::Mat sampled;
  cv::remap(texture, sampled, map_x, map_y, cv::INTER_LINEAR, cv::BORDER_CONSTANT,
            cv::Scalar(background));
  if (rays.supersample() == 1) return sampled;
  cv::Mat out;
  cv::resize(sampled, out, rays.imageSize(), 0, 0, cv::INTER_AREA);
  return out;
}

}  // namespace pulsetrack::sim
