// What voxelization and transmittance share inside gpu/slicemap/: the view
// a slicemap is drawn in, one voxelization's configuration, and the
// voxelization itself (slicemap.cpp), which transmittance runs once per group
// of absorbers (transmittance.cpp).
#pragma once

#include <string>
#include <string_view>
#include <vector>

#include <fmt/format.h>
#include <glm/glm.hpp>

#include "common/coordinates.h"
#include "common/status.h"
#include "visq/gpu/slicemap.h"

namespace visq::gpu::slicemap_internal {

// Same constant as kMinLocalRange in slicemap.frag.
constexpr float kMinLocalRange = 1.0f / 1048576.0f;

// How the GL passes map anchor-relative positions to the image and depth.
struct ViewSetup {
  glm::mat4 clip_from_anchor{1.0f};
  glm::vec4 depth_plane{0.0f};  // orthographic depth fraction
  bool perspective = false;
  glm::vec3 light{0.0f};   // perspective: anchor-relative light
  glm::vec2 radial{0.0f};  // perspective: (r0, 1 / (r1 - r0))
  OrientedBox box;         // orthographic: the box the grid fills
};

struct PassConfig : SlicemapSettings {};

// Finite and within visq's coordinate range (common/coordinates.h).
inline std::string Vec(const glm::dvec3& v) { return fmt::format("({}, {}, {})", v.x, v.y, v.z); }

// The width, height and slice caps, and the byte cap on the packed result
// (three grids for a solid) and on one pass's targets; errors name
// `prefix` + the field.
[[nodiscard]] Status ValidateGridSize(std::string_view prefix, uint32_t width, uint32_t height, uint32_t slices,
                                      bool solid, uint64_t max_bytes);

// The orthographic view of a box, relative to the scene's anchor, in double
// and then float.
ViewSetup OrthographicView(const OrientedBox& box, const glm::dvec3& anchor);

// Runs the passes (GL jobs per pass and band of rows) and resolves a solid,
// band by band; with `sink`, each band goes to it (see Voxelize); with
// `surface_out`, also the surface grid, whole.
[[nodiscard]] StatusOr<VoxelizeResult> VoxelizeView(GpuWorker& worker, const GpuScene& scene, const ViewSetup& view,
                                                    const PassConfig& config, const VoxelizeBandSink& sink,
                                                    SlicemapGrid* surface_out);

}  // namespace visq::gpu::slicemap_internal
