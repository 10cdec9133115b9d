// Real-time update of obscurances when objects move (paper, section 5).
//
// Per dynamic object (a node and its subtree) the updater keeps the list of
// influenced patches: patches some of whose rays meet the object first within
// d_max. The recomputed values are the ray estimator of eq. 6
// (obscurance_rays.h), so they agree with a GPU rebake within the Monte Carlo
// noise of both, not bit for bit. Rays are cast through an Embree scene in
// which every dynamic object is an instance.
//
// The updater keeps, for each patch (and triangle) it has traced, a tally of
// what its rays found: the sum of their values in fixed point and how many
// met each dynamic object first. Moving an object changes the first hit of a
// ray only if the ray meets the object (alone) where it was or where it is
// now. So the fast path visits the patches within d_max of the object's old
// and new bounds (a grid over the static patches, patch_index.h, and the list
// of patches on dynamic objects), generates only their rays towards the
// object's old or new balls, keeps those that meet the object alone at either
// pose, and traces just those: in the scene before the move (their old value
// leaves the tally) and after it (their new value joins it). Integer sums do
// not depend on the order rays join and leave them, so a tally so kept is
// bit for bit the tally of tracing all the patch's rays in the moved scene.
// Patches with no tally yet, and the object's own patches (all their rays
// move), are traced in full.
//
// The plain path (UpdaterOptions::exhaustive) is the reference: candidates
// from a scan of every texel, and every patch to recompute traced in full:
//   - the patches of the old list (they saw the object where it was),
//   - the object's own patches,
//   - the patches whose rays meet the object where it is now.
// Both paths change the same texels to the same bits, and keep the same
// lists; every other patch keeps its value bit for bit.
#pragma once

