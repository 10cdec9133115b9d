#include "core/obscurance_work.h"

#include <algorithm>
#include <map>
#include <unordered_map>

#include <glm/glm.hpp>

#include "common/parallel.h"
#include "core/structure_estimate.h"
#include "core/work_budget.h"
#include "obscurance/obscurance_rays.h"
#include "obscurance/patch_index.h"

namespace visq::core {
namespace {

// An Embree scene built over the whole scene (the estimator's, the
// updater's): the BVH and the vertices and indices it copies, and as much
// again for the build's own references while it runs.
uint64_t EmbreeBuildBytes(const ObscuranceWorkShape& s) {
  return s.triangles * (2 * kEmbreeBvhBytesPerTriangle + kEmbreeSharedIndexBytesPerTriangle) +
         s.positions * 2 * kEmbreeBvhBytesPerVertex;
}

// A node of a std::map or std::unordered_map as the allocator hands it out:
// the value and the node's links, rounded up to malloc's 16 bytes.
template <typename Value>
constexpr uint64_t TreeNodeBytes() {
  return (sizeof(Value) + 4 * sizeof(void*) + 15) / 16 * 16;
}
template <typename Value>
constexpr uint64_t HashNodeBytes() {
  return (sizeof(Value) + sizeof(void*) + 15) / 16 * 16 + sizeof(void*);  // and its bucket
}

// A ray tally the updater keeps per traced patch or triangle (its layout
// is private to the updater: sums and squares per channel in fixed point,
// the ray count, and its list of (object, rays), one small allocation).
struct TallyLayout {
  int64_t sum[3], sum_of_squares[3];
  uint32_t rays;
  void* first_hits[3];
};
constexpr uint64_t kTallyBytes = HashNodeBytes<std::pair<const uint32_t, TallyLayout>>() + 32;

}  // namespace

ObscuranceWorkShape ObscuranceShapeOf(const Scene& scene, uint32_t resolution, const obscurance::ObscuranceParams& params) {
  ObscuranceWorkShape s;
  s.texels = uint64_t{resolution} * resolution;
  s.triangles = scene.TriangleCount();
  s.positions = scene.PositionCount();
  s.scene_bytes = scene.CpuBytes();
  s.channels = params.color_bleeding ? 3 : 1;
  const glm::dvec3 extent = scene.bounds.Empty() ? glm::dvec3(0.0) : scene.bounds.Extent();
  s.index_cell_bytes = obscurance::PatchIndex::CellBytesAtMost(extent, params.d_max);
  return s;
}

uint64_t ObscuranceResultBytes(const ObscuranceWorkShape& s) {
  // Per texel W, I, the flag, the effective count, the variance and the
  // strata's; per triangle W, its count and variance; per position W.
  return s.texels * (2 * sizeof(glm::vec3) + 1 + 3 * sizeof(float)) +
         s.triangles * (sizeof(glm::vec3) + 2 * sizeof(float)) + s.positions * sizeof(glm::vec3);
}

uint64_t RayEstimateWorkBytes(const ObscuranceWorkShape& s, uint32_t rays_per_patch) {
  // Per triangle the rays' weighted sums (obscurance_rays.cpp's
  // TriangleRays: three dvec3, three doubles, a count and a flag) and its
  // own W, count and variance until they join the result; per position the
  // vertex averages' sums; per texel the list BuildResult refills.
  const uint64_t per_triangle = 3 * sizeof(glm::dvec3) + 4 * sizeof(double) + 2 * (sizeof(glm::vec3) + 2 * sizeof(float));
  const uint64_t per_position = sizeof(glm::dvec3) + sizeof(double);
  return EmbreeBuildBytes(s) + s.triangles * per_triangle + s.positions * per_position +
         s.texels * sizeof(uint32_t) + obscurance::RayEstimateBatchBytes(rays_per_patch) +
         obscurance::PatchRayScratchBytes(rays_per_patch, s.triangles);
}

uint64_t ObscuranceUpdaterBytes(const ObscuranceWorkShape& s, uint32_t update_rays_per_patch) {
  // Per texel: the patch's ball, its place in the patch index, the
  // static-patch flag, its tally flag and a tally once traced, and its
  // entries in the dynamic lists. Per triangle: its object, its corner
  // lists, its plane, its tally flag and tally, its objects' lists. Per
  // position: the triangle offsets (and their cursor while built).
  const uint64_t per_texel = sizeof(glm::dvec3) + sizeof(double) + obscurance::PatchIndex::kMaxBytesPerBall + 2 +
                             kTallyBytes + 2 * sizeof(uint32_t);
  const uint64_t per_triangle = sizeof(int32_t) + 3 * sizeof(uint32_t) + sizeof(glm::dvec4) + 1 + kTallyBytes +
                                2 * sizeof(uint32_t);
  const uint64_t per_position = 2 * sizeof(uint32_t);
  // Its copies of the scene and the result, its Embree scene, and what one
  // thread's rays of a patch take (obscurance::GeneratePatchRays) while it
  // traces the patches near a dynamic node.
  return s.scene_bytes + ObscuranceResultBytes(s) + EmbreeBuildBytes(s) + s.texels * per_texel +
         s.triangles * per_triangle + s.positions * per_position + s.index_cell_bytes +
         ParallelWorkers() * obscurance::PatchRayScratchBytes(update_rays_per_patch, s.triangles);
}

uint64_t ObscuranceAnswerExtraBytes(const ObscuranceWorkShape& s) {
  // The bounds (a float per texel, triangle and position); the texels'
  // estimates (a float each) and the statement's sorted copies of the
  // texels' bounds and estimates (a float and a double each); the answer's
  // messages, as many as a stream's queue holds.
  const uint64_t bounds = (s.texels + s.triangles + s.positions) * sizeof(float);
  return bounds + s.texels * (2 * sizeof(float) + sizeof(double)) +
         std::min(kStreamedAnswerQueueBytes, ObscuranceResultBytes(s) + bounds);
}

uint64_t ObscuranceUpdateCallBytes(const ObscuranceWorkShape& s, uint32_t rays_per_patch) {
  // Per changed texel: its W and I merged over the moves (two map nodes),
  // a move's lists (index, W, I), the answer's (the same and the bound),
  // and its message and the serialized copy (the same again, twice). Per
  // texel looked at: the candidate search's pool, near, kept, candidate
  // and union lists, a re-trace record and its counters, and a fresh tally.
  const uint64_t node = TreeNodeBytes<std::pair<const uint32_t, glm::vec3>>();
  const uint64_t listed = sizeof(uint32_t) + 2 * sizeof(glm::vec3);
  const uint64_t per_texel = 2 * node + 2 * listed + sizeof(float) + 2 * (listed + sizeof(float)) +
                             (5 * sizeof(uint32_t) + 1 + 48 + 2 * sizeof(uint64_t) + sizeof(TallyLayout));
  // Per changed triangle and vertex: a map node, the lists and bound, the
  // message twice.
  const uint64_t per_element = node + 2 * (sizeof(uint32_t) + sizeof(glm::vec3)) + sizeof(float) +
                               2 * (sizeof(uint32_t) + sizeof(glm::vec3) + sizeof(float));
  return s.texels * per_texel + (s.triangles + s.positions) * per_element +
         obscurance::PatchRayScratchBytes(rays_per_patch, s.triangles);
}

}  // namespace visq::core
