// CPU reference voxelizer, independent of the GPU slicemap (gpu/slicemap):
//   - surface: a voxel is occupied when a triangle touches its closed box,
//     decided by the exact separating-axis triangle-box test
//     (Akenine-Möller 2001) in double precision;
//   - solid: a voxel is inside when the ray along its column, through the
//     column's center, has crossed the surface an odd number of times before
//     the voxel's center (Embree, visq_raycast), plus the surface voxels.
// The grid and packed layout are the slicemap's (slicemap_request.h):
// word (y * width + x) * words_per_column + k / 32, bit k % 32, k = 0 at the
// box's front face.
#pragma once

#include <cstdint>
#include <vector>

#include <glm/glm.hpp>

#include "common/status.h"
#include "scene/scene.h"
#include "voxel_reference/voxel_box.h"

namespace visq::voxel_reference {

struct ReferenceGrid {
  uint32_t width = 0, height = 0, slices = 0, words_per_column = 0;
  std::vector<uint32_t> bits;

  bool Get(uint32_t x, uint32_t y, uint32_t k) const {
    return (bits[(size_t{y} * width + x) * words_per_column + k / 32] >> (k % 32)) & 1u;
  }
  uint64_t CountOccupied() const;
};

struct SurfaceOptions {
  // [first, first + count) triangle ranges; empty: all triangles.
  std::vector<std::pair<uint32_t, uint32_t>> triangles;
  // Local precision: per column (y * width + x), the depth range its slices
  // split, as fractions of the box depth (the GPU's column_near/column_far).
  // Empty: uniform slices.
  std::vector<float> column_near, column_far;
  int threads = 0;  // 0: hardware concurrency
};

struct SurfaceStats {
  // Local precision: triangle-column touches in columns the given ranges
  // call empty (near > far); such touches cannot be placed in any slice.
  uint64_t touches_in_empty_columns = 0;
  double milliseconds = 0;
};

[[nodiscard]] StatusOr<ReferenceGrid> VoxelizeSurface(const Scene& scene, const GridBox& box,
                                                      const SurfaceOptions& options = {},
                                                      SurfaceStats* stats = nullptr);

struct SolidReference {
  ReferenceGrid solid;    // interior voxels (center inside) + surface voxels
  ReferenceGrid surface;  // as VoxelizeSurface
  // Per column: 1 when its crossings alternate entering / leaving (by the
  // triangle's facing) starting outside and ending outside.
  std::vector<uint8_t> column_consistent;
  double milliseconds = 0;
};

// Uniform slices only. The box must contain the mesh along w for the parity
// to start outside (crossings before the front face are not seen).
[[nodiscard]] StatusOr<SolidReference> VoxelizeSolid(const Scene& scene, const GridBox& box, int threads = 0);

// What a standard (non-conservative) rasterizer can see: for every triangle
// and every column center (x + 0.5, y + 0.5) inside its projection (edges
// included), the voxel holding the triangle's depth there. A voxel that
// VoxelizeSurface has and this grid lacks is touched only by triangles that
// miss its column's center at its depth (edge-on or thin triangles): the
// slicemap's standard mode cannot see it. Same options as VoxelizeSurface.
//
// margin > 0 keeps only what every rasterizer that rounds to that precision
// must see: a center closer than margin columns to a triangle's edge, or a
// depth closer than margin slices to a slice boundary, is left out (GPUs
// snap vertices to a sub-pixel grid, so such a center can fall either side).
[[nodiscard]] StatusOr<ReferenceGrid> SampleColumnCenters(const Scene& scene, const GridBox& box,
                                                          const SurfaceOptions& options = {},
                                                          double margin = 0.0);

// Exact (up to double rounding) separating-axis test between a triangle and
// the closed axis-aligned box center +- half; touching counts as overlap.
bool TriangleBoxOverlap(const glm::dvec3& center, const glm::dvec3& half, const glm::dvec3& a, const glm::dvec3& b,
                        const glm::dvec3& c);

}  // namespace visq::voxel_reference