#include <array>
#include <cstdint>
#include <memory>
#include <unordered_map>
#include <utility>
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
  // candidates from a scan of every atlas texel, and every patch to
  // recompute traced in full. The fast path (a spatial index over patches,
  // only the rays that can meet the moved object traced) gives the same
  // answers.
  bool exhaustive = false;
  // Trace the rays of a patch traced in full as one Embree stream
  // (rtcIntersect1M) instead of one rtcIntersect1 per ray. Off by default:
  // on the 2-core test box it gained under 10 % (generating the rays costs
  // more than tracing them), and packet traversal rounds a few grazing rays
  // through the instance transform differently from a single ray (16 of
  // 262,144 Sponza texels came out different after five moves at 64 rays).
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
  // Figures. candidates: patches (not the object's own) with a ray that
  // meets the object alone where it is now; recomputed: patches traced,
  // in full or in part.
  uint32_t influenced_before = 0, influenced_after = 0, own_patches = 0, candidates = 0, recomputed = 0;
  // Patches the candidate search looked at (from the patch index, or every
  // texel on the plain path) and those within d_max of the object's balls.
  uint32_t pooled = 0, within_reach = 0;
  // Rays traced through the full scene (patches and triangles; on the fast
  // path an affected ray counts twice, before and after the move), of them
  // for the triangles, and rays generated and tested against the object alone.
  uint64_t rays = 0, triangle_rays = 0, probed_rays = 0;
  double milliseconds = 0;
  // Where the time went: moving the geometry and re-committing the instance,
  // finding the patches that meet the object (on the fast path with tracing
  // their affected rays before the move), tracing patches after the move,
  // the triangles' own rays, and the rest (lists, gutters, averages).
  double move_ms = 0, candidates_ms = 0, trace_ms = 0, triangles_ms = 0;
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
  // What the rays of one patch or triangle found in the current scene: the
  // sum of their values in fixed point (kFixedOne per unit) and, per dynamic
  // object, how many met it first. Integer sums are exact, so removing a
  // ray's old value and adding its new one gives the bits of a full re-trace.
  struct RayTally {
    std::array<int64_t, 3> sum{};
    std::array<int64_t, 3> sum_of_squares{};
    uint32_t rays = 0;
    std::vector<std::pair<int32_t, int32_t>> first_hits;  // (object, rays)
    void Add(const glm::dvec3& value, int32_t object, int sign);
    int32_t FirstHits(int32_t object) const;
    glm::vec3 Mean() const;
    // LargestChannelVariance of the values, with the fixed point's rounding.
    float Variance() const;
  };
  static constexpr double kFixedOne = 4294967296.0;  // 2^32

  // A patch or a triangle whose rays the fast path re-traces in part: the
  // rays that meet the moved object alone before or after the move.
  struct Retrace {
    uint32_t element = 0;
    RayTally* tally = nullptr;  // none yet: traced in full if it meets the object now
    std::vector<PatchRay> rays;
    bool meets_now = false;
  };

  ObscuranceUpdater() = default;
  Status Rebuild();
  // Patch centers and radii (texels with fragments) from current positions.
  void ComputePatchBounds(const std::vector<uint32_t>& texels);
  void ComputePatchBound(uint32_t texel);
  // All rays_per_patch rays of each texel traced in the current scene.
  std::vector<RayTally> TracePatches(const std::vector<uint32_t>& texels) const;
  RayTally TraceRays(const std::vector<PatchRay>& rays) const;
  // The rays of one triangle's own estimate: rays_per_patch for each texel
  // of its area, from one patch's worth up to kMostTexelsPerTriangle.
  uint32_t TriangleRayCount(uint32_t triangle) const;
  std::vector<uint32_t> Candidates(const Object& object, ObscuranceUpdate* figures = nullptr) const;
  // Bounding balls of groups of the object's triangles.
  std::vector<Ball> ClusterBalls(const Object& object) const;
  // The balls among `balls` that rays leaving a patch (ball `center`,
  // `radius`; triangles' planes `planes`) can reach within d_max.
  void BallsInReach(const glm::dvec3& center, double radius, const std::vector<glm::dvec4>& planes,
                    const std::vector<Ball>& balls, std::vector<Ball>& out) const;
  // The fast path's search: of `rays` (leaving one element), those that meet
  // object k alone where it was (the Embree scene before the move) or where
  // it is now (the probe), the ones whose old first hits leave `out.tally`.
  void FindAffectedRays(size_t k, const std::vector<PatchRay>& rays, const std::vector<Ball>& old_balls,
                        const std::vector<Ball>& new_balls, Retrace& out, uint64_t& traced) const;
  // Moves object k's triangles in the scene, with the patch bounds and
  // triangle planes that follow from their positions; the figures of an
  // update that begins with it.
  [[nodiscard]] Status MoveObjectPositions(size_t k, const glm::dmat4& new_world, ObscuranceUpdate& update);
  // The fast path (MoveNodeFast): re-traces only the rays that meet the
  // moved object alone before or after the move.
  StatusOr<ObscuranceUpdate> MoveNodeFast(size_t k, const glm::dmat4& new_world);
  // Its steps. The object's cluster balls before and after the move, each
  // pose's enclosing ball, and both of those (`reach`).
  struct MoveBalls {
    MoveBalls(std::vector<Ball> before, std::vector<Ball> after);
    std::vector<Ball> old_balls, new_balls;
    std::vector<Ball> old_bound, new_bound;
    std::vector<Ball> reach;
  };
  // Patches within d_max of either pose (static ones from the index, the
  // dynamic objects' all tested), the object's own left out.
  std::vector<uint32_t> PatchesNearMove(const Object& object, const MoveBalls& balls, ObscuranceUpdate& update) const;
  // Triangles with tallies of their own among those patches' and the moved
  // object's fragments (not the object's own), within d_max of either pose.
  std::vector<uint32_t> TrianglesNearMove(size_t k, const std::vector<uint32_t>& near, const MoveBalls& balls) const;
  // Each element's affected rays (FindAffectedRays), whose old values leave
  // its tally (found here): before the Embree scene moves the object.
  void SearchAffectedRays(size_t k, const MoveBalls& balls, std::vector<Retrace>& patches,
                          std::vector<Retrace>& triangles, ObscuranceUpdate& update);
  // After it moved: the affected rays' new values join the tallies, and the
  // patches that need it are traced in full. The patches recomputed, sorted.
  std::vector<uint32_t> RetraceAfterMove(size_t k, std::vector<Retrace>& patches, std::vector<Retrace>& triangles,
                                         ObscuranceUpdate& update);
  StatusOr<ObscuranceUpdate> MoveNodePlain(size_t k, const glm::dmat4& new_world);
  // What both paths share once the changed patches have new tallies: W,
  // lists, gutters, intensities, triangles and vertices.
  void Finish(size_t k, const std::vector<uint32_t>& changed, ObscuranceUpdate& update);

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
  // Tallies of the patches and triangles traced since the last Rebuild:
  // a map (few elements have one), and a byte per element that spares the
  // many look-ups of elements without one.
  class Tallies {
   public:
    void Reset(size_t elements) { map_.clear(); present_.assign(elements, 0); }
    RayTally* Find(uint32_t i) {
      if (!present_[i]) return nullptr;
      return &map_.find(i)->second;
    }
    bool Contains(uint32_t i) const { return present_[i] != 0; }
    const RayTally& At(uint32_t i) const { return map_.at(i); }
    void Set(uint32_t i, RayTally tally) {
      map_[i] = std::move(tally);
      present_[i] = 1;
    }
    void Erase(uint32_t i) {
      if (present_[i]) map_.erase(i);
      present_[i] = 0;
    }
   private:
    std::unordered_map<uint32_t, RayTally> map_;
    std::vector<uint8_t> present_;
  };
  Tallies patch_tally_, triangle_tally_;
  // Unit normal and offset of every triangle at its current pose.
  std::vector<glm::dvec4> triangle_plane_;
};

}  // namespace visq::obscurance
