#include "pulsetrack/analysis/plate.hpp"

#include <fmt/format.h>

#include <Eigen/SVD>
#include <algorithm>
#include <cmath>
#include <unsupported/Eigen/LevenbergMarquardt>
#include <unsupported/Eigen/NumericalDiff>

namespace pulsetrack::analysis {

const std::array<Vec3, 8>& plateDivots() {
  static const std::array<Vec3, 8> d = {Vec3(30, 15, 0),   Vec3(15, 30, 0),  Vec3(30, -15, 0),
                                        Vec3(15, -30, 0),  Vec3(-15, 30, 0), Vec3(-30, 15, 0),
                                        Vec3(-15, -30, 0), Vec3(-30, -15, 0)};
  return d;
}

const std::array<Vec3, 6>& plateFeatures() {
  static const std::array<Vec3, 6> f = {Vec3(10, 0, 0), Vec3(5, 0, 0),  Vec3(0, 10, 0),
                                        Vec3(0, 5, 0),  Vec3(0, -5, 0), Vec3(0, -10, 0)};
  return f;
}

PlaneFit fitPlane(const std::vector<Vec3>& points) {
  PlaneFit f;
  if (points.size() < 3) return f;
  for (const Vec3& p : points) f.centroid += p;
  f.centroid /= static_cast<double>(points.size());
  Eigen::Matrix3d c = Eigen::Matrix3d::Zero();
  for (const Vec3& p : points) c += (p - f.centroid) * (p - f.centroid).transpose();
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es(c);
  f.normal = es.eigenvectors().col(0).normalized();  // the smallest eigenvalue's
  std::vector<double> d;
  d.reserve(points.size());
  for (const Vec3& p : points) d.push_back(std::fabs((p - f.centroid).dot(f.normal)));
  double sum = 0, ss = 0;
  for (const double x : d) sum += x;
  f.mean_mm = sum / static_cast<double>(d.size());
  for (const double x : d) ss += (x - f.mean_mm) * (x - f.mean_mm);
  f.sd_mm = d.size() > 1 ? std::sqrt(ss / static_cast<double>(d.size() - 1)) : 0.0;
  f.max_mm = *std::max_element(d.begin(), d.end());
  return f;
}

Vec3 projectOntoPlane(const PlaneFit& plane, const Vec3& p) {
  return p - (p - plane.centroid).dot(plane.normal) * plane.normal;
}

DivotCalibration calibrateDivots(const std::array<Vec3, 8>& digitized_o, const Pose& o_t_m) {
  DivotCalibration c;
  std::vector<Vec3> in_m;
  in_m.reserve(digitized_o.size());
  for (const Vec3& p : digitized_o) in_m.push_back(o_t_m.inverse() * p);  // eq. (6)
  c.plane = fitPlane(in_m);
  for (size_t i = 0; i < 8; ++i) c.in_markers[i] = projectOntoPlane(c.plane, in_m[i]);
  return c;
}

namespace {

Pose frameFromAxes(const Vec3& xx, const Vec3& yy_prime, const Vec3& origin) {
  const Vec3 x = xx.normalized();
  const Vec3 z = x.cross(yy_prime).normalized();  // eq. (10) / (16)
  const Vec3 y = z.cross(x);                      // eq. (11) / (17)
  Pose t = Pose::Identity();
  t.linear().col(0) = x;
  t.linear().col(1) = y;
  t.linear().col(2) = z;
  t.translation() = origin;
  return t;
}

}  // namespace

Pose divotFrame(const std::array<Vec3, 8>& p) {
  const Vec3 xx = (p[0] + p[1] + p[2] + p[3]) - (p[4] + p[5] + p[6] + p[7]);  // eq. (8)
  const Vec3 yy = (p[0] + p[1] + p[4] + p[5]) - (p[2] + p[3] + p[6] + p[7]);  // eq. (9)
  Vec3 o = Vec3::Zero();
  for (const Vec3& q : p) o += q;
  return frameFromAxes(xx, yy, o / 8.0);  // eq. (12)
}

Pose featureFrame(const std::array<Vec3, 6>& p) {
  const Vec3 f0 = (p[2] + p[3] + p[4] + p[5]) / 4.0;
  const Vec3 xx = (p[0] + p[1]) / 2.0 - f0;
  const Vec3 yy = (p[2] + p[3]) / 2.0 - p[4];
  return frameFromAxes(xx, yy, f0);
}

Pose fitRigid(const std::vector<Vec3>& from, const std::vector<Vec3>& to) {
  Vec3 ca = Vec3::Zero(), cb = Vec3::Zero();
  for (size_t i = 0; i < from.size(); ++i) {
    ca += from[i];
    cb += to[i];
  }
  ca /= static_cast<double>(from.size());
  cb /= static_cast<double>(to.size());
  Eigen::Matrix3d h = Eigen::Matrix3d::Zero();
  for (size_t i = 0; i < from.size(); ++i) h += (from[i] - ca) * (to[i] - cb).transpose();
  const Eigen::JacobiSVD<Eigen::Matrix3d> svd(h, Eigen::ComputeFullU | Eigen::ComputeFullV);
  const Eigen::Matrix3d& v = svd.matrixV();
  const Eigen::Matrix3d& u = svd.matrixU();
  const double d = (v * u.transpose()).determinant() < 0 ? -1.0 : 1.0;
  Pose t = Pose::Identity();
  t.linear() = v * Eigen::Vector3d(1, 1, d).asDiagonal() * u.transpose();
  t.translation() = cb - t.linear() * ca;
  return t;
}

vision::Result<FeatureIdentification> identifyPlateFeatures(const std::vector<Vec3>& points,
                                                            double max_rms_mm) {
  const int n = static_cast<int>(points.size());
  if (n < 6) return vision::fail(fmt::format("{} points, the plate has six features", n));
  if (n > 12)
    return vision::fail(
        fmt::format("{} points: too many candidates for the six plate features", n));
  const auto& layout = plateFeatures();
  FeatureIdentification best;
  best.rms_mm = 1e300;
  std::vector<int> pick(static_cast<size_t>(n), 0);
  std::fill(pick.end() - 6, pick.end(), 1);
  do {
    std::vector<int> six;
    for (int i = 0; i < n; ++i) {
      if (pick[static_cast<size_t>(i)] != 0) six.push_back(i);
    }
    // The two off the line are 1 and 2 (1 the farther); the four on it are 3..6 along y.
    for (int a = 0; a < 6; ++a) {
      for (int b = a + 1; b < 6; ++b) {
        std::vector<int> line;
        for (int k = 0; k < 6; ++k) {
          if (k != a && k != b) line.push_back(six[static_cast<size_t>(k)]);
        }
        const Vec3 pa = points[static_cast<size_t>(six[static_cast<size_t>(a)])];
        const Vec3 pb = points[static_cast<size_t>(six[static_cast<size_t>(b)])];
        Vec3 c = Vec3::Zero();
        for (const int i : line) c += points[static_cast<size_t>(i)];
        c /= 4.0;
        const bool a_far = (pa - c).norm() > (pb - c).norm();
        const Vec3 p1 = a_far ? pa : pb, p2 = a_far ? pb : pa;
        const Vec3 x = (p1 - c).normalized();
        std::vector<Vec3> all = {p1, p2};
        for (const int i : line) all.push_back(points[static_cast<size_t>(i)]);
        const PlaneFit plane = fitPlane(all);
        Vec3 z = plane.normal;
        if (z.dot(-c) < 0) z = -z;  // the face the camera sees
        const Vec3 y = z.cross(x);
        std::sort(line.begin(), line.end(), [&](int i, int j) {
          return points[static_cast<size_t>(i)].dot(y) > points[static_cast<size_t>(j)].dot(y);
        });
        std::array<int, 6> idx = {a_far ? six[static_cast<size_t>(a)] : six[static_cast<size_t>(b)],
                                  a_far ? six[static_cast<size_t>(b)] : six[static_cast<size_t>(a)],
                                  line[0],
                                  line[1],
                                  line[2],
                                  line[3]};
        std::vector<Vec3> from(layout.begin(), layout.end()), to;
        for (const int i : idx) to.push_back(points[static_cast<size_t>(i)]);
        const Pose t = fitRigid(from, to);
        double ss = 0;
        for (size_t k = 0; k < 6; ++k) ss += (t * from[k] - to[k]).squaredNorm();
        const double rms = std::sqrt(ss / 6.0);
        if (rms < best.rms_mm) best = {idx, rms};
      }
    }
  } while (std::next_permutation(pick.begin(), pick.end()));
  if (best.rms_mm > max_rms_mm)
    return vision::fail(fmt::format(
        "no six of the {} points match the plate's feature layout (best fit {:.2f} mm RMS, at most "
        "{:.2f} mm)",
        n, best.rms_mm, max_rms_mm));
  return best;
}

Pose errorMatrix(const Pose& o_t_d, const Pose& o_t_c, const Pose& c_t_f) {
  return o_t_d.inverse() * o_t_c * c_t_f;
}

double translationError(const Pose& e) { return e.translation().norm(); }

double rotationErrorDeg(const Pose& e) {
  return Eigen::AngleAxisd(e.linear()).angle() * 180.0 / M_PI;
}

namespace {

Pose poseFromParams(const Eigen::VectorXd& x) {
  Pose t = Pose::Identity();
  const Vec3 r(x[0], x[1], x[2]);
  const double a = r.norm();
  t.linear() = a > 0 ? Eigen::AngleAxisd(a, r / a).toRotationMatrix() : Eigen::Matrix3d::Identity();
  t.translation() = Vec3(x[3], x[4], x[5]);
  return t;
}

Vec3 rotationVector(const Eigen::Matrix3d& r) {
  const Eigen::AngleAxisd aa(r);
  return aa.angle() * aa.axis();
}

struct RegistrationCost : Eigen::DenseFunctor<double> {
  const std::vector<Pose>* o_t_d;
  const std::vector<Pose>* c_t_f;
  double lever;
  int* evaluations;
  RegistrationCost(const std::vector<Pose>* d, const std::vector<Pose>* f, double l, int* e)
      : DenseFunctor<double>(6, static_cast<int>(6 * d->size())),
        o_t_d(d),
        c_t_f(f),
        lever(l),
        evaluations(e) {}
  int operator()(const Eigen::VectorXd& x, Eigen::VectorXd& fvec) const {
    ++*evaluations;
    const Pose o_t_c = poseFromParams(x);
    for (size_t i = 0; i < o_t_d->size(); ++i) {
      const Pose e = errorMatrix((*o_t_d)[i], o_t_c, (*c_t_f)[i]);
      fvec.segment<3>(static_cast<Eigen::Index>(6 * i)) = e.translation();
      fvec.segment<3>(static_cast<Eigen::Index>(6 * i + 3)) = lever * rotationVector(e.linear());
    }
    return 0;
  }
};

}  // namespace

vision::Result<Registration> registerFrames(const std::vector<Pose>& o_t_d,
                                            const std::vector<Pose>& c_t_f, double lever_mm) {
  if (o_t_d.size() != c_t_f.size())
    return vision::fail("registration: as many tracker frames as camera frames are needed");
  if (o_t_d.size() < 3)
    return vision::fail(
        fmt::format("registration: {} acquisitions, at least 3 are needed", o_t_d.size()));
  // Kabsch on the frames' origins and the tips of their axes (lever_mm long).
  std::vector<Vec3> from, to;
  for (size_t i = 0; i < o_t_d.size(); ++i) {
    for (int k = -1; k < 3; ++k) {
      const Vec3 tip = k < 0 ? Vec3::Zero() : Vec3(Vec3::Unit(k) * lever_mm);
      from.push_back(c_t_f[i] * tip);
      to.push_back(o_t_d[i] * tip);
    }
  }
  const Pose init = fitRigid(from, to);
  Eigen::VectorXd x(6);
  x.head<3>() = rotationVector(init.linear());
  x.tail<3>() = init.translation();
  Registration reg;
  reg.lever_mm = lever_mm;
  RegistrationCost cost(&o_t_d, &c_t_f, lever_mm, &reg.evaluations);
  Eigen::NumericalDiff<RegistrationCost> diff(cost);
  Eigen::LevenbergMarquardt<Eigen::NumericalDiff<RegistrationCost>> lm(diff);
  lm.setXtol(1e-14);
  lm.setFtol(1e-14);
  lm.minimize(x);
  if (!x.allFinite()) return vision::fail("registration: the optimisation diverged");
  reg.o_t_c = poseFromParams(x);
  for (size_t i = 0; i < o_t_d.size(); ++i)
    reg.residuals.push_back(errorMatrix(o_t_d[i], reg.o_t_c, c_t_f[i]));
  return reg;
}

}  // namespace pulsetrack::analysis
