// A bounding-volume hierarchy over boxes (private to lib/exact/): the
// occluders of one tree, or the triangles of a whole scene.
#pragma once

#include <algorithm>
#include <bit>
#include <cstdint>
#include <limits>
#include <utility>
#include <vector>

#include <glm/glm.hpp>

#include "common/check.h"

namespace visq::exact::detail {

// A bounding-volume hierarchy over the occluders' boxes (far and near), so
// that a query visits the occluders near its pyramid instead of all of them
// (a receiver tile's tree holds hundreds, a point's pyramid meets a few
// dozen; docs/exact-method-notes.md). Built once per tree; read-only afterwards.
class OccluderIndex {
 public:
  // The items' own boxes are not kept (48 bytes each; Collect needs only
  // the nodes', and CountUpTo asks the caller about each item).
  //
  // box_of(i) gives item i's box as a pair (lo, hi). The items are put in
  // the Morton order of their boxes' centres (on cubic cells over the
  // centres' box), and every node splits its range of that order, with its
  // box the union of its children's: a split that costs a sort once instead
  // of a partition a level. On a 382K-triangle room the halving at each
  // level's median along the node's widest axis cost twice the tree's
  // queries (docs/exact-method-notes.md).
  //
  // With full_leaves (the scene's index, where memory rules), every split
  // gives its lower half a whole number of full leaves (kLeafSize x a power
  // of two), so all leaves but one per level hold kLeafSize items:
  // 2 / kLeafSize nodes an item whatever the count. Halving at the median
  // instead left between kLeafSize / 2 and kLeafSize items a leaf, as the
  // count falls: the scene's index of 20M triangles held 27 bytes of nodes a
  // triangle where 66K held 17.
  //
  // Without (a tree's occluders, where queries rule), a node splits where
  // the highest bit in which its first and last codes differ turns on: a
  // spatial median, as in Karras's LBVH (a count median where the codes are
  // equal). Nodes then follow space rather than counts: Sponza's queries
  // took 8 % fewer instructions than with count halving, for 2 more bytes
  // of nodes an occluder; a binned SAH build saved 1 % more and cost nine
  // times the build on veach-ajar's 382K occluders.
  template <typename BoxOf>
  void Build(uint32_t count, const BoxOf& box_of, bool full_leaves = false) {
    nodes_.clear();
    order_.clear();
    if (count == 0) {
      nodes_.shrink_to_fit();
      order_.shrink_to_fit();
      return;
    }
    // box_of is asked twice (for the centres' box, then for the codes)
    // rather than keeping every box twice: a large room's boxes are tens of
    // megabytes, and fresh memory costs its page faults.
    glm::dvec3 centre_lo(std::numeric_limits<double>::infinity()), centre_hi(-std::numeric_limits<double>::infinity());
    for (uint32_t i = 0; i < count; ++i) {
      const auto [lo, hi] = box_of(i);
      centre_lo = glm::min(centre_lo, lo + hi);
      centre_hi = glm::max(centre_hi, lo + hi);
    }
    const glm::dvec3 extent = centre_hi - centre_lo;
    const double largest = std::max({extent.x, extent.y, extent.z});
    // The cell of a centre coordinate: its place in [0, 1] across the
    // largest extent (a ratio, so a subnormal extent cannot overflow it),
    // then scaled; anything not a number in [0, 1] goes to an end.
    const auto cell = [&](double offset) {
      double t = largest > 0.0 ? offset / largest : 0.0;
      if (!(t >= 0.0)) t = 0.0;
      if (!(t <= 1.0)) t = 1.0;
      return static_cast<uint32_t>(t * (kMortonCells - 1));
    };
    std::vector<std::pair<uint64_t, uint32_t>> keys(count);
    for (uint32_t i = 0; i < count; ++i) {
      const auto [lo, hi] = box_of(i);
      const glm::dvec3 offset = (lo + hi) - centre_lo;
      keys[i] = {Morton(cell(offset.x), cell(offset.y), cell(offset.z)), i};
    }
    std::sort(keys.begin(), keys.end());
    order_.resize(count);
    std::vector<Box> boxes(count);
    for (uint32_t i = 0; i < count; ++i) {
      order_[i] = keys[i].second;
      boxes[i] = box_of(order_[i]);
    }
    if (!full_leaves) {
      // At most 2 x count nodes, however the codes fall.
      std::vector<uint64_t> codes(count);
      for (uint32_t i = 0; i < count; ++i) codes[i] = keys[i].first;
      keys = {};
      nodes_.reserve(2 * static_cast<size_t>(count) + 1);
      nodes_.emplace_back();
      BuildSpatial(boxes, codes, 0, 0, count);
      nodes_.shrink_to_fit();
      return;
    }
    keys = {};
    nodes_.reserve(NodeCount(count));
    nodes_.emplace_back();
    BuildFullLeaves(boxes, 0, 0, count);
    VISQ_DCHECK_EQ(nodes_.size(), nodes_.capacity());
  }

