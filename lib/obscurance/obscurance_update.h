// Real-time update of obscurances when objects move (paper, section 5).
//
// Per dynamic object (a node and its subtree) the updater keeps the list of
// influenced patches: patches some of whose rays meet the object first within
// d_max. Moving the object recomputes, by ray casting through an Embree scene
// in which every dynamic object is an instance:
//   - the patches of the old list (they saw the object where it was),
//   - the object's own patches,
//   - the patches whose rays meet the object where it is now (found among the
//     patches within d_max of its new bounding sphere, which a grid over the
//     static patches (patch_index.h) and the list of patches on dynamic
//     objects give without scanning the atlas: a ray-sphere test, then rays
//     against the object alone, then the full scene),
// and the new list is the set of recomputed patches whose rays met it. Every
// other patch keeps its value bit for bit. The recomputed values are the ray
// estimator of eq. 6 (obscurance_rays.h), so they agree with a GPU rebake
// within the Monte Carlo noise of both, not bit for bit.
#pragma once

#include <cstdint>
#include <memory>
#include <vector>

#include <glm/glm.hpp>

#include "common/status.h"
#include "obscurance/instanced_ray_scene.h"
#include "obscurance/obscurance_atlas.h"
#include "obscurance/obscurance_model.h"
#include "obscurance/obscurance_rays.h"
#include "obscurance/patch_index.h"
#include "scene/scene.h"

namespace visq::obscurance {

struct UpdaterOptions {
  uint32_t rays_per_patch = 64;
  uint64_t seed = 7;
  int threads = 0;  // 0: all cores
  // The plain path, kept as the reference the tests hold the fast one to:
  // candidates from a scan of every atlas texel and rays traced one at a
  // time. The fast path (a spatial index over patches, ray streams) gives
  // the same answers.
  bool exhaustive = false;
  // Trace each patch's rays as one Embree stream (rtcIntersect1M) instead
  // of one rtcIntersect1 per ray. Off by default: on the 2-core test box it
  // gained under 10 % (generating the rays costs more than tracing them),
  // and packet traversal rounds a few grazing rays through the instance
  // transform differently, so 16 of 262,144 Sponza texels came out
  // different from the single-ray path after five moves at 64 rays.
  bool ray_streams = false;
};

struct ObscuranceUpdate {
  // Changed texels, sorted, with their new W and I. Includes gutter texels
  // refilled next to changed patches.
  std::vector<uint32_t> texels;
  std::vector<glm::vec3> w;
  std::vector<glm::vec3> intensity;
  std::vector<uint32_t> triangles;  // triangles touching a changed texel
  std::vector<glm::vec3> triangle_w;
  std::vector<uint32_t> vertices;   // their vertices
  std::vector<glm::vec3> vertex_w;
  // Figures.
  uint32_t influenced_before = 0, influenced_after = 0, own_patches = 0, candidates = 0, recomputed = 0;
  // Patches the candidate search looked at (from the patch index, or every
  // texel on the plain path) and those within d_max of the object's balls.
  uint32_t pooled = 0, within_reach = 0;
  uint64_t rays = 0;
  double milliseconds = 0;
  // Where the time went: moving the geometry and re-committing the instance,
  // finding the patches that meet the object now, tracing every recomputed
  // patch, and the rest (lists, gutters, averages).
  double move_ms = 0, candidates_ms = 0, trace_ms = 0;
};

class ObscuranceUpdater {
 public:
  // `baked` is the current solution for `scene` (a GPU bake or a ray
  // estimate); `dynamic_nodes` the nodes that may move (each with its
  // subtree; subtrees must be disjoint). Builds the Embree scene and the
  // influenced-patch list of every dynamic object.
  [[nodiscard]] static StatusOr<std::unique_ptr<ObscuranceUpdater>> Create(
      Scene scene, ObscuranceAtlas atlas, const ObscuranceParams& params, ObscuranceResult baked,
      std::vector<uint32_t> dynamic_nodes, const UpdaterOptions& options = {});
  ~ObscuranceUpdater();

  // Moves `node` (and subtree) so that its world matrix becomes `new_world`
  // and updates the solution. A node not declared dynamic becomes one first
  // (rebuilding the Embree scene: slower once). INVALID_ARGUMENT for an
  // unknown node or a non-finite matrix.
  [[nodiscard]] StatusOr<ObscuranceUpdate> MoveNode(uint32_t node, const glm::dmat4& new_world);

  // Declares another dynamic node (rebuilds the Embree scene and lists).
  [[nodiscard]] Status AddDynamicNode(uint32_t node);

  const ObscuranceResult& result() const { return result_; }
  const Scene& scene() const { return scene_; }
  const ObscuranceAtlas& atlas() const { return atlas_; }
  // Influenced patches of a dynamic node, sorted; empty for other nodes.
  std::vector<uint32_t> InfluencedPatches(uint32_t node) const;
  std::vector<uint32_t> OwnPatches(uint32_t node) const;

 private:
  struct Object {
    uint32_t node = 0;
    std::vector<uint32_t> triangles;
    std::vector<uint32_t> own;         // texels with a fragment of the object, sorted
    std::vector<uint32_t> influenced;  // sorted
    glm::dmat4 pose_at_build{1.0};     // node world when the Embree scene was built
  };
  ObscuranceUpdater() = default;
  Status Rebuild();
  // Patch centers and radii (texels with fragments) from current positions.
  void ComputePatchBounds(const std::vector<uint32_t>& texels);
  // Traces rays_per_patch rays for each texel; value[i] and which objects
  // were met first within d_max (bit k of hit_objects, first 64 objects;
  // more are tracked through met_object).
  void TracePatches(const std::vector<uint32_t>& texels, std::vector<glm::vec3>& value,
                    std::vector<std::vector<int32_t>>& met) const;
  std::vector<uint32_t> Candidates(const Object& object, ObscuranceUpdate* figures = nullptr) const;
  // Bounding balls of groups of the object's triangles.
  std::vector<Ball> ClusterBalls(const Object& object) const;

  Scene scene_;
  ObscuranceAtlas atlas_;
  ObscuranceParams params_;
  UpdaterOptions options_;
  AmbientModel ambient_;
  ObscuranceResult result_;
  std::vector<Object> objects_;
  std::vector<int32_t> object_of_triangle_;
  std::vector<glm::dvec3> patch_center_;
  std::vector<double> patch_radius_;
  // The patches of static surface only, indexed once per Rebuild; patches
  // with a fragment of any dynamic object move, so they are listed apart
  // (sorted) and tested one by one.
  PatchIndex static_patches_;
  std::vector<uint32_t> dynamic_patches_;
  std::vector<uint32_t> vertex_begin_, vertex_triangles_;  // triangles per position
  std::unique_ptr<InstancedRayScene> rays_;
};

}  // namespace visq::obscurance
