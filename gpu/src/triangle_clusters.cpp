#include "visq/gpu/triangle_clusters.h"

#include <algorithm>
#include <array>
#include <bit>
#include <cmath>
#include <limits>
#include <utility>

#include "common/parallel.h"

namespace visq::gpu {

namespace {

constexpr int kBitsPerAxis = 10;  // a 30-bit Morton code
constexpr size_t kGrain = size_t{1} << 16;  // triangles a parallel chunk

// The low 10 bits of v, two zero bits after each.
uint32_t Spread(uint32_t v) {
  v &= 0x3ffu;
  v = (v | (v << 16)) & 0x030000ffu;
  v = (v | (v << 8)) & 0x0300f00fu;
  v = (v | (v << 4)) & 0x030c30c3u;
  v = (v | (v << 2)) & 0x09249249u;
  return v;
}

bool Finite(const glm::vec3& p) { return std::isfinite(p.x) && std::isfinite(p.y) && std::isfinite(p.z); }

// Where Morton codes are taken: the bounds of a set of centroids.
struct CentroidBox {
  glm::dvec3 origin{0.0};
  glm::dvec3 extent{1.0};
  // A 30-bit code; 0 for a centroid that is not finite. In double: the
  // extent of float centroids never overflows there.
  uint32_t Code(const glm::vec3& c) const {
    if (!Finite(c)) return 0;
    constexpr double kCells = double(1 << kBitsPerAxis);
    const glm::dvec3 q =
        glm::clamp((glm::dvec3(c) - origin) / extent * kCells, glm::dvec3(0.0), glm::dvec3(kCells - 1));
    return Spread(uint32_t(q.x)) << 2 | Spread(uint32_t(q.y)) << 1 | Spread(uint32_t(q.z));
  }
};

// The box of the finite centroids of triangles triangle_at(0 .. count - 1).
template <typename TriangleAt, typename Centroid>
CentroidBox CentroidBounds(size_t count, TriangleAt triangle_at, Centroid centroid) {
  const size_t chunks = (count + kGrain - 1) / kGrain;
  std::vector<glm::vec3> chunk_lo(chunks, glm::vec3(std::numeric_limits<float>::max()));
  std::vector<glm::vec3> chunk_hi(chunks, glm::vec3(std::numeric_limits<float>::lowest()));
  ParallelFor(count, kGrain, [&](size_t begin, size_t end) {
    glm::vec3& lo = chunk_lo[begin / kGrain];
    glm::vec3& hi = chunk_hi[begin / kGrain];
    for (size_t k = begin; k < end; ++k) {
      const glm::vec3 c = centroid(triangle_at(k));
      if (!Finite(c)) continue;
      lo = glm::min(lo, c);
      hi = glm::max(hi, c);
    }
  });
  glm::vec3 lo(std::numeric_limits<float>::max()), hi(std::numeric_limits<float>::lowest());
  for (size_t k = 0; k < chunks; ++k) {
    lo = glm::min(lo, chunk_lo[k]);
    hi = glm::max(hi, chunk_hi[k]);
  }
  CentroidBox box;
  box.origin = glm::dvec3(lo);
  box.extent = glm::max(glm::dvec3(hi) - box.origin, glm::dvec3(1e-300));
  return box;
}

// Stable least-significant-digit radix sort of (code << 32 | triangle) by
// the code: equal codes keep the scene's order, so a build is reproducible.
void RadixSortByCode(std::vector<uint64_t>& keys) {
  constexpr int kDigitBits = 10;
  constexpr uint64_t kDigits = uint64_t{1} << kDigitBits;
  std::vector<uint64_t> sorted(keys.size());
  for (int shift = 32; shift < 32 + 3 * kBitsPerAxis; shift += kDigitBits) {
    std::array<size_t, kDigits> start{};
    for (const uint64_t k : keys) ++start[(k >> shift) & (kDigits - 1)];
    size_t sum = 0;
    for (size_t& s : start) sum += std::exchange(s, sum);
    for (const uint64_t k : keys) sorted[start[(k >> shift) & (kDigits - 1)]++] = k;
    keys.swap(sorted);
  }
}

}  // namespace

TriangleClusters TriangleClusters::Build(std::span<const glm::vec3> corners, std::vector<uint32_t>& order) {
  TriangleClusters out;
  const size_t triangles = corners.size() / 3;
  order.resize(triangles);
  if (triangles == 0) return out;

  // Morton codes of the centroids over the centroids' bounds; a triangle
  // with a corner that is not finite gets code 0 (its cluster is never culled).
  auto centroid = [&corners](size_t t) { return (corners[3 * t] + corners[3 * t + 1] + corners[3 * t + 2]) / 3.0f; };
  std::vector<uint64_t> keys(triangles);
  {
    const CentroidBox box = CentroidBounds(triangles, [](size_t t) { return t; }, centroid);
    ParallelFor(triangles, kGrain, [&](size_t begin, size_t end) {
      for (size_t t = begin; t < end; ++t) keys[t] = uint64_t{box.Code(centroid(t))} << 32 | t;
    });
  }
  RadixSortByCode(keys);
  std::vector<uint64_t> codes(triangles);
  for (size_t i = 0; i < triangles; ++i) {
    codes[i] = keys[i] & ~uint64_t{0xffffffff};
    order[i] = static_cast<uint32_t>(keys[i]);
  }
  std::vector<uint64_t>().swap(keys);

  // A cell holding more than a cluster, in a scene whose extent a few far
  // triangles set (a sky dome around a level), is coded again over its own
  // centroids' bounds, into the low half of the code: else the level would
  // sit in a handful of cells and its clusters would cut across it.
  for (size_t i = 0; i < triangles;) {
    size_t j = i + 1;
    while (j < triangles && codes[j] == codes[i]) ++j;
    if (j - i > kMaxClusterTriangles) {
      const CentroidBox box = CentroidBounds(j - i, [&](size_t k) { return order[i + k]; }, centroid);
      std::vector<uint64_t> fine(j - i);
      for (size_t k = i; k < j; ++k) fine[k - i] = uint64_t{box.Code(centroid(order[k]))} << 32 | order[k];
      std::sort(fine.begin(), fine.end());
      for (size_t k = i; k < j; ++k) {
        codes[k] |= fine[k - i] >> 32;
        order[k] = static_cast<uint32_t>(fine[k - i]);
      }
    }
    i = j;
  }

  // The tree: ranges split at the highest differing Morton bit (in the
  // middle where every code is equal) until each is a cluster.
  out.nodes_.reserve(2 * (triangles / (kMaxClusterTriangles / 2) + 1));
  std::vector<uint32_t> leaves;
  auto split = [&](auto& self, uint32_t first, uint32_t last) -> uint32_t {
    const auto index = static_cast<uint32_t>(out.nodes_.size());
    out.nodes_.push_back({});
    out.nodes_[index].first = first;
    out.nodes_[index].count = last - first;
    if (last - first <= kMaxClusterTriangles) {
      leaves.push_back(index);
      return index;
    }
    uint32_t middle = first + (last - first) / 2;
    const uint64_t differ = codes[first] ^ codes[last - 1];
    if (differ != 0) {
      const int bit = 63 - std::countl_zero(differ);
      middle = static_cast<uint32_t>(
          std::partition_point(codes.begin() + first, codes.begin() + last,
                               [bit](uint64_t code) { return ((code >> bit) & 1u) == 0; }) -
          codes.begin());
    }
    self(self, first, middle);
    out.nodes_[index].second_child = self(self, middle, last);
    return index;
  };
  split(split, 0, static_cast<uint32_t>(triangles));
  out.clusters_ = leaves.size();

  // The clusters' boxes from their corners (an unbounded box for a corner
  // that is not finite), read in the scene's order: the corners are read
  // once, in sequence, while the boxes written stay in cache (gathering
  // corners in cluster order misses the cache at every triangle of a scene
  // not already in spatial order).
  std::vector<uint32_t> leaf_of(triangles);
  ParallelFor(leaves.size(), 1024, [&](size_t begin, size_t end) {
    for (size_t k = begin; k < end; ++k) {
      const Node& node = out.nodes_[leaves[k]];
      for (uint32_t i = node.first; i < node.first + node.count; ++i) leaf_of[order[i]] = leaves[k];
    }
  });
  for (const uint32_t leaf : leaves) {
    out.nodes_[leaf].lo = glm::vec3(std::numeric_limits<float>::infinity());
    out.nodes_[leaf].hi = glm::vec3(-std::numeric_limits<float>::infinity());
  }
  std::vector<uint8_t> unbounded(out.nodes_.size(), 0);
  for (size_t t = 0; t < triangles; ++t) {
    Node& node = out.nodes_[leaf_of[t]];
    for (int c = 0; c < 3; ++c) {
      const glm::vec3& p = corners[3 * t + c];
      if (!Finite(p)) unbounded[leaf_of[t]] = 1;
      node.lo = glm::min(node.lo, p);
      node.hi = glm::max(node.hi, p);
    }
  }
  for (const uint32_t leaf : leaves)
    if (unbounded[leaf]) {
      out.nodes_[leaf].lo = glm::vec3(-std::numeric_limits<float>::infinity());
      out.nodes_[leaf].hi = glm::vec3(std::numeric_limits<float>::infinity());
    }
  for (size_t index = out.nodes_.size(); index-- > 0;) {
    Node& node = out.nodes_[index];
    if (node.second_child == 0) continue;
    const Node &left = out.nodes_[index + 1], &right = out.nodes_[node.second_child];
    node.lo = glm::min(left.lo, right.lo);
    node.hi = glm::max(left.hi, right.hi);
  }
  out.nodes_.shrink_to_fit();
  return out;
}

// Keeps the clusters for which no plane k has most < -slack(k, magnitude):
// `magnitude` is |n| . max|x| + |w| over the node's box.
template <typename Plane, typename Slack>
std::vector<TriangleClusters::Range> CullNodes(const std::vector<TriangleClusters::Node>& nodes,
                                               std::span<const Plane> planes, Slack slack) {
  std::vector<TriangleClusters::Range> ranges;
  if (nodes.empty()) return ranges;
  auto emit = [&ranges](const TriangleClusters::Node& node) {
    if (!ranges.empty() && ranges.back().first + ranges.back().count == node.first)
      ranges.back().count += node.count;
    else
      ranges.push_back({node.first, node.count});
  };
  std::vector<uint32_t> stack = {0};
  while (!stack.empty()) {
    const TriangleClusters::Node& node = nodes[stack.back()];
    const uint32_t index = stack.back();
    stack.pop_back();
    bool outside = false, inside = true;
    for (size_t k = 0; k < planes.size(); ++k) {
      const Plane& plane = planes[k];
      double most = plane.w, least = plane.w, magnitude = std::abs(double(plane.w));
      for (int axis = 0; axis < 3; ++axis) {
        const double a = plane[axis], lo = node.lo[axis], hi = node.hi[axis];
        most += a * (a >= 0 ? hi : lo);
        least += a * (a >= 0 ? lo : hi);
        magnitude += std::abs(a) * std::max(std::abs(lo), std::abs(hi));
      }
      // NaN (an unbounded box) compares false: kept, and looked into.
      if (most < -slack(k, magnitude)) { outside = true; break; }
      inside = inside && least >= 0.0;
    }
    if (outside) continue;
    if (inside || node.second_child == 0) {
      emit(node);
      continue;
    }
    stack.push_back(node.second_child);
    stack.push_back(index + 1);
  }
  return ranges;
}

std::vector<TriangleClusters::Range> TriangleClusters::Cull(std::span<const glm::vec4> planes) const {
  // The float32 test n . x + w < 0 errs by at most a few units in the last
  // place of |n| . |x| + |w| (4 products and sums: under 2.4e-7 of it); a
  // cluster is dropped only when its box is outside by 1e-6 of that.
  constexpr double kFloatMargin = 1e-6;
  return CullNodes(nodes_, planes, [](size_t, double magnitude) { return kFloatMargin * magnitude; });
}

std::vector<TriangleClusters::Range> TriangleClusters::Cull(std::span<const glm::dvec4> planes,
                                                            std::span<const double> slack) const {
  return CullNodes(nodes_, planes, [slack](size_t k, double) { return slack[k]; });
}

}  // namespace visq::gpu
