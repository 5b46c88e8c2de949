#include "pulsetrack/analysis/motion.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <map>
#include <opencv2/core.hpp>

namespace pulsetrack::analysis {

using vision::fail;

std::vector<double> naturalCubicSpline(const std::vector<double>& x, const std::vector<double>& y,
                                       const std::vector<double>& at) {
  const size_t n = x.size();
  std::vector<double> out(at.size(), n > 0 ? y[0] : 0.0);
  if (n < 2) return out;
  // Second derivatives m: tridiagonal system (Thomas algorithm), m[0] = m[n-1] = 0.
  std::vector<double> m(n, 0.0), c(n, 0.0), d(n, 0.0);
  for (size_t i = 1; i + 1 < n; ++i) {
    const double h0 = x[i] - x[i - 1], h1 = x[i + 1] - x[i];
    const double a = h0, b = 2 * (h0 + h1), cc = h1;
    const double r = 6 * ((y[i + 1] - y[i]) / h1 - (y[i] - y[i - 1]) / h0);
    const double denom = b - a * c[i - 1];
    c[i] = cc / denom;
    d[i] = (r - a * d[i - 1]) / denom;
  }
  for (size_t i = n - 2; i >= 1; --i) {
    m[i] = d[i] - c[i] * m[i + 1];
    if (i == 1) break;
  }
  for (size_t k = 0; k < at.size(); ++k) {
    const double t = std::clamp(at[k], x.front(), x.back());
    size_t i = static_cast<size_t>(std::upper_bound(x.begin(), x.end(), t) - x.begin());
    i = std::clamp<size_t>(i, 1, n - 1);
    const double h = x[i] - x[i - 1], a = (x[i] - t) / h, b = (t - x[i - 1]) / h;
    out[k] = a * y[i - 1] + b * y[i] +
             ((a * a * a - a) * m[i - 1] + (b * b * b - b) * m[i]) * h * h / 6.0;
  }
  return out;
}

namespace {

struct FrameRows {
  double t = 0;
  std::vector<const record::TrackRow*> ok;
};

void namePeaks(std::vector<SpectralPeak>& peaks, double resolution_hz) {
  const auto strongest = [&](double lo, double hi) -> SpectralPeak* {
    SpectralPeak* best = nullptr;
    for (SpectralPeak& p : peaks) {
      if (p.name.empty() && p.frequency_hz >= lo && p.frequency_hz <= hi &&
          (best == nullptr || p.amplitude_mm > best->amplitude_mm))
        best = &p;
    }
    return best;
  };
  const double tol = std::max(0.03, 1.5 * resolution_hz);
  // Breathing first, then the heart (0.6-2.5 Hz: 36-150 beats per minute) before breathing's
  // harmonics, which can fall on the heart rate (5 x 0.2 Hz = 1 Hz).
  SpectralPeak* breathing = strongest(0.1, 0.6);
  if (breathing != nullptr) breathing->name = "breathing";
  if (SpectralPeak* c = strongest(0.6, 2.5)) {
    c->name = "cardiac";
    const double fc = c->frequency_hz;
    if (SpectralPeak* h = strongest(2 * fc - tol, 2 * fc + tol)) h->name = "cardiac harmonic 2";
  }
  if (breathing != nullptr) {
    const double fb = breathing->frequency_hz;
    for (int n = 2; n <= 4; ++n) {
      if (SpectralPeak* h = strongest(n * fb - tol, n * fb + tol))
        h->name = fmt::format("breathing harmonic {}", n);
    }
  }
  if (SpectralPeak* v = strongest(0.025, 0.07)) v->name = "vasomotor";
}

void spectrum(MotionAnalysis& a, const MotionOptions& options) {
  const size_t ns = a.t.size();
  a.frequency_hz.clear();
  a.amplitude_mm.clear();
  a.peaks.clear();
  // Spectrum: Hann window, zero padding, amplitude of a sinusoid = 2 |X| / sum(w).
  const int nfft = cv::getOptimalDFTSize(static_cast<int>(ns) * std::max(1, options.zero_padding));
  std::vector<double> w(ns);
  double wsum = 0;
  for (size_t i = 0; i < ns; ++i) {
    w[i] = 0.5 - 0.5 * std::cos(2 * M_PI * static_cast<double>(i) / static_cast<double>(ns - 1));
    wsum += w[i];
  }
  const int bins = nfft / 2 + 1;
  std::vector<double> power(static_cast<size_t>(bins), 0.0);
  for (int axis = 0; axis < 3; ++axis) {
    cv::Mat in = cv::Mat::zeros(1, nfft, CV_64F), out;
    for (size_t i = 0; i < ns; ++i)
      in.at<double>(0, static_cast<int>(i)) = a.detrended[i][axis] * w[i];
    cv::dft(in, out, cv::DFT_COMPLEX_OUTPUT);
    for (int k = 0; k < bins; ++k) {
      const cv::Vec2d c = out.at<cv::Vec2d>(0, k);
      const double amp = 2.0 * std::hypot(c[0], c[1]) / wsum;
      power[static_cast<size_t>(k)] += amp * amp;
    }
  }
  const double df = 1.0 / (a.period_s * nfft);
  for (int k = 0; k < bins; ++k) {
    a.frequency_hz.push_back(k * df);
    a.amplitude_mm.push_back(std::sqrt(power[static_cast<size_t>(k)]));
  }
  // Peaks: local maxima above the floor, beyond the window's main lobe at DC.
  const double duration = a.period_s * static_cast<double>(ns);
  const double resolution = 1.0 / duration;
  std::vector<double> tail(a.amplitude_mm.begin() + 1, a.amplitude_mm.end());
  const double floor = std::max(options.min_peak_mm, options.floor_factor * quantile(tail, 0.5));
  for (int k = 1; k + 1 < bins; ++k) {
    const double y0 = a.amplitude_mm[static_cast<size_t>(k - 1)],
                 y1 = a.amplitude_mm[static_cast<size_t>(k)],
                 y2 = a.amplitude_mm[static_cast<size_t>(k) + 1];
    if (!(y1 > y0 && y1 >= y2) || y1 < floor ||
        a.frequency_hz[static_cast<size_t>(k)] < 1.5 * resolution)
      continue;
    const double den2 = y0 - 2 * y1 + y2;
    const double off = den2 != 0 ? 0.5 * (y0 - y2) / den2 : 0.0;
    SpectralPeak p;
    p.frequency_hz = (k + off) * df;
    p.amplitude_mm = y1 - 0.25 * (y0 - y2) * off;
    a.peaks.push_back(p);
  }
  // Within a main lobe (2 bins of the unpadded length) of a stronger peak: its side lobe.
  std::vector<SpectralPeak> kept;
  for (const SpectralPeak& p : a.peaks) {
    bool shadowed = false;
    for (const SpectralPeak& q : a.peaks) {
      if (q.amplitude_mm > p.amplitude_mm &&
          std::fabs(q.frequency_hz - p.frequency_hz) < 2 * resolution)
        shadowed = true;
    }
    if (!shadowed) kept.push_back(p);
  }
  a.peaks = kept;
}

}  // namespace

vision::Result<MotionAnalysis> analyzeMotion(const std::vector<record::TrackRow>& rows,
                                             const MotionOptions& options) {
  std::map<long, FrameRows> frames;
  for (const record::TrackRow& r : rows) {
    FrameRows& f = frames[r.frame];
    f.t = r.t;
    if (r.ok()) f.ok.push_back(&r);
  }
  // The cloud's displacement per frame with at least one ok feature.
  std::map<int, Vec3> ref;
  std::vector<double> ts;
  std::vector<Vec3> disp;
  Vec3 last = Vec3::Zero();
  std::map<int, std::pair<double, Vec3>> previous;  // feature -> (t, position) at its last ok frame
  std::vector<double> speeds;
  double prev_t = std::nan("");
  for (const auto& [frame, f] : frames) {
    if (f.ok.empty()) continue;
    Vec3 sum = Vec3::Zero();
    int n = 0;
    for (const record::TrackRow* r : f.ok) {
      const auto it = ref.find(r->id);
      if (it == ref.end()) continue;
      sum += Vec3(r->x, r->y, r->z) - it->second;
      ++n;
    }
    // No feature of this frame has a reference (every feature is new: a re-detection replaced
    // them all): continue the cloud's motion from the two frames before (linearly), when they
    // are recent; else hold the last displacement.
    Vec3 d = last;
    if (n > 0) {
      d = sum / n;
    } else if (disp.size() >= 2 && f.t - ts.back() <= 2.5 * (ts.back() - ts[ts.size() - 2])) {
      const double h = ts.back() - ts[ts.size() - 2];
      d = disp.back() + (disp.back() - disp[disp.size() - 2]) * ((f.t - ts.back()) / h);
    }
    for (const record::TrackRow* r : f.ok) {
      const Vec3 p(r->x, r->y, r->z);
      if (!ref.contains(r->id)) ref[r->id] = p - d;
      const auto pv = previous.find(r->id);
      if (pv != previous.end() && !std::isnan(prev_t) &&
          std::fabs(pv->second.first - prev_t) < 1e-9)
        speeds.push_back((p - pv->second.second).norm() / (f.t - prev_t));
      previous[r->id] = {f.t, p};
    }
    prev_t = f.t;
    last = d;
    ts.push_back(f.t);
    disp.push_back(d);
  }
  return analyzeSeries(ts, disp, static_cast<int>(ref.size()), speeds, options);
}

vision::Result<MotionAnalysis> analyzeMotion(const std::vector<record::DeformationRow>& rows,
                                             const MotionOptions& options) {
  std::vector<double> ts;
  std::vector<Vec3> disp;
  int features = 0;
  for (const record::DeformationRow& r : rows) {
    if (!ts.empty() && !(r.t > ts.back()))
      return fail(fmt::format("frame {}: the deformation's timestamps do not increase", r.frame));
    ts.push_back(r.t);
    disp.emplace_back(r.dx, r.dy, r.dz);
    features = std::max(features, r.total);
  }
  return analyzeSeries(ts, disp, features, {}, options);
}

vision::Result<MotionAnalysis> analyzeSeries(const std::vector<double>& ts,
                                             const std::vector<Vec3>& disp, int features,
                                             const std::vector<double>& speeds,
                                             const MotionOptions& options) {
  if (ts.size() < 16)
    return fail(fmt::format(
        "{} frames with ok features: too few for a motion analysis (16 at least)", ts.size()));
  std::vector<double> steps;
  for (size_t i = 1; i < ts.size(); ++i) steps.push_back(ts[i] - ts[i - 1]);
  MotionAnalysis a;
  a.features = features;
  a.feature_speed_mm_s = summarize(speeds);
  a.period_s = quantile(steps, 0.5);
  if (!(a.period_s > 0)) return fail("the track's timestamps do not increase");
  // The uniform grid; frames off it by more than a quarter period are a timestamp problem.
  const double t0 = ts.front();
  const auto k_last = static_cast<long>(std::llround((ts.back() - t0) / a.period_s));
  a.frames_expected = static_cast<int>(k_last + 1);
  a.frames_measured = static_cast<int>(ts.size());
  a.frames_filled = a.frames_expected - a.frames_measured;
  for (long k = 0; k <= k_last; ++k) a.t.push_back(static_cast<double>(k) * a.period_s);
  std::vector<double> x(ts.size());
  for (size_t i = 0; i < ts.size(); ++i) x[i] = ts[i] - t0;
  a.displacement.assign(a.t.size(), Vec3::Zero());
  for (int axis = 0; axis < 3; ++axis) {
    std::vector<double> y(disp.size());
    for (size_t i = 0; i < disp.size(); ++i) y[i] = disp[i][axis];
    const std::vector<double> g = naturalCubicSpline(x, y, a.t);
    for (size_t i = 0; i < g.size(); ++i) a.displacement[i][axis] = g[i];
  }
  // DC and trend, then the spectrum and its peaks; then DC, trend and the peaks' sinusoids
  // fitted together (a sinusoid of few periods is not orthogonal to a line: fitted alone, the
  // trend takes part of it), the trend removed, the spectrum again. The peaks' amplitudes are the
  // joint fit's.
  const size_t ns = a.t.size();
  std::vector<double> fit_freqs;
  Vec3 intercept = Vec3::Zero();
  std::vector<double> ls_amplitude;
  for (int pass = 0; pass < 3; ++pass) {
    const auto cols = static_cast<Eigen::Index>(2 + 2 * fit_freqs.size());
    Eigen::MatrixXd design(static_cast<Eigen::Index>(ns), cols);
    Eigen::MatrixXd rhs(static_cast<Eigen::Index>(ns), 3);
    for (size_t i = 0; i < ns; ++i) {
      const auto r = static_cast<Eigen::Index>(i);
      design(r, 0) = 1.0;
      design(r, 1) = a.t[i];
      for (size_t k = 0; k < fit_freqs.size(); ++k) {
        design(r, static_cast<Eigen::Index>(2 + 2 * k)) =
            std::cos(2 * M_PI * fit_freqs[k] * a.t[i]);
        design(r, static_cast<Eigen::Index>(3 + 2 * k)) =
            std::sin(2 * M_PI * fit_freqs[k] * a.t[i]);
      }
      rhs.row(r) = a.displacement[i].transpose();
    }
    const Eigen::MatrixXd coef = design.colPivHouseholderQr().solve(rhs);
    intercept = coef.row(0).transpose();
    a.trend_mm_per_s = coef.row(1).transpose();
    ls_amplitude.clear();
    for (size_t k = 0; k < fit_freqs.size(); ++k)
      ls_amplitude.push_back(
          std::sqrt(coef.row(static_cast<Eigen::Index>(2 + 2 * k)).squaredNorm() +
                    coef.row(static_cast<Eigen::Index>(3 + 2 * k)).squaredNorm()));
    if (pass == 2) break;
    a.detrended.resize(ns);
    for (size_t i = 0; i < ns; ++i)
      a.detrended[i] = a.displacement[i] - intercept - a.trend_mm_per_s * a.t[i];
    spectrum(a, options);
    fit_freqs.clear();
    for (const SpectralPeak& p : a.peaks) fit_freqs.push_back(p.frequency_hz);
  }
  for (size_t k = 0; k < a.peaks.size() && k < ls_amplitude.size(); ++k)
    a.peaks[k].amplitude_mm = ls_amplitude[k];
  // A peak the joint fit finds below the threshold was leakage of the trend, not motion.
  std::erase_if(a.peaks,
                [&](const SpectralPeak& p) { return p.amplitude_mm < options.min_peak_mm; });
  Eigen::Matrix3d cov = Eigen::Matrix3d::Zero();
  for (const Vec3& d : a.detrended) cov += d * d.transpose();
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es(cov);
  a.principal_axis = es.eigenvectors().col(2);
  if (a.principal_axis.z() < 0) a.principal_axis = -a.principal_axis;
  double lo = 1e300, hi = -1e300;
  for (const Vec3& d : a.detrended) {
    a.along_axis.push_back(d.dot(a.principal_axis));
    lo = std::min(lo, a.along_axis.back());
    hi = std::max(hi, a.along_axis.back());
  }
  a.peak_to_peak_mm = hi - lo;
  const double resolution = 1.0 / (a.period_s * static_cast<double>(ns));
  namePeaks(a.peaks, resolution);
  return a;
}

}  // namespace pulsetrack::analysis
