// The plate's frames (eqs. 8-18), the features' identification against eq. (5), the
// registration (eq. 20) and the readers of the reference tracker's files.

#include "pulsetrack/analysis/plate.hpp"

#include <gtest/gtest.h>

#include <algorithm>
#include <fstream>
#include <random>

#include "pulsetrack/analysis/reference.hpp"
#include "test_util.hpp"

namespace pulsetrack::analysis {
namespace {

Pose randomPose(std::mt19937& rng, double depth) {
  std::uniform_real_distribution<double> u(-1, 1);
  Pose p = Pose::Identity();
  p.linear() = (Eigen::AngleAxisd(0.5 * u(rng), Vec3::UnitX()) *
                Eigen::AngleAxisd(0.5 * u(rng), Vec3::UnitY()) *
                Eigen::AngleAxisd(3.0 * u(rng), Vec3::UnitZ()))
                   .toRotationMatrix();
  // Facing the camera at the origin: the plate's z towards -z of {C}.
  p.linear() = Eigen::AngleAxisd(M_PI, Vec3::UnitX()).toRotationMatrix() * p.linear();
  p.translation() = Vec3(25 * u(rng), 25 * u(rng), depth + 20 * u(rng));
  return p;
}

double poseDistance(const Pose& a, const Pose& b) {
  return (a.matrix() - b.matrix()).cwiseAbs().maxCoeff();
}

TEST(PlateFrames, NominalLayoutGivesThePlateFrameAndFollowsAnyPose) {
  std::array<Vec3, 6> f{};
  std::array<Vec3, 8> d{};
  std::copy(plateFeatures().begin(), plateFeatures().end(), f.begin());
  std::copy(plateDivots().begin(), plateDivots().end(), d.begin());
  EXPECT_LT(poseDistance(featureFrame(f), Pose::Identity()), 1e-12);  // eq. (13)
  EXPECT_LT(poseDistance(divotFrame(d), Pose::Identity()), 1e-12);
  std::mt19937 rng(3);
  for (int i = 0; i < 20; ++i) {
    const Pose t = randomPose(rng, 450);
    std::array<Vec3, 6> tf{};
    std::array<Vec3, 8> td{};
    for (size_t k = 0; k < 6; ++k) tf[k] = t * f[k];
    for (size_t k = 0; k < 8; ++k) td[k] = t * d[k];
    EXPECT_LT(poseDistance(featureFrame(tf), t), 1e-9);
    EXPECT_LT(poseDistance(divotFrame(td), t), 1e-9);
  }
}

TEST(PlateFrames, IdentifiesTheSixFeaturesShuffledWithNoiseAndStrayPoints) {
  std::mt19937 rng(4);
  std::normal_distribution<double> noise(0, 0.03);
  for (int trial = 0; trial < 30; ++trial) {
    const Pose t = randomPose(rng, 450);
    std::vector<Vec3> pts;
    std::vector<int> truth;
    for (size_t k = 0; k < 6; ++k) {
      pts.push_back(t * plateFeatures()[k] + Vec3(noise(rng), noise(rng), noise(rng)));
      truth.push_back(static_cast<int>(k));
    }
    if (trial % 3 == 0) {  // two stray blobs on the plate
      pts.push_back(t * Vec3(12, 12, 0));
      truth.push_back(-1);
      pts.push_back(t * Vec3(-9, 4, 0));
      truth.push_back(-1);
    }
    std::vector<size_t> order(pts.size());
    for (size_t i = 0; i < order.size(); ++i) order[i] = i;
    std::shuffle(order.begin(), order.end(), rng);
    std::vector<Vec3> shuffled;
    shuffled.reserve(order.size());
    for (const size_t i : order) shuffled.push_back(pts[i]);
    auto id = identifyPlateFeatures(shuffled);
    ASSERT_TRUE(id) << id.error().message;
    for (size_t k = 0; k < 6; ++k)
      EXPECT_EQ(truth[order[static_cast<size_t>(id->index[k])]], static_cast<int>(k))
          << "trial " << trial;
    EXPECT_LT(id->rms_mm, 0.1);
  }
  std::vector<Vec3> random;
  std::uniform_real_distribution<double> u(-20, 20);
  random.reserve(6);
  for (int i = 0; i < 6; ++i) random.emplace_back(u(rng), u(rng), 450 + u(rng));
  auto bad = identifyPlateFeatures(random);
  ASSERT_FALSE(bad);
  EXPECT_NE(bad.error().message.find("no six of the 6 points match"), std::string::npos)
      << bad.error().message;
  EXPECT_FALSE(identifyPlateFeatures({Vec3::Zero(), Vec3::Ones()}));
}

TEST(PlateFrames, DivotsProjectedOntoTheirPlane) {
  std::array<Vec3, 8> d{};
  const Pose o_t_m = randomPose(*std::make_unique<std::mt19937>(9), 1000);
  // Off the plane by 0.04 mm, in a pattern with no constant or tilt part: the plane is z = 0.
  const double bumps[8] = {0.04, -0.04, 0.04, -0.04, -0.04, 0.04, -0.04, 0.04};
  for (size_t k = 0; k < 8; ++k) d[k] = o_t_m * (plateDivots()[k] + Vec3(0, 0, bumps[k]));
  const DivotCalibration c = calibrateDivots(d, o_t_m);
  EXPECT_NEAR(c.plane.mean_mm, 0.04, 1e-9);
  EXPECT_NEAR(c.plane.max_mm, 0.04, 1e-9);
  for (size_t k = 0; k < 8; ++k)
    EXPECT_NEAR((c.in_markers[k] - plateDivots()[k]).norm(), 0.0, 1e-9);
}

TEST(Registration, RecoversOTCExactlyFromExactFramesAndResidualsAreZero) {
  std::mt19937 rng(8);
  Pose o_t_c = Pose::Identity();
  o_t_c.linear() = Eigen::AngleAxisd(1.1, Vec3(0.4, -0.9, 0.2).normalized()).toRotationMatrix();
  o_t_c.translation() = Vec3(180, -320, 1880);
  std::vector<Pose> od, cf;
  for (int i = 0; i < 10; ++i) {
    cf.push_back(randomPose(rng, 450));
    od.push_back(o_t_c * cf.back());
  }
  auto reg = registerFrames(od, cf);
  ASSERT_TRUE(reg) << reg.error().message;
  EXPECT_LT(poseDistance(reg->o_t_c, o_t_c), 1e-6);
  for (const Pose& e : reg->residuals) {
    EXPECT_LT(translationError(e), 1e-6);
    EXPECT_LT(rotationErrorDeg(e), 1e-6);
  }
  EXPECT_FALSE(registerFrames({od[0], od[1]}, {cf[0], cf[1]}));
  EXPECT_FALSE(registerFrames(od, {cf[0]}));
}

TEST(Registration, NoisyFramesGiveSmallerErrorsThanTheNoiseWithMoreAcquisitions) {
  std::mt19937 rng(12);
  std::normal_distribution<double> n(0, 1);
  Pose o_t_c = Pose::Identity();
  o_t_c.linear() = Eigen::AngleAxisd(0.7, Vec3(0.1, 0.9, 0.3).normalized()).toRotationMatrix();
  o_t_c.translation() = Vec3(100, 200, 1500);
  const auto perturb = [&](const Pose& p, double mm, double rad) {
    Pose q = p;
    q.translation() += mm * Vec3(n(rng), n(rng), n(rng));
    q.linear() = Eigen::AngleAxisd(rad * n(rng), Vec3(n(rng), n(rng), n(rng)).normalized())
                     .toRotationMatrix() *
                 q.linear();
    return q;
  };
  double err10 = 0, err40 = 0;
  for (int rep = 0; rep < 10; ++rep) {
    for (const int count : {10, 40}) {
      std::vector<Pose> od, cf;
      for (int i = 0; i < count; ++i) {
        const Pose truth = randomPose(rng, 450);
        cf.push_back(perturb(truth, 0.03, 0.003));
        od.push_back(perturb(o_t_c * truth, 0.05, 0.002));
      }
      auto reg = registerFrames(od, cf);
      ASSERT_TRUE(reg);
      // The registration's error where it is used: at the plate's workspace centre.
      const Vec3 centre(0, 0, 450);
      (count == 10 ? err10 : err40) += (reg->o_t_c * centre - o_t_c * centre).norm() / 10;
    }
  }
  std::cout << "noisy registration, error at the workspace centre: 10 acquisitions " << err10
            << " mm, 40 acquisitions " << err40 << " mm\n";
  EXPECT_LT(err10, 0.06);
  EXPECT_LT(err40, err10);
}

TEST(ReferenceFiles, NdiQuaternionsMatricesMissingRowsAndBadInput) {
  test::TempDir dir;
  std::ofstream(dir / "ndi.csv")
      << "Frame,Time,Q0,Qx,Qy,Qz,Tx,Ty,Tz\n"
         "1,0.10,1,0,0,0,10,20,30\n"
         "2,0.20,MISSING,MISSING,MISSING,MISSING,MISSING,MISSING,MISSING\n"
         "3,0.30,0.7071067811865476,0.7071067811865476,0,0,1,2,3\n";
  auto ndi = readPoses(dir / "ndi.csv");
  ASSERT_TRUE(ndi) << ndi.error().message;
  ASSERT_EQ(ndi->poses.size(), 2U);
  EXPECT_EQ(ndi->missing, 1);
  EXPECT_EQ(ndi->poses[1].frame, 3);
  EXPECT_EQ(ndi->poses[1].t_ns, 300'000'000);
  EXPECT_NEAR((ndi->poses[1].pose * Vec3(0, 1, 0) - Vec3(1, 2, 4)).norm(), 0, 1e-9);
  std::ofstream(dir / "m.csv") << "t_ns,m00,m01,m02,m03,m10,m11,m12,m13,m20,m21,m22,m23\n"
                                  "5,1,0,0,1,0,1,0,2,0,0,1,3\n";
  auto m = readPoses(dir / "m.csv");
  ASSERT_TRUE(m) << m.error().message;
  EXPECT_EQ(m->poses[0].pose.translation(), Vec3(1, 2, 3));
  const auto expectError = [&](const std::string& name, const std::string& text,
                               const std::string& needle) {
    std::ofstream(dir / name) << text;
    auto r = readPoses(dir / name);
    ASSERT_FALSE(r) << text;
    EXPECT_NE(r.error().message.find(needle), std::string::npos) << r.error().message;
  };
  expectError("b1.csv", "t,qw,qx,qy,qz,tx,ty,tz\n0.1,1,0,0,0,x,0,0\n",
              "b1.csv:2: column 'tx': 'x' is not a number");
  expectError("b2.csv", "t,qw,qx,qy,qz,tx,ty,tz\n0.1,2,0,0,0,0,0,0\n",
              "b2.csv:2: the quaternion's norm is 2");
  expectError("b3.csv", "t,a,b\n1,2,3\n", "no pose columns");
  expectError("b4.csv", "t,qw,qx,qy,qz,tx,ty,tz\n0.1,1,0,0\n",
              "b4.csv:2: 4 cells, the header has 8");
  expectError("b5.csv",
              "t_ns,m00,m01,m02,m03,m10,m11,m12,m13,m20,m21,m22,m23\n0,2,0,0,0,0,1,0,0,0,0,1,0\n",
              "not a rotation");
  EXPECT_NE(readPoses(dir / "none.csv").error().message.find("none.csv: cannot open"),
            std::string::npos);
  // Numbers past what the column holds are named, not cast (fuzz_reference's finding: a frame
  // of 7.8e74 was converted to long, undefined behaviour).
  expectError("b6.csv",
              "frame,m00,m01,m02,m03,m10,m11,m12,m13,m20,m21,m22,m23\n"
              "0777777777777777777777777777777777777777777777777777777777777777777777777777,1,0,"
              "0,1,0,1,0,2,0,0,1,3\n",
              "b6.csv:2: column 'frame': '0777777777777777777777777777777777777777777777777777777"
              "777777777777777777777' is not a whole number from 0 to 2147483647");
  expectError("b7.csv", "t_ns,qw,qx,qy,qz,tx,ty,tz\n1e300,1,0,0,0,0,0,0\n",
              "b7.csv:2: column 't_ns': '1e300' is not a whole number");
  {
    // A system-clock stamp in ns (past 2^53) is read exactly, not through a double.
    std::ofstream(dir / "ns.csv")
        << "t_ns,qw,qx,qy,qz,tx,ty,tz\n1733130000123456789,1,0,0,0,0,0,0\n";
    auto ns = readPoses(dir / "ns.csv");
    ASSERT_TRUE(ns) << ns.error().message;
    EXPECT_EQ(ns->poses.at(0).t_ns, 1733130000123456789LL);
  }
  expectError("b8.csv", "t,qw,qx,qy,qz,tx,ty,tz\n1e300,1,0,0,0,0,0,0\n",
              "b8.csv:2: column 't': 1e+300 s is not a time");
  std::ofstream(dir / "d9.csv") << "divot,x,y,z\n1e300,0,0,0\n";
  EXPECT_NE(readDivots(dir / "d9.csv").error().message.find("d9.csv:2: divot 1e+300"),
            std::string::npos);

  std::ofstream(dir / "d.csv")
      << "divot,x,y,z\n1,0,0,0\n2,0,0,0\n3,0,0,0\n4,0,0,0\n5,0,0,0\n6,0,0,0\n7,0,0,0\n";
  auto d = readDivots(dir / "d.csv");
  ASSERT_FALSE(d);
  EXPECT_NE(d.error().message.find("divot 8 is missing"), std::string::npos);
  std::ofstream(dir / "p.csv")
      << "set,acquisition,first_frame,last_frame,roi_left_x,roi_left_y,roi_left_w,"
         "roi_left_h,roi_right_x,roi_right_y,roi_right_w,roi_right_h\n"
         "0,0,5,4,1,1,100,100,1,1,100,100\n";
  auto p = readProtocol(dir / "p.csv");
  ASSERT_FALSE(p);
  EXPECT_NE(p.error().message.find("p.csv:2: last_frame before first_frame"), std::string::npos);
  std::ofstream(dir / "p2.csv")
      << "set,acquisition,first_frame,last_frame,roi_left_x,roi_left_y,roi_left_w,"
         "roi_left_h,roi_right_x,roi_right_y,roi_right_w,roi_right_h\n"
         "0,0,0,4,1,1,1e19,100,1,1,100,100\n";
  EXPECT_NE(readProtocol(dir / "p2.csv")
                .error()
                .message.find("p2.csv:2: column 'roi_left_w': '1e19' is not a whole number"),
            std::string::npos);
}

}  // namespace
}  // namespace pulsetrack::analysis
