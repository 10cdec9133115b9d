// Query-relative precision for the sampled methods. RASTER and RAYCAST trace
// float32 copies of a scene, and a scene's own copies are anchored at its
// centre: there a query resolves occluders only to 2^-17 of its distance
// from the centre (sampling::ResolvableEndpointTolerances). A query far from
// it (a room 5e5 units out in a world spanning 1e6, or 5e2 units out beside a
// copy of the room 1e3 away) is traced instead against a copy of the region
// around it, rebased in double to the region's centre before it becomes
// float: whenever the scene's own frame would ignore more than
// sampling::kNegligibleToleranceShare of a sample spacing and the region
// resolves the query at least twice as finely (Engine::LocalFrameFor).
//
// The region is a cube of side 2c on a grid of step c, c the least power of
// two at least the query's extent: it holds every segment of the query, the
// queries nearby share it, and a scene moved by a multiple of c gives the
// same float32 copy, hence the same bits.
#pragma once

#include <list>
#include <memory>
#include <mutex>

#include <glm/glm.hpp>

#include "common/status.h"
#include "exact/light_visibility.h"
#include "raycast/embree_scene.h"
#include "sampling/visibility_sampling.h"
#include "scene/scene.h"
#include "visq/gpu/gpu_scene.h"
#include "raycast/flat_bvh.h"
#include "visq/gpu/ray_scene.h"

namespace visq::core {

struct LocalFrame {
  glm::dvec3 lo{0.0};  // the region [lo, lo + side]^3, world space
  double side = 0.0;
  std::shared_ptr<const Scene> scene;  // the triangles that meet the region, world space
  glm::dvec3 origin() const { return lo + glm::dvec3(0.5 * side); }
  sampling::FloatFrame float_frame() const { return {origin(), scene->bounds}; }

  // Its float32 copies, built by the first query that traces them.
  std::mutex mutex;
  std::shared_ptr<gpu::GpuScene> gpu_scene;
  std::shared_ptr<raycast::EmbreeScene> embree_scene;
  std::shared_ptr<gpu::RayScene> ray_scene;
};

// The local frames of one resident scene, the most recently used kept.
class LocalFrames {
 public:
  static constexpr size_t kMaxFrames = 8;

  // The frame holding `hull`'s region: the cached one, or a new copy of the
  // triangles of `scene` (indexed by `index`) that meet it.
  [[nodiscard]] std::shared_ptr<LocalFrame> For(const Scene& scene, const exact::SceneTriangleIndex& index,
                                                const Bounds& hull);
  size_t size() const;
  // The region For would copy for `hull` (before copying anything).
  static Bounds RegionAround(const Bounds& hull);

 private:
  mutable std::mutex mutex_;
  std::list<std::shared_ptr<LocalFrame>> frames_;  // most recent first
};

}  // namespace visq::core
