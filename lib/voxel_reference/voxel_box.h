// The voxel grid's box, one type for the GPU slicemap (VoxelizeParams::box in
// slicemap_request.h) and the CPU reference voxelizer alike. Header only:
// the GPU floor names it without linking the reference.
#pragma once

#include <cstdint>

#include <glm/glm.hpp>

namespace visq::voxel_reference {

// An oriented orthographic box in world coordinates. The axes must be
// orthonormal (checked where a box is used); w is the depth (slice)
// direction.
struct OrientedBox {
  glm::dvec3 center{0.0};
  glm::dvec3 axis_u{1.0, 0.0, 0.0};
  glm::dvec3 axis_v{0.0, 1.0, 0.0};
  glm::dvec3 axis_w{0.0, 0.0, 1.0};
  glm::dvec3 half_extent{1.0};  // along u, v, w
};

// The box cut into width x height columns of `slices` voxels.
struct GridBox : OrientedBox {
  uint32_t width = 0, height = 0, slices = 0;
};

}  // namespace visq::voxel_reference
