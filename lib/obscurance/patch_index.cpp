#include "obscurance/patch_index.h"

#include <algorithm>
#include <bit>
#include <cmath>
#include <limits>

namespace visq::obscurance {

glm::ivec3 PatchIndex::CellOf(const glm::dvec3& p) const {
  glm::ivec3 c;
  for (int a = 0; a < 3; ++a) {
    const double f = std::floor((p[a] - origin_[a]) / cell_);
    c[a] = static_cast<int>(std::clamp(f, 0.0, static_cast<double>(dims_[a] - 1)));
  }
  return c;
}

void PatchIndex::Build(const std::vector<glm::dvec3>& center, const std::vector<double>& radius,
                       const std::vector<uint8_t>& indexed, double cell_hint) {
  cell_begin_.clear();
  cell_texels_.clear();
  dims_ = glm::ivec3(0);
  texel_count_ = center.size();
  // The grid's box: every indexed ball.
  glm::dvec3 lo(std::numeric_limits<double>::infinity()), hi(-std::numeric_limits<double>::infinity());
  for (size_t i = 0; i < center.size(); ++i) {
    if (!indexed[i] || radius[i] < 0) continue;
    lo = glm::min(lo, center[i] - radius[i]);
    hi = glm::max(hi, center[i] + radius[i]);
  }
  if (lo.x > hi.x) return;
  const glm::dvec3 extent = hi - lo;
  const double longest = std::max({extent.x, extent.y, extent.z});
  cell_ = std::max({cell_hint, longest / kMaxCellsPerAxis, 1e-12 * std::max(1.0, longest)});
  origin_ = lo;
  auto set_dims = [&] {
    for (int a = 0; a < 3; ++a)
      dims_[a] = std::clamp(static_cast<int>(std::ceil(extent[a] / cell_)), 1, kMaxCellsPerAxis);
  };
  set_dims();
  // Each ball is listed in every cell its box meets: balls as wide as the
  // scene (a triangle that is one point in the atlas is one patch) would be
  // listed in up to 128^3 cells each. Coarser cells until the lists hold at
  // most kMostEntriesPerBall entries a ball (counted from the boxes, before
  // anything is allocated), so the index's memory is bounded by its texels.
  size_t balls = 0;
  for (size_t i = 0; i < center.size(); ++i) balls += indexed[i] && radius[i] >= 0;
  for (;;) {
    uint64_t entries = 0;
    for (size_t i = 0; i < center.size(); ++i) {
      if (!indexed[i] || radius[i] < 0) continue;
      const glm::ivec3 a = CellOf(center[i] - radius[i]), b = CellOf(center[i] + radius[i]);
      entries += uint64_t(b.x - a.x + 1) * uint64_t(b.y - a.y + 1) * uint64_t(b.z - a.z + 1);
    }
    if (entries <= kMostEntriesPerBall * balls || (dims_.x == 1 && dims_.y == 1 && dims_.z == 1)) break;
    cell_ *= 2.0;
    set_dims();
  }
  // Counting pass, then the fill: each ball goes into every cell its box meets.
  const size_t cells = static_cast<size_t>(dims_.x) * dims_.y * dims_.z;
  cell_begin_.assign(cells + 1, 0);
  auto for_each_cell = [&](size_t i, auto&& body) {
    const glm::ivec3 a = CellOf(center[i] - radius[i]), b = CellOf(center[i] + radius[i]);
    for (int z = a.z; z <= b.z; ++z)
      for (int y = a.y; y <= b.y; ++y)
        for (int x = a.x; x <= b.x; ++x) body(Linear({x, y, z}));
  };
  for (size_t i = 0; i < center.size(); ++i)
    if (indexed[i] && radius[i] >= 0) for_each_cell(i, [&](size_t c) { ++cell_begin_[c + 1]; });
  for (size_t c = 1; c <= cells; ++c) cell_begin_[c] += cell_begin_[c - 1];
  cell_texels_.resize(cell_begin_[cells]);
  std::vector<uint32_t> cursor(cell_begin_.begin(), cell_begin_.end() - 1);
  for (size_t i = 0; i < center.size(); ++i)
    if (indexed[i] && radius[i] >= 0)
      for_each_cell(i, [&](size_t c) { cell_texels_[cursor[c]++] = static_cast<uint32_t>(i); });
}

uint64_t PatchIndex::CellBytesAtMost(const glm::dvec3& extent, double cell_hint) {
  const double longest = std::max({extent.x, extent.y, extent.z});
  uint64_t cells = 1;
  for (int a = 0; a < 3; ++a) {
    const double across = (extent[a] + longest) / cell_hint + 1.0;
    cells *= std::isfinite(across) ? static_cast<uint64_t>(std::clamp(across, 1.0, double{kMaxCellsPerAxis}))
                                   : uint64_t{kMaxCellsPerAxis};
  }
  return 2 * sizeof(uint32_t) * (cells + 1);
}

void PatchIndex::Query(const glm::dvec3& lo, const glm::dvec3& hi, std::vector<uint32_t>& out) const {
  if (cell_begin_.empty()) return;
  // Boxes wholly outside the grid meet no ball (CellOf would clamp them in).
  const glm::dvec3 grid_hi = origin_ + glm::dvec3(dims_) * cell_;
  for (int a = 0; a < 3; ++a)
    if (hi[a] < origin_[a] || lo[a] > grid_hi[a]) return;
  // The cells' texels marked in a bitmap over the atlas, then read off it
  // in order: a ball in several cells is listed once, and the list comes
  // out sorted without sorting the ~150K entries around an object, which
  // would cost more than the rest of the pool.
  thread_local std::vector<uint64_t> marked;
  marked.assign((texel_count_ + 63) / 64, 0);
  const glm::ivec3 a = CellOf(lo), b = CellOf(hi);
  for (int z = a.z; z <= b.z; ++z)
    for (int y = a.y; y <= b.y; ++y)
      for (int x = a.x; x <= b.x; ++x) {
        const size_t c = Linear({x, y, z});
        for (uint32_t k = cell_begin_[c]; k < cell_begin_[c + 1]; ++k)
          marked[cell_texels_[k] >> 6] |= uint64_t{1} << (cell_texels_[k] & 63);
      }
  for (size_t w = 0; w < marked.size(); ++w)
    for (uint64_t bits = marked[w]; bits != 0; bits &= bits - 1)
      out.push_back(static_cast<uint32_t>(64 * w + static_cast<size_t>(std::countr_zero(bits))));
}

}  // namespace visq::obscurance
