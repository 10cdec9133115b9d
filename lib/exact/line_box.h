// Line boxes (the lines through the query point that meet a convex set, as a
// box), and a uniform grid over the line boxes of a subtraction's fragments,
// so that an occluder's shadow is tested against the fragments near it
// rather than all of them (SubtractOccluders).
#ifndef VISQ_LIB_EXACT_LINE_BOX_H_
#define VISQ_LIB_EXACT_LINE_BOX_H_

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

#include "common/check.h"

namespace visq::exact::detail {

// An enclosure of the lines through the query point P that pass through a
// convex set, as a box in gnomonic coordinates: the direction d = x - P maps
// to (d[u] / d[k], d[v] / d[k]), the same point for d and -d, so every line
// through P is one point and the lines through a convex set whose directions
// all have d[k] of one strict sign are the convex hull of its vertices'
// images. Bounds are outward-rounded (interval arithmetic): two boxes that
// are apart certify that no line through P meets both sets.
struct LineBox {
  double lo[2], hi[2];
  bool Apart(const LineBox& o) const {
    return hi[0] < o.lo[0] || o.hi[0] < lo[0] || hi[1] < o.lo[1] || o.hi[1] < lo[1];
  }
};

// Seen through foliage, a penumbra point's light is left in about 1,450
// fragments while 9,700 candidates are tested against them: testing each
// candidate's shadow box against every fragment's box was 72 % of the
// foliage's time (docs/exact-method-notes.md). Here each cell lists the
// fragments whose boxes meet it.
//
// The grid only ever answers what the boxes answer: the cell of a
// coordinate is monotone in it (a difference and a product by a positive
// constant, rounded, then floor and clamp), so two boxes that meet share a
// cell, and every fragment it lists is then tested box against box. So
// "no fragment's box meets the shadow's" is the same verdict as the test of
// every fragment, and the fragments a shadow may cut are the same.
//
// Fragments are known by their index in the caller's vector, which keeps
// removed ones in place (dead) until the caller compacts it: indices stay
// valid, and the live ones keep their order.
class FragmentGrid {
 public:
  static constexpr int kSide = 32;

  // Starts over, over `bounds` (the union of the boxes to come; boxes
  // outside it are clamped into its border cells, which keeps the cells
  // monotone). False when the bounds are not finite.
  bool Reset(const LineBox& bounds) {
    cells_.resize(size_t{kSide} * kSide);
    for (std::vector<uint32_t>& cell : cells_) cell.clear();
    boxes_.clear();
    alive_.clear();
    seen_.clear();
    live_ = 0;
    union_ = EmptyBox();
    union_stale_ = false;
    for (int axis = 0; axis < 2; ++axis) {
      if (!std::isfinite(bounds.lo[axis]) || !std::isfinite(bounds.hi[axis])) return false;
      lo_[axis] = bounds.lo[axis];
      const double width = bounds.hi[axis] - bounds.lo[axis];
      const double scale = width > 0.0 ? kSide / width : 0.0;
      scale_[axis] = std::isfinite(scale) ? scale : 0.0;
    }
    return true;
  }

  // Lists fragment `index` (the next index: fragments are added in their
  // vector's order). False when its box is not finite.
  bool Add(uint32_t index, const LineBox& box) {
    VISQ_CHECK_EQ(size_t(index), boxes_.size());
    for (int axis = 0; axis < 2; ++axis) {
      if (!std::isfinite(box.lo[axis]) || !std::isfinite(box.hi[axis])) return false;
    }
    boxes_.push_back(box);
    for (int axis = 0; axis < 2; ++axis) {
      union_.lo[axis] = std::min(union_.lo[axis], box.lo[axis]);
      union_.hi[axis] = std::max(union_.hi[axis], box.hi[axis]);
    }
    alive_.push_back(1);
    seen_.push_back(0);
    ++live_;
    const CellRange r = Cells(box);
    for (int y = r.lo[1]; y <= r.hi[1]; ++y) {
      for (int x = r.lo[0]; x <= r.hi[0]; ++x) cells_[size_t(y) * kSide + x].push_back(index);
    }
    return true;
  }

  void Remove(uint32_t index) {
    VISQ_DCHECK_LT(size_t(index), alive_.size());
    VISQ_DCHECK(alive_[index] != 0);
    alive_[index] = 0;
    --live_;
    // The union shrinks only where this box held one of its sides.
    const LineBox& box = boxes_[index];
    for (int axis = 0; axis < 2; ++axis) {
      union_stale_ |= box.lo[axis] == union_.lo[axis] || box.hi[axis] == union_.hi[axis];
    }
  }

