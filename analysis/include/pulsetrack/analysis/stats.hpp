#pragma once
// Descriptive statistics and the nonparametric tests of the paper's sections 4.D.1-4.D.2:
// Kruskal-Wallis across groups (ties corrected, as scipy.stats.kruskal) and Dunn's pairwise
// comparisons of mean ranks with the Bonferroni correction.

#include <string>
#include <vector>

#include "pulsetrack/vision/error.hpp"

namespace pulsetrack::analysis {

struct Summary {
  size_t n = 0;
  double mean = 0, sd = 0, min = 0, q1 = 0, median = 0, q3 = 0, max = 0;
};
// Sample standard deviation (n - 1); quartiles by linear interpolation (numpy's default).
Summary summarize(std::vector<double> v);
double quantile(std::vector<double> v, double q);

struct KruskalWallis {
  double h = 0;  // tie-corrected statistic
  double p = 1;  // chi-square survival with groups - 1 degrees of freedom
  int dof = 0;
  std::vector<double> mean_ranks;
};
// Fails when fewer than two groups have data, or when every value is the same.
vision::Result<KruskalWallis> kruskalWallis(const std::vector<std::vector<double>>& groups);

struct PairwiseComparison {
  int a = 0, b = 0;
  double z = 0;
  double p = 1;           // two-sided
  double p_adjusted = 1;  // Bonferroni: p times the number of pairs, at most 1
  bool significant = false;
};
// Dunn's test on the pooled ranks (tie-corrected variance), every pair, at level alpha.
std::vector<PairwiseComparison> dunnBonferroni(const std::vector<std::vector<double>>& groups,
                                               double alpha = 0.05);

// P(chi-square with dof degrees of freedom > x), closed forms (exact for every integer dof).
double chiSquareSurvival(double x, int dof);

// Groups of (nearly) equal size by the value of `key`: the tertile (or n-tile) limits.
std::vector<double> equalCountLimits(const std::vector<double>& key, int groups);

}  // namespace pulsetrack::analysis
