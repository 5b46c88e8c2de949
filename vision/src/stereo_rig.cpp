#include "pulsetrack/vision/stereo_rig.hpp"

#include <fmt/format.h>

#include <cmath>
#include <limits>
#include <opencv2/core.hpp>
#include <opencv2/core/persistence.hpp>
#include <system_error>

namespace pulsetrack::vision {

Ray StereoRig::backProjectRight(const cv::Vec2d& pixel) const noexcept {
  const Ray in_right = right.backProject(pixel);
  return {rightCentre(), r.t() * in_right.direction};
}

cv::Matx33d StereoRig::essential() const noexcept {
  const cv::Matx33d tx(0, -t[2], t[1], t[2], 0, -t[0], -t[1], t[0], 0);
  return tx * r;
}

cv::Matx33d StereoRig::fundamental() const noexcept {
  return right.k().inv().t() * essential() * left.k().inv();
}

namespace {

// The signed distance of x from the line, the normal's larger component taken positive (so
// that neighbouring points' lines, which turn little, give the same side the same sign).
double signedDistance(const cv::Vec3d& line, const cv::Vec3d& x) noexcept {
  const double major = std::abs(line[1]) >= std::abs(line[0]) ? line[1] : line[0];
  return (major < 0 ? -1.0 : 1.0) * line.dot(x) / std::hypot(line[0], line[1]);
}

}  // namespace

cv::Vec2d StereoRig::epipolarDistances(const cv::Vec2d& left_px,
                                       const cv::Vec2d& right_px) const noexcept {
  const cv::Vec2d ul = left.undistortPixel(left_px);
  const cv::Vec2d ur = right.undistortPixel(right_px);
  const cv::Matx33d f = fundamental();
  const cv::Vec3d xl(ul[0], ul[1], 1.0);
  const cv::Vec3d xr(ur[0], ur[1], 1.0);
  // x_r^T F x_l = 0: F x_l is x_l's line in the right image, F^T x_r x_r's in the left.
  return {std::abs(signedDistance(f * xl, xr)), std::abs(signedDistance(f.t() * xr, xl))};
}

double StereoRig::epipolarOffset(const cv::Vec2d& left_px,
                                 const cv::Vec2d& right_px) const noexcept {
  const cv::Vec2d ul = left.undistortPixel(left_px);
  const cv::Vec2d ur = right.undistortPixel(right_px);
  return signedDistance(fundamental() * cv::Vec3d(ul[0], ul[1], 1.0), cv::Vec3d(ur[0], ur[1], 1.0));
}

cv::Vec3d midpoint(const Ray& a, const Ray& b) noexcept {
  // (I - g1 g1^T)(x - p1) + (I - g2 g2^T)(x - p2) = 0  =>  A x = c
  const cv::Matx33d i = cv::Matx33d::eye();
  const cv::Matx33d a1 = i - a.direction * a.direction.t();
  const cv::Matx33d a2 = i - b.direction * b.direction.t();
  const cv::Matx33d m = a1 + a2;
  const cv::Vec3d c = a1 * a.origin + a2 * b.origin;
  // Matx arithmetic stays on the stack: this runs per feature and frame.
  if (std::abs(cv::determinant(m)) < 1e-12) {
    const double nan = std::numeric_limits<double>::quiet_NaN();
    return {nan, nan, nan};
  }
  return cv::Vec3d(m.solve(cv::Matx31d(c[0], c[1], c[2]), cv::DECOMP_LU).val);
}

namespace {

bool allFinite(const cv::Matx33d& m) {
  for (double v : m.val) {
    if (!std::isfinite(v)) return false;
  }
  return true;
}

Result<void> validateCamera(const CameraModel& cam, const std::string& where, const char* k_key,
                            const char* d_key) {
  const cv::Matx33d& k = cam.k();
  if (!allFinite(k))
    return fail(
        fmt::format("{}: key '{}': camera matrix has NaN or infinite values", where, k_key));
  if (!(k(0, 0) > 0.0) || !(k(1, 1) > 0.0)) {
    return fail(fmt::format("{}: key '{}': focal lengths must be positive (fx={}, fy={})", where,
                            k_key, k(0, 0), k(1, 1)));
  }
  if (k(0, 1) != 0.0 || k(1, 0) != 0.0 || k(2, 0) != 0.0 || k(2, 1) != 0.0 || k(2, 2) != 1.0) {
    return fail(
        fmt::format("{}: key '{}': camera matrix must be [fx 0 cx; 0 fy cy; 0 0 1] (OpenCV's model "
                    "has no skew)",
                    where, k_key));
  }
  for (int i = 0; i < cam.numDistortion(); ++i) {
    if (!std::isfinite(cam.dist()[static_cast<size_t>(i)])) {
      return fail(fmt::format("{}: key '{}': coefficient {} is not finite", where, d_key, i));
    }
  }
  return {};
}

}  // namespace

Result<void> validateRig(const StereoRig& rig, const std::string& where) {
  if (auto ok = validateCamera(rig.left, where, "M1", "D1"); !ok) return ok;
  if (auto ok = validateCamera(rig.right, where, "M2", "D2"); !ok) return ok;
  const cv::Size size = rig.left.imageSize();
  if (size.width <= 0 || size.height <= 0) {
    return fail(fmt::format("{}: key 'image_size': must be positive, got {}x{}", where, size.width,
                            size.height));
  }
  if (!allFinite(rig.r)) return fail(fmt::format("{}: key 'R': has NaN or infinite values", where));
  const double orth = cv::norm(rig.r.t() * rig.r - cv::Matx33d::eye(), cv::NORM_INF);
  const double det = cv::determinant(rig.r);
  if (orth > 1e-6 || std::abs(det - 1.0) > 1e-6) {
    return fail(
        fmt::format("{}: key 'R': not a rotation matrix (|R^T R - I| = {:.3g}, det = {:.6f})",
                    where, orth, det));
  }
  if (!std::isfinite(rig.t[0]) || !std::isfinite(rig.t[1]) || !std::isfinite(rig.t[2])) {
    return fail(fmt::format("{}: key 'T': has NaN or infinite values", where));
  }
  if (!(cv::norm(rig.t) > 0.0)) return fail(fmt::format("{}: key 'T': baseline is zero", where));
  if (!std::isfinite(rig.rms) || rig.rms < 0.0) {
    return fail(
        fmt::format("{}: key 'rms': must be a finite non-negative number, got {}", where, rig.rms));
  }
  return {};
}

namespace {

Result<cv::Mat> readMatrix(const cv::FileStorage& fs, const std::string& where, const char* key) {
  const cv::FileNode node = fs[key];
  if (node.empty()) return fail(fmt::format("{}: key '{}' is missing", where, key));
  if (!node.isMap()) {
    return fail(fmt::format("{}: key '{}': expected an opencv-matrix, got a {}", where, key,
                            node.isSeq() ? "sequence" : "scalar"));
  }
  cv::Mat m;
  try {
    node >> m;
  } catch (const cv::Exception& e) {
    return fail(fmt::format("{}: key '{}': not a readable opencv-matrix ({})", where, key, e.err));
  }
  if (m.empty()) return fail(fmt::format("{}: key '{}': empty or malformed matrix", where, key));
  if (m.channels() != 1)
    return fail(fmt::format("{}: key '{}': matrix must have one channel", where, key));
  m.convertTo(m, CV_64F);
  for (auto it = m.begin<double>(); it != m.end<double>(); ++it) {
    if (!std::isfinite(*it))
      return fail(fmt::format("{}: key '{}': contains NaN or infinity", where, key));
  }
  return m;
}

Result<cv::Matx33d> readMatx33(const cv::FileStorage& fs, const std::string& where,
                               const char* key) {
  auto m = readMatrix(fs, where, key);
  if (!m) return std::unexpected(m.error());
  if (m->rows != 3 || m->cols != 3) {
    return fail(fmt::format("{}: key '{}': expected a 3x3 matrix, got {}x{}", where, key, m->rows,
                            m->cols));
  }
  return cv::Matx33d(m->ptr<double>());
}

Result<CameraModel> readCamera(const cv::FileStorage& fs, const std::string& where,
                               const char* k_key, const char* d_key, cv::Size size) {
  auto k = readMatx33(fs, where, k_key);
  if (!k) return std::unexpected(k.error());
  auto d = readMatrix(fs, where, d_key);
  if (!d) return std::unexpected(d.error());
  const int n = static_cast<int>(d->total());
  if ((d->rows != 1 && d->cols != 1) || (n != 4 && n != 5 && n != 8)) {
    return fail(fmt::format(
        "{}: key '{}': expected 4, 5 or 8 distortion coefficients (k1 k2 p1 p2 [k3 [k4 k5 k6]]) as "
        "one row or column, got {}x{}",
        where, d_key, d->rows, d->cols));
  }
  cv::Mat row = d->reshape(1, 1).clone();
  return CameraModel(*k, row.ptr<double>(), n, size);
}

}  // namespace

Result<StereoRig> loadRig(const std::filesystem::path& path) {
  const std::string where = path.string();
  std::error_code ec;
  if (!std::filesystem::is_regular_file(path, ec)) {
    return fail(fmt::format("{}: rig file not found or not a regular file", where));
  }
  cv::FileStorage fs;
  try {
    if (!fs.open(where, cv::FileStorage::READ)) {
      return fail(fmt::format("{}: cannot open as OpenCV YAML", where));
    }
  } catch (const cv::Exception& e) {
    return fail(
        fmt::format("{}: not valid OpenCV YAML (truncated or malformed): {}", where, e.err));
  }

  const cv::FileNode size_node = fs["image_size"];
  if (size_node.empty()) return fail(fmt::format("{}: key 'image_size' is missing", where));
  if (!size_node.isSeq() || size_node.size() != 2 || !size_node[0].isInt() ||
      !size_node[1].isInt()) {
    return fail(
        fmt::format("{}: key 'image_size': expected [width, height] as two integers", where));
  }
  const cv::Size size(static_cast<int>(size_node[0]), static_cast<int>(size_node[1]));

  StereoRig rig;
  auto left = readCamera(fs, where, "M1", "D1", size);
  if (!left) return std::unexpected(left.error());
  auto right = readCamera(fs, where, "M2", "D2", size);
  if (!right) return std::unexpected(right.error());
  rig.left = *left;
  rig.right = *right;
  auto r = readMatx33(fs, where, "R");
  if (!r) return std::unexpected(r.error());
  rig.r = *r;
  auto t = readMatrix(fs, where, "T");
  if (!t) return std::unexpected(t.error());
  if (t->total() != 3 || (t->rows != 1 && t->cols != 1)) {
    return fail(
        fmt::format("{}: key 'T': expected a 3x1 vector, got {}x{}", where, t->rows, t->cols));
  }
  rig.t = cv::Vec3d(t->ptr<double>());

  const cv::FileNode rms = fs["rms"];
  if (rms.empty()) return fail(fmt::format("{}: key 'rms' is missing", where));
  if (!rms.isReal() && !rms.isInt())
    return fail(fmt::format("{}: key 'rms': expected a number", where));
  rig.rms = static_cast<double>(rms);

  if (auto ok = validateRig(rig, where); !ok) return std::unexpected(ok.error());
  return rig;
}

Result<void> saveRig(const StereoRig& rig, const std::filesystem::path& path) {
  const std::string where = path.string();
  if (auto ok = validateRig(rig, "calibration for " + where); !ok) return ok;
  try {
    cv::FileStorage fs(where, cv::FileStorage::WRITE);
    if (!fs.isOpened()) return fail(fmt::format("{}: cannot open for writing", where));
    fs.writeComment("pulsetrack stereo rig: OpenCV stereo_calib keys; x_right = R x_left + T");
    fs << "image_size"
       << "[" << rig.left.imageSize().width << rig.left.imageSize().height << "]";
    fs << "M1" << cv::Mat(rig.left.k());
    fs << "D1"
       << cv::Mat(1, rig.left.numDistortion(), CV_64F, const_cast<double*>(rig.left.dist().data()));
    fs << "M2" << cv::Mat(rig.right.k());
    fs << "D2"
       << cv::Mat(1, rig.right.numDistortion(), CV_64F,
                  const_cast<double*>(rig.right.dist().data()));
    fs << "R" << cv::Mat(rig.r);
    fs << "T" << cv::Mat(rig.t);
    fs << "rms" << rig.rms;
    fs << "baseline" << rig.baseline();
    fs << "E" << cv::Mat(rig.essential());
    fs << "F" << cv::Mat(rig.fundamental());
    fs.release();
  } catch (const cv::Exception& e) {
    return fail(fmt::format("{}: write failed: {}", where, e.err));
  }
  return {};
}

}  // namespace pulsetrack::vision
