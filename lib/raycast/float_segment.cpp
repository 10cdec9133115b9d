#include "raycast/float_segment.h"

#include <algorithm>
#include <cmath>
#include <limits>

namespace visq::raycast {

namespace {
double LargestCoordinate(const glm::dvec3& v) { return std::max({std::abs(v.x), std::abs(v.y), std::abs(v.z)}); }
}  // namespace

FloatSegment ToFloatSegment(const Segment& segment, const glm::dvec3& frame_origin, double extent) {
  const glm::dvec3 p = segment.p - frame_origin;
  const glm::dvec3 q = segment.q - frame_origin;
  const glm::dvec3 d = segment.q - segment.p;
  const double length = glm::length(d);
  // The lower end (the ray's origin) is offset by what rounding p alone
  // leaves; the upper end's offset covers the rounding of t along the whole
  // segment as well, so it takes the larger of both ends' magnitudes.
  const double near_magnitude = std::max(LargestCoordinate(p), extent * 0x1p-3);
  const double far_magnitude = std::max({LargestCoordinate(p), LargestCoordinate(q), extent * 0x1p-3});
  const double t_near = length > 0.0 ? 0x1p-17 * near_magnitude / length : 0.0;
  const double t_far = 1.0 - (length > 0.0 ? 0x1p-17 * far_magnitude / length : 1.0);
  FloatSegment out;
  out.origin = glm::vec3(p);
  out.direction = glm::vec3(d);
  out.t_near = static_cast<float>(t_near);
  out.t_far = static_cast<float>(t_far);
  if (!(length > 0.0) || !(t_far > t_near) || !(out.t_far > out.t_near)) {
    out.t_near = 1.0f;
    out.t_far = 0.0f;
  }
  return out;
}

FloatSegment ToFloatRay(const Ray& ray, const glm::dvec3& frame_origin, double extent) {
  const glm::dvec3 o = ray.origin - frame_origin;
  const double length = glm::length(ray.direction);
  const double magnitude = std::max(LargestCoordinate(o), extent * 0x1p-3);
  const double t_near = length > 0.0 ? 0x1p-17 * magnitude / length : 0.0;
  const double t_far = std::min(std::isfinite(ray.tmax) ? ray.tmax : std::numeric_limits<double>::max(),
                                static_cast<double>(std::numeric_limits<float>::max()));
  FloatSegment out;
  out.origin = glm::vec3(o);
  out.direction = glm::vec3(ray.direction);
  out.t_near = static_cast<float>(t_near);
  out.t_far = static_cast<float>(t_far);
  if (!(length > 0.0) || !(t_far > t_near)) {
    out.t_near = 1.0f;
    out.t_far = 0.0f;
  }
  return out;
}

}  // namespace visq::raycast