  // Appends the occluders whose boxes `box_misses` does not rule out.
  template <typename BoxMisses>
  void Collect(const BoxMisses& box_misses, std::vector<uint32_t>* out) const {
    if (nodes_.empty()) return;
    uint32_t stack[128];
    int top = 0;
    stack[top++] = 0;
    while (top > 0) {
      const Node& node = nodes_[stack[--top]];
      if (box_misses(node.lo, node.hi)) continue;
      if (node.left == kLeaf) {
        for (uint32_t i = node.begin; i < node.end; ++i) out->push_back(order_[i]);
      } else {
        stack[top++] = node.left;
        stack[top++] = node.left + 1;
      }
    }
  }

  // How many items pass `item_misses(i) == false` among those whose nodes
  // `box_misses` does not rule out, counting no further than `limit`.
  template <typename BoxMisses, typename ItemMisses>
  size_t CountUpTo(const BoxMisses& box_misses, const ItemMisses& item_misses, size_t limit) const {
    if (nodes_.empty()) return 0;
    uint32_t stack[128];
    int top = 0;
    stack[top++] = 0;
    size_t count = 0;
    while (top > 0 && count < limit) {
      const Node& node = nodes_[stack[--top]];
      if (box_misses(node.lo, node.hi)) continue;
      if (node.left == kLeaf) {
        for (uint32_t i = node.begin; i < node.end; ++i) count += item_misses(order_[i]) ? 0 : 1;
      } else {
        stack[top++] = node.left;
        stack[top++] = node.left + 1;
      }
    }
    return std::min(count, limit);
  }

  // The box around every item (the root's); a point box at the origin when
  // there are none.
  std::pair<glm::dvec3, glm::dvec3> Bounds() const {
    if (nodes_.empty()) return {glm::dvec3(0.0), glm::dvec3(0.0)};
    return {nodes_[0].lo, nodes_[0].hi};
  }

  size_t MemoryBytes() const {
    return order_.capacity() * 4 + nodes_.capacity() * sizeof(Node);
  }

 private:
  static constexpr uint32_t kLeaf = UINT32_MAX;
  static constexpr uint32_t kLeafSize = 8;
  struct Node {
    glm::dvec3 lo, hi;
    uint32_t begin, end;
    uint32_t left;  // children at left and left + 1, or kLeaf
  };

  using Box = std::pair<glm::dvec3, glm::dvec3>;

  // How many items a node of `count` gives its lower child.
  static uint32_t LowerHalf(uint32_t count) {
    // The least kLeafSize x 2^k that is at least half.
    uint32_t half = kLeafSize;
    while (2 * half < count) half *= 2;
    return half;
  }

  // The nodes BuildFullLeaves makes for `count` items (reserved up front: the
  // hierarchy of a large room is megabytes, grown and then shrunk it was
  // copied twice). A level's counts take few distinct values, so each is
  // counted once.
  static size_t NodeCount(uint32_t count) {
    std::vector<std::pair<uint32_t, size_t>> known;
    const auto count_of = [&](const auto& self, uint32_t n) -> size_t {
      if (n <= kLeafSize) return 1;
      for (const auto& [m, nodes] : known)
        if (m == n) return nodes;
      const uint32_t half = LowerHalf(n);
      const size_t nodes = 1 + self(self, half) + self(self, n - half);
      known.emplace_back(n, nodes);
      return nodes;
    };
    return count_of(count_of, count);
  }

