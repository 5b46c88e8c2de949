// Rig YAML: round trip, OpenCV-readable keys, and a clear error for every malformed file.

#include "pulsetrack/vision/stereo_rig.hpp"

#include <fmt/format.h>
#include <gtest/gtest.h>

#include <fstream>
#include <opencv2/calib3d.hpp>
#include <opencv2/core/persistence.hpp>
#include <regex>

#include "test_util.hpp"

namespace pulsetrack::vision {
namespace {

StereoRig sampleRig() {
  StereoRig rig;
  const double d1[5] = {-0.21, 0.35, 0.0012, -0.0008, -0.9};
  const double d2[8] = {-0.3, 0.1, 0.001, -0.002, 0.05, 0.02, -0.01, 0.03};
  rig.left = CameraModel({5376.3, 0, 680.2, 0, 5371.8, 511.7, 0, 0, 1}, d1, 5, {1360, 1024});
  rig.right = CameraModel({5380.1, 0, 690.5, 0, 5379.9, 505.2, 0, 0, 1}, d2, 8, {1360, 1024});
  cv::Matx33d r;
  cv::Rodrigues(cv::Vec3d(0.01, -0.14, 0.005), r);
  rig.r = r;
  rig.t = {-60.0, 0.4, 4.5};
  rig.rms = 0.21;
  return rig;
}

class RigFile : public ::testing::Test {
 protected:
  test::TempDir dir;
  std::string good = dir / "rig.yaml";
  void SetUp() override { ASSERT_TRUE(saveRig(sampleRig(), good)); }

