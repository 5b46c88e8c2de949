#include "pulsetrack/sim/cortex.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <opencv2/calib3d.hpp>
#include <opencv2/imgproc.hpp>
#include <opencv2/photo.hpp>
#include <random>

#include "texture_paint.hpp"

namespace pulsetrack::sim {

namespace {

constexpr double kTwoPi = 2.0 * CV_PI;

// Index of grid vertex (i, j) in an n x n grid stored row by row.
size_t gridIndex(int i, int j, int n) {
  return static_cast<size_t>(j) * static_cast<size_t>(n) + static_cast<size_t>(i);
}

cv::Matx33d rotationAbout(const cv::Vec3d& axis, double angle) {
  cv::Matx33d r;
  cv::Rodrigues(cv::normalize(axis) * angle, r);
  return r;
}

// Band-limited Gaussian noise with unit standard deviation and correlation length sigma_px:
// white noise blurred (at a reduced resolution for large scales, then upsampled). Unlike
// upsampled coarse noise it has no grid-aligned artefacts, which a corner detector would find.
cv::Mat gaussianNoise(cv::Size size, double sigma_px, cv::RNG& rng) {
  const int f = std::max(1, static_cast<int>(sigma_px / 3.0));
  const cv::Size small((size.width + f - 1) / f, (size.height + f - 1) / f);
  cv::Mat noise(small, CV_32FC1);
  rng.fill(noise, cv::RNG::NORMAL, 0.0, 1.0);
  cv::GaussianBlur(noise, noise, cv::Size(0, 0), sigma_px / f);
  cv::Scalar mean, stddev;
  cv::meanStdDev(noise, mean, stddev);
  noise = (noise - mean[0]) / std::max(stddev[0], 1e-9);
  if (f == 1) return noise;
  cv::Mat big;
  cv::resize(noise, big, size, 0, 0, cv::INTER_LINEAR);
  return big;
}

// Sum of noise octaves: (correlation length in px, weight).
cv::Mat noiseField(cv::Size size, cv::RNG& rng,
                   const std::vector<std::pair<double, double>>& octaves) {
  cv::Mat acc(size, CV_32FC1, cv::Scalar(0));
  for (const auto& [sigma, weight] : octaves) acc += gaussianNoise(size, sigma, rng) * weight;
  return acc;
}

struct Segment {
  cv::Point2d a, b;
  double width_mm;
};

// A vessel tree grown as a random walk with smoothly turning direction, branching with
// narrowing children (Murray-like width ratios).
void growVessel(cv::Point2d p, double heading, double width, int depth, double limit_r,
                std::mt19937& rng, std::vector<Segment>& out) {
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  std::normal_distribution<double> turn(0.0, 0.10);
  double curvature = 0.0;
  double until_branch = 2.0 + 6.0 * unit(rng);
  const double step = 0.25;
  for (int i = 0; i < 2000 && width > 0.06; ++i) {
    curvature = 0.85 * curvature + turn(rng);
    heading += curvature * step;
    const cv::Point2d q = p + step * cv::Point2d(std::cos(heading), std::sin(heading));
    out.push_back({p, q, width});
    p = q;
    if (std::hypot(p.x, p.y) > limit_r) return;
    until_branch -= step;
    if (until_branch <= 0.0) {
      until_branch = 1.5 + 5.0 * unit(rng) * std::min(1.0, width * 2.0);
      if (depth < 7) {
        const double side = unit(rng) < 0.5 ? -1.0 : 1.0;
        const double angle = (0.45 + 0.6 * unit(rng)) * side;
        growVessel(p, heading + angle, width * (0.55 + 0.2 * unit(rng)), depth + 1, limit_r, rng,
                   out);
      }
      width *= 0.86;
      heading -= 0.15 * (unit(rng) - 0.5);
    }
    width *= 0.9985;
  }
}

// Whether the segment p0-p1 passes through the finite cylinder of radius r around q0-q1 with
// flat caps (the rendered instrument: its mesh is capped flat, so a capsule test would call
// points up to a radius beyond the tip hidden). The segment's points inside the infinite
// cylinder form an interval of s (a quadratic), those between the caps another (linear).
bool segmentHitsCylinder(const cv::Vec3d& p0, const cv::Vec3d& p1, const cv::Vec3d& q0,
                         const cv::Vec3d& q1, double r) {
  const cv::Vec3d axis = q1 - q0;
  const double len = cv::norm(axis);
  if (len <= 0.0) return false;
  const cv::Vec3d u = axis / len;
  const cv::Vec3d d = p1 - p0, w = p0 - q0;
  // Axial coordinate a(s) = (w + s d).u in [0, len].
  const double a0 = w.dot(u), da = d.dot(u);
  double lo = 0.0, hi = 1.0;
  if (std::abs(da) < 1e-12) {
    if (a0 < 0.0 || a0 > len) return false;
  } else {
    double s0 = -a0 / da, s1 = (len - a0) / da;
    if (s0 > s1) std::swap(s0, s1);
    lo = std::max(lo, s0);
    hi = std::min(hi, s1);
  }
  if (lo > hi) return false;
  // Radial: |(w + s d) - a(s) u|^2 <= r^2.
  const cv::Vec3d wp = w - a0 * u, dp = d - da * u;
  const double qa = dp.dot(dp), qb = 2.0 * wp.dot(dp), qc = wp.dot(wp) - r * r;
  if (qa < 1e-12) return qc <= 0.0;
  const double disc = qb * qb - 4.0 * qa * qc;
  if (disc < 0.0) return false;
  const double sq = std::sqrt(disc);
  const double r0 = (-qb - sq) / (2.0 * qa), r1 = (-qb + sq) / (2.0 * qa);
  return std::max(lo, r0) <= std::min(hi, r1);
}

}  // namespace

std::vector<Oscillation> paperMotion() {
  std::vector<Oscillation> m;
  Oscillation vaso;
  vaso.name = "vasomotor";
  vaso.amplitude_mm = 0.12;
  vaso.frequency_hz = 0.05;
  vaso.phase_rad = 0.4;
  vaso.gradient = {0.2, 0.1};
  vaso.direction = {0.1, 0.0, 1.0};
  m.push_back(vaso);
  Oscillation breathing;
  breathing.name = "breathing";
  breathing.amplitude_mm = 0.45;
  breathing.frequency_hz = 0.2;
  breathing.harmonics = {{2.0, 0.3, 0.5}, {3.0, 0.12, 1.1}};
  breathing.gradient = {0.3, -0.25};
  breathing.direction = {0.15, 0.1, 1.0};
  m.push_back(breathing);
  Oscillation cardiac;
  cardiac.name = "cardiac";
  cardiac.amplitude_mm = 0.15;
  cardiac.frequency_hz = 1.0;
  cardiac.phase_rad = 1.3;
  cardiac.harmonics = {{2.0, 0.25, 0.7}};
  cardiac.gradient = {-0.2, 0.3};
  cardiac.direction = {0.0, 0.1, 1.0};
  m.push_back(cardiac);
  return m;
}

CortexScene::CortexScene(const CortexSpec& spec) : spec_(spec) {
  for (const Oscillation& o : spec_.oscillations) clocks_.emplace_back(o);
  // {S}: origin at the patch centre; z towards the cameras, tilted by tilt_deg.
  t_cs_ = cv::Vec3d(spec.offset_mm[0], spec.offset_mm[1], spec.distance_mm);
  const cv::Vec3d towards_camera = -cv::normalize(t_cs_);
  const double az = spec.azimuth_deg * CV_PI / 180.0;
  cv::Vec3d axis = cv::Vec3d(std::cos(az), std::sin(az), 0.0);
  axis -= towards_camera * axis.dot(towards_camera);
  const cv::Vec3d z = rotationAbout(axis, spec.tilt_deg * CV_PI / 180.0) * towards_camera;
  const cv::Vec3d x = cv::normalize(cv::Vec3d(0, 1, 0).cross(z));
  const cv::Vec3d y = z.cross(x);
  r_cs_ = cv::Matx33d(x[0], y[0], z[0], x[1], y[1], z[1], x[2], y[2], z[2]);
  // The lamp, 600 mm from the patch, about half-way from the camera's direction to
  // its mirror image in the surface: where the tissue's wrinkles and gyri tilt the normal by
  // some 10 degrees the mirror condition holds, and glints appear, different in each camera.
  const cv::Vec3d to_camera = cv::normalize(-t_cs_);
  const cv::Vec3d mirror = 2.0 * z.dot(to_camera) * z - to_camera;
  light_c_ = t_cs_ + 600.0 * cv::normalize(0.45 * to_camera + 0.55 * mirror);
  buildTexture();
  buildMeshes();
}

cv::Vec3d CortexScene::restPosition(double u, double v) const {
  const double r2 = u * u + v * v;
  const double a = spec_.gyri_amplitude_mm;
  const double gyri = a * (0.6 * std::sin(kTwoPi * (0.8 * u + 0.6 * v) / 16.0 + 0.3) +
                           0.4 * std::sin(kTwoPi * (-0.5 * u + 0.87 * v) / 11.0 + 1.9));
  return {u, v, -r2 / (2.0 * spec_.curvature_radius_mm) + gyri};
}

OscillationClock::OscillationClock(const Oscillation& o, double horizon_s) : o_(o) {
  changes_ = std::isfinite(o.frequency_end_hz) || std::isfinite(o.amplitude_end_mm) ||
             o.irregularity > 0.0;
  if (o.irregularity <= 0.0 || o.frequency_hz <= 0.0) return;
  // Irregular cycles: lengths and amplitudes drawn around the nominal ones at their start.
  std::mt19937 rng(o.irregularity_seed);
  std::normal_distribution<double> g(0.0, 1.0);
  const auto draw = [&] { return std::clamp(g(rng), -2.5, 2.5) * o.irregularity; };
  double t = 0.0;
  cycle_start_.push_back(0.0);
  cycle_amp_.push_back(1.0 + draw());
  while (t < horizon_s) {
    t += std::max(0.2, 1.0 + draw()) / std::max(frequency(t), 1e-3);
    cycle_start_.push_back(t);
    cycle_amp_.push_back(std::max(0.1, 1.0 + draw()));
  }
}

double OscillationClock::frequency(double t) const {
  if (!std::isfinite(o_.frequency_end_hz)) return o_.frequency_hz;
  const double d = std::max(o_.change_duration_s, 1e-9);
  const double a = std::clamp((t - o_.change_start_s) / d, 0.0, 1.0);
  return o_.frequency_hz + a * (o_.frequency_end_hz - o_.frequency_hz);
}

double OscillationClock::amplitude(double t) const {
  if (!std::isfinite(o_.amplitude_end_mm)) return o_.amplitude_mm;
  const double d = std::max(o_.change_duration_s, 1e-9);
  const double a = std::clamp((t - o_.change_start_s) / d, 0.0, 1.0);
  return o_.amplitude_mm + a * (o_.amplitude_end_mm - o_.amplitude_mm);
}

double OscillationClock::theta(double t) const {
  if (!cycle_start_.empty()) {
    // Cycle k spans [start_k, start_k+1): theta = 2 pi (k + fraction).
    if (t <= 0.0) return kTwoPi * t * o_.frequency_hz;
    const auto it = std::upper_bound(cycle_start_.begin(), cycle_start_.end(), t);
    if (it == cycle_start_.end()) return kTwoPi * static_cast<double>(cycle_start_.size());
    const size_t k = static_cast<size_t>(it - cycle_start_.begin()) - 1;
    const double frac = (t - cycle_start_[k]) / (cycle_start_[k + 1] - cycle_start_[k]);
    return kTwoPi * (static_cast<double>(k) + frac);
  }
  if (!std::isfinite(o_.frequency_end_hz)) return kTwoPi * o_.frequency_hz * t;
  // The integral of the piecewise linear frequency.
  const double f0 = o_.frequency_hz, f1 = o_.frequency_end_hz, ts = o_.change_start_s;
  const double d = std::max(o_.change_duration_s, 1e-9);
  if (t <= ts) return kTwoPi * f0 * t;
  const double r = std::min(t - ts, d);
  double cycles = f0 * ts + f0 * r + 0.5 * (f1 - f0) / d * r * r;
  if (t > ts + d) cycles += f1 * (t - ts - d);
  return kTwoPi * cycles;
}

double OscillationClock::value(double t) const {
  if (!changes_) {  // the original closed form, bit for bit
    double s = std::sin(kTwoPi * o_.frequency_hz * t + o_.phase_rad);
    for (const Harmonic& h : o_.harmonics)
      s += h.relative_amplitude * std::sin(kTwoPi * h.multiple * o_.frequency_hz * t + h.phase_rad);
    return o_.amplitude_mm * s;
  }
  const double th = theta(t);
  double s = std::sin(th + o_.phase_rad);
  for (const Harmonic& h : o_.harmonics)
    s += h.relative_amplitude * std::sin(h.multiple * th + h.phase_rad);
  double a = amplitude(t);
  if (!cycle_start_.empty() && t > 0.0) {
    const auto it = std::upper_bound(cycle_start_.begin(), cycle_start_.end(), t);
    if (it != cycle_start_.end()) {
      const size_t k = static_cast<size_t>(it - cycle_start_.begin()) - 1;
      const double frac = (t - cycle_start_[k]) / (cycle_start_[k + 1] - cycle_start_[k]);
      const double blend = 0.5 - 0.5 * std::cos(CV_PI * frac);
      a *= cycle_amp_[k] + blend * (cycle_amp_[k + 1] - cycle_amp_[k]);
    }
  }
  return a * s;
}

cv::Vec3d CortexScene::displacement(double u, double v, double t) const {
  cv::Vec3d d(0, 0, 0);
  const double radius = spec_.radius_mm;
  for (size_t i = 0; i < spec_.oscillations.size(); ++i) {
    const Oscillation& o = spec_.oscillations[i];
    if (!o.enabled) continue;
    const double w = 1.0 + (o.gradient[0] * u + o.gradient[1] * v) / radius;
    d += cv::normalize(o.direction) * (clocks_[i].value(t) * w);
  }
  if (spec_.sag.enabled) {
    const double r2 = (u * u + v * v) / (radius * radius);
    const double sink = spec_.sag.depth_mm * (1.0 - std::exp(-t / spec_.sag.time_constant_s));
    d[2] -= sink * (1.0 - 0.5 * r2);
    if (spec_.sag.rotation_deg != 0.0) {
      const double angle =
          spec_.sag.rotation_deg * CV_PI / 180.0 * (1.0 - std::exp(-t / spec_.sag.time_constant_s));
      cv::Matx33d rot;
      cv::Rodrigues(cv::normalize(spec_.sag.rotation_axis) * angle, rot);
      const cv::Vec3d rest = restPosition(u, v);
      d = rot * (rest + d) - rest;
    }
  }
  return d;
}

cv::Vec3d CortexScene::position(double u, double v, double t) const {
  return r_cs_ * (restPosition(u, v) + displacement(u, v, t)) + t_cs_;
}

bool CortexScene::materialAt(const vision::StereoRig& rig, const cv::Vec2d& px, double t,
                             cv::Vec2d& uv) const {
  const vision::Ray ray = rig.backProjectLeft(px);
  // Start on the plane z_S = 0, then Gauss-Newton on position(u, v, t) = lambda g.
  const cv::Vec3d n = r_cs_ * cv::Vec3d(0, 0, 1);
  double lambda = n.dot(t_cs_) / n.dot(ray.direction);
  cv::Vec3d s = r_cs_.t() * (lambda * ray.direction - t_cs_);
  double u = s[0], v = s[1];
  for (int it = 0; it < 30; ++it) {
    const cv::Vec3d f = position(u, v, t) - lambda * ray.direction;
    const double h = 1e-4;
    const cv::Vec3d du = (position(u + h, v, t) - position(u - h, v, t)) / (2 * h);
    const cv::Vec3d dv = (position(u, v + h, t) - position(u, v - h, t)) / (2 * h);
    const cv::Matx33d j(du[0], dv[0], -ray.direction[0], du[1], dv[1], -ray.direction[1], du[2],
                        dv[2], -ray.direction[2]);
    cv::Vec3d step;
    if (!cv::solve(j, f, step)) return false;
    u -= step[0];
    v -= step[1];
    lambda -= step[2];
    if (cv::norm(step) < 1e-12) break;
  }
  uv = {u, v};
  return std::hypot(u, v) <= spec_.radius_mm;
}

double CortexScene::instrumentTime(double t) const {
  const Instrument& in = spec_.instrument;
  if (!in.enabled || t < in.start_s) return -1.0;
  double local = t - in.start_s;
  if (in.period_s > 0.0) {
    const double k = std::floor(local / in.period_s);
    if (in.repeats > 0 && k >= in.repeats) return -1.0;
    local -= k * in.period_s;
  }
  return local <= in.duration_s ? local : -1.0;
}

cv::Vec3d CortexScene::instrumentTip(double t) const {
  const Instrument& in = spec_.instrument;
  const double local = instrumentTime(t);
  const double phase = local < 0.0 ? 0.0 : std::clamp(local / in.duration_s, 0.0, 1.0);
  const double ramp = (1.0 - in.hold_fraction) / 2.0;
  const double s = phase < ramp         ? std::sin(CV_PI / 2.0 * phase / ramp)
                   : phase > 1.0 - ramp ? std::sin(CV_PI / 2.0 * (1.0 - phase) / ramp)
                                        : 1.0;
  const cv::Vec2d xy = in.from_mm + (in.to_mm - in.from_mm) * s;
  return {xy[0], xy[1], in.height_mm};
}

bool CortexScene::occluded(const cv::Vec3d& p, const cv::Vec3d& camera_centre, double t) const {
  const Instrument& in = spec_.instrument;
  if (instrumentTime(t) < 0.0) return false;
  const cv::Vec3d tip = r_cs_ * instrumentTip(t) + t_cs_;
  const cv::Vec3d end = tip + r_cs_ * cv::Vec3d(-in.length_mm, 0, 0);
  return segmentHitsCylinder(camera_centre, p, tip, end, in.radius_mm);
}

namespace {

// A real photograph as the albedo (CortexSpec::texture "image"): its glints inpainted, scaled
// to texture_image_mm across at texture_px_per_mm, centred on the patch and mirrored outwards
// to `size`. Its grey levels are the albedo (what that camera saw, the scene's light and
// shading on top; tissue_albedo is not used).
cv::Mat imageTexture(const CortexSpec& spec, cv::Size size) {
  const cv::Mat& grey = spec.texture_image_grey;
  cv::Mat glints = grey >= 240;
  cv::dilate(glints, glints, cv::getStructuringElement(cv::MORPH_ELLIPSE, {5, 5}));
  cv::Mat clean;
  cv::inpaint(grey, glints, clean, 3.0, cv::INPAINT_TELEA);
  const double px_per_image_px = spec.texture_image_mm * spec.texture_px_per_mm / grey.cols;
  cv::Mat scaled;
  cv::resize(clean, scaled,
             cv::Size(std::max(1, static_cast<int>(std::lround(grey.cols * px_per_image_px))),
                      std::max(1, static_cast<int>(std::lround(grey.rows * px_per_image_px)))),
             0, 0, px_per_image_px < 1.0 ? cv::INTER_AREA : cv::INTER_CUBIC);
  // Mirrored outwards to cover `size` (REFLECT_101 repeats for borders wider than the image),
  // then cut centred.
  const int bx = std::max(0, (size.width - scaled.cols + 1) / 2);
  const int by = std::max(0, (size.height - scaled.rows + 1) / 2);
  if (bx > 0 || by > 0) cv::copyMakeBorder(scaled, scaled, by, by, bx, bx, cv::BORDER_REFLECT_101);
  const cv::Rect centre((scaled.cols - size.width) / 2, (scaled.rows - size.height) / 2, size.width,
                        size.height);
  cv::Mat out;
  scaled(centre).convertTo(out, CV_32FC1);  // its grey levels are the albedo
  return out;
}

}  // namespace

void CortexScene::buildTexture() {
  std::mt19937 rng(spec_.seed);
  cv::RNG cvrng(spec_.seed * 104729ULL + 1ULL);
  const double k = spec_.texture_px_per_mm;
  const double extent = spec_.radius_mm + 3.0;
  const int n = static_cast<int>(std::ceil(2.0 * extent * k));
  const cv::Size size(n, n);
  // Tissue: blotches (mm to cm) and fine capillary texture (0.1-0.4 mm).
  cv::Mat noise = noiseField(
      size, cvrng,
      {{8.0 * k, 0.07}, {2.5 * k, 0.06}, {0.8 * k, 0.05}, {0.25 * k, 0.05}, {0.1 * k, 0.04}});
  // Vessels: trees entering from the rim, plus a few sulci (wide, faint).
  std::vector<Segment> segments;
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  for (int i = 0; i < spec_.vessel_trees; ++i) {
    const double a = kTwoPi * (i + 0.5 * unit(rng)) / spec_.vessel_trees;
    const cv::Point2d start = (extent - 0.5) * cv::Point2d(std::cos(a), std::sin(a));
    const double heading = a + CV_PI + (unit(rng) - 0.5) * 1.0;
    growVessel(start, heading, 0.7 + 0.8 * unit(rng), 0, extent + 1.0, rng, segments);
  }
  std::sort(segments.begin(), segments.end(),
            [](const Segment& a, const Segment& b) { return a.width_mm < b.width_mm; });
  cv::Mat vessels(size, CV_8UC1, cv::Scalar(0));
  const auto to_px = [&](const cv::Point2d& p) {
    constexpr int kShift = 4;
    return cv::Point(static_cast<int>(((p.x + extent) * k - 0.5) * (1 << kShift)),
                     static_cast<int>(((p.y + extent) * k - 0.5) * (1 << kShift)));
  };
  for (const Segment& s : segments) {
    const int thickness = std::max(1, static_cast<int>(std::lround(s.width_mm * k)));
    const double strength = std::min(1.0, 0.35 + s.width_mm / 1.2);
    cv::line(vessels, to_px(s.a), to_px(s.b), cv::Scalar(255 * strength), thickness, cv::LINE_AA,
             4);
  }
  cv::Mat vessel_f;
  vessels.convertTo(vessel_f, CV_32FC1, 1.0 / 255.0);
  cv::GaussianBlur(vessel_f, vessel_f, cv::Size(0, 0), 0.35 * k * 0.1 + 0.6);
  std::vector<Segment> sulci;
  for (int i = 0; i < 3; ++i) {
    const double a = kTwoPi * unit(rng);
    growVessel(extent * cv::Point2d(std::cos(a), std::sin(a)), a + CV_PI, 2.5, 6, extent + 1.0, rng,
               sulci);
  }
  cv::Mat sulcus(size, CV_8UC1, cv::Scalar(0));
  for (const Segment& s : sulci) {
    cv::line(sulcus, to_px(s.a), to_px(s.b), cv::Scalar(255),
             std::max(1, static_cast<int>(s.width_mm * k)), cv::LINE_AA, 4);
  }
  cv::Mat sulcus_f;
  sulcus.convertTo(sulcus_f, CV_32FC1, 1.0 / 255.0);
  cv::GaussianBlur(sulcus_f, sulcus_f, cv::Size(0, 0), 1.0 * k);
  texture_ = static_cast<float>(spec_.tissue_albedo) *
             (1.0F + noise)
                 .mul(1.0F - static_cast<float>(spec_.vessel_contrast) * vessel_f)
                 .mul(1.0F - 0.3F * sulcus_f);
  // (A spec made in code without the image keeps the procedural texture.)
  if (spec_.texture == "image" && !spec_.texture_image_grey.empty())
    texture_ = imageTexture(spec_, size);
  if (spec_.texture == "dots") {
    texture_.setTo(static_cast<float>(spec_.tissue_albedo));
    for (double v = -std::floor(extent / 4) * 4; v <= extent; v += 4.0) {
      for (double u = -std::floor(extent / 4) * 4; u <= extent; u += 4.0) {
        paintDisc(texture_, {(u + extent) * k - 0.5, (v + extent) * k - 0.5}, 0.4 * k,
                  [](double) { return 0.2; });
      }
    }
  }

  // Bone and drapes around the craniotomy: bright, low contrast.
  const double bone_k = 4.0;
  const int bn = static_cast<int>(2.0 * (spec_.radius_mm + 30.0) * bone_k);
  bone_texture_ =
      185.0F * (1.0F + noiseField({bn, bn}, cvrng, {{6.0 * bone_k, 0.05}, {1.0 * bone_k, 0.04}}));
  // Wet-tissue wrinkles (0.5-2 mm) as a height field in material coordinates: their slopes
  // tilt the normals and break the highlights into glints that move with the tissue.
  const double bump_k = 8.0;
  const int bnn = static_cast<int>(std::ceil(2.0 * extent * bump_k));
  cv::Mat bump = noiseField({bnn, bnn}, cvrng, {{1.2 * bump_k, 0.07}, {0.5 * bump_k, 0.03}});
  cv::Sobel(bump, bump_du_, CV_32F, 1, 0, 3, bump_k / 8.0);
  cv::Sobel(bump, bump_dv_, CV_32F, 0, 1, 3, bump_k / 8.0);
  bump_px_per_mm_ = bump_k;
  flat_texture_ = cv::Mat(2, 2, CV_32FC1, cv::Scalar(1.0));
}

void CortexScene::buildMeshes() {
  const double h = spec_.mesh_step_mm;
  const double half = spec_.radius_mm + 1.0;
  grid_n_ = static_cast<int>(std::ceil(2.0 * half / h)) + 1;
  const int n = grid_n_;
  grid_uv_.resize(static_cast<size_t>(n) * static_cast<size_t>(n));
  for (int j = 0; j < n; ++j) {
    for (int i = 0; i < n; ++i) grid_uv_[gridIndex(i, j, n)] = {-half + i * h, -half + j * h};
  }
  const double keep = (half + h) * (half + h);
  for (int j = 0; j + 1 < n; ++j) {
    for (int i = 0; i + 1 < n; ++i) {
      const int a = j * n + i, b = a + 1, c = a + n, d = c + 1;
      const cv::Vec2d& p = grid_uv_[static_cast<size_t>(a)];
      if (p[0] * p[0] + p[1] * p[1] > keep &&
          (p[0] + h) * (p[0] + h) + (p[1] + h) * (p[1] + h) > keep &&
          p[0] * p[0] + (p[1] + h) * (p[1] + h) > keep &&
          (p[0] + h) * (p[0] + h) + p[1] * p[1] > keep) {
        continue;
      }
      cortex_tris_.emplace_back(a, b, d);
      cortex_tris_.emplace_back(a, d, c);
    }
  }
  world_.resize(grid_uv_.size());
  normal_.resize(grid_uv_.size());
  bump_grad_.resize(grid_uv_.size());
  const double bump_extent = spec_.radius_mm + 3.0;
  for (size_t i = 0; i < grid_uv_.size(); ++i) {
    const int bx = std::clamp(static_cast<int>((grid_uv_[i][0] + bump_extent) * bump_px_per_mm_), 0,
                              bump_du_.cols - 1);
    const int by = std::clamp(static_cast<int>((grid_uv_[i][1] + bump_extent) * bump_px_per_mm_), 0,
                              bump_du_.rows - 1);
    bump_grad_[i] = static_cast<float>(spec_.wrinkle_slope) *
                    cv::Vec2f(bump_du_.at<float>(by, bx), bump_dv_.at<float>(by, bx));
  }
  screen_.resize(grid_uv_.size());

  // Bone rim: rings from just inside the craniotomy edge outwards, 2 mm above the brain's rim.
  const double r0 = spec_.radius_mm;
  const double rim_z = -r0 * r0 / (2.0 * spec_.curvature_radius_mm) + 2.0;
  const std::vector<double> rings = {r0 - 0.5, r0 + 0.5, r0 + 2, r0 + 5, r0 + 10, r0 + 18, r0 + 28};
  const int sectors = 180;
  const double bone_k = 4.0;
  const double bone_half = spec_.radius_mm + 30.0;
  for (double r : rings) {
    for (int s = 0; s < sectors; ++s) {
      const double a = kTwoPi * s / sectors;
      const cv::Vec3d p_s(r * std::cos(a), r * std::sin(a), rim_z + 0.04 * (r - r0));
      bone_c_.push_back(r_cs_ * p_s + t_cs_);
      bone_uv_.emplace_back((p_s[0] + bone_half) * bone_k - 0.5,
                            (p_s[1] + bone_half) * bone_k - 0.5);
    }
  }
  for (int ring = 0; ring + 1 < static_cast<int>(rings.size()); ++ring) {
    for (int s = 0; s < sectors; ++s) {
      const int a = ring * sectors + s, b = ring * sectors + (s + 1) % sectors;
      const int c = a + sectors, d = b + sectors;
      bone_tris_.emplace_back(a, b, d);
      bone_tris_.emplace_back(a, d, c);
    }
  }
  bone_screen_.resize(bone_c_.size());

  // Instrument: a cylinder along -x of {S} from the tip, capped at the tip.
  const int around = 24;
  const double rad = spec_.instrument.radius_mm;
  for (double x : {0.0, -spec_.instrument.length_mm}) {
    for (int s = 0; s < around; ++s) {
      const double a = kTwoPi * s / around;
      tool_local_.emplace_back(x, rad * std::cos(a), rad * std::sin(a));
    }
  }
  tool_local_.emplace_back(0.0, 0.0, 0.0);  // cap centre
  for (int s = 0; s < around; ++s) {
    const int a = s, b = (s + 1) % around, c = s + around, d = (s + 1) % around + around;
    tool_tris_.emplace_back(a, b, d);
    tool_tris_.emplace_back(a, d, c);
    tool_tris_.emplace_back(2 * around, b, a);
  }
  tool_screen_.resize(tool_local_.size());
}

void CortexScene::render(const vision::StereoRig& rig, double t, Rasterizer& raster, cv::Mat& left,
                         cv::Mat& right) {
  const int n = grid_n_;
  const double radius = spec_.radius_mm;
  // Deformed positions, then normals from the grid (central differences).
  for (size_t i = 0; i < grid_uv_.size(); ++i)
    world_[i] = position(grid_uv_[i][0], grid_uv_[i][1], t);
  const cv::Vec3d z_s = r_cs_ * cv::Vec3d(0, 0, 1);
  const cv::Vec3d x_s = r_cs_ * cv::Vec3d(1, 0, 0);
  const cv::Vec3d y_s = r_cs_ * cv::Vec3d(0, 1, 0);
  for (int j = 0; j < n; ++j) {
    for (int i = 0; i < n; ++i) {
      const auto at = [&](int ii, int jj) {
        return world_[gridIndex(std::clamp(ii, 0, n - 1), std::clamp(jj, 0, n - 1), n)];
      };
      cv::Vec3d nn = (at(i + 1, j) - at(i - 1, j)).cross(at(i, j + 1) - at(i, j - 1));
      if (nn.dot(z_s) < 0) nn = -nn;
      const cv::Vec2f& g = bump_grad_[gridIndex(i, j, n)];
      const double gu = g[0];
      const double gv = g[1];
      normal_[gridIndex(i, j, n)] = cv::normalize(cv::normalize(nn) - gu * x_s - gv * y_s);
    }
  }
  const double illum_t =
      1.0 + spec_.illumination_drift * std::sin(kTwoPi * t / spec_.illumination_period_s);
  const Shadow& sh = spec_.shadow;
  const bool shadow_on = sh.enabled && t >= sh.start_s && t <= sh.start_s + sh.duration_s;
  const double shadow_x = shadow_on
                              ? -(radius + 2 * sh.width_mm) + (2 * radius + 4 * sh.width_mm) *
                                                                  (t - sh.start_s) / sh.duration_s
                              : 0.0;
  const auto shadowAt = [&](double u, double v) {
    if (!shadow_on) return 1.0;
    const double across = 0.8 * u + 0.6 * v - shadow_x;
    const double inside =
        std::clamp((sh.width_mm / 2 - std::abs(across)) / sh.softness_mm + 0.5, 0.0, 1.0);
    const double smooth = inside * inside * (3 - 2 * inside);
    return 1.0 - sh.depth * smooth;
  };
  const double k = spec_.texture_px_per_mm;
  const double extent = spec_.radius_mm + 3.0;
  const Instrument& in = spec_.instrument;
  const bool tool_on = instrumentTime(t) >= 0.0;
  const cv::Vec3d tip_c = r_cs_ * instrumentTip(t) + t_cs_;

  for (int cam = 0; cam < 2; ++cam) {
    const vision::CameraModel& model = cam == 0 ? rig.left : rig.right;
    const cv::Matx33d r_xc = cam == 0 ? cv::Matx33d::eye() : rig.r;
    const cv::Vec3d t_xc = cam == 0 ? cv::Vec3d(0, 0, 0) : rig.t;
    const cv::Vec3d centre = cam == 0 ? cv::Vec3d(0, 0, 0) : rig.rightCentre();
    const auto project = [&](const cv::Vec3d& p, ScreenVertex& sv) {
      const cv::Vec3d pc = r_xc * p + t_xc;
      const cv::Vec2d px = model.project(pc);
      sv.valid = std::isfinite(px[0]);
      sv.x = static_cast<float>(px[0]);
      sv.y = static_cast<float>(px[1]);
      sv.z = static_cast<float>(pc[2]);
    };
    for (size_t i = 0; i < world_.size(); ++i) {
      ScreenVertex& sv = screen_[i];
      const cv::Vec3d& p = world_[i];
      project(p, sv);
      const cv::Vec3d l = cv::normalize(light_c_ - p);
      const cv::Vec3d view = cv::normalize(centre - p);
      const cv::Vec3d& nn = normal_[i];
      const double diffuse = std::max(0.0, nn.dot(l));
      const cv::Vec2d& uv = grid_uv_[i];
      const double illum =
          illum_t * (1.0 + spec_.illumination_gradient * (uv[0] - 0.5 * uv[1]) / radius);
      const double shadow = shadowAt(uv[0], uv[1]);
      const double hdot = std::max(0.0, nn.dot(cv::normalize(l + view)));
      sv.a0 = static_cast<float>((uv[0] + extent) * k - 0.5);
      sv.a1 = static_cast<float>((uv[1] + extent) * k - 0.5);
      sv.a2 = static_cast<float>(illum * shadow * (0.5 + 0.6 * diffuse));
      sv.s = static_cast<float>(spec_.specular_strength * std::pow(hdot, spec_.specular_shininess) *
                                shadow);
    }
    for (size_t i = 0; i < bone_c_.size(); ++i) {
      ScreenVertex& sv = bone_screen_[i];
      project(bone_c_[i], sv);
      sv.a0 = static_cast<float>(bone_uv_[i][0]);
      sv.a1 = static_cast<float>(bone_uv_[i][1]);
      sv.a2 = static_cast<float>(
          illum_t * (0.4 + 0.6 * std::max(0.0, z_s.dot(cv::normalize(light_c_ - bone_c_[i])))));
      sv.s = 0.0F;
    }
    raster.clear(30.0F);
    raster.drawTextured(screen_, cortex_tris_, texture_);
    raster.drawTextured(bone_screen_, bone_tris_, bone_texture_);
    if (tool_on) {
      for (size_t i = 0; i < tool_local_.size(); ++i) {
        const cv::Vec3d p = tip_c + r_cs_ * tool_local_[i];
        ScreenVertex& sv = tool_screen_[i];
        project(p, sv);
        const cv::Vec3d nn =
            i + 1 == tool_local_.size()
                ? cv::Vec3d(r_cs_ * cv::Vec3d(1, 0, 0))
                : cv::normalize(r_cs_ * cv::Vec3d(0, tool_local_[i][1], tool_local_[i][2]));
        const cv::Vec3d l = cv::normalize(light_c_ - p);
        const cv::Vec3d view = cv::normalize(centre - p);
        const double hdot = std::max(0.0, nn.dot(cv::normalize(l + view)));
        sv.a0 = 0.5F;
        sv.a1 = 0.5F;
        sv.a2 = static_cast<float>(255.0 * in.albedo * (0.3 + 0.7 * std::max(0.0, nn.dot(l))));
        sv.s = static_cast<float>(300.0 * std::pow(hdot, 20.0));
      }
      raster.drawTextured(tool_screen_, tool_tris_, flat_texture_);
    }
    raster.resolve(cam == 0 ? left : right);
  }
}

}  // namespace pulsetrack::sim
