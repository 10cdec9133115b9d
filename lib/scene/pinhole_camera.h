// A pinhole camera shared by the algorithms that render an image from a
// viewpoint (volumetric shadows, the obscurance preview): what it is, how it
// is validated, and the raster transform every one of them uses, so that
// the same camera gives the same pixels everywhere. Part of the scene
// vocabulary, so that requests in lib/, the core and the transport name it
// without naming gpu/.
#pragma once

#include <cstdint>

#include <glm/glm.hpp>

#include "common/status.h"
#include "scene/scene.h"

namespace visq {

struct PinholeCamera {
  glm::dvec3 position{0.0};
  glm::dvec3 forward{0.0, 0.0, -1.0};  // viewing direction (normalized by the call)
  glm::dvec3 up{0.0, 1.0, 0.0};        // need not be orthogonal to forward; not parallel
  double vertical_fov_deg = 60.0;      // in (0, 180)
  uint32_t width = 160;
  uint32_t height = 120;
};

// Checks the camera without touching the GPU: INVALID_ARGUMENT naming the
// field and value ("camera.position: non-finite (nan, 0, 0)"),
// RESOURCE_EXHAUSTED when a side exceeds `max_size`.
[[nodiscard]] Status ValidatePinholeCamera(const PinholeCamera& camera, uint32_t max_size);

// The camera's clip transform for positions relative to `anchor` (a
// GpuScene's), perspective with the near and far planes around `bounds`
// (far just beyond its farthest corner, near 1e-5 of that); window row 0 is
// the image's BOTTOM row (GL's convention). Call with a validated camera.
glm::dmat4 PinholeClipFromAnchor(const PinholeCamera& camera, const glm::dvec3& anchor, const Bounds& bounds);

}  // namespace visq
