// Kruskal-Wallis against scipy.stats.kruskal (Debian's python3-scipy) on the same data, ties
// included; Dunn's pairwise z and Bonferroni p against the textbook formula computed by numpy
// from scipy.stats.rankdata; the chi-square survival against scipy.stats.chi2.sf.

#include "pulsetrack/analysis/stats.hpp"

#include <fmt/format.h>
#include <gtest/gtest.h>

#include <fstream>
#include <random>
#include <sstream>

#include "test_util.hpp"

namespace pulsetrack::analysis {
namespace {

constexpr const char* kPython = "/usr/bin/python3";

bool haveScipy() {
  return test::run(std::string(kPython) + " -c 'import scipy.stats, numpy'").exit_code == 0;
}

// Writes the groups one per line and returns what the python script prints (numbers).
std::vector<double> python(const test::TempDir& dir, const std::vector<std::vector<double>>& groups,
                           const std::string& script) {
  {
    std::ofstream f(dir / "groups.txt");
    for (const auto& g : groups) {
      for (size_t i = 0; i < g.size(); ++i) f << (i ? " " : "") << fmt::format("{:.17g}", g[i]);
      f << "\n";
    }
    std::ofstream(dir / "script.py") << script;
  }
  const auto r = test::run(fmt::format("{} {} {}", kPython, dir / "script.py", dir / "groups.txt"));
  EXPECT_EQ(r.exit_code, 0) << r.output;
  std::stringstream ss(r.output);
  std::vector<double> out;
  for (double x = 0; ss >> x;) out.push_back(x);
  return out;
}

const char* kKruskal = R"(
import sys, scipy.stats
groups = [[float(x) for x in l.split()] for l in open(sys.argv[1])]
h, p = scipy.stats.kruskal(*groups)
print(repr(float(h)), repr(float(p)))
)";

const char* kDunn = R"(
import sys, itertools, numpy as np, scipy.stats
groups = [[float(x) for x in l.split()] for l in open(sys.argv[1])]
allv = np.concatenate(groups)
r = scipy.stats.rankdata(allv)
n = len(allv)
_, t = np.unique(allv, return_counts=True)
var = n * (n + 1) / 12.0 - np.sum(t**3 - t) / (12.0 * (n - 1))
idx = np.cumsum([0] + [len(g) for g in groups])
mean = [r[idx[i]:idx[i+1]].mean() for i in range(len(groups))]
m = len(groups) * (len(groups) - 1) / 2
for a, b in itertools.combinations(range(len(groups)), 2):
    z = (mean[a] - mean[b]) / np.sqrt(var * (1.0 / len(groups[a]) + 1.0 / len(groups[b])))
    p = 2 * scipy.stats.norm.sf(abs(z))
    print(repr(float(z)), repr(float(min(1.0, p * m))))
)";

std::vector<std::vector<std::vector<double>>> datasets() {
  std::mt19937 rng(5);
  std::normal_distribution<double> g(0, 1);
  std::vector<std::vector<std::vector<double>>> d;
  // Four sets of ten, continuous, shifted (the static analysis' shape).
  d.push_back({});
  for (int s = 0; s < 4; ++s) {
    d.back().emplace_back();
    for (int i = 0; i < 10; ++i)
      d.back().back().push_back(0.1 + 0.02 * s + 0.05 * std::fabs(g(rng)));
  }
  // Heavy ties: values rounded to a 0.1 mm grid, unequal sizes.
  d.push_back({});
  for (int s = 0; s < 3; ++s) {
    d.back().emplace_back();
    for (int i = 0; i < 20 + 7 * s; ++i)
      d.back().back().push_back(std::round((0.3 + 0.1 * s + 0.2 * g(rng)) * 10) / 10);
  }
  // Two groups, a clear difference (a tiny p).
  d.push_back({{}, {}});
  for (int i = 0; i < 60; ++i) {
    d.back()[0].push_back(g(rng));
    d.back()[1].push_back(g(rng) + 1.5);
  }
  return d;
}