  std::string text() const {
    std::ifstream f(good);
    return {std::istreambuf_iterator<char>(f), std::istreambuf_iterator<char>()};
  }
  // Writes a variant of the good file and expects loading it to fail with a message that names
  // the file and matches `expected`.
  void expectError(const std::string& content, const std::string& expected) const {
    const std::string bad = dir / "bad.yaml";
    std::ofstream(bad) << content;
    auto rig = loadRig(bad);
    ASSERT_FALSE(rig) << "loaded a bad file; expected: " << expected;
    EXPECT_NE(rig.error().message.find(bad), std::string::npos) << rig.error().message;
    EXPECT_TRUE(std::regex_search(rig.error().message, std::regex(expected)))
        << "message: " << rig.error().message << "\nexpected: " << expected;
  }
  // The good file's text with the block of `key` replaced.
  std::string replaceKey(const std::string& key, const std::string& block) const {
    std::string t = text();
    const size_t start = t.find("\n" + key + ":");
    EXPECT_NE(start, std::string::npos) << key;
    size_t end = t.find('\n', start + 1);
    while (end != std::string::npos && end + 1 < t.size() && t[end + 1] == ' ')
      end = t.find('\n', end + 1);
    return t.substr(0, start + 1) + block + (end == std::string::npos ? "" : t.substr(end));
  }
  std::string removeKey(const std::string& key) const { return replaceKey(key, "dummy: 0"); }
};

TEST_F(RigFile, RoundTripIsExact) {
  auto rig = loadRig(good);
  ASSERT_TRUE(rig) << rig.error().message;
  const StereoRig ref = sampleRig();
  EXPECT_EQ(rig->left.numDistortion(), 5);
  EXPECT_EQ(rig->right.numDistortion(), 8);
  for (int i = 0; i < 9; ++i) EXPECT_EQ(rig->left.k().val[i], ref.left.k().val[i]);
  for (int i = 0; i < 8; ++i) EXPECT_EQ(rig->right.dist()[i], ref.right.dist()[i]);
  for (int i = 0; i < 9; ++i) EXPECT_EQ(rig->r.val[i], ref.r.val[i]);
  EXPECT_EQ(rig->t, ref.t);
  EXPECT_EQ(rig->rms, ref.rms);
  EXPECT_EQ(rig->left.imageSize(), cv::Size(1360, 1024));
}

TEST_F(RigFile, OpenCvReadsTheStereoCalibKeys) {
  cv::FileStorage fs(good, cv::FileStorage::READ);
  cv::Mat m1, d1, m2, d2, r, t;
  fs["M1"] >> m1;
  fs["D1"] >> d1;
  fs["M2"] >> m2;
  fs["D2"] >> d2;
  fs["R"] >> r;
  fs["T"] >> t;
  EXPECT_EQ(m1.size(), cv::Size(3, 3));
  EXPECT_EQ(d2.total(), 8U);
  EXPECT_DOUBLE_EQ(t.at<double>(0), -60.0);
  EXPECT_DOUBLE_EQ(static_cast<double>(fs["rms"]), 0.21);
}

TEST_F(RigFile, MissingFile) {
  auto rig = loadRig(dir / "nope.yaml");
  ASSERT_FALSE(rig);
  EXPECT_NE(rig.error().message.find("nope.yaml"), std::string::npos);
  EXPECT_NE(rig.error().message.find("not found"), std::string::npos);
}

TEST_F(RigFile, NotYaml) {
  expectError("this is not\n  yaml: [at all", "bad.yaml:[0-9]+: not valid OpenCV YAML");
}

TEST_F(RigFile, Truncated) {
  const std::string t = text();
  expectError(t.substr(0, t.find("M2:") + 40), "truncated|malformed|key 'M2'|not valid");
}

TEST_F(RigFile, EmptyFile) {
  expectError("", "bad.yaml: empty: not valid OpenCV YAML \\(no keys\\)");
}

TEST_F(RigFile, MissingKeys) {
  for (const char* key : {"M1", "D1", "M2", "D2", "R", "T"}) {
    SCOPED_TRACE(key);
    expectError(removeKey(key), std::string("key '") + key + "' is missing");
  }
}

TEST_F(RigFile, WrongMatrixSize) {
  expectError(
      replaceKey(
          "M1",
          "M1: !!opencv-matrix\n   rows: 2\n   cols: 3\n   dt: d\n   data: [ 1, 0, 1, 0, 1, 1 ]"),
      "key 'M1': expected a 3x3 matrix, got 2x3");
  expectError(
      replaceKey(
          "D2",
          "D2: !!opencv-matrix\n   rows: 1\n   cols: 6\n   dt: d\n   data: [ 0, 0, 0, 0, 0, 0 ]"),
      "key 'D2': expected 4, 5 or 8 distortion coefficients");
  expectError(
      replaceKey("T", "T: !!opencv-matrix\n   rows: 2\n   cols: 1\n   dt: d\n   data: [ 1, 0 ]"),
      "key 'T': expected a 3x1 vector");
}

TEST_F(RigFile, NonPositiveFocalLength) {
  expectError(replaceKey("M2",
                         "M2: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ -5380, "
                         "0, 690, 0, 5380, 505, 0, 0, 1 ]"),
              "key 'M2': focal lengths must be positive");
}

TEST_F(RigFile, SkewOrBadLastRow) {
  expectError(replaceKey("M1",
                         "M1: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ 5380, "
                         "3, 690, 0, 5380, 505, 0, 0, 1 ]"),
              "key 'M1': camera matrix must be");
}

TEST_F(RigFile, NotARotation) {
  expectError(replaceKey("R",
                         "R: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ 1, 0.1, "
                         "0, 0, 1, 0, 0, 0, 1 ]"),
              "key 'R': not a rotation matrix");
  expectError(replaceKey("R",
                         "R: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ -1, 0, "
                         "0, 0, 1, 0, 0, 0, 1 ]"),
              "key 'R': not a rotation matrix .*det = -1");
}

TEST_F(RigFile, NaNValues) {
  expectError(
      replaceKey("T",
                 "T: !!opencv-matrix\n   rows: 3\n   cols: 1\n   dt: d\n   data: [ .Nan, 0, 0 ]"),
      "key 'T': contains NaN");
  expectError(
      replaceKey(
          "D1",
          "D1: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n   data: [ 0, .Inf, 0, 0, 0 ]"),
      "key 'D1': contains NaN or infinity");
}

TEST_F(RigFile, WrongTypes) {
  expectError(replaceKey("M1", "M1: 5"), "key 'M1': expected an opencv-matrix, got a scalar");
  expectError(replaceKey("image_size", "image_size: [ 1360 ]"),
              "key 'image_size': expected \\[width, height\\]");
  expectError(replaceKey("image_size", "image_size: [ 1360, -4 ]"),
              "key 'image_size': must be 1 to 16384 px on each side, got 1360x-4");
  expectError(replaceKey("rms", "rms: hello"), "key 'rms': expected a number");
  expectError(replaceKey("rms", "rms: -1.0"), "key 'rms': must be a finite non-negative");
}

TEST_F(RigFile, ZeroBaseline) {
  expectError(
      replaceKey("T", "T: !!opencv-matrix\n   rows: 3\n   cols: 1\n   dt: d\n   data: [ 0, 0, 0 ]"),
      "key 'T': baseline is zero");
}

// Found by fuzzing (issue 15), each reproduced on the release build before the fix.
TEST_F(RigFile, NestingNoRigHasIsAnErrorNotAStackOverflow) {
  // 100 000 levels overflowed the stack inside cv::FileStorage (SIGSEGV); yaml-cpp's depth guard
  // refuses them, and the message names the file and line.
  expectError(text() + "zz: " + std::string(100000, '[') + "\n",
              "bad.yaml:[0-9]+: not valid OpenCV YAML");
  std::string dashes = "zz:\n";
  for (int i = 0; i < 50000; ++i) dashes += "- ";
  expectError(text() + dashes + "1\n", "bad.yaml:[0-9]+: not valid OpenCV YAML");
  // Brackets in quotes and comments are text.
  const std::string quoted = dir / "quoted.yaml";
  std::ofstream(quoted) << text() << "note: \"" << std::string(100, '[') << "\"  # "
                        << std::string(100, '{') << "\n";
  EXPECT_TRUE(loadRig(quoted)) << loadRig(quoted).error().message;
}

TEST_F(RigFile, AFileThatIsNotAMapIsAnErrorNotAnException) {
  // fuzz_rig's first finding: OpenCV asserts (throws cv::Exception) on fs["key"] when the top
  // level is a sequence or a scalar; it escaped loadRig and terminated the program.
  expectError("%YAML:1.0\n---\n- 1\n- 2\n", "bad.yaml: the top level must be a map of keys");
  expectError("%YAML:1.0\n---\n42\n", "bad.yaml: the top level must be a map");
}

TEST_F(RigFile, AKeyOpenCvThrowsAStandardExceptionOnIsAnError) {
  // fuzz_rig's third finding: "   :dt: d" in a matrix made cv::FileStorage::open throw
  // std::length_error, which escaped loadRig and terminated the program. (The file is read with
  // yaml-cpp since; the key is then simply not "dt".)
  std::string t = text();
  t.replace(t.find("   dt: d"), 8, "   :dt: d");
  expectError(t, "bad.yaml: key 'M1': matrix must have one channel \\(dt d, f or i\\), got ''");
}

TEST_F(RigFile, FilesOpenCvsParserNeverReturnsOnAreErrors) {
  // fuzz_rig's second and fourth findings: OpenCV's FileStorage never returned on these; read
  // with yaml-cpp since.
  expectError("%YAML:1.\n---L:0\n--\n#\n-",
              "bad.yaml: more than one YAML document: a rig file is one");
  expectError("%YAML:1.\n - 4\nM0\n-", "bad.yaml: more than one YAML document: a rig file is one");
  // A second document is refused, not left unread.
  expectError(text() + "---\nM1: 1\n", "bad.yaml: more than one YAML document: a rig file is one");
}

TEST_F(RigFile, AFileYamlCppsLoadAllNeverReturnsOnIsAnError) {
  // fuzz_rig, after the switch to yaml-cpp: YAML::LoadAll yields empty documents without end on
  // this (found as a 10 s timeout); the documents are counted with a bound since.
  std::string input = "%YAML:1.0\n,--\nFFFFFFFFFFFFFFFFFFFFFFFFFzz: [[[[[[[[[N[[[[[[[[[[[[[[[[";
  input += std::string("\x01\0\0\0\0[[[\n", 9);
  expectError(input, "bad.yaml: more than one YAML document: a rig file is one");
}

TEST_F(RigFile, AMatrixHeaderOpenCvWouldAllocateFromIsBounded) {
  // cols: NaN made OpenCV try a 48 GB allocation before any check could run.
  for (const char* v : {"NaN", "1e9", "100000", "-3", "0", "3.5", "3 4", ""}) {
    SCOPED_TRACE(v);
    expectError(replaceKey("M1", std::string("M1: !!opencv-matrix\n   rows: 3\n   cols: ") + v +
                                     "\n   dt: d\n   data: [ 1, 0, 1, 0, 1, 1, 0, 0, 1 ]"),
                "bad.yaml: key 'M1': cols must be an integer from 1 to 64");
  }
  expectError(text() + std::string(2 << 20, ' '), "bytes is not a rig file");
}

TEST_F(RigFile, ValuesNoRealRigHasAreRefusedWithTheirKey) {
  // fx = 2^31-1 passed and made the tracker ask for ~365 GB.
  expectError(replaceKey("M2",
                         "M2: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ "
                         "2147483647, 0, 690, 0, 5380, 505, 0, 0, 1 ]"),
              "key 'M2': focal lengths must be at most 100000 px");
  expectError(replaceKey("M1",
                         "M1: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ "
                         "5380, 0, 9000, 0, 5380, 505, 0, 0, 1 ]"),
              "key 'M1': principal point \\(9000, 505\\) lies outside the 1360x1024 image");
  // k1 = 1e300 passed and failed later as "ROI pair does not triangulate".
  expectError(replaceKey("D1",
                         "D1: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n   data: [ "
                         "1e300, 0, 0, 0, 0 ]"),
              "key 'D1': the distortion does not map the image one to one");
  // A lens that folds the image (strong negative k1 at this focal length).
  expectError(replaceKey("D2",
                         "D2: !!opencv-matrix\n   rows: 1\n   cols: 4\n   dt: d\n   data: [ "
                         "-2000, 0, 0, 0 ]"),
              "key 'D2': the distortion does not map the image one to one");
  expectError(replaceKey("image_size", "image_size: [ 2147483647, 1024 ]"),
              "key 'image_size': must be 1 to 16384 px");
  expectError(
      replaceKey("T",
                 "T: !!opencv-matrix\n   rows: 3\n   cols: 1\n   dt: d\n   data: [ 1e9, 0, 0 ]"),
      "key 'T': baseline 1000000000 mm is more than");
}

// OpenCV's own stereoCalibrate output as its stereo_calib sample and many tools save it: float
// matrices, T as a row, neither image_size nor rms. The size then comes from the images.
TEST(RigForms, OpenCvFileWithoutImageSizeOrRmsTakesTheImagesSize) {
  test::TempDir dir;
  const StereoRig ref = sampleRig();
  const std::string path = dir / "extrinsics.yml";
  {
    cv::FileStorage fs(path, cv::FileStorage::WRITE);
    cv::Mat m1, m2, d1, d2, r, t;
    cv::Mat(ref.left.k()).convertTo(m1, CV_32F);
    cv::Mat(ref.right.k()).convertTo(m2, CV_32F);
    cv::Mat(1, 5, CV_64F, const_cast<double*>(ref.left.dist().data())).convertTo(d1, CV_32F);
    cv::Mat(1, 8, CV_64F, const_cast<double*>(ref.right.dist().data())).convertTo(d2, CV_32F);
    cv::Mat(ref.r).convertTo(r, CV_32F);
    cv::Mat(ref.t).reshape(1, 1).convertTo(t, CV_32F);  // 1x3
    fs << "M1" << m1 << "D1" << d1 << "M2" << m2 << "D2" << d2 << "R" << r << "T" << t;
  }
  auto no_images = loadRig(path);
  ASSERT_FALSE(no_images);
  EXPECT_NE(no_images.error().message.find("key 'image_size' is missing, and there are no images"),
            std::string::npos)
      << no_images.error().message;
  auto rig = loadRig(path, {1360, 1024}, "video.mp4");
  ASSERT_TRUE(rig) << rig.error().message;
  EXPECT_EQ(rig->left.imageSize(), cv::Size(1360, 1024));
  EXPECT_EQ(rig->rms, 0.0);
  for (int i = 0; i < 9; ++i) EXPECT_NEAR(rig->left.k().val[i], ref.left.k().val[i], 1e-3);
  for (int i = 0; i < 8; ++i) EXPECT_NEAR(rig->right.dist()[i], ref.right.dist()[i], 1e-6);
  for (int i = 0; i < 3; ++i) EXPECT_NEAR(rig->t[i], ref.t[i], 1e-5);
  for (int i = 0; i < 9; ++i) EXPECT_NEAR(rig->r.val[i], ref.r.val[i], 1e-6);
}

// A calibration of rectified or undistorted images written without D1/D2 (the RecoverTissueDeform
// in-vivo sample's, issue 32): read as free of distortion, and said; one of the two alone is a
// damaged file.
TEST(RigForms, OpenCvFileWithoutDistortionIsReadAsUndistortedAndSaid) {
  test::TempDir dir;
  const StereoRig ref = sampleRig();
  const std::string path = dir / "rectified.yml";
  {
    cv::FileStorage fs(path, cv::FileStorage::WRITE);
    fs << "M1" << cv::Mat(ref.left.k()) << "M2" << cv::Mat(ref.right.k()) << "R" << cv::Mat(ref.r)
       << "T" << cv::Mat(ref.t);
  }
  auto rig = loadRig(path, {1360, 1024}, "the images");
  ASSERT_TRUE(rig) << rig.error().message;
  EXPECT_FALSE(rig->distortion_given);
  for (const double d : rig->left.dist()) EXPECT_EQ(d, 0.0);
  for (const double d : rig->right.dist()) EXPECT_EQ(d, 0.0);
  for (int i = 0; i < 9; ++i) EXPECT_EQ(rig->right.k().val[i], ref.right.k().val[i]);
  const std::string note = rigNotes(*rig, path);
  EXPECT_NE(note.find("rectified.yml: no D1/D2 (lens distortion): the images are taken as free of "
                      "it"),
            std::string::npos)
      << note;
  ASSERT_TRUE(saveRig(ref, dir / "full.yml"));
  auto with = loadRig(dir / "full.yml");
  ASSERT_TRUE(with) << with.error().message;
  EXPECT_TRUE(with->distortion_given);
  EXPECT_EQ(rigNotes(*with, "full.yml"), "");
  const std::string half = dir / "half.yml";
  {
    cv::FileStorage fs(half, cv::FileStorage::WRITE);
    fs << "M1" << cv::Mat(ref.left.k()) << "D1" << cv::Mat(1, 4, CV_64F, cv::Scalar(0.0)) << "M2"
       << cv::Mat(ref.right.k()) << "R" << cv::Mat(ref.r) << "T" << cv::Mat(ref.t);
  }
  auto damaged = loadRig(half, {1360, 1024}, "the images");
  ASSERT_FALSE(damaged);
  EXPECT_NE(damaged.error().message.find("half.yml: key 'D2' is missing (D1 is given: give both, "
                                         "or neither"),
            std::string::npos)
      << damaged.error().message;
}

TEST(RigForms, ACalibrationOfAnotherSizeIsANamedError) {
  test::TempDir dir;
  ASSERT_TRUE(saveRig(sampleRig(), dir / "rig.yaml"));
  auto rig = loadRig(dir / "rig.yaml", {640, 512}, "each view of case7.mp4");
  ASSERT_FALSE(rig);
  EXPECT_NE(rig.error().message.find("rig.yaml: key 'image_size': the calibration is for "
                                     "1360x1024 images, each view of case7.mp4 is 640x512"),
            std::string::npos)
      << rig.error().message;
  EXPECT_TRUE(loadRig(dir / "rig.yaml", {1360, 1024}, "x"));
}

TEST(RigForms, TheRealEndoscopeCalibrationAsShippedLoads) {
  const auto dir = data::shared("surgt-labelling-sample");
  PULSETRACK_SKIP_WITHOUT_DATA(dir);
  // As shipped: no image_size, no rms (the issue's "key 'image_size' is missing").
  auto rig = loadRig(dir / "rig.yaml", {1280, 1024}, "each view of video.mp4");
  ASSERT_TRUE(rig) << rig.error().message;
  EXPECT_EQ(rig->left.imageSize(), cv::Size(1280, 1024));
  EXPECT_GT(cv::norm(rig->t), 1.0);  // a stereo endoscope's baseline: mm, not 0
  EXPECT_LT(cv::norm(rig->t), 10.0);
}

TEST(RigForms, RectifiedFocalPrincipalPointAndBaseline) {
  auto rig = parseRectified("579.05,180,144,5.5", {360, 288});
  ASSERT_TRUE(rig) << rig.error().message;
  EXPECT_EQ(rig->left.imageSize(), cv::Size(360, 288));
  EXPECT_DOUBLE_EQ(rig->left.k()(0, 0), 579.05);
  EXPECT_DOUBLE_EQ(rig->right.k()(1, 2), 144.0);
  EXPECT_DOUBLE_EQ(rig->t[0], -5.5);
  // A point at 40 mm: disparity f B / Z, rows aligned.
  const cv::Vec3d p(3.0, -2.0, 40.0);
  const cv::Vec2d l = rig->projectLeft(p), r = rig->projectRight(p);
  EXPECT_NEAR(l[0] - r[0], 579.05 * 5.5 / 40.0, 1e-9);
  EXPECT_NEAR(l[1], r[1], 1e-9);
  for (const char* bad : {"579,180,144", "579,180,144,5.5,1", "f,180,144,5.5", "579,180,,5.5",
                          "579,180,144,0", "-579,180,144,5.5", "579,180,144,nan"}) {
    SCOPED_TRACE(bad);
    auto r2 = parseRectified(bad, {360, 288});
    ASSERT_FALSE(r2);
    EXPECT_NE(r2.error().message.find(std::string("--rectified ") + bad), std::string::npos)
        << r2.error().message;
  }
  EXPECT_FALSE(parseRectified("579,180,144,5.5", {}));
}

// A ROS camera_info file in camera_calibration_parsers' documented layout.
std::string cameraInfoYaml(const char* name, const CameraModel& cam, const char* model,
                           const cv::Mat& rect, const cv::Mat& proj) {
  const auto row = [](const double* v, int n) {
    std::string s;
    for (int i = 0; i < n; ++i) s += fmt::format("{}{}", i ? ", " : "", v[i]);
    return s;
  };
  const auto block = [&](const char* key, int rows, int cols, const double* v) {
    return fmt::format("{}:\n  rows: {}\n  cols: {}\n  data: [{}]\n", key, rows, cols,
                       row(v, rows * cols));
  };
  return fmt::format("image_width: {}\nimage_height: {}\ncamera_name: {}\n", cam.imageSize().width,
                     cam.imageSize().height, name) +
         block("camera_matrix", 3, 3, cam.k().val) + fmt::format("distortion_model: {}\n", model) +
         block("distortion_coefficients", 1, cam.numDistortion(), cam.dist().data()) +
         block("rectification_matrix", 3, 3, rect.ptr<double>()) +
         block("projection_matrix", 3, 4, proj.ptr<double>());
}

TEST(RigForms, RosCameraInfoPairGivesTheRigBack) {
  test::TempDir dir;
  const StereoRig ref = sampleRig();
  // What ROS's stereo calibration does: OpenCV's stereoRectify, lengths in metres.
  cv::Mat r1, r2, p1, p2, q;
  cv::stereoRectify(
      cv::Mat(ref.left.k()), cv::Mat(1, 5, CV_64F, const_cast<double*>(ref.left.dist().data())),
      cv::Mat(ref.right.k()), cv::Mat(1, 8, CV_64F, const_cast<double*>(ref.right.dist().data())),
      ref.left.imageSize(), cv::Mat(ref.r), cv::Mat(ref.t * 1e-3), r1, r2, p1, p2, q, 0);
  std::ofstream(dir / "left.yaml") << cameraInfoYaml("left", ref.left, "plumb_bob", r1, p1);
  std::ofstream(dir / "right.yaml")
      << cameraInfoYaml("right", ref.right, "rational_polynomial", r2, p2);
  auto rig = loadCameraInfoPair(dir / "left.yaml", dir / "right.yaml", {1360, 1024}, "x");
  ASSERT_TRUE(rig) << rig.error().message;
  for (int i = 0; i < 9; ++i) EXPECT_NEAR(rig->r.val[i], ref.r.val[i], 1e-9);
  for (int i = 0; i < 3; ++i) EXPECT_NEAR(rig->t[i], ref.t[i], 1e-6);  // mm
  for (int i = 0; i < 9; ++i) EXPECT_EQ(rig->right.k().val[i], ref.right.k().val[i]);
  EXPECT_EQ(rig->right.numDistortion(), 8);

  // The left file given twice: its P has no baseline.
  auto twice = loadCameraInfoPair(dir / "left.yaml", dir / "left.yaml");
  ASSERT_FALSE(twice);
  EXPECT_NE(twice.error().message.find("P[0][3] (Tx = -fx * baseline) is zero"), std::string::npos)
      << twice.error().message;
  // Another size than the images; a missing key; an unknown distortion model.
  auto size = loadCameraInfoPair(dir / "left.yaml", dir / "right.yaml", {640, 480}, "cam.mp4");
  ASSERT_FALSE(size);
  EXPECT_NE(size.error().message.find("left.yaml: image_width x image_height 1360x1024, cam.mp4 is "
                                      "640x480"),
            std::string::npos)
      << size.error().message;
  std::ofstream(dir / "bad.yaml") << "image_width: 1360\nimage_height: 1024\n";
  auto missing = loadCameraInfoPair(dir / "left.yaml", dir / "bad.yaml");
  ASSERT_FALSE(missing);
  EXPECT_NE(missing.error().message.find("bad.yaml"), std::string::npos);
  EXPECT_NE(missing.error().message.find("camera_matrix"), std::string::npos)
      << missing.error().message;
  std::ofstream(dir / "fish.yaml") << cameraInfoYaml("right", ref.right, "equidistant", r2, p2);
  auto fish = loadCameraInfoPair(dir / "left.yaml", dir / "fish.yaml");
  ASSERT_FALSE(fish);
  EXPECT_NE(fish.error().message.find("'equidistant' is not supported"), std::string::npos)
      << fish.error().message;
}

TEST(RigSave, RefusesAnInvalidRig) {
  test::TempDir dir;
  StereoRig rig = sampleRig();
  rig.r(0, 1) = 0.5;
  auto ok = saveRig(rig, dir / "x.yaml");
  ASSERT_FALSE(ok);
  EXPECT_NE(ok.error().message.find("not a rotation"), std::string::npos);
  auto unwritable = saveRig(sampleRig(), "/proc/definitely/not/here.yaml");
  ASSERT_FALSE(unwritable);
  EXPECT_NE(unwritable.error().message.find("/proc/definitely/not/here.yaml"), std::string::npos);
}

}  // namespace
}  // namespace pulsetrack::vision