  bool Alive(uint32_t index) const { return alive_[index] != 0; }
  size_t Live() const { return live_; }
  size_t Size() const { return boxes_.size(); }

  // Whether some live fragment's box meets `shadow` (not Apart).
  bool AnyMeets(const LineBox& shadow) {
    bool any = false;
    ForEachMeeting(shadow, [&](uint32_t) {
      any = true;
      return false;
    });
    return any;
  }

  // The live fragments whose boxes meet `shadow`, in increasing index.
  void Meeting(const LineBox& shadow, std::vector<uint32_t>* indices) {
    indices->clear();
    ForEachMeeting(shadow, [&](uint32_t index) {
      indices->push_back(index);
      return true;
    });
    std::sort(indices->begin(), indices->end());
  }

  // The box around the live fragments' boxes: kept as they come, and
  // taken again from them only after a removal of a box on its side (a
  // cut fragment's pieces lie inside it, so that is rare).
  const LineBox& Union() {
    if (!union_stale_) return union_;
    union_ = EmptyBox();
    for (size_t i = 0; i < boxes_.size(); ++i) {
      if (alive_[i] == 0) continue;
      for (int axis = 0; axis < 2; ++axis) {
        union_.lo[axis] = std::min(union_.lo[axis], boxes_[i].lo[axis]);
        union_.hi[axis] = std::max(union_.hi[axis], boxes_[i].hi[axis]);
      }
    }
    union_stale_ = false;
    return union_;
  }

 private:
  static LineBox EmptyBox() {
    LineBox box;
    box.lo[0] = box.lo[1] = std::numeric_limits<double>::infinity();
    box.hi[0] = box.hi[1] = -std::numeric_limits<double>::infinity();
    return box;
  }

  struct CellRange {
    int lo[2], hi[2];
  };

  int Cell(int axis, double x) const {
    const double t = std::floor((x - lo_[axis]) * scale_[axis]);
    // NaN (an infinite shadow bound times a zero scale) goes to the whole
    // range: the caller clamps lo to 0 and hi to the last cell.
    if (!(t >= 0.0)) return t < 0.0 ? 0 : -1;
    return t >= kSide - 1 ? kSide - 1 : static_cast<int>(t);
  }

  CellRange Cells(const LineBox& box) const {
    CellRange r;
    for (int axis = 0; axis < 2; ++axis) {
      r.lo[axis] = std::max(Cell(axis, box.lo[axis]), 0);
      const int hi = Cell(axis, box.hi[axis]);
      r.hi[axis] = hi < 0 ? kSide - 1 : hi;
    }
    return r;
  }

  // Calls visit(index) once for each live fragment whose box meets
  // `shadow`, until it returns false; drops dead entries from the cells it
  // reads.
  template <typename Visit>
  void ForEachMeeting(const LineBox& shadow, const Visit& visit) {
    if (++stamp_ == 0) {
      std::fill(seen_.begin(), seen_.end(), 0);
      stamp_ = 1;
    }
    const CellRange r = Cells(shadow);
    for (int y = r.lo[1]; y <= r.hi[1]; ++y) {
      for (int x = r.lo[0]; x <= r.hi[0]; ++x) {
        std::vector<uint32_t>& cell = cells_[size_t(y) * kSide + x];
        size_t kept = 0;
        bool go_on = true;
        for (size_t k = 0; k < cell.size(); ++k) {
          const uint32_t index = cell[k];
          if (alive_[index] == 0) continue;
          cell[kept++] = index;
          if (!go_on || seen_[index] == stamp_) continue;
          seen_[index] = stamp_;
          if (!boxes_[index].Apart(shadow)) go_on = visit(index);
        }
        cell.resize(kept);
        if (!go_on) return;
      }
    }
  }

  double lo_[2] = {0.0, 0.0}, scale_[2] = {0.0, 0.0};
  std::vector<std::vector<uint32_t>> cells_;
  std::vector<LineBox> boxes_;
  std::vector<uint8_t> alive_;
  std::vector<uint32_t> seen_;  // the stamp of the last walk that met each fragment
  uint32_t stamp_ = 0;
  size_t live_ = 0;
  LineBox union_ = EmptyBox();
  bool union_stale_ = false;
};

}  // namespace visq::exact::detail

#endif  // VISQ_LIB_EXACT_LINE_BOX_H_
