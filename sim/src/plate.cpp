#include "pulsetrack/sim/plate.hpp"

#include <cmath>
#include <opencv2/calib3d.hpp>
#include <opencv2/imgproc.hpp>
#include <random>

#include "texture_paint.hpp"

namespace pulsetrack::sim {

namespace {

constexpr double kHalf = 40.0;  // the plate is 80 x 80 mm

cv::Matx33d rodrigues(const cv::Vec3d& v) {
  cv::Matx33d r;
  cv::Rodrigues(v, r);
  return r;
}

// Pose facing the camera: {P} z towards the camera, tilted by (tx, ty) about x and y and
// turned by rz about its normal, centred at `centre` in {C}.
Pose facingPose(const cv::Vec3d& centre, double tx, double ty, double rz) {
  const cv::Matx33d facing(1, 0, 0, 0, -1, 0, 0, 0, -1);  // z_P = -z_C, x_P = x_C
  const cv::Matx33d r = rodrigues({tx, ty, 0.0}) * facing * rodrigues({0.0, 0.0, rz});
  return {r, centre};
}

}  // namespace

const std::array<cv::Vec3d, 8>& nominalDivots() {
  static const std::array<cv::Vec3d, 8> kDivots = {
      cv::Vec3d(30, 15, 0),  cv::Vec3d(15, 30, 0),  cv::Vec3d(30, -15, 0),  cv::Vec3d(15, -30, 0),
      cv::Vec3d(-15, 30, 0), cv::Vec3d(-30, 15, 0), cv::Vec3d(-15, -30, 0), cv::Vec3d(-30, -15, 0)};
  return kDivots;
}

const std::array<cv::Vec3d, 6>& nominalFeatures() {
  static const std::array<cv::Vec3d, 6> kFeatures = {cv::Vec3d(10, 0, 0), cv::Vec3d(5, 0, 0),
                                                     cv::Vec3d(0, 10, 0), cv::Vec3d(0, 5, 0),
                                                     cv::Vec3d(0, -5, 0), cv::Vec3d(0, -10, 0)};
  return kFeatures;
}

PlateScene::PlateScene(const PlateSpec& spec, double fps, unsigned seed) : spec_(spec) {
  std::mt19937 rng(static_cast<unsigned>(spec.setup_seed));
  std::uniform_real_distribution<double> unit(-1.0, 1.0);
  // The tracker stands about 2 m away, looking at the field from the side.
  o_t_c_ = {rodrigues({0.4 + 0.1 * unit(rng), -0.9 + 0.1 * unit(rng), 0.2 + 0.1 * unit(rng)}),
            {150.0 + 50 * unit(rng), -300.0 + 50 * unit(rng), 1900.0 + 50 * unit(rng)}};
  // The markers' rigid body: origin near a corner, turned.
  p_t_m_ = {rodrigues({0.02, -0.03, CV_PI / 2 + 0.05}), {-36.0, 34.0, 4.0}};
  buildTrajectory(fps, seed);
  buildTexture();
  const double h = 1.0;
  const int n = static_cast<int>(2 * kHalf / h) + 1;
  for (int j = 0; j < n; ++j) {
    for (int i = 0; i < n; ++i) grid_.emplace_back(-kHalf + i * h, -kHalf + j * h);
  }
  for (int j = 0; j + 1 < n; ++j) {
    for (int i = 0; i + 1 < n; ++i) {
      const int a = j * n + i;
      tris_.emplace_back(a, a + 1, a + n + 1);
      tris_.emplace_back(a, a + n + 1, a + n);
    }
  }
  screen_.resize(grid_.size());
}

void PlateScene::buildTrajectory(double fps, unsigned seed) {
  std::mt19937 rng(seed + 1);
  std::uniform_real_distribution<double> unit(-1.0, 1.0);
  std::uniform_real_distribution<double> pos(0.0, 1.0);
  std::normal_distribution<double> gauss(0.0, 1.0);
  const double tilt = spec_.max_tilt_deg * CV_PI / 180.0;
  // Tracker noise on the markers' frame, sized so the divots move by tracker_noise_mm RMS:
  // half of the variance from translation (3 sigma_t^2), half from rotation (for a small
  // isotropic rotation, E|w x p|^2 = 2 sigma_r^2 |p|^2, p a divot in {M}).
  double d2 = 0.0;
  for (const cv::Vec3d& d : nominalDivots()) {
    const cv::Vec3d p = p_t_m_.inverse() * d;
    d2 += p.dot(p) / 8.0;
  }
  const double var = spec_.tracker_noise_mm * spec_.tracker_noise_mm;
  const double sigma_t = std::sqrt(var / 2.0 / 3.0);
  const double sigma_r = std::sqrt(var / 2.0 / (2.0 * d2));
  const auto measure = [&](const Pose& c_t_p) {
    const Pose truth = o_t_c_ * c_t_p * p_t_m_;
    const Pose noise{rodrigues({sigma_r * gauss(rng), sigma_r * gauss(rng), sigma_r * gauss(rng)}),
                     {sigma_t * gauss(rng), sigma_t * gauss(rng), sigma_t * gauss(rng)}};
    return truth * noise;  // in the markers' frame: rotation noise about {O}'s origin, 2 m away,
                           // would be 20x larger
  };
  const auto randomStatic = [&](double depth) {
    const cv::Vec3d centre(spec_.lateral_range_mm * unit(rng), spec_.lateral_range_mm * unit(rng),
                           depth + spec_.depth_spread_mm * unit(rng));
    return facingPose(centre, tilt * unit(rng), tilt * unit(rng), CV_PI * unit(rng));
  };
  double t = 0.0;
  const double dt = 1.0 / fps;
  if (spec_.protocol == PlateProtocol::kStatic) {
    const double mid = 0.5 * (spec_.set_depths_mm.front() + spec_.set_depths_mm.back());
    for (int a = 0; a < spec_.registration_acquisitions; ++a) {
      const Pose p = randomStatic(mid + (spec_.set_depths_mm.back() - mid) * unit(rng));
      samples_.push_back({0, a, 0, t, p, measure(p)});
      t += dt;
    }
    for (int s = 0; s < spec_.sets; ++s) {
      for (int a = 0; a < spec_.acquisitions_per_set; ++a) {
        const Pose p =
            randomStatic(spec_.set_depths_mm[static_cast<size_t>(s) % spec_.set_depths_mm.size()]);
        samples_.push_back({s + 1, a, 0, t, p, measure(p)});
        t += dt;
      }
    }
  } else {
    for (int s = 0; s < spec_.sets; ++s) {
      for (int a = 0; a < spec_.acquisitions_per_set; ++a) {
        const Pose start =
            randomStatic(spec_.set_depths_mm[static_cast<size_t>(s) % spec_.set_depths_mm.size()]);
        // Smooth motion: a translation and a rotation oscillating at ~0.15 Hz whose peak
        // speeds spread from slow to the protocol's maxima (so the three speed populations of
        // section 4.D.2 are all filled).
        const double v_peak = spec_.max_speed_mm_s * (0.08 + 0.92 * std::pow(pos(rng), 1.5));
        const double w_peak =
            spec_.max_angular_speed_deg_s * CV_PI / 180.0 * (0.05 + 0.95 * std::pow(pos(rng), 1.5));
        const double f = 0.12 + 0.08 * pos(rng);
        const double phase = CV_PI * unit(rng);
        const cv::Vec3d dir = cv::normalize(cv::Vec3d(unit(rng), unit(rng), 0.5 * unit(rng)));
        const cv::Vec3d axis = cv::normalize(cv::Vec3d(unit(rng), unit(rng), unit(rng)));
        const double amp = v_peak / (2 * CV_PI * f);
        const double ang = w_peak / (2 * CV_PI * f);
        for (int k = 0; k < spec_.frames_per_acquisition; ++k) {
          const double tau = k * dt;
          const double s_t = std::sin(2 * CV_PI * f * tau + phase) - std::sin(phase);
          const Pose p{rodrigues(axis * (ang * s_t)) * start.r, start.t + dir * (amp * s_t)};
          samples_.push_back({s + 1, a, k, t, p, measure(p)});
          t += dt;
        }
        t += 1.0;  // a pause between acquisitions
      }
    }
  }
  // Section 4.A: the divots digitized once with the plate at its first pose.
  const Pose& first = samples_.front().c_t_p;
  digitization_o_t_m_ = measure(first);
  const double sigma_d = spec_.tracker_noise_mm / std::sqrt(3.0);
  for (size_t i = 0; i < 8; ++i) {
    const cv::Vec3d truth = o_t_c_ * (first * nominalDivots()[i]);
    digitized_[i] =
        truth + cv::Vec3d(sigma_d * gauss(rng), sigma_d * gauss(rng), sigma_d * gauss(rng));
  }
}

void PlateScene::buildTexture() {
  const double k = spec_.texture_px_per_mm;
  const int n = static_cast<int>(2 * kHalf * k);
  cv::Mat tex(n, n, CV_32FC1);
  cv::RNG rng(12345);
  rng.fill(tex, cv::RNG::NORMAL, 0.0, 1.0);
  cv::GaussianBlur(tex, tex, cv::Size(0, 0), 0.4 * k);
  tex = 200.0F + 6.0F * tex;  // matt white plastic with a faint texture
  const auto to_px = [&](const cv::Vec3d& p) {
    return cv::Point2d((p[0] + kHalf) * k - 0.5, (p[1] + kHalf) * k - 0.5);
  };
  const auto hole = [&](const cv::Vec3d& centre, double radius_mm, double depth_dark, double rim) {
    paintDisc(tex, to_px(centre), radius_mm * k,
              [&](double q) { return 1.0 - depth_dark * (1.0 - rim * q); });
  };
  // Features: conical holes 0.5 mm across, darkest at the apex (eq. 5).
  for (const cv::Vec3d& f : nominalFeatures()) hole(f, 0.25, 0.85, 0.8);
  // Divots: 3 mm hemispherical holes (eq. 4), shaded.
  for (const cv::Vec3d& d : nominalDivots()) hole(d, 1.5, 0.55, 0.5);
  // LED markers at the corners (what the tracker sees), dark housings.
  for (const cv::Vec3d& m : {cv::Vec3d(35, 35, 0), cv::Vec3d(-35, 35, 0), cv::Vec3d(35, -35, 0),
                             cv::Vec3d(-35, -35, 0)}) {
    hole(m, 2.5, 0.8, 0.0);
  }
  texture_ = tex;
}

void PlateScene::render(const vision::StereoRig& rig, const Pose& c_t_p, Rasterizer& raster,
                        cv::Mat& left, cv::Mat& right) {
  const double k = spec_.texture_px_per_mm;
  const cv::Vec3d normal = c_t_p.r * cv::Vec3d(0, 0, 1);
  for (int cam = 0; cam < 2; ++cam) {
    const vision::CameraModel& model = cam == 0 ? rig.left : rig.right;
    const cv::Matx33d r_xc = cam == 0 ? cv::Matx33d::eye() : rig.r;
    const cv::Vec3d t_xc = cam == 0 ? cv::Vec3d(0, 0, 0) : rig.t;
    const cv::Vec3d centre = cam == 0 ? cv::Vec3d(0, 0, 0) : rig.rightCentre();
    for (size_t i = 0; i < grid_.size(); ++i) {
      const cv::Vec3d p = c_t_p * cv::Vec3d(grid_[i][0], grid_[i][1], 0.0);
      const cv::Vec3d pc = r_xc * p + t_xc;
      const cv::Vec2d px = model.project(pc);
      ScreenVertex& sv = screen_[i];
      sv.valid = std::isfinite(px[0]);
      sv.x = static_cast<float>(px[0]);
      sv.y = static_cast<float>(px[1]);
      sv.z = static_cast<float>(pc[2]);
      sv.a0 = static_cast<float>((grid_[i][0] + kHalf) * k - 0.5);
      sv.a1 = static_cast<float>((grid_[i][1] + kHalf) * k - 0.5);
      // Lit from the camera's side: brightness follows the plate's tilt.
      sv.a2 = static_cast<float>(0.55 + 0.45 * std::abs(normal.dot(cv::normalize(centre - p))));
      sv.s = 0.0F;
    }
    raster.clear(30.0F);
    raster.drawTextured(screen_, tris_, texture_);
    raster.resolve(cam == 0 ? left : right);
  }
}

}  // namespace pulsetrack::sim
