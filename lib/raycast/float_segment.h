// A segment as a float32 tracer sees it: the open segment (p, q) of
// raycast::Segment moved into an upload frame and rounded, with the
// interval [t_near, t_far] of p + t (q - p) that the endpoint offsets leave
// (EmbreeScene::Occluded documents the rule). Embree and the GPU ray method
// trace the same FloatSegment, so their bits differ only where float
// arithmetic ties on a triangle's edge.
#pragma once

#include <glm/glm.hpp>

#include "raycast/embree_scene.h"

namespace visq::raycast {

// Two vec4s in std430: (origin, t_near), (direction, t_far). An empty
// interval (a degenerate segment, or one shorter than its offsets) has
// t_near = 1 > t_far = 0, and nothing blocks it.
struct FloatSegment {
  glm::vec3 origin{0.0f};
  float t_near = 1.0f;
  glm::vec3 direction{0.0f};
  float t_far = 0.0f;
};
static_assert(sizeof(FloatSegment) == 32);

// `segment` in the frame at `frame_origin` whose stored geometry spans
// `extent` (the largest side of its bounds).
FloatSegment ToFloatSegment(const Segment& segment, const glm::dvec3& frame_origin, double extent);

// A ray for a closest hit (EmbreeScene::Intersect): t from the origin's
// offset to tmax (at most the largest float), along the ray's own direction.
FloatSegment ToFloatRay(const Ray& ray, const glm::dvec3& frame_origin, double extent);

}  // namespace visq::raycast
