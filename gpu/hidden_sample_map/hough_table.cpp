#include "hough_table.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <limits>
#include <numbers>

#include "common/parallel.h"

namespace visq::gpu::hsm {

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

  const double two_pi = 2.0 * std::numbers::pi;
  const double dtheta = two_pi / tt;
  const double r_max = layout.r_max, dr = 2.0 * r_max / tr;
  const double inf = std::numeric_limits<double>::infinity();
  std::vector<double> r_lo(tr), r_hi(tr);
  for (int ri = 0; ri < tr; ++ri) {
    r_lo[ri] = ri == 0 ? -inf : -r_max + ri * dr - kHoughMargin;
    r_hi[ri] = ri == tr - 1 ? inf : -r_max + (ri + 1) * dr + kHoughMargin;
  }
  std::vector<double> rho(n), phi(n);
  for (int i = 0; i < n; ++i) {
    rho[i] = std::hypot(double(centred[i].x), double(centred[i].y));
    phi[i] = std::atan2(double(centred[i].y), double(centred[i].x));
  }
  // Whether angle a lies in [lo, lo + width] modulo 2 pi.
  auto in_range = [&](double a, double lo, double width) {
    double t = std::fmod(a - lo, two_pi);
    if (t < 0) t += two_pi;
    return t <= width;
  };

  // Rows of theta are independent: split them over the cores.
  std::atomic<bool> stopped{false};
  auto build_rows = [&](int first, int last) {
    for (int ti = first; ti < last; ++ti) {
      if (stopped.load(std::memory_order_relaxed)) return;
      if (stop.Stopped()) {
        stopped = true;
        return;
      }
      const double t0 = -std::numbers::pi + ti * dtheta - kHoughMargin;
      const double width = dtheta + 2.0 * kHoughMargin;
      for (int i = 0; i < n; ++i) {
        // Range of cos(theta) x + sin(theta) y = rho cos(theta - phi) over the cell.
        const double c0 = rho[i] * std::cos(t0 - phi[i]), c1 = rho[i] * std::cos(t0 + width - phi[i]);
        const double g_max = in_range(phi[i], t0, width) ? rho[i] : std::max(c0, c1);
        const double g_min = in_range(phi[i] + std::numbers::pi, t0, width) ? -rho[i] : std::min(c0, c1);
        const int word = i >> 5;
        const uint32_t bit = 1u << (i & 31);
        const size_t layer_offset = size_t(word >> 2) * tt * tr * 4 + (word & 3);
        for (int ri = 0; ri < tr; ++ri) {
          const size_t at = layer_offset + (size_t(ti) * tr + ri) * 4;
          if (g_min - r_hi[ri] > kHoughMargin) {
            table[at] |= bit;  // left of every line of the cell
          } else if (g_max - r_lo[ri] >= -kHoughMargin) {
            table[plane_words + at] |= bit;  // could be on either side
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
