// A spatial index over patches for the obscurance update: a uniform grid
// over the patches' bounding balls, so that the patches within reach of a
// moved object are found by visiting the grid cells around it instead of
// every texel of the atlas.
#pragma once

#include <cstdint>
#include <vector>

#include <glm/glm.hpp>

namespace visq::obscurance {

class PatchIndex {
 public:
  // Indexes texel i when indexed[i] and radius[i] >= 0 (a patch's bounding
  // ball: center[i], radius[i]). `cell_hint` is the wanted cell size (the
  // update passes d_max); the grid keeps at most kMaxCellsPerAxis cells per
  // axis whatever it is.
  void Build(const std::vector<glm::dvec3>& center, const std::vector<double>& radius,
             const std::vector<uint8_t>& indexed, double cell_hint);
  // Appends, sorted and without repeats, every indexed texel whose ball
  // meets the box [lo, hi] (and some whose ball only meets its cells).
  void Query(const glm::dvec3& lo, const glm::dvec3& hi, std::vector<uint32_t>& out) const;
  size_t cell_count() const { return cell_begin_.empty() ? 0 : cell_begin_.size() - 1; }

  static constexpr int kMaxCellsPerAxis = 128;
  // The cells' lists hold at most this many entries per indexed ball on
  // average (the grid grows coarser until they do): with the cells' offsets
  // and their cursor while built, the index holds at most kMaxBytesPerBall
  // a ball plus CellBytesAtMost.
  static constexpr uint64_t kMostEntriesPerBall = 8;
  static constexpr uint64_t kMaxBytesPerBall = 4 * kMostEntriesPerBall;
  // For balls of patches on surfaces within a box of `extent` (a ball
  // reaches past its patch's box by less than the box's longest side).
  static uint64_t CellBytesAtMost(const glm::dvec3& extent, double cell_hint);

 private:
  glm::ivec3 CellOf(const glm::dvec3& p) const;
  size_t Linear(const glm::ivec3& c) const {
    return (static_cast<size_t>(c.z) * dims_.y + static_cast<size_t>(c.y)) * dims_.x + static_cast<size_t>(c.x);
  }

  glm::dvec3 origin_{0.0};
  double cell_ = 1.0;
  size_t texel_count_ = 0;
  glm::ivec3 dims_{0};
  // Texels per cell: [cell_begin_[c], cell_begin_[c + 1]) of cell_texels_.
  std::vector<uint32_t> cell_begin_;
  std::vector<uint32_t> cell_texels_;
};

}  // namespace visq::obscurance
