#pragma once
// What a real camera does to the scene's radiance: defocus blur, vignetting, gain changes,
// sensor noise (Gaussian, sigma in grey levels), 8-bit quantization with saturation, lossy
// compression (JPEG), and dropped frames (decided per frame from the seed, so a scene is
// reproducible).

#include <opencv2/core.hpp>
#include <random>
#include <vector>

namespace pulsetrack::sim {

struct CameraEffectsSpec {
  double blur_sigma_px = 0.7;  // defocus, Gaussian
  double noise_sigma = 2.0;    // grey levels
  double vignetting = 0.25;    // relative fall-off at the image corner
  // Where the fall-off is centred, px from the image centre: lenses differ (decentred elements),
  // so the two views' shading ratio varies over the image.
  cv::Vec2d vignetting_centre_px{0.0, 0.0};
  double gain = 1.0;            // the camera's gain (the two cameras' differ: unequal gains)
  double gain_amplitude = 0.0;  // relative, sinusoidal drift around `gain`
  double gain_period_s = 30.0;
  double gain_phase_deg = 0.0;    // independent drift per camera
  double drop_probability = 0.0;  // per frame
  // Lossy compression as a video link or recorder applies it: each 8-bit frame through JPEG at
  // this quality (1-100; 0: none). Blocking and ringing are what matter to a matcher; an H.264
  // stream adds motion-compensated prediction on top (not modelled here).
  int jpeg_quality = 0;
};

class CameraEffects {
 public:
  CameraEffects(const CameraEffectsSpec& spec, cv::Size image_size, unsigned seed);
  // radiance (CV_32FC1) -> 8-bit image. `camera` 0/1 picks the noise stream. `blurred`: the
  // radiance went through defocus() already (an interlaced frame's fields, each on its own).
  void apply(const cv::Mat& radiance, double t, cv::Mat& out, bool blurred = false);
  // The lens's defocus blur alone, in place.
  void defocus(cv::Mat& radiance) const;
  // Whether frame `index` is dropped (deterministic per index).
  [[nodiscard]] bool dropped(uint64_t index) const;
  [[nodiscard]] double gain(double t) const;
  [[nodiscard]] const CameraEffectsSpec& spec() const { return spec_; }

 private:
  CameraEffectsSpec spec_;
  unsigned seed_;
  cv::Mat vignette_;  // CV_32FC1 multiplier
  cv::Mat work_;
  cv::Mat noise_;
  std::vector<uint8_t> jpeg_;
  cv::RNG rng_;
};

}  // namespace pulsetrack::sim
