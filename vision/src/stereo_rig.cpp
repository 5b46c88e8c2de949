#include "pulsetrack/vision/stereo_rig.hpp"

#include <fmt/format.h>
#include <yaml-cpp/eventhandler.h>
#include <yaml-cpp/yaml.h>

#include <array>
#include <cctype>
#include <cmath>
#include <cstdlib>
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
// `need_dt`: ROS camera_info matrices carry rows, cols and data only.
Result<cv::Mat> readMatrix(const YAML::Node& root, const std::string& where, const char* key,
                           bool need_dt = true) {
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
  const bool dt_ok =
      dt ? dt.IsScalar() && (dt.Scalar() == "d" || dt.Scalar() == "f" || dt.Scalar() == "i")
         : !need_dt;
  if (!dt_ok) {
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

// `undistorted`: the file has neither D1 nor D2 (the images are taken as free of distortion).
Result<CameraModel> readCamera(const YAML::Node& root, const std::string& where, const char* k_key,
                               const char* d_key, cv::Size size, bool undistorted) {
  auto k = readMatx33(root, where, k_key);
  if (!k) return std::unexpected(k.error());
  if (undistorted) {
    constexpr std::array<double, 4> kNone{};
    return CameraModel(*k, kNone.data(), static_cast<int>(kNone.size()), size);
  }
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
Result<StereoRig> readRigKeys(const YAML::Node& root, const std::string& where, cv::Size data_size,
                              const std::string& data_name) {
  if (root.IsNull()) return fail(fmt::format("{}: empty: not valid OpenCV YAML (no keys)", where));
  if (!root.IsMap()) {
    return fail(
        fmt::format("{}: the top level must be a map of keys (image_size, M1, D1, ...)", where));
  }
  // image_size is optional (OpenCV's stereo_calib sample and many tools do not write it): the
  // images' size is taken then. When both are known they must agree.
  const YAML::Node size_node = root["image_size"];
  cv::Size size = data_size;
  if (size_node) {
    int wh[2] = {0, 0};
    if (!size_node.IsSequence() || size_node.size() != 2 ||
        !YAML::convert<int>::decode(size_node[0], wh[0]) ||
        !YAML::convert<int>::decode(size_node[1], wh[1])) {
      return fail(
          fmt::format("{}: key 'image_size': expected [width, height] as two integers", where));
    }
    size = cv::Size(wh[0], wh[1]);
    if (!data_size.empty() && data_size != size) {
      return fail(fmt::format(
          "{}: key 'image_size': the calibration is for {}x{} images, {} {}x{}: a calibration "
          "of another camera mode or a resized video (calibrate at this size)",
          where, size.width, size.height, data_name.empty() ? "the images are" : data_name + " is",
          data_size.width, data_size.height));
    }
  } else if (data_size.empty()) {
    return fail(fmt::format(
        "{}: key 'image_size' is missing, and there are no images here to take the size from",
        where));
  }

  StereoRig rig;
  // D1 and D2 are optional together (a calibration of rectified or undistorted images: some
  // tools write none); one without the other is a damaged file.
  const bool has_d1 = static_cast<bool>(root["D1"]), has_d2 = static_cast<bool>(root["D2"]);
  for (const char* k : {"M1", "M2"}) {  // a truncated file: its first broken key is named
    if (auto m = readMatx33(root, where, k); !m) return std::unexpected(m.error());
  }
  if (has_d1 != has_d2) {
    return fail(fmt::format(
        "{}: key '{}' is missing ({} is given: give both, or neither for images without lens "
        "distortion)",
        where, has_d1 ? "D2" : "D1", has_d1 ? "D1" : "D2"));
  }
  rig.distortion_given = has_d1;
  auto left = readCamera(root, where, "M1", "D1", size, !has_d1);
  if (!left) return std::unexpected(left.error());
  auto right = readCamera(root, where, "M2", "D2", size, !has_d2);
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

  // rms is the calibration's report, not needed to track: optional (0: not given).
  if (const YAML::Node rms = root["rms"]; rms) {
    const auto rms_value = scalarNumber(rms);
    if (!rms_value) return fail(fmt::format("{}: key 'rms': expected a number", where));
    rig.rms = *rms_value;
  }
  return rig;
}

}  // namespace

namespace {

// A small YAML file's text, its size bounded (kMaxRigFileBytes) and one document only.
Result<std::string> readYamlText(const std::filesystem::path& path, const char* what) {
  const std::string where = path.string();
  std::error_code ec;
  if (!std::filesystem::is_regular_file(path, ec)) {
    return fail(fmt::format("{}: {} not found or not a regular file", where, what));
  }
  const auto bytes = std::filesystem::file_size(path, ec);
  if (ec) return fail(fmt::format("{}: cannot read: {}", where, ec.message()));
  if (bytes > kMaxRigFileBytes) {
    return fail(
        fmt::format("{}: {} bytes is not a {} (at most {})", where, bytes, what, kMaxRigFileBytes));
  }
  std::string text;
  {
    std::ifstream in(path, std::ios::binary);
    text.assign(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
    if (!in.good() && !in.eof()) return fail(fmt::format("{}: cannot read", where));
  }
  if (text.size() > kMaxRigFileBytes) {
    return fail(fmt::format("{}: more than {} bytes: not a {}", where, kMaxRigFileBytes, what));
  }
  return text;
}

// Parses text with yaml-cpp and hands the root to read; YAML errors name the file and line.
template <typename T, typename Read>
Result<T> parseYaml(const std::string& text, const std::string& where, const char* what,
                    Read&& read) {
  try {
    // A second document is refused rather than silently left unread. Counted with a parser that
    // stops at two: YAML::LoadAll never returns on some inputs (fuzz_rig: "%YAML:1.0\n,--\n..."
    // makes yaml-cpp 0.7 yield empty documents without end).
    if (countDocuments(text, 2) > 1) {
      return fail(fmt::format("{}: more than one YAML document: a {} is one", where, what));
    }
    return read(YAML::Load(text));
  } catch (const YAML::Exception& e) {
    return fail(fmt::format("{}:{}: not valid {} (truncated or malformed): {}", where,
                            e.mark.line + 1,
                            std::string_view(what) == "rig file" ? "OpenCV YAML" : "YAML", e.msg));
  }
}

}  // namespace

std::string rigNotes(const StereoRig& rig, const std::string& where) {
  if (rig.distortion_given) return {};
  return fmt::format(
      "{}: no D1/D2 (lens distortion): the images are taken as free of it (rectified or "
      "undistorted video); if they are not, depth is biased towards the image borders",
      where);
}

Result<StereoRig> loadRig(const std::filesystem::path& path, cv::Size data_size,
                          const std::string& data_name) {
  const std::string where = path.string();
  auto text = readYamlText(path, "rig file");
  if (!text) return std::unexpected(text.error());
  // Parsed with yaml-cpp (its depth guard and OSS-Fuzz history), not OpenCV's FileStorage: that
  // parser looped forever on 24-byte files and threw std::length_error on others (fuzz_rig).
  // The files are the ones OpenCV writes (saveRig) and reads, keys of its stereo_calib sample.
  auto rig = parseYaml<StereoRig>(*text, where, "rig file", [&](const YAML::Node& root) {
    return readRigKeys(root, where, data_size, data_name);
  });
  if (!rig) return rig;
  if (auto ok = validateRig(*rig, where); !ok) return std::unexpected(ok.error());
  return rig;
}

Result<StereoRig> rectifiedRig(double focal_px, cv::Point2d principal, double baseline_mm,
                               cv::Size size, const std::string& where) {
  if (size.empty())
    return fail(fmt::format("{}: the image size is unknown (no images to take it from)", where));
  StereoRig rig;
  const cv::Matx33d k(focal_px, 0, principal.x, 0, focal_px, principal.y, 0, 0, 1);
  const std::array<double, 5> none{};
  rig.left = CameraModel(k, none.data(), 5, size);
  rig.right = rig.left;
  rig.t = cv::Vec3d(-baseline_mm, 0.0, 0.0);
  if (auto ok = validateRig(rig, where); !ok) return std::unexpected(ok.error());
  return rig;
}

Result<StereoRig> parseRectified(const std::string& text, cv::Size size) {
  const std::string where = fmt::format("--rectified {}", text);
  std::array<double, 4> v{};
  size_t at = 0;
  for (size_t k = 0; k < v.size(); ++k) {
    const size_t comma = text.find(',', at);
    const std::string field =
        text.substr(at, comma == std::string::npos ? std::string::npos : comma - at);
    char* end = nullptr;
    v[k] = std::strtod(field.c_str(), &end);
    if (field.empty() || end != field.c_str() + field.size() || !std::isfinite(v[k]) ||
        (comma == std::string::npos) != (k + 1 == v.size())) {
      return fail(fmt::format(
          "{}: expected four numbers f,cx,cy,baseline_mm (focal length and principal point in "
          "px of the rectified images, baseline in mm)",
          where));
    }
    at = comma + 1;
  }
  return rectifiedRig(v[0], {v[1], v[2]}, v[3], size, where);
}

namespace {

// One camera of a ROS camera_info YAML file (camera_calibration_parsers' layout): the raw
// camera (K, D), its rectification rotation R and the rectified projection P.
struct CameraInfo {
  cv::Size size;
  cv::Matx33d k, r;
  cv::Matx34d p;
  std::vector<double> d;
};

Result<CameraInfo> readCameraInfo(const YAML::Node& root, const std::string& where) {
  if (!root.IsMap())
    return fail(fmt::format("{}: not a ROS camera_info file (the top level is not a map)", where));
  CameraInfo info;
  int wh[2] = {0, 0};
  for (int k = 0; k < 2; ++k) {
    const char* key = k == 0 ? "image_width" : "image_height";
    const YAML::Node n = root[key];
    if (!n || !n.IsScalar() || !YAML::convert<int>::decode(n, wh[k]))
      return fail(fmt::format("{}: key '{}' is missing or not an integer", where, key));
  }
  info.size = cv::Size(wh[0], wh[1]);
  const YAML::Node model = root["distortion_model"];
  const std::string m = model && model.IsScalar() ? model.Scalar() : std::string("plumb_bob");
  if (m != "plumb_bob" && m != "rational_polynomial") {
    return fail(fmt::format(
        "{}: key 'distortion_model': '{}' is not supported (plumb_bob or rational_polynomial)",
        where, m));
  }
  auto k = readMatrix(root, where, "camera_matrix", false);
  if (!k) return std::unexpected(k.error());
  auto d = readMatrix(root, where, "distortion_coefficients", false);
  if (!d) return std::unexpected(d.error());
  auto r = readMatrix(root, where, "rectification_matrix", false);
  if (!r) return std::unexpected(r.error());
  auto p = readMatrix(root, where, "projection_matrix", false);
  if (!p) return std::unexpected(p.error());
  if (k->total() != 9 || r->total() != 9 || p->total() != 12) {
    return fail(fmt::format(
        "{}: camera_matrix and rectification_matrix must be 3x3, projection_matrix 3x4", where));
  }
  info.k = cv::Matx33d(k->ptr<double>());
  info.r = cv::Matx33d(r->ptr<double>());
  info.p = cv::Matx34d(p->ptr<double>());
  info.d.assign(d->ptr<double>(), d->ptr<double>() + d->total());
  // ROS writes an all-zero D for no distortion, sometimes shorter than five.
  if (info.d.size() < 4) info.d.resize(5, 0.0);
  if (info.d.size() != 4 && info.d.size() != 5 && info.d.size() != 8) {
    return fail(fmt::format("{}: key 'distortion_coefficients': {} coefficients (4, 5 or 8)", where,
                            info.d.size()));
  }
  return info;
}

}  // namespace

Result<StereoRig> loadCameraInfoPair(const std::filesystem::path& left_path,
                                     const std::filesystem::path& right_path, cv::Size data_size,
                                     const std::string& data_name) {
  CameraInfo info[2];
  const std::filesystem::path paths[2] = {left_path, right_path};
  for (int c = 0; c < 2; ++c) {
    const std::string where = paths[c].string();
    auto text = readYamlText(paths[c], "camera_info file");
    if (!text) return std::unexpected(text.error());
    auto one = parseYaml<CameraInfo>(*text, where, "camera_info file", [&](const YAML::Node& root) {
      return readCameraInfo(root, where);
    });
    if (!one) return std::unexpected(one.error());
    info[c] = *one;
    if (!data_size.empty() && info[c].size != data_size) {
      return fail(fmt::format(
          "{}: image_width x image_height {}x{}, {} {}x{}: another camera mode or a resized video",
          where, info[c].size.width, info[c].size.height,
          data_name.empty() ? "the images are" : data_name + " is", data_size.width,
          data_size.height));
    }
  }
  const std::string where = fmt::format("{} + {}", left_path.string(), right_path.string());
  if (info[0].size != info[1].size)
    return fail(fmt::format("{}: the two cameras' image sizes differ", where));
  // The rectified frames: x_rect = R_c x_c; the right's rectified centre sits at
  // (P(0,3)/P(0,0), P(1,3)/P(1,1), 0) relative to the left's (P's Tx = -fx' B).
  const cv::Matx34d& pr = info[1].p;
  if (!(pr(0, 0) > 0.0) || !(pr(1, 1) > 0.0))
    return fail(
        fmt::format("{}: key 'projection_matrix': focal length not positive", right_path.string()));
  const cv::Vec3d t_rect(pr(0, 3) / pr(0, 0), pr(1, 3) / pr(1, 1), 0.0);
  if (!(cv::norm(t_rect) > 0.0)) {
    return fail(fmt::format(
        "{}: key 'projection_matrix': P[0][3] (Tx = -fx * baseline) is zero: this is a left or "
        "monocular camera's file, not the right camera of a stereo pair",
        right_path.string()));
  }
  StereoRig rig;
  rig.left =
      CameraModel(info[0].k, info[0].d.data(), static_cast<int>(info[0].d.size()), info[0].size);
  rig.right =
      CameraModel(info[1].k, info[1].d.data(), static_cast<int>(info[1].d.size()), info[1].size);
  // x_r = R2^T (R1 x_l + t_rect): R = R2^T R1, T = R2^T t_rect. ROS's lengths are metres
  // (REP 103; camera_calibration's --square is in metres): the rig's are millimetres.
  rig.r = info[1].r.t() * info[0].r;
  rig.t = info[1].r.t() * (t_rect * 1000.0);
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
