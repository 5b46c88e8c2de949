#include "pulsetrack/vision/stereo_rig.hpp"

#include <fmt/format.h>
#include <yaml-cpp/eventhandler.h>
#include <yaml-cpp/yaml.h>

#include <cctype>
#include <cmath>
#include <fstream>
#include <iterator>
#include <limits>
#include <opencv2/core.hpp>
#include <opencv2/core/persistence.hpp>
#include <optional>
#include <sstream>
#include <system_error>
#include <vector>

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
  // Bounds of a real rig (a value past them is a corrupt or hostile file, and would make the
  // tracker size its search boxes from it): focal lengths up to 1e5 px (a 16k sensor behind a
  // long lens stays well below), the principal point within the image.
  const cv::Size size = cam.imageSize();
  if (k(0, 0) > kMaxFocalPx || k(1, 1) > kMaxFocalPx) {
    return fail(fmt::format("{}: key '{}': focal lengths must be at most {} px (fx={}, fy={})",
                            where, k_key, kMaxFocalPx, k(0, 0), k(1, 1)));
  }
  if (k(0, 2) < 0.0 || k(0, 2) > size.width || k(1, 2) < 0.0 || k(1, 2) > size.height) {
    return fail(fmt::format("{}: key '{}': principal point ({}, {}) lies outside the {}x{} image",
                            where, k_key, k(0, 2), k(1, 2), size.width, size.height));
  }
  for (int i = 0; i < cam.numDistortion(); ++i) {
    if (!std::isfinite(cam.dist()[static_cast<size_t>(i)])) {
      return fail(fmt::format("{}: key '{}': coefficient {} is not finite", where, d_key, i));
    }
  }
  // The lens must map the image one to one: every pixel of a grid over it (corners and edges
  // included) undistorted and distorted again comes back to itself, and the distortion does
  // not fold there. A coefficient like 1e300 passes the finiteness test and fails this one.
  constexpr int kSteps = 8;
  for (int gy = 0; gy <= kSteps; ++gy) {
    for (int gx = 0; gx <= kSteps; ++gx) {
      const cv::Vec2d px(size.width * gx / double(kSteps), size.height * gy / double(kSteps));
      const cv::Vec2d n = cam.undistortToNormalized(px);
      cv::Matx22d j;
      const cv::Vec2d d = cam.distortNormalized(n, j);
      const cv::Vec2d back(k(0, 0) * d[0] + k(0, 2), k(1, 1) * d[1] + k(1, 2));
      const double det = j(0, 0) * j(1, 1) - j(0, 1) * j(1, 0);
      if (!(cv::norm(back - px) < 0.01) || !(det > 0.0)) {
        return fail(fmt::format(
            "{}: key '{}': the distortion does not map the image one to one (pixel ({:.0f}, "
            "{:.0f}) does not come back through it): not a real lens's coefficients",
            where, d_key, px[0], px[1]));
      }
    }
  }
  return {};
}

}  // namespace

Result<void> validateRig(const StereoRig& rig, const std::string& where) {
  const cv::Size size = rig.left.imageSize();
  if (size.width <= 0 || size.height <= 0 || size.width > kMaxImageSide ||
      size.height > kMaxImageSide) {
    return fail(fmt::format("{}: key 'image_size': must be 1 to {} px on each side, got {}x{}",
                            where, kMaxImageSide, size.width, size.height));
  }
  if (auto ok = validateCamera(rig.left, where, "M1", "D1"); !ok) return ok;
  if (auto ok = validateCamera(rig.right, where, "M2", "D2"); !ok) return ok;
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
  if (cv::norm(rig.t) > kMaxBaselineMm) {
    return fail(fmt::format("{}: key 'T': baseline {:.0f} mm is more than a stereo rig's {} mm",
                            where, cv::norm(rig.t), kMaxBaselineMm));
  }
  if (!std::isfinite(rig.rms) || rig.rms < 0.0) {
    return fail(
        fmt::format("{}: key 'rms': must be a finite non-negative number, got {}", where, rig.rms));
  }
  return {};
}

