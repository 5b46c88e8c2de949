#include "pulsetrack/tools/image_pairs.hpp"

#include <gtest/gtest.h>

#include <fstream>

#include "test_util.hpp"

namespace pulsetrack::tools {
namespace {

void touch(const std::string& path) { std::ofstream(path) << "x"; }

TEST(WildcardKey, IsThePartTheWildcardsMatch) {
  EXPECT_EQ(wildcardKey("d/left*.jpg", "d/left07.jpg"), "7");
  EXPECT_EQ(wildcardKey("d/left0*.jpg", "d/left07.jpg"), "7");
  EXPECT_EQ(wildcardKey("d/left*.jpg", "d/left00.jpg"), "0");
  EXPECT_EQ(wildcardKey("d/*_L.png", "d/0001_L.png"), "1");
  EXPECT_EQ(wildcardKey("d/*_L.png", "d/a001_L.png"), "a001");
  EXPECT_EQ(wildcardKey("d/cam0_??.png", "d/cam0_12.png"), "12");
  EXPECT_EQ(wildcardKey("d/img[0-9]*.tif", "d/img3x.tif"), "3x");
  EXPECT_EQ(wildcardKey("d/one.png", "d/one.png"), "");
}

TEST(PairImages, PairsByKeyNotByPosition) {
  test::TempDir dir;
  for (const char* n :
       {"left01.png", "left02.png", "left10.png", "right01.png", "right02.png", "right10.png"}) {
    touch(dir / n);
  }
  auto pairs = pairImages(dir / "left*.png", dir / "right*.png");
  ASSERT_TRUE(pairs) << pairs.error().message;
  ASSERT_EQ(pairs->size(), 3U);
  EXPECT_EQ((*pairs)[2].first, dir / "left10.png");
  EXPECT_EQ((*pairs)[2].second, dir / "right10.png");
}

TEST(PairImages, NoMatchNamesTheGlob) {
  test::TempDir dir;
  touch(dir / "right01.png");
  auto pairs = pairImages(dir / "left*.png", dir / "right*.png");
  ASSERT_FALSE(pairs);
  EXPECT_EQ(pairs.error().message, "--left '" + (dir / "left*.png") + "': no file matches");
}

TEST(PairImages, UnpairedImagesAreListed) {
  test::TempDir dir;
  for (const char* n :
       {"left01.png", "left02.png", "left03.png", "right01.png", "right03.png", "right04.png"}) {
    touch(dir / n);
  }
  auto pairs = pairImages(dir / "left*.png", dir / "right*.png");
  ASSERT_FALSE(pairs);
  const std::string& m = pairs.error().message;
  EXPECT_NE(m.find("2 unpaired image(s)"), std::string::npos) << m;
  EXPECT_NE(m.find("left02.png has no right image"), std::string::npos) << m;
  EXPECT_NE(m.find("right04.png has no left image"), std::string::npos) << m;
}

}  // namespace
}  // namespace pulsetrack::tools
