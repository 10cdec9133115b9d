// The range of coordinates visq accepts from a request or a file. Beyond it a
// double keeps less than 1/8 of a unit, a float conversion or a squared
// length can overflow to infinity, and Embree or GL would be handed a ray
// or a vertex it cannot take.
#pragma once

#include <cmath>

#include <glm/glm.hpp>

namespace visq {

inline constexpr double kMaxCoordinate = 1e15;

inline bool InCoordinateRange(double v) { return std::isfinite(v) && std::abs(v) <= kMaxCoordinate; }
inline bool InCoordinateRange(const glm::dvec3& v) {
  return InCoordinateRange(v.x) && InCoordinateRange(v.y) && InCoordinateRange(v.z);
}

}  // namespace visq
