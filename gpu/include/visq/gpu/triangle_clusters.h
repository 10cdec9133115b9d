// A bounding-volume hierarchy over clusters of a scene's triangles, so that a
// draw pays for the triangles near a query instead of the whole scene.
//
// The triangles are put in Morton order of their centroids (a cell holding
// more than a cluster coded again over its own bounds, so that a few far
// triangles do not squeeze the rest into a few cells) and split, the way a
// linear BVH is (Lauterbach et al. 2009), at the highest Morton bit that
// differs until a range holds at most kMaxClusterTriangles: each node
// covers one contiguous range of that order, so whatever survives a cull is
// a few index ranges of one element buffer (GpuScene keeps it on the GPU).
// Pure CPU and immutable once built: any thread may cull.
#pragma once

#include <cstdint>
#include <span>
#include <vector>

#include <glm/glm.hpp>

namespace visq::gpu {

class TriangleClusters {
 public:
  // Small enough that a cluster straddling a shaft's side wastes little,
  // large enough that the hierarchy costs about 1 byte a triangle and a cull
  // yields few draw ranges.
  static constexpr uint32_t kMaxClusterTriangles = 128;

  // A run of the cluster order: triangles order[first] .. order[first + count - 1].
  struct Range {
    uint32_t first = 0;
    uint32_t count = 0;
    bool operator==(const Range&) const = default;
  };

  TriangleClusters() = default;  // no triangles

  // `corners` holds 3 corners a triangle, as the GPU receives them. `order`
  // gets the triangles in cluster order (order[i] is a triangle id).
  static TriangleClusters Build(std::span<const glm::vec3> corners, std::vector<uint32_t>& order);

  // The ranges, ascending and merged where they touch, of every cluster that
  // is not wholly outside one of `planes` ((n, w), inside where n . x + w >= 0).
  // Conservative for a float32 evaluation of the same test: a triangle of a
  // dropped cluster has every corner evaluate below 0 in float, as the
  // geometry shaders' per-triangle test does. A corner that is not finite
  // keeps its cluster.
  std::vector<Range> Cull(std::span<const glm::vec4> planes) const;
  // The same with planes in double and, per plane, the slack by which a box
  // must be outside to be dropped (for corners the GPU places with a float
  // transform, whose rounding the caller knows).
  std::vector<Range> Cull(std::span<const glm::dvec4> planes, std::span<const double> slack) const;
  // The box of every corner.
  glm::vec3 lo() const { return nodes_.empty() ? glm::vec3(0.0f) : nodes_[0].lo; }
  glm::vec3 hi() const { return nodes_.empty() ? glm::vec3(0.0f) : nodes_[0].hi; }

  uint32_t triangle_count() const { return nodes_.empty() ? 0 : nodes_[0].count; }
  size_t node_count() const { return nodes_.size(); }
  size_t cluster_count() const { return clusters_; }
  size_t memory_bytes() const { return nodes_.capacity() * sizeof(Node); }

  // Depth-first layout: a node's first child follows it, `second_child`
  // names the other (0 for a cluster, a leaf).
  struct Node {
    glm::vec3 lo{0.0f};
    glm::vec3 hi{0.0f};
    uint32_t first = 0;
    uint32_t count = 0;
    uint32_t second_child = 0;
  };

 private:
  std::vector<Node> nodes_;
  size_t clusters_ = 0;
};

}  // namespace visq::gpu