TEST(KruskalWallis, AgreesWithScipyIncludingTies) {
  ASSERT_TRUE(haveScipy())
      << "/usr/bin/python3 with scipy is needed (scripts/bootstrap installs python3-scipy)";
  test::TempDir dir;
  for (const auto& groups : datasets()) {
    auto kw = kruskalWallis(groups);
    ASSERT_TRUE(kw) << kw.error().message;
    const auto ref = python(dir, groups, kKruskal);
    ASSERT_EQ(ref.size(), 2U);
    EXPECT_NEAR(kw->h, ref[0], 1e-9 * std::max(1.0, ref[0]));
    EXPECT_NEAR(kw->p, ref[1], 1e-9);
    std::cout << fmt::format("H {:.12g} (scipy {:.12g}), p {:.12g} (scipy {:.12g})\n", kw->h,
                             ref[0], kw->p, ref[1]);
  }
}

TEST(KruskalWallis, DunnBonferroniAgreesWithTheFormulaOnScipyRanks) {
  ASSERT_TRUE(haveScipy())
      << "/usr/bin/python3 with scipy is needed (scripts/bootstrap installs python3-scipy)";
  test::TempDir dir;
  for (const auto& groups : datasets()) {
    const auto pairs = dunnBonferroni(groups);
    const auto ref = python(dir, groups, kDunn);
    ASSERT_EQ(ref.size(), 2 * pairs.size());
    for (size_t i = 0; i < pairs.size(); ++i) {
      EXPECT_NEAR(pairs[i].z, ref[2 * i], 1e-9);
      EXPECT_NEAR(pairs[i].p_adjusted, ref[2 * i + 1], 1e-9);
    }
  }
}

TEST(KruskalWallis, ChiSquareSurvivalAgreesWithScipy) {
  ASSERT_TRUE(haveScipy())
      << "/usr/bin/python3 with scipy is needed (scripts/bootstrap installs python3-scipy)";
  const auto r =
      test::run(std::string(kPython) +
                " -c 'import scipy.stats as s\nfor k in range(1, 8):\n for x in (0.01, 0.5, 2.0, "
                "7.5, 20.0, 60.0): print(repr(float(s.chi2.sf(x, k))))'");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  std::stringstream ss(r.output);
  for (int k = 1; k < 8; ++k) {
    for (const double x : {0.01, 0.5, 2.0, 7.5, 20.0, 60.0}) {
      double ref = 0;
      ss >> ref;
      EXPECT_NEAR(chiSquareSurvival(x, k), ref, 1e-12 + 1e-9 * ref) << "dof " << k << " x " << x;
    }
  }
}

TEST(KruskalWallis, RefusesWhatItCannotTest) {
  EXPECT_FALSE(kruskalWallis({{1.0, 2.0}}));
  EXPECT_FALSE(kruskalWallis({{1.0, 1.0}, {1.0}}));
  EXPECT_TRUE(kruskalWallis({{1.0, 2.0}, {}, {3.0}}));  // an empty group is left out
}

TEST(Summary, QuartilesAsNumpy) {
  const Summary s = summarize({4, 1, 3, 2, 10});
  EXPECT_DOUBLE_EQ(s.median, 3);
  EXPECT_DOUBLE_EQ(s.q1, 2);
  EXPECT_DOUBLE_EQ(s.q3, 4);
  EXPECT_DOUBLE_EQ(s.mean, 4);
  EXPECT_NEAR(s.sd, std::sqrt(12.5), 1e-12);
  const auto lim = equalCountLimits({1, 2, 3, 4, 5, 6, 7, 8, 9}, 3);
  ASSERT_EQ(lim.size(), 2U);
  EXPECT_NEAR(lim[0], 11.0 / 3.0, 1e-12);
}

}  // namespace
}  // namespace pulsetrack::analysis
