#include "pulsetrack/sim/camera_effects.hpp"

#include <cmath>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

namespace pulsetrack::sim {

CameraEffects::CameraEffects(const CameraEffectsSpec& spec, cv::Size size, unsigned seed)
    : spec_(spec), seed_(seed), rng_(seed * 7919ULL + 17ULL) {
  vignette_.create(size, CV_32FC1);
  const double cx = (size.width - 1) / 2.0 + spec.vignetting_centre_px[0];
  const double cy = (size.height - 1) / 2.0 + spec.vignetting_centre_px[1];
  const double hx = (size.width - 1) / 2.0, hy = (size.height - 1) / 2.0;
  const double corner2 = hx * hx + hy * hy;
  for (int y = 0; y < size.height; ++y) {
    auto* row = vignette_.ptr<float>(y);
    for (int x = 0; x < size.width; ++x) {
      const double r2 = ((x - cx) * (x - cx) + (y - cy) * (y - cy)) / corner2;
      row[x] = static_cast<float>(std::max(0.0, 1.0 - spec.vignetting * r2));
    }
  }
  work_.create(size, CV_32FC1);
  noise_.create(size, CV_32FC1);
}

double CameraEffects::gain(double t) const {
  return spec_.gain * (1.0 + spec_.gain_amplitude * std::sin(2.0 * CV_PI * t / spec_.gain_period_s +
                                                             spec_.gain_phase_deg * CV_PI / 180.0));
}

bool CameraEffects::dropped(uint64_t index) const {
  if (spec_.drop_probability <= 0.0 || index == 0) return false;
  std::mt19937_64 g(seed_ * 0x9E3779B97F4A7C15ULL + index);
  return std::uniform_real_distribution<double>(0.0, 1.0)(g) < spec_.drop_probability;
}

void CameraEffects::defocus(cv::Mat& radiance) const {
  if (spec_.blur_sigma_px > 0.0)
    cv::GaussianBlur(radiance, radiance, cv::Size(0, 0), spec_.blur_sigma_px);
}

void CameraEffects::apply(const cv::Mat& radiance, double t, cv::Mat& out, bool blurred) {
  cv::multiply(radiance, vignette_, work_, gain(t));
  if (!blurred) defocus(work_);
  if (spec_.noise_sigma > 0.0) {
    rng_.fill(noise_, cv::RNG::NORMAL, 0.0, spec_.noise_sigma);
    work_ += noise_;
  }
  work_.convertTo(out, CV_8UC1);  // rounds and saturates: highlights clip at 255
  if (spec_.jpeg_quality > 0) {
    cv::imencode(".jpg", out, jpeg_, {cv::IMWRITE_JPEG_QUALITY, spec_.jpeg_quality});
    cv::imdecode(jpeg_, cv::IMREAD_GRAYSCALE, &out);
  }
}

}  // namespace pulsetrack::sim
