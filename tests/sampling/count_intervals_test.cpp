// Per-texel bounds from the counts (sampling/count_intervals.h): the beta
// function against the binomial sums it stands for, the limits' shape, and
// their coverage for stratified (Poisson-binomial) counts by simulation.
#include "sampling/count_intervals.h"

#include <cmath>
#include <random>
#include <vector>

#include <gtest/gtest.h>

namespace visq::sampling {
namespace {

double BinomialAtLeast(int n, int k, double p) {
  double sum = 0.0;
  for (int j = k; j <= n; ++j)
    sum += std::exp(std::lgamma(n + 1.0) - std::lgamma(j + 1.0) - std::lgamma(n - j + 1.0) + j * std::log(p) +
                    (n - j) * std::log1p(-p));
  return sum;
}

TEST(CountIntervals, IncompleteBetaIsTheBinomialTail) {
  for (int n : {1, 7, 64, 300})
    for (int k = 1; k <= n; k += std::max(1, n / 9))
      for (double p : {0.01, 0.3, 0.5, 0.77, 0.999})
        EXPECT_NEAR(RegularizedIncompleteBeta(k, n - k + 1, p), BinomialAtLeast(n, k, p), 1e-10)
            << "n " << n << " k " << k << " p " << p;
}

TEST(CountIntervals, LimitsBracketTheCountAndGrowWithIt) {
  for (int n : {1, 16, 256, 4096, 65536}) {
    auto limits = StratifiedCountIntervals(n, 0.95);
    std::vector<int> all(size_t(n) + 1);
    for (int k = 0; k <= n; ++k) all[size_t(k)] = k;
    if (n > 4096) all = {0, 1, 2, n / 3, n / 2, n / 2 + 1, n - 1, n};  // a map needs a few
    limits->Prepare(all);
    for (size_t i = 0; i < all.size(); ++i) {
      const int k = all[i];
      EXPECT_LE(limits->Low(k), float(k) / n);
      EXPECT_GE(limits->High(k), float(k) / n);
      if (i > 0) {
        EXPECT_GE(limits->Low(k), limits->Low(all[i - 1]));
        EXPECT_GE(limits->High(k), limits->High(all[i - 1]));
      }
    }
    EXPECT_EQ(limits->Low(0), 0.0f);
    EXPECT_EQ(limits->High(n), 1.0f);
  }
  // The figure the header gives: 256 samples all visible, at 95 %.
  auto limits = StratifiedCountIntervals(256, 0.95);
  std::printf("256 samples, all visible: true fraction >= %.4f (Hoeffding's worst case: 1 - %.4f)\n",
              limits->Low(256), std::sqrt(std::log(2.0 / 0.05) / (2.0 * 256)));
  EXPECT_NEAR(1.0 - limits->Low(256), 0.022, 0.001);
  // Half visible: Clopper-Pearson's 95 % half-width sqrt(.25 / n) * 1.96,
  // plus the count of widening.
  const double half_width = limits->High(128) - 0.5;
  EXPECT_NEAR(half_width, 1.96 * std::sqrt(0.25 / 256) + 1.0 / 256, 0.006);
}

// One jittered sample per cell: cell i is visible with its own probability
// p_i (a shadow edge crossing some cells). The stated interval must hold
// for at least the stated share of maps, for each configuration.
TEST(CountIntervals, CoverStratifiedCountsAtTheirConfidence) {
  std::mt19937_64 random(12345);
  const int n = 64;
  auto limits = StratifiedCountIntervals(n, 0.95);
  std::vector<int> all;
  for (int k = 0; k <= n; ++k) all.push_back(k);
  limits->Prepare(all);
  std::vector<std::vector<double>> cases;
  for (double edge : {0.05, 0.3, 0.5, 0.8}) {
    std::vector<double> p(n);
    for (int i = 0; i < n; ++i) {
      const double x = (i + 0.5) / n;
      p[i] = std::clamp((x - edge) * 8.0 + 0.5, 0.0, 1.0);  // a soft edge across a few cells
    }
    cases.push_back(p);
  }
  cases.push_back(std::vector<double>(n, 0.5));   // the binomial itself
  cases.push_back(std::vector<double>(n, 0.97));
  for (size_t c = 0; c < cases.size(); ++c) {
    double truth = 0.0;
    for (double q : cases[c]) truth += q / n;
    const int trials = 20000;
    int covered = 0;
    for (int t = 0; t < trials; ++t) {
      int visible = 0;
      for (double q : cases[c]) visible += std::bernoulli_distribution(q)(random);
      covered += limits->Low(visible) <= truth && truth <= limits->High(visible);
    }
    EXPECT_GE(double(covered) / trials, 0.95 - 0.005) << "case " << c << ", true fraction " << truth;
  }
}

}  // namespace
}  // namespace visq::sampling
