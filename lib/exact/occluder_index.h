// A bounding-volume hierarchy over boxes (private to lib/exact/): the
// occluders of one tree, or the triangles of a whole scene.
#pragma once

#include <algorithm>
#include <cstdint>
#include <limits>
#include <utility>
#include <vector>

#include <glm/glm.hpp>

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
  // With full_leaves, every split gives its lower half a whole number of
  // full leaves (kLeafSize x a power of two), so all leaves but one per level
  // hold kLeafSize items: 2 / kLeafSize nodes an item whatever the count.
  // Halving at the median instead leaves between kLeafSize / 2 and
  // kLeafSize items a leaf, as the count falls: the scene's index of 20M
  // triangles held 27 bytes of nodes a triangle where 66K held 17.
  // Takes the boxes by value: they are freed when the build returns.
  void Build(std::vector<std::pair<glm::dvec3, glm::dvec3>> boxes, bool full_leaves = false) {
    order_.resize(boxes.size());
    for (uint32_t i = 0; i < order_.size(); ++i) order_[i] = i;
    nodes_.clear();
    if (boxes.empty()) return;
    nodes_.emplace_back();
    BuildNode(boxes, full_leaves, 0, 0, static_cast<uint32_t>(order_.size()));
    nodes_.shrink_to_fit();
  }

  // Appends the occluders whose boxes `box_misses` does not rule out.
  template <typename BoxMisses>
  void Collect(const BoxMisses& box_misses, std::vector<uint32_t>* out) const {
    if (nodes_.empty()) return;
    uint32_t stack[64];
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
    uint32_t stack[64];
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

  // Fills node `id` with the occluders order_[begin, end); its children go
  // to two new consecutive slots. Depth stays under 64: each split halves.
  void BuildNode(const std::vector<std::pair<glm::dvec3, glm::dvec3>>& boxes, bool full_leaves, uint32_t id,
                 uint32_t begin, uint32_t end) {
    glm::dvec3 lo(std::numeric_limits<double>::infinity()), hi(-std::numeric_limits<double>::infinity());
    glm::dvec3 centre_lo = lo, centre_hi = hi;
    for (uint32_t i = begin; i < end; ++i) {
      const auto& [box_lo, box_hi] = boxes[order_[i]];
      lo = glm::min(lo, box_lo);
      hi = glm::max(hi, box_hi);
      centre_lo = glm::min(centre_lo, box_lo + box_hi);
      centre_hi = glm::max(centre_hi, box_lo + box_hi);
    }
    nodes_[id] = Node{lo, hi, begin, end, kLeaf};
    if (end - begin <= kLeafSize) return;
    const glm::dvec3 spread = centre_hi - centre_lo;
    const int axis = spread.x >= spread.y && spread.x >= spread.z ? 0 : spread.y >= spread.z ? 1 : 2;
    uint32_t half = (end - begin) / 2;
    if (full_leaves) {
      // The lower part: the least kLeafSize x 2^k that is at least half.
      half = kLeafSize;
      while (2 * half < end - begin) half *= 2;
    }
    const uint32_t middle = begin + half;
    std::nth_element(order_.begin() + begin, order_.begin() + middle, order_.begin() + end, [&](uint32_t x, uint32_t y) {
      return boxes[x].first[axis] + boxes[x].second[axis] < boxes[y].first[axis] + boxes[y].second[axis];
    });
    const uint32_t left = static_cast<uint32_t>(nodes_.size());
    nodes_.emplace_back();
    nodes_.emplace_back();
    nodes_[id].left = left;
    BuildNode(boxes, full_leaves, left, begin, middle);
    BuildNode(boxes, full_leaves, left + 1, middle, end);
  }

  std::vector<uint32_t> order_;
  std::vector<Node> nodes_;
};

}  // namespace visq::exact::detail
