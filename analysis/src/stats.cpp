#include "pulsetrack/analysis/stats.hpp"

#include <algorithm>
#include <cmath>
#include <numeric>

namespace pulsetrack::analysis {

double quantile(std::vector<double> v, double q) {
  if (v.empty()) return std::nan("");
  std::sort(v.begin(), v.end());
  const double pos = q * static_cast<double>(v.size() - 1);
  const auto i = static_cast<size_t>(std::floor(pos));
  if (i + 1 >= v.size()) return v.back();
  return v[i] + (pos - static_cast<double>(i)) * (v[i + 1] - v[i]);
}

Summary summarize(std::vector<double> v) {
  Summary s;
  s.n = v.size();
  if (v.empty()) return s;
  std::sort(v.begin(), v.end());
  s.mean = std::accumulate(v.begin(), v.end(), 0.0) / static_cast<double>(s.n);
  double ss = 0;
  for (const double x : v) ss += (x - s.mean) * (x - s.mean);
  s.sd = s.n > 1 ? std::sqrt(ss / static_cast<double>(s.n - 1)) : 0.0;
  s.min = v.front();
  s.max = v.back();
  s.q1 = quantile(v, 0.25);
  s.median = quantile(v, 0.5);
  s.q3 = quantile(v, 0.75);
  return s;
}

double chiSquareSurvival(double x, int dof) {
  if (!(x > 0)) return 1.0;
  const double h = x / 2;
  if (dof % 2 == 0) {
    // e^-h * sum_{i < dof/2} h^i / i!
    double term = 1, sum = 1;
    for (int i = 1; i < dof / 2; ++i) {
      term *= h / i;
      sum += term;
    }
    return std::exp(-h) * sum;
  }
  // erfc(sqrt(h)) + e^-h * sum_{i=1}^{(dof-1)/2} h^(i-1/2) / Gamma(i+1/2)
  double q = std::erfc(std::sqrt(h));
  double term = std::sqrt(h) / std::tgamma(1.5);  // i = 1
  double sum = 0;
  for (int i = 1; i <= (dof - 1) / 2; ++i) {
    if (i > 1) term *= h / (i - 0.5);
    sum += term;
  }
  return q + std::exp(-h) * sum;
}

namespace {

struct Ranked {
  std::vector<std::vector<double>> ranks;  // per group
  double n = 0;
  double ties = 0;  // sum of t^3 - t over tied runs
};

Ranked rankAll(const std::vector<std::vector<double>>& groups) {
  std::vector<std::pair<double, std::pair<size_t, size_t>>> all;
  for (size_t g = 0; g < groups.size(); ++g)
    for (size_t i = 0; i < groups[g].size(); ++i) all.push_back({groups[g][i], {g, i}});
  std::sort(all.begin(), all.end(), [](const auto& a, const auto& b) { return a.first < b.first; });
  Ranked r;
  r.ranks.resize(groups.size());
  for (size_t g = 0; g < groups.size(); ++g) r.ranks[g].resize(groups[g].size());
  r.n = static_cast<double>(all.size());
  for (size_t i = 0; i < all.size();) {
    size_t j = i;
    while (j + 1 < all.size() && all[j + 1].first == all[i].first) ++j;
    const double rank = (static_cast<double>(i) + static_cast<double>(j)) / 2.0 + 1.0;
    const auto t = static_cast<double>(j - i + 1);
    r.ties += t * t * t - t;
    for (size_t k = i; k <= j; ++k) r.ranks[all[k].second.first][all[k].second.second] = rank;
    i = j + 1;
  }
  return r;
}

}  // namespace

vision::Result<KruskalWallis> kruskalWallis(const std::vector<std::vector<double>>& groups) {
  std::vector<std::vector<double>> used;
  for (const auto& g : groups) {
    if (!g.empty()) used.push_back(g);
  }
  if (used.size() < 2) return vision::fail("Kruskal-Wallis: fewer than two groups hold data");
  const Ranked r = rankAll(used);
  const double n = r.n;
  const double correction = 1.0 - r.ties / (n * n * n - n);
  if (correction <= 0) return vision::fail("Kruskal-Wallis: every value is the same");
  KruskalWallis kw;
  double sum = 0;
  for (const auto& g : r.ranks) {
    const double s = std::accumulate(g.begin(), g.end(), 0.0);
    sum += s * s / static_cast<double>(g.size());
    kw.mean_ranks.push_back(s / static_cast<double>(g.size()));
  }
  kw.h = (12.0 / (n * (n + 1.0)) * sum - 3.0 * (n + 1.0)) / correction;
  kw.dof = static_cast<int>(used.size()) - 1;
  kw.p = chiSquareSurvival(kw.h, kw.dof);
  return kw;
}

std::vector<PairwiseComparison> dunnBonferroni(const std::vector<std::vector<double>>& groups,
                                               double alpha) {
  const Ranked r = rankAll(groups);
  const double n = r.n;
  const size_t k = groups.size();
  const double pairs = static_cast<double>(k) * static_cast<double>(k - 1) / 2.0;
  const double var = n * (n + 1.0) / 12.0 - r.ties / (12.0 * (n - 1.0));
  std::vector<PairwiseComparison> out;
  for (size_t a = 0; a < k; ++a) {
    for (size_t b = a + 1; b < k; ++b) {
      if (groups[a].empty() || groups[b].empty()) continue;
      const auto mean = [](const std::vector<double>& v) {
        return std::accumulate(v.begin(), v.end(), 0.0) / static_cast<double>(v.size());
      };
      PairwiseComparison c;
      c.a = static_cast<int>(a);
      c.b = static_cast<int>(b);
      const double se = std::sqrt(var * (1.0 / static_cast<double>(groups[a].size()) +
                                         1.0 / static_cast<double>(groups[b].size())));
      c.z = se > 0 ? (mean(r.ranks[a]) - mean(r.ranks[b])) / se : 0.0;
      c.p = std::erfc(std::fabs(c.z) / std::sqrt(2.0));
      c.p_adjusted = std::min(1.0, c.p * pairs);
      c.significant = c.p_adjusted < alpha;
      out.push_back(c);
    }
  }
  return out;
}

std::vector<double> equalCountLimits(const std::vector<double>& key, int groups) {
  std::vector<double> limits;
  for (int i = 1; i < groups; ++i) limits.push_back(quantile(key, double(i) / groups));
  return limits;
}

}  // namespace pulsetrack::analysis