namespace {

// A number of the file: yaml-cpp's conversion, plus OpenCV's spellings of NaN and infinity
// (".Nan", ".Inf", "-.Inf", which YAML's core schema spells otherwise).
std::optional<double> scalarNumber(const YAML::Node& n) {
  if (!n.IsScalar()) return std::nullopt;
  double v = 0.0;
  if (YAML::convert<double>::decode(n, v)) return v;
  std::string s = n.Scalar();
  for (char& c : s) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  if (s == ".nan") return std::numeric_limits<double>::quiet_NaN();
  if (s == ".inf" || s == "+.inf") return std::numeric_limits<double>::infinity();
  if (s == "-.inf") return -std::numeric_limits<double>::infinity();
  return std::nullopt;
}

// An opencv-matrix (rows, cols, dt, data) as OpenCV's FileStorage writes it, read without
// OpenCV's parser (it loops forever on some malformed files: fuzz_rig).
Result<cv::Mat> readMatrix(const YAML::Node& root, const std::string& where, const char* key) {
  const YAML::Node node = root[key];
  if (!node) return fail(fmt::format("{}: key '{}' is missing", where, key));
  if (!node.IsMap()) {
    return fail(fmt::format("{}: key '{}': expected an opencv-matrix, got a {}", where, key,
                            node.IsSequence() ? "sequence" : "scalar"));
  }
  constexpr int kMaxSide = 64;  // a rig's matrices are 3x3 or 1x8
  int size[2] = {0, 0};
  for (int k = 0; k < 2; ++k) {
    const char* field = k == 0 ? "rows" : "cols";
    const YAML::Node n = node[field];
    int v = 0;
    if (!n || !n.IsScalar() || !YAML::convert<int>::decode(n, v) || v < 1 || v > kMaxSide) {
      return fail(fmt::format("{}: key '{}': {} must be an integer from 1 to {}", where, key, field,
                              kMaxSide));
    }
    size[k] = v;
  }
  const YAML::Node dt = node["dt"];
  if (!dt || !dt.IsScalar() || (dt.Scalar() != "d" && dt.Scalar() != "f" && dt.Scalar() != "i")) {
    return fail(fmt::format("{}: key '{}': matrix must have one channel (dt d, f or i), got '{}'",
                            where, key, dt && dt.IsScalar() ? dt.Scalar() : std::string()));
  }
  const YAML::Node data = node["data"];
  const auto n = static_cast<size_t>(size[0]) * static_cast<size_t>(size[1]);
  if (!data || !data.IsSequence() || data.size() != n) {
    return fail(fmt::format("{}: key '{}': data must hold rows x cols = {} numbers, got {}", where,
                            key, n, data && data.IsSequence() ? data.size() : 0));
  }
  cv::Mat m(size[0], size[1], CV_64F);
  for (size_t k = 0; k < n; ++k) {
    const auto v = scalarNumber(data[k]);
    if (!v) {
      return fail(fmt::format("{}: key '{}': value {} is not a number", where, key, k + 1));
    }
    if (!std::isfinite(*v))
      return fail(fmt::format("{}: key '{}': contains NaN or infinity", where, key));
    m.at<double>(static_cast<int>(k)) = *v;
  }
  return m;
}

Result<cv::Matx33d> readMatx33(const YAML::Node& root, const std::string& where, const char* key) {
  auto m = readMatrix(root, where, key);
  if (!m) return std::unexpected(m.error());
  if (m->rows != 3 || m->cols != 3) {
    return fail(fmt::format("{}: key '{}': expected a 3x3 matrix, got {}x{}", where, key, m->rows,
                            m->cols));
  }
  return cv::Matx33d(m->ptr<double>());
}

Result<CameraModel> readCamera(const YAML::Node& root, const std::string& where, const char* k_key,
                               const char* d_key, cv::Size size) {
  auto k = readMatx33(root, where, k_key);
  if (!k) return std::unexpected(k.error());
  auto d = readMatrix(root, where, d_key);
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

namespace {

// Ignores every event: the parser's document count is all that is wanted.
class DocumentCounter final : public YAML::EventHandler {
 public:
  void OnDocumentStart(const YAML::Mark& /*mark*/) override {}
  void OnDocumentEnd() override {}
  void OnNull(const YAML::Mark& /*mark*/, YAML::anchor_t /*anchor*/) override {}
  void OnAlias(const YAML::Mark& /*mark*/, YAML::anchor_t /*anchor*/) override {}
  void OnScalar(const YAML::Mark& /*mark*/, const std::string& /*tag*/, YAML::anchor_t /*anchor*/,
                const std::string& /*value*/) override {}
  void OnSequenceStart(const YAML::Mark& /*mark*/, const std::string& /*tag*/,
                       YAML::anchor_t /*anchor*/, YAML::EmitterStyle::value /*style*/) override {}
  void OnSequenceEnd() override {}
  void OnMapStart(const YAML::Mark& /*mark*/, const std::string& /*tag*/, YAML::anchor_t /*anchor*/,
                  YAML::EmitterStyle::value /*style*/) override {}
  void OnMapEnd() override {}
};

// The number of YAML documents in text, counting no further than limit. Throws YAML::Exception.
int countDocuments(const std::string& text, int limit) {
  std::istringstream in(text);
  YAML::Parser parser(in);
  DocumentCounter counter;
  int documents = 0;
  while (documents < limit && parser.HandleNextDocument(counter)) ++documents;
  return documents;
}

// The keys of a parsed rig file.
Result<StereoRig> readRigKeys(const YAML::Node& root, const std::string& where) {
  if (root.IsNull()) return fail(fmt::format("{}: empty: not valid OpenCV YAML (no keys)", where));
  if (!root.IsMap()) {
    return fail(
        fmt::format("{}: the top level must be a map of keys (image_size, M1, D1, ...)", where));
  }
  const YAML::Node size_node = root["image_size"];
  if (!size_node) return fail(fmt::format("{}: key 'image_size' is missing", where));
  int wh[2] = {0, 0};
  if (!size_node.IsSequence() || size_node.size() != 2 ||
      !YAML::convert<int>::decode(size_node[0], wh[0]) ||
      !YAML::convert<int>::decode(size_node[1], wh[1])) {
    return fail(
        fmt::format("{}: key 'image_size': expected [width, height] as two integers", where));
  }
  const cv::Size size(wh[0], wh[1]);

  StereoRig rig;
  auto left = readCamera(root, where, "M1", "D1", size);
  if (!left) return std::unexpected(left.error());
  auto right = readCamera(root, where, "M2", "D2", size);
  if (!right) return std::unexpected(right.error());
  rig.left = *left;
  rig.right = *right;
  auto r = readMatx33(root, where, "R");
  if (!r) return std::unexpected(r.error());
  rig.r = *r;
  auto t = readMatrix(root, where, "T");
  if (!t) return std::unexpected(t.error());
  if (t->total() != 3 || (t->rows != 1 && t->cols != 1)) {
    return fail(
        fmt::format("{}: key 'T': expected a 3x1 vector, got {}x{}", where, t->rows, t->cols));
  }
  rig.t = cv::Vec3d(t->ptr<double>());

  const YAML::Node rms = root["rms"];
  if (!rms) return fail(fmt::format("{}: key 'rms' is missing", where));
  const auto rms_value = scalarNumber(rms);
  if (!rms_value) return fail(fmt::format("{}: key 'rms': expected a number", where));
  rig.rms = *rms_value;
  return rig;
}

}  // namespace

Result<StereoRig> loadRig(const std::filesystem::path& path) {
  const std::string where = path.string();
  std::error_code ec;
  if (!std::filesystem::is_regular_file(path, ec)) {
    return fail(fmt::format("{}: rig file not found or not a regular file", where));
  }
  const auto bytes = std::filesystem::file_size(path, ec);
  if (ec) return fail(fmt::format("{}: cannot read: {}", where, ec.message()));
  if (bytes > kMaxRigFileBytes) {
    return fail(
        fmt::format("{}: {} bytes is not a rig file (at most {})", where, bytes, kMaxRigFileBytes));
  }
  std::string text;
  {
    std::ifstream in(path, std::ios::binary);
    text.assign(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
    if (!in.good() && !in.eof()) return fail(fmt::format("{}: cannot read", where));
  }
  if (text.size() > kMaxRigFileBytes) {
    return fail(fmt::format("{}: more than {} bytes: not a rig file", where, kMaxRigFileBytes));
  }
  // Parsed with yaml-cpp (its depth guard and OSS-Fuzz history), not OpenCV's FileStorage: that
  // parser looped forever on 24-byte files and threw std::length_error on others (fuzz_rig).
  // The files are the ones OpenCV writes (saveRig) and reads, keys of its stereo_calib sample.
  Result<StereoRig> rig = fail("");
  try {
    // A second document is refused rather than silently left unread. Counted with a parser that
    // stops at two: YAML::LoadAll never returns on some inputs (fuzz_rig: "%YAML:1.0\n,--\n..."
    // makes yaml-cpp 0.7 yield empty documents without end).
    if (countDocuments(text, 2) > 1) {
      return fail(fmt::format("{}: more than one YAML document: a rig file is one", where));
    }
    rig = readRigKeys(YAML::Load(text), where);
  } catch (const YAML::Exception& e) {
    return fail(fmt::format("{}:{}: not valid OpenCV YAML (truncated or malformed): {}", where,
                            e.mark.line + 1, e.msg));
  }
  if (!rig) return rig;
  if (auto ok = validateRig(*rig, where); !ok) return std::unexpected(ok.error());
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
