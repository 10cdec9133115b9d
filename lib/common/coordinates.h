// The range of coordinates visq accepts from a request or a file. Beyond it a
// double keeps less than 1/8 of a unit, a float conversion or a squared
// length can overflow to infinity, and Embree or GL would be handed a ray
// or a vertex it cannot take.
#pragma once

#include <algorithm>
#include <cmath>

#include <glm/glm.hpp>

namespace visq {

inline constexpr double kMaxCoordinate = 1e15;

// The smallest scale a placement (a node's world transform, an instance's)
// may shrink its mesh by, zero aside. Structures that instance a mesh work
// in the mesh's own space, where a point in range lands at up to
// kMaxCoordinate / scale: with this floor at most 1e30, which float32 holds
// with its full precision. Below it Embree's float inverse of the transform
// overflowed and its traversal never ended (instances scaled by 1e-40).
inline constexpr double kMinPlacementScale = 1.0 / kMaxCoordinate;

// How much `linear` (a transform's upper 3x3) stretches at most, to within
// a factor of sqrt(3): its longest column.
inline double PlacementScale(const glm::dmat3& linear) {
  return std::max({glm::length(linear[0]), glm::length(linear[1]), glm::length(linear[2])});
}

// A position (a point, a box corner, a patch's origin or edge) from a
// request: finite and within the range. A direction is checked with
// IsDirection, a scalar with std::isfinite.
inline bool InCoordinateRange(double v) { return std::isfinite(v) && std::abs(v) <= kMaxCoordinate; }
inline bool InCoordinateRange(const glm::dvec3& v) {
  return InCoordinateRange(v.x) && InCoordinateRange(v.y) && InCoordinateRange(v.z);
}

// A direction from a request: its length finite (no NaN or infinite
// component, none so large that the length overflows) and above zero, so
// that normalizing it gives a unit vector.
inline bool IsDirection(const glm::dvec3& v) {
  const double length = glm::length(v);
  return std::isfinite(length) && length > 0.0;
}

}  // namespace visq
