#include "scene/pinhole_camera.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <numbers>
#include <string>

#include <fmt/format.h>
#include <glm/gtc/matrix_transform.hpp>

#include "common/coordinates.h"

namespace visq {
namespace {

std::string Vec(const glm::dvec3& v) { return fmt::format("({}, {}, {})", v.x, v.y, v.z); }
Status Invalid(std::string message) { return absl::InvalidArgumentError(message); }

}  // namespace

Status ValidatePinholeCamera(const PinholeCamera& camera, uint32_t max_size) {
  if (!InCoordinateRange(camera.position))
    return Invalid(fmt::format("camera.position: {} is not finite or beyond ±{:g}", Vec(camera.position),
                               kMaxCoordinate));
  if (!IsDirection(camera.forward))
    return Invalid(fmt::format("camera.forward: {} is not a direction (zero, not finite or too long to normalize)",
                               Vec(camera.forward)));
  if (!IsDirection(camera.up) ||
      glm::length(glm::cross(glm::normalize(camera.forward), camera.up)) < 1e-9 * glm::length(camera.up))
    return Invalid(fmt::format("camera.up: {} is zero, not finite, too long to normalize or parallel to camera.forward",
                               Vec(camera.up)));
  if (!(camera.vertical_fov_deg > 0.0 && camera.vertical_fov_deg < 180.0))
    return Invalid(fmt::format("camera.vertical_fov_deg: {} is not in (0, 180)", camera.vertical_fov_deg));
  if (camera.width == 0 || camera.height == 0)
    return Invalid(fmt::format("camera resolution: {} x {} has a zero side", camera.width, camera.height));
  if (camera.width > max_size || camera.height > max_size)
    return absl::ResourceExhaustedError(fmt::format("camera resolution: {} x {} exceeds the cap of {} per side",
                                                    camera.width, camera.height, max_size));
  return absl::OkStatus();
}

glm::dmat4 PinholeClipFromAnchor(const PinholeCamera& camera, const glm::dvec3& anchor, const Bounds& bounds) {
  // The depth range: from the eye to just beyond the farthest corner.
  const double diagonal = std::max(glm::length(bounds.Extent()), 1e-9);
  const glm::dvec3 eye = camera.position - anchor;
  double far_distance = 0;
  for (int i = 0; i < 8; ++i) {
    const glm::dvec3 corner(i & 1 ? bounds.max.x : bounds.min.x, i & 2 ? bounds.max.y : bounds.min.y,
                            i & 4 ? bounds.max.z : bounds.min.z);
    far_distance = std::max(far_distance, glm::length(corner - anchor - eye));
  }
  far_distance = far_distance * 1.01 + 1e-6 * diagonal;
  const double near_distance = std::max(far_distance * 1e-5, 1e-9);
  // The view: right = forward x up, the image's up orthogonal to forward.
  const glm::dvec3 f = glm::normalize(camera.forward);
  const glm::dvec3 r = glm::normalize(glm::cross(f, camera.up));
  const glm::dvec3 cu = glm::cross(r, f);
  const double aspect = double(camera.width) / camera.height;
  return glm::perspective(camera.vertical_fov_deg * std::numbers::pi / 180.0, aspect, near_distance, far_distance) *
         glm::lookAt(eye, eye + f, cu);
}

}  // namespace visq
