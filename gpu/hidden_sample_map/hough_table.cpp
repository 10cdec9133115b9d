#include "hough_table.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <limits>
#include <numbers>

#include "common/parallel.h"

namespace visq::gpu::hsm {
namespace {

constexpr double kTwoPi = 2.0 * std::numbers::pi;

// Whether angle a lies in [lo, lo + width] modulo 2 pi, for a - lo in
// (-2 pi, 4 pi): fmod's answer there without its cost (a - lo - 2 pi is
// exact from 2 pi to 4 pi, Sterbenz's lemma).
bool InAngleRange(double a, double lo, double width) {
  double t = a - lo;
  if (t < 0.0) {
    t += kTwoPi;
  } else if (t >= kTwoPi) {
    t -= kTwoPi;
  }
  return t <= width;
}

// How many leading cells of a row `holds` (true on a prefix of the row),
// walked from `guess` by the very comparisons that define the prefix, so
// that the answer is theirs whatever rounding did to the guess.
template <class Holds>
int PrefixLength(double guess, int cells, const Holds& holds) {
  int k = guess >= 0.0 ? static_cast<int>(std::min(guess, double(cells))) : 0;
  while (k < cells && holds(k)) ++k;
  while (k > 0 && !holds(k - 1)) --k;
  return k;
}

}  // namespace

std::vector<uint32_t> BuildHoughTable(const std::vector<glm::vec2>& centred, HoughTableLayout& layout,
                                      const StopToken& stop) {
  const int n = static_cast<int>(centred.size());
  layout.sample_count = n;
  double rho_max = 0.0;
  for (const glm::vec2& s : centred) rho_max = std::max(rho_max, std::hypot(double(s.x), double(s.y)));
  // Lines beyond every sample land in the clamped edge texels, which are then
  // all-or-nothing; a little headroom keeps the outer cells useful.
  layout.r_max = static_cast<float>(rho_max * (1.0 + 4.0 / layout.r_res) + 1e-3);
  const int groups = layout.groups();
  const int tr = layout.r_res, tt = layout.theta_res;
  const size_t plane_words = size_t(groups) * tt * tr * 4;
  std::vector<uint32_t> table(2 * plane_words, 0u);

  const double dtheta = kTwoPi / tt;
  const double r_max = layout.r_max, dr = 2.0 * r_max / tr;
  const double inf = std::numeric_limits<double>::infinity();
  std::vector<double> r_lo(tr), r_hi(tr);
  for (int ri = 0; ri < tr; ++ri) {
    r_lo[ri] = ri == 0 ? -inf : -r_max + ri * dr - kHoughMargin;
    r_hi[ri] = ri == tr - 1 ? inf : -r_max + (ri + 1) * dr + kHoughMargin;
  }
  std::vector<double> x(n), y(n), rho(n), phi(n);
  for (int i = 0; i < n; ++i) {
    x[i] = centred[i].x;
    y[i] = centred[i].y;
    rho[i] = std::hypot(x[i], y[i]);
    phi[i] = std::atan2(y[i], x[i]);
  }

  // Within a row of theta, r_hi and r_lo grow with the r index, so the cells
  // where a sample is left of every line are a prefix of the row, and so are
  // those where it could be left of one. Each sample is filed under the cell
  // where each prefix ends, and one sweep down the row ORs them in: a row
  // costs O(n + r n / 32), not the O(n r) of testing every cell, which made
  // the table of 1,024 samples longer to build than most maps that use it.
  const int words = (n + 31) / 32;
  std::atomic<bool> stopped{false};
  auto build_rows = [&](int first, int last) {
    std::vector<uint32_t> left_ends_at(size_t(tr + 1) * words), either_ends_at(size_t(tr + 1) * words);
    for (int ti = first; ti < last; ++ti) {
      if (stopped.load(std::memory_order_relaxed)) return;
      if (stop.Stopped()) {
        stopped = true;
        return;
      }
      std::fill(left_ends_at.begin(), left_ends_at.end(), 0u);
      std::fill(either_ends_at.begin(), either_ends_at.end(), 0u);
      const double t0 = -std::numbers::pi + ti * dtheta - kHoughMargin;
      const double width = dtheta + 2.0 * kHoughMargin;
      const double cos0 = std::cos(t0), sin0 = std::sin(t0);
      const double cos1 = std::cos(t0 + width), sin1 = std::sin(t0 + width);
      for (int i = 0; i < n; ++i) {
        // The range of g = cos(theta) x + sin(theta) y over the cell's
        // angles: its ends, or +-rho where the sample's direction (or its
        // opposite) lies inside them.
        const double c0 = x[i] * cos0 + y[i] * sin0, c1 = x[i] * cos1 + y[i] * sin1;
        const double g_max = InAngleRange(phi[i], t0, width) ? rho[i] : std::max(c0, c1);
        const double g_min = InAngleRange(phi[i] + std::numbers::pi, t0, width) ? -rho[i] : std::min(c0, c1);
        // Left of every line of cell ri: g_min - r_hi[ri] > margin. Possibly
        // left of one: g_max - r_lo[ri] >= -margin.
        const int left_end = PrefixLength((g_min + r_max) / dr - 1.0, tr,
                                          [&](int ri) { return g_min - r_hi[ri] > kHoughMargin; });
        const int either_end = PrefixLength((g_max + r_max) / dr, tr,
                                            [&](int ri) { return g_max - r_lo[ri] >= -kHoughMargin; });
        const uint32_t bit = 1u << (i & 31);
        left_ends_at[size_t(left_end) * words + (i >> 5)] |= bit;
        either_ends_at[size_t(either_end) * words + (i >> 5)] |= bit;
      }
      // Down the row: cell ri holds the samples whose prefix ends after it.
      // A group's four words are one texel, so its cells are written in
      // order, the row's texels of one layer after another.
      for (int group = 0; 4 * group < words; ++group) {
        const int lanes = std::min(4, words - 4 * group);
        uint32_t left[4] = {}, either[4] = {};
        uint32_t* left_texels = &table[(size_t(group) * tt + ti) * tr * 4];
        uint32_t* either_texels = left_texels + plane_words;
        for (int ri = tr - 1; ri >= 0; --ri) {
          const uint32_t* left_here = &left_ends_at[size_t(ri + 1) * words + 4 * group];
          const uint32_t* either_here = &either_ends_at[size_t(ri + 1) * words + 4 * group];
          for (int lane = 0; lane < lanes; ++lane) {
            left[lane] |= left_here[lane];
            either[lane] |= either_here[lane];
            left_texels[ri * 4 + lane] = left[lane];                     // left of every line of the cell
            either_texels[ri * 4 + lane] = either[lane] & ~left[lane];  // could be on either side
          }
        }
      }
    }
  };
  ParallelFor(static_cast<size_t>(tt), 8, [&](size_t begin, size_t end) {
    build_rows(static_cast<int>(begin), static_cast<int>(end));
  });
  if (stopped) return {};
  return table;
}

}  // namespace visq::gpu::hsm
