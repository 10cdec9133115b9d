// A bounding volume hierarchy over a scene's triangles laid out for a GPU
// traversal (gpu/rays): built by Embree's own SAH builder (rtcBuildBVH)
// through its node callbacks, then flattened depth first into one array of
// 32-byte nodes and one array of triangle corners in leaf order. The
// triangles are flattened (placements applied) and stored as float32
// relative to the frame EmbreeScene would choose (the bounds' centre and
// largest side), so that a FloatSegment means the same to both tracers.
#pragma once

#include <cstddef>
#include <cstdint>
#include <optional>
#include <vector>

#include <glm/glm.hpp>

#include "common/status.h"
#include "common/stop_token.h"
#include "scene/scene.h"

namespace visq::raycast {

// Two vec4s in std430. An inner node's first child follows it; `right` is
// the index of its second. A leaf (count > 0) holds triangles [first,
// first + count) of FlatBvh::corners / 3.
struct FlatBvhNode {
  glm::vec3 lower{0.0f};
  uint32_t right_or_first = 0;
  glm::vec3 upper{0.0f};
  uint32_t count = 0;  // 0: an inner node
};
static_assert(sizeof(FlatBvhNode) == 32);

// 16 bytes in std430. The first of a triangle's three corners names its
// scene triangle (an ignored triangle is recognised by it); the others', 0.
struct FlatBvhCorner {
  glm::vec3 position{0.0f};
  uint32_t triangle = 0;
};
static_assert(sizeof(FlatBvhCorner) == 16);

struct FlatBvh {
  std::vector<FlatBvhNode> nodes;  // empty for a scene without triangles
  // Three per triangle in leaf order, frame-relative.
  std::vector<FlatBvhCorner> corners;
  glm::dvec3 origin{0.0};
  double extent = 0.0;  // the largest side of the scene's bounds
  uint32_t depth = 0;   // levels below the root, for the traversal's stack

  size_t bytes() const { return nodes.size() * sizeof(FlatBvhNode) + corners.size() * sizeof(FlatBvhCorner); }
  size_t triangle_count() const { return corners.size() / 3; }
};

struct FlatBvhOptions {
  std::optional<glm::dvec3> origin;  // default: the scene bounds' centre, as EmbreeScene
  StopToken stop;                    // asked by the builder's progress callback
};

// The deepest tree a traversal's stack must hold (gpu/rays' shaders keep a
// stack of this many entries); the builder is held to it.
inline constexpr uint32_t kMaxFlatBvhDepth = 48;

[[nodiscard]] StatusOr<FlatBvh> BuildFlatBvh(const Scene& scene, const FlatBvhOptions& options = {});

}  // namespace visq::raycast
