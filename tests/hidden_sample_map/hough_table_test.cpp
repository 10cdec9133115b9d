// The Hough table against its definition (hough_table.h), cell by cell: for
// every (theta, r) cell and sample, plane L holds the samples left of every
// line of the widened cell and plane A those that could be on either side.
// The reference tests each cell on its own, as the table was first built;
// the table sweeps prefixes of each row and must give the same words.
#include <algorithm>
#include <atomic>
#include <bit>
#include <cmath>
#include <cstdint>
#include <limits>
#include <numbers>
#include <random>
#include <vector>

#include <gtest/gtest.h>

#include "hough_table.h"

namespace visq::gpu::hsm {
namespace {

std::vector<uint32_t> TableByDefinition(const std::vector<glm::vec2>& centred, const HoughTableLayout& layout) {
  const int n = static_cast<int>(centred.size());
  const int tt = layout.theta_res, tr = layout.r_res;
  const size_t plane_words = size_t(layout.groups()) * tt * tr * 4;
  std::vector<uint32_t> table(2 * plane_words, 0u);
  const double two_pi = 2.0 * std::numbers::pi, dtheta = two_pi / tt;
  const double r_max = layout.r_max, dr = 2.0 * r_max / tr, inf = std::numeric_limits<double>::infinity();
  auto in_range = [&](double a, double lo, double width) {
    double t = std::fmod(a - lo, two_pi);
    if (t < 0) t += two_pi;
    return t <= width;
  };
  for (int ti = 0; ti < tt; ++ti) {
    const double t0 = -std::numbers::pi + ti * dtheta - kHoughMargin, width = dtheta + 2.0 * kHoughMargin;
    for (int i = 0; i < n; ++i) {
      const double x = centred[i].x, y = centred[i].y;
      const double rho = std::hypot(x, y), phi = std::atan2(y, x);
      // g = cos(theta) x + sin(theta) y at the cell's two ends.
      const double c0 = x * std::cos(t0) + y * std::sin(t0);
      const double c1 = x * std::cos(t0 + width) + y * std::sin(t0 + width);
      const double g_max = in_range(phi, t0, width) ? rho : std::max(c0, c1);
      const double g_min = in_range(phi + std::numbers::pi, t0, width) ? -rho : std::min(c0, c1);
      const int word = i >> 5;
      for (int ri = 0; ri < tr; ++ri) {
        const double r_lo = ri == 0 ? -inf : -r_max + ri * dr - kHoughMargin;
        const double r_hi = ri == tr - 1 ? inf : -r_max + (ri + 1) * dr + kHoughMargin;
        const size_t at = size_t(word >> 2) * tt * tr * 4 + (word & 3) + (size_t(ti) * tr + ri) * 4;
        if (g_min - r_hi > kHoughMargin) {
          table[at] |= 1u << (i & 31);
        } else if (g_max - r_lo >= -kHoughMargin) {
          table[plane_words + at] |= 1u << (i & 31);
        }
      }
    }
  }
  return table;
}

void ExpectTheDefinitionsWords(const std::vector<glm::vec2>& centred, int theta_res, int r_res) {
  HoughTableLayout layout;
  layout.theta_res = theta_res;
  layout.r_res = r_res;
  const std::vector<uint32_t> table = BuildHoughTable(centred, layout);
  ASSERT_EQ(layout.sample_count, static_cast<int>(centred.size()));
  const std::vector<uint32_t> reference = TableByDefinition(centred, layout);
  ASSERT_EQ(table.size(), reference.size());
  size_t differing = 0, first = table.size();
  for (size_t w = 0; w < table.size(); ++w) {
    if (table[w] != reference[w]) {
      ++differing;
      first = std::min(first, w);
    }
  }
  EXPECT_EQ(differing, 0u) << "of " << table.size() << " words, first at " << first << " for " << centred.size()
                           << " samples, " << theta_res << " x " << r_res << " cells";
  // Neither plane is empty: the comparison above compared something.
  size_t set_bits = 0;
  for (uint32_t w : table) set_bits += std::popcount(w);
  EXPECT_GT(set_bits, 0u);
}

std::vector<glm::vec2> RandomSamples(int n, unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> u(-0.5f, 0.5f);
  std::vector<glm::vec2> samples(n);
  for (glm::vec2& s : samples) s = {u(rng), u(rng)};
  return samples;
}

TEST(HoughTable, RandomSamplesGiveTheDefinitionsWords) {
  ExpectTheDefinitionsWords(RandomSamples(32, 1), 256, 256);
  ExpectTheDefinitionsWords(RandomSamples(1000, 2), 64, 96);  // a last word half full
  ExpectTheDefinitionsWords(RandomSamples(4096, 3), 32, 48);
}

TEST(HoughTable, GridsCentresAndRepeatsGiveTheDefinitionsWords) {
  // Samples on a grid sit on many lines of the table exactly; the centre has
  // no angle; repeats and the patch's corners are the edge cases of the sweep.
  std::vector<glm::vec2> samples;
  for (int y = 0; y < 16; ++y)
    for (int x = 0; x < 16; ++x) samples.push_back({(x + 0.5f) / 16.0f - 0.5f, (y + 0.5f) / 16.0f - 0.5f});
  samples.push_back({0.0f, 0.0f});
  samples.push_back({0.0f, 0.0f});
  samples.push_back({-0.5f, -0.5f});
  samples.push_back({0.5f, 0.5f});
  samples.push_back({0.5f, -0.5f});
  samples.push_back(samples[17]);
  ExpectTheDefinitionsWords(samples, 256, 256);
  ExpectTheDefinitionsWords(samples, 7, 5);  // resolutions that are not powers of two
  ExpectTheDefinitionsWords({{0.0f, 0.0f}}, 16, 16);
}

TEST(HoughTable, AStopBeforeTheFirstRowGivesNoTable) {
  HoughTableLayout layout;
  const std::atomic<bool> cancelled{true};
  EXPECT_TRUE(BuildHoughTable(RandomSamples(64, 4), layout, StopToken{.cancelled = &cancelled}).empty());
}

}  // namespace
}  // namespace visq::gpu::hsm
