// The REGULAR and JITTERED source patterns cover the patch evenly for every
// sample count: each sample stands for the same area, so a visible fraction
// estimated from them is unbiased, and the Hoeffding bound's premise (for
// JITTERED: independent samples of equal-area strata) holds.
#include <cmath>
#include <vector>

#include <gtest/gtest.h>

#include "common/random.h"
#include "sampling/visibility_sampling.h"

namespace visq::sampling {
namespace {

constexpr int kMaxSamples = kMaxHiddenSampleMapSamples;

// The cells the obscurance rays are stratified over: for every n, n cells
// of area 1/n each, every point of the square in exactly one of them, and
// the same layout as the hidden-sample map's regular pattern (its sample i
// is cell i's centre).
TEST(EqualAreaCells, TileTheSquareForEveryCount) {
  SplitMix rng{11};
  std::vector<int> counts;
  for (int n = 1; n <= 300; ++n) counts.push_back(n);
  for (int n : {511, 512, 513, 1000, 1024, 2080, 4095, 4096}) counts.push_back(n);
  for (int n : counts) {
    std::vector<EqualAreaCell> cells;
    double area = 0.0;
    for (int j = 0; j < n; ++j) {
      cells.push_back(EqualAreaCellOf(n, j));
      EXPECT_NEAR(cells.back().width * cells.back().height, 1.0 / n, 1e-12) << "n " << n << " cell " << j;
      area += cells.back().width * cells.back().height;
    }
    EXPECT_NEAR(area, 1.0, 1e-9) << "n " << n;
    for (int k = 0; k < 200; ++k) {
      const double x = rng.Uniform(), y = rng.Uniform();
      int holding = 0;
      for (const EqualAreaCell& c : cells)
        holding += x >= c.x0 && x < c.x0 + c.width && y >= c.y0 && y < c.y0 + c.height;
      EXPECT_EQ(holding, 1) << "n " << n << " point (" << x << ", " << y << ")";
    }
    const std::vector<glm::dvec2> regular = StratifiedSamplePattern(n, SamplePattern::kRegular, 0);
    ASSERT_EQ(regular.size(), cells.size());
    for (int j = 0; j < n; ++j) {
      EXPECT_NEAR(regular[j].x, cells[j].x0 + 0.5 * cells[j].width, 1e-12) << "n " << n << " cell " << j;
      EXPECT_NEAR(regular[j].y, cells[j].y0 + 0.5 * cells[j].height, 1e-12) << "n " << n << " cell " << j;
    }
  }
}

TEST(StratifiedSamplePattern, EveryCountGivesThatManySamplesInsideThePatch) {
  for (SamplePattern pattern : {SamplePattern::kRegular, SamplePattern::kJittered})
    for (int n = 1; n <= kMaxSamples; ++n) {
      const std::vector<glm::dvec2> uv = StratifiedSamplePattern(n, pattern, 7);
      ASSERT_EQ(uv.size(), size_t(n));
      for (const glm::dvec2& p : uv) {
        ASSERT_GE(p.x, 0.0) << n;
        ASSERT_LT(p.x, 1.0) << n;
        ASSERT_GE(p.y, 0.0) << n;
        ASSERT_LT(p.y, 1.0) << n;
      }
    }
}

TEST(StratifiedSamplePattern, SquareCountsAreTheSquareGrid) {
  for (int k : {1, 8, 16, 64}) {
    const std::vector<glm::dvec2> uv = StratifiedSamplePattern(k * k, SamplePattern::kRegular, 1);
    for (int r = 0; r < k; ++r)
      for (int c = 0; c < k; ++c) {
        EXPECT_DOUBLE_EQ(uv[size_t(r) * k + c].x, (c + 0.5) / k);
        EXPECT_DOUBLE_EQ(uv[size_t(r) * k + c].y, (r + 0.5) / k);
      }
  }
}

// REGULAR: the centroid is the patch's centre for every count (a grid of
// ceil(sqrt n) columns with a partly empty last row pulls it down by up to
// 1/(2 sqrt n)), and every cell of a coarser k x k grid holds its share of
// the samples, up to the samples its boundary cuts.
TEST(StratifiedSamplePattern, RegularSamplesFallEvenlyOverAnyGridOfCells) {
  for (int n = 1; n <= kMaxSamples; ++n) {
    const std::vector<glm::dvec2> uv = StratifiedSamplePattern(n, SamplePattern::kRegular, 1);
    glm::dvec2 mean(0.0);
    for (const glm::dvec2& p : uv) mean += p / double(n);
    ASSERT_NEAR(mean.x, 0.5, 1e-12) << n;
    ASSERT_NEAR(mean.y, 0.5, 1e-12) << n;
    for (int k = 2; k <= 8; ++k) {
      if (n < 4 * k * k) break;
      std::vector<int> counts(size_t(k) * k, 0);
      for (const glm::dvec2& p : uv) ++counts[size_t(int(p.y * k)) * k + int(p.x * k)];
      const double share = double(n) / (k * k);
      const double cut = 3.0 * (std::sqrt(double(n)) + 1.0) / k + 4.0;
      for (int cell = 0; cell < k * k; ++cell)
        ASSERT_LE(std::abs(counts[cell] - share), cut) << n << " samples, " << k << "x" << k << " cell " << cell;
    }
  }
}

// JITTERED: over many seeds, the fraction of samples on one side of a light
// edge (a diagonal, so no row or column lines up with it) averages to that
// side's area, for counts that are squares, primes, and the planner's 768
// and 2080. The old grid's half-empty last row was off by 0.01-0.02 here.
TEST(StratifiedSamplePattern, JitteredEstimatesAreUnbiasedForEveryCount) {
  constexpr int kSeeds = 256;
  for (int n : {1, 2, 3, 5, 7, 31, 32, 33, 127, 128, 129, 500, 511, 512, 513, 768, 1000, 2080, 4093, 4096}) {
    for (const double edge : {0.8, 1.3}) {
      // Area of {u + v < edge} in the unit square.
      const double area = edge <= 1.0 ? 0.5 * edge * edge : 1.0 - 0.5 * (2.0 - edge) * (2.0 - edge);
      double sum = 0.0, sum_sq = 0.0;
      for (int seed = 1; seed <= kSeeds; ++seed) {
        int inside = 0;
        for (const glm::dvec2& p : StratifiedSamplePattern(n, SamplePattern::kJittered, uint64_t(seed) * 977))
          inside += p.x + p.y < edge;
        const double fraction = double(inside) / n;
        sum += fraction;
        sum_sq += fraction * fraction;
      }
      const double mean = sum / kSeeds;
      const double spread = std::sqrt(std::max(0.0, sum_sq / kSeeds - mean * mean));
      const double standard_error = spread / std::sqrt(double(kSeeds));
      EXPECT_NEAR(mean, area, 5.0 * standard_error + 1e-9) << n << " samples, edge " << edge;
    }
  }
}

// The visible fraction of a half-lit source, through ComputeSourceSamples
// (what every sampled method uses): REGULAR's estimate is within one row's
// or column's share of the truth for every count.
TEST(StratifiedSamplePattern, SourceSamplesUseThePattern) {
  for (int n : {7, 512, 768, 2080}) {
    SourceSpec source;
    source.sample_count = n;
    source.pattern = SamplePattern::kRegular;
    auto samples = ComputeSourceSamples(source);
    ASSERT_TRUE(samples.ok()) << samples.status();
    EXPECT_EQ(samples->uv, StratifiedSamplePattern(n, SamplePattern::kRegular, source.seed));
    int below = 0;
    for (const glm::dvec2& p : samples->uv) below += p.y < 0.5;
    EXPECT_NEAR(double(below) / n, 0.5, 1.0 / std::sqrt(double(n)) + 1e-12) << n;
  }
}

}  // namespace
}  // namespace visq::sampling
