#include "visq/gpu/triangle_clusters.h"

#include <algorithm>
#include <array>
#include <bit>
#include <cmath>
#include <limits>
#include <utility>

namespace visq::gpu {

namespace {

constexpr int kBitsPerAxis = 10;  // a 30-bit Morton code

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

// Stable least-significant-digit radix sort of `ids` by `keys` (both
// permuted): equal codes keep the scene's order, so a build is reproducible.
void RadixSort(std::vector<uint32_t>& keys, std::vector<uint32_t>& ids) {
  constexpr int kDigitBits = 10;
  constexpr uint32_t kDigits = 1u << kDigitBits;
  std::vector<uint32_t> keys_out(keys.size()), ids_out(ids.size());
  for (int shift = 0; shift < 3 * kBitsPerAxis; shift += kDigitBits) {
    std::array<uint32_t, kDigits> start{};
    for (const uint32_t k : keys) ++start[(k >> shift) & (kDigits - 1)];
    uint32_t sum = 0;
    for (uint32_t& s : start) sum += std::exchange(s, sum);
    for (size_t i = 0; i < keys.size(); ++i) {
      const uint32_t at = start[(keys[i] >> shift) & (kDigits - 1)]++;
      keys_out[at] = keys[i];
      ids_out[at] = ids[i];
    }
    keys.swap(keys_out);
    ids.swap(ids_out);
  }
}

}  // namespace

TriangleClusters TriangleClusters::Build(std::span<const glm::vec3> corners, std::vector<uint32_t>& order) {
  TriangleClusters out;
  const size_t triangles = corners.size() / 3;
  order.resize(triangles);
  for (size_t t = 0; t < triangles; ++t) order[t] = static_cast<uint32_t>(t);
  if (triangles == 0) return out;

  // Morton codes of the centroids over the centroids' bounds; a triangle
  // with a corner that is not finite gets code 0 (its cluster is never culled).
  std::vector<glm::vec3> centroids(triangles);
  glm::vec3 lo(std::numeric_limits<float>::max()), hi(std::numeric_limits<float>::lowest());
  for (size_t t = 0; t < triangles; ++t) {
    centroids[t] = (corners[3 * t] + corners[3 * t + 1] + corners[3 * t + 2]) / 3.0f;
    if (!Finite(centroids[t])) continue;
    lo = glm::min(lo, centroids[t]);
    hi = glm::max(hi, centroids[t]);
  }
  const glm::vec3 extent = glm::max(hi - lo, glm::vec3(std::numeric_limits<float>::min()));
  constexpr float kCells = float(1 << kBitsPerAxis);
  std::vector<uint32_t> codes(triangles, 0);
  for (size_t t = 0; t < triangles; ++t) {
    if (!Finite(centroids[t])) continue;
    const glm::vec3 q = glm::clamp((centroids[t] - lo) / extent * kCells, glm::vec3(0.0f), glm::vec3(kCells - 1.0f));
    codes[t] = Spread(uint32_t(q.x)) << 2 | Spread(uint32_t(q.y)) << 1 | Spread(uint32_t(q.z));
  }
  std::vector<glm::vec3>().swap(centroids);
  RadixSort(codes, order);

  // Split ranges at the highest differing Morton bit (in the middle where
  // every code is equal) until each is a cluster; boxes from the leaves up.
  out.nodes_.reserve(2 * (triangles / (kMaxClusterTriangles / 2) + 1));
  auto build = [&](auto& self, uint32_t first, uint32_t last) -> uint32_t {
    const auto index = static_cast<uint32_t>(out.nodes_.size());
    out.nodes_.push_back({});
    out.nodes_[index].first = first;
    out.nodes_[index].count = last - first;
    if (last - first <= kMaxClusterTriangles) {
      glm::vec3 box_lo(std::numeric_limits<float>::infinity()), box_hi(-std::numeric_limits<float>::infinity());
      bool finite = true;
      for (uint32_t i = first; i < last; ++i)
        for (int c = 0; c < 3; ++c) {
          const glm::vec3& p = corners[3 * size_t(order[i]) + c];
          finite = finite && Finite(p);
          box_lo = glm::min(box_lo, p);
          box_hi = glm::max(box_hi, p);
        }
      if (!finite) {
        box_lo = glm::vec3(-std::numeric_limits<float>::infinity());
        box_hi = glm::vec3(std::numeric_limits<float>::infinity());
      }
      out.nodes_[index].lo = box_lo;
      out.nodes_[index].hi = box_hi;
      ++out.clusters_;
      return index;
    }
    uint32_t split = first + (last - first) / 2;
    const uint32_t differ = codes[first] ^ codes[last - 1];
    if (differ != 0) {
      const int bit = 31 - std::countl_zero(differ);
      split = static_cast<uint32_t>(
          std::partition_point(codes.begin() + first, codes.begin() + last,
                               [bit](uint32_t code) { return ((code >> bit) & 1u) == 0; }) -
          codes.begin());
    }
    const uint32_t left = self(self, first, split);
    const uint32_t right = self(self, split, last);
    out.nodes_[index].second_child = right;
    out.nodes_[index].lo = glm::min(out.nodes_[left].lo, out.nodes_[right].lo);
    out.nodes_[index].hi = glm::max(out.nodes_[left].hi, out.nodes_[right].hi);
    return index;
  };
  build(build, 0, static_cast<uint32_t>(triangles));
  out.nodes_.shrink_to_fit();
  return out;
}

std::vector<TriangleClusters::Range> TriangleClusters::Cull(std::span<const glm::vec4> planes) const {
  std::vector<Range> ranges;
  if (nodes_.empty()) return ranges;
  auto emit = [&ranges](const Node& node) {
    if (!ranges.empty() && ranges.back().first + ranges.back().count == node.first)
      ranges.back().count += node.count;
    else
      ranges.push_back({node.first, node.count});
  };
  // The float32 test n . x + w < 0 errs by at most a few units in the last
  // place of |n| . |x| + |w| (4 products and sums: under 2.4e-7 of it); a
  // cluster is dropped only when its box is outside by 1e-6 of that.
  constexpr double kFloatMargin = 1e-6;
  std::vector<uint32_t> stack = {0};
  while (!stack.empty()) {
    const Node& node = nodes_[stack.back()];
    const uint32_t index = stack.back();
    stack.pop_back();
    bool outside = false, inside = true;
    for (const glm::vec4& plane : planes) {
      double most = plane.w, least = plane.w, magnitude = std::abs(double(plane.w));
      for (int axis = 0; axis < 3; ++axis) {
        const double a = plane[axis], lo = node.lo[axis], hi = node.hi[axis];
        most += a * (a >= 0 ? hi : lo);
        least += a * (a >= 0 ? lo : hi);
        magnitude += std::abs(a) * std::max(std::abs(lo), std::abs(hi));
      }
      // NaN (an unbounded box) compares false: kept, and looked into.
      if (most < -kFloatMargin * magnitude) { outside = true; break; }
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

}  // namespace visq::gpu
