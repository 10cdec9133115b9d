// The ray-cast estimator of eq. 6: N rays per patch, from points uniform in
// the patch's area, cosine-distributed around the surface normal; each ray
// gathers rho(d) (times R(Q) with color bleeding) of the first surface within
// d_max, or the unoccluded value. It is the paper's estimator for the update
// (section 5) and, traced with raycast::EmbreeScene, the independent
// reference the GPU bake is tested against.
//
// How it relates to the bake: a bundle of parallel lines with a uniform
// random direction hits a patch in proportion to its projected area, so the
// directions a patch receives are cosine-distributed and the points uniform
// over its area: the bake's sum/count estimates the same patch average as
// this estimator (Sbert 1997). Both are unbiased Monte Carlo estimates of one
// number, so they agree within their noise, not bit for bit.
#pragma once

#include <cstdint>
#include <functional>
#include <span>
#include <vector>

#include <glm/glm.hpp>

#include "common/status.h"
#include "common/stop_token.h"
#include "obscurance/obscurance_atlas.h"
#include "obscurance/obscurance_model.h"
#include "raycast/embree_scene.h"
#include "scene/scene.h"

namespace visq::obscurance {

struct PatchRay {
  glm::dvec3 origin{0.0};     // on the triangle
  glm::dvec3 direction{0.0};  // unit, in the front hemisphere
  uint32_t triangle = 0;      // the triangle the ray leaves
};

struct Ball {
  glm::dvec3 center{0.0};
  double radius = 0;
};

// Directions that may reach one of a few balls from a patch: a ray leaving
// any point within patch_radius of patch_center along such a direction can
// pass within a ball's radius of its center.
// `bounds`, if any, are balls that hold all the targets between them: a
// direction must pass one of them first, which spares testing the many
// targets for most directions.
struct DirectionFilter {
  glm::dvec3 patch_center{0.0};
  double patch_radius = 0;
  std::span<const Ball> targets;
  std::span<const Ball> bounds;
  bool MayMeet(const glm::dvec3& direction) const;
};

// N rays of texel `texel` (nothing if the texel holds no surface), each
// independent of the others: ray j's direction is uniform in cell j of N
// equal cells of the square it is made from (EqualAreaCellOf: sin^2 of the
// polar angle, the azimuth), its origin uniform over the patch, from a
// stream of its own hashed from (seed, texel, j). So the rays' mean value
// is an unbiased estimate of the patch's W and Hoeffding's inequality
// holds for it (independent values in [0, 1], not identically
// distributed), while the directions still cover the hemisphere evenly.
// A low-discrepancy sequence under one random rotation per patch would be
// as even, but its rays would not be independent, and no Hoeffding bound
// would hold for them. The same (seed, texel, n) give the same rays.
// With `only_towards`, the rays whose direction fails it are left out (and
// their origins never computed: the update's candidate search skips most
// rays this way); the others are the same rays, bit for bit.
void GeneratePatchRays(const Scene& scene, const ObscuranceAtlas& atlas, uint32_t texel, uint64_t seed, uint32_t n,
                       std::vector<PatchRay>& out, const DirectionFilter* only_towards = nullptr);

// N rays of one triangle: points uniform on it, cosine-distributed around
// its normal, stratified and independent as GeneratePatchRays's, from
// streams hashed from seed and triangle (none for a degenerate triangle).
// `only_towards` as for GeneratePatchRays.
void GenerateTriangleRays(const Scene& scene, uint32_t triangle, uint64_t seed, uint32_t n, std::vector<PatchRay>& out,
                          const DirectionFilter* only_towards = nullptr);

// What one ray contributes, given its closest hit within d_max (hit false:
// none). RGB; gray without color bleeding.
glm::dvec3 RayValue(const Scene& scene, const AmbientModel& ambient, bool color_bleeding, double d_max, bool hit,
                    double distance, uint32_t hit_triangle);

// Closest hits for a batch of rays with raycast::EmbreeScene::Intersect's
// semantics over the scene's triangles in its flattened order (another
// tracer of the same rays: the GPU's, gpu/rays).
using ClosestHits = std::function<StatusOr<std::vector<raycast::Hit>>(std::span<const raycast::Ray> rays)>;

struct RayEstimateOptions {
  // Empty: an Embree scene of the scene's own, built by the call.
  ClosestHits closest_hits;
  uint32_t rays_per_patch = 64;
  uint64_t seed = 1;
  int threads = 0;  // 0: all cores
  // Asked between batches of rays: once it says stop, the estimate returns
  // its CANCELLED or DEADLINE_EXCEEDED.
  StopToken stop;
};

// The texels of one batch of EstimateObscurancesByRays: as many as make
// about kRayEstimateBatchRays rays, at least one and at most 4,096. What a
// batch holds follows from it (RayEstimateBatchBytes), whatever
// rays_per_patch is.
inline constexpr uint64_t kRayEstimateBatchRays = uint64_t{1} << 16;
uint32_t RayEstimateBatchTexels(uint32_t rays_per_patch);
// The most one batch of EstimateObscurancesByRays holds: its rays, their
// texels, hits and values, and the per-texel sums.
uint64_t RayEstimateBatchBytes(uint32_t rays_per_patch);
// The most GeneratePatchRays holds on one thread for n rays of a texel of
// `fragments` fragments: the rays, a sampler per fragment picked (at most
// n), and the per-fragment sums and slots.
uint64_t PatchRayScratchBytes(uint32_t n, uint64_t fragments);

// The reference: every covered texel estimated with rays_per_patch rays,
// traced with raycast::EmbreeScene (helper-independent of the GPU bake and
// of the update's instanced scene).
[[nodiscard]] StatusOr<ObscuranceResult> EstimateObscurancesByRays(const Scene& scene, const ObscuranceAtlas& atlas,
                                                                   const ObscuranceParams& params,
                                                                   const RayEstimateOptions& options);

// W of every triangle by its own rays_per_patch rays (GenerateTriangleRays),
// traced with raycast::EmbreeScene: an estimate of each triangle's W that
// knows nothing of the atlas, for the tests and benches to hold the
// per-triangle W of the bake to (degenerate triangles: 0).
[[nodiscard]] StatusOr<std::vector<glm::vec3>> EstimateTriangleObscuranceByRays(const Scene& scene,
                                                                               const ObscuranceParams& params,
                                                                               const RayEstimateOptions& options);

}  // namespace visq::obscurance