  // 2^21 cells an axis: three axes' bits fill a 63-bit code.
  static constexpr double kMortonCells = 2097152.0;
  static uint64_t SpreadBits(uint32_t x) {
    uint64_t v = x & 0x1FFFFF;
    v = (v | v << 32) & 0x1F00000000FFFFull;
    v = (v | v << 16) & 0x1F0000FF0000FFull;
    v = (v | v << 8) & 0x100F00F00F00F00Full;
    v = (v | v << 4) & 0x10C30C30C30C30C3ull;
    v = (v | v << 2) & 0x1249249249249249ull;
    return v;
  }
  static uint64_t Morton(uint32_t x, uint32_t y, uint32_t z) {
    return SpreadBits(x) << 2 | SpreadBits(y) << 1 | SpreadBits(z);
  }

  void MakeLeaf(const std::vector<Box>& boxes, uint32_t id, uint32_t begin, uint32_t end) {
    glm::dvec3 lo(std::numeric_limits<double>::infinity()), hi(-std::numeric_limits<double>::infinity());
    for (uint32_t i = begin; i < end; ++i) {
      lo = glm::min(lo, boxes[i].first);
      hi = glm::max(hi, boxes[i].second);
    }
    nodes_[id] = Node{lo, hi, begin, end, kLeaf};
  }
  void JoinChildren(uint32_t id, uint32_t begin, uint32_t end, uint32_t left) {
    const Node& a = nodes_[left];
    const Node& b = nodes_[left + 1];
    nodes_[id] = Node{glm::min(a.lo, b.lo), glm::max(a.hi, b.hi), begin, end, left};
  }

  // Fills node `id` with the items [begin, end) of the order, whose boxes
  // `boxes` holds in that order; its children go to two new consecutive
  // slots. Depth stays under 64: each split halves.
  void BuildFullLeaves(const std::vector<Box>& boxes, uint32_t id, uint32_t begin, uint32_t end) {
    if (end - begin <= kLeafSize) {
      MakeLeaf(boxes, id, begin, end);
      return;
    }
    const uint32_t middle = begin + LowerHalf(end - begin);
    const uint32_t left = static_cast<uint32_t>(nodes_.size());
    nodes_.emplace_back();
    nodes_.emplace_back();
    BuildFullLeaves(boxes, left, begin, middle);
    BuildFullLeaves(boxes, left + 1, middle, end);
    JoinChildren(id, begin, end, left);
  }

  // Fills node `id` with the items [begin, end), split at their codes'
  // highest differing bit. Depth stays under 63 + 32: each bit split lowers
  // that bit, each count split halves.
  void BuildSpatial(const std::vector<Box>& boxes, const std::vector<uint64_t>& codes, uint32_t id, uint32_t begin,
                    uint32_t end) {
    if (end - begin <= kLeafSize) {
      MakeLeaf(boxes, id, begin, end);
      return;
    }
    uint32_t middle = begin + (end - begin) / 2;
    const uint64_t first = codes[begin], last = codes[end - 1];
    if (first != last) {
      // The first code with that bit set: both sides keep at least one.
      const int bit = 63 - std::countl_zero(first ^ last);
      const uint64_t split = last & (~uint64_t{0} << bit);
      middle = static_cast<uint32_t>(std::lower_bound(codes.begin() + begin, codes.begin() + end, split) -
                                     codes.begin());
    }
    const uint32_t left = static_cast<uint32_t>(nodes_.size());
    nodes_.emplace_back();
    nodes_.emplace_back();
    BuildSpatial(boxes, codes, left, begin, middle);
    BuildSpatial(boxes, codes, left + 1, middle, end);
    JoinChildren(id, begin, end, left);
  }

  std::vector<uint32_t> order_;
  std::vector<Node> nodes_;
};

}  // namespace visq::exact::detail
