// Embree scene for the obscurance update: the static triangles as one mesh,
// each dynamic object as an instance of its own mesh, so that moving an
// object is a new instance transform and a top-level re-commit (no BVH
// rebuild of the scene). raycast::EmbreeScene has no instancing, hence this
// class; it keeps the same float32 precision rule (geometry uploaded relative
// to a frame origin, queries moved into that frame in double).
#pragma once

#include <cstdint>
#include <memory>
#include <span>
#include <vector>

#include <glm/glm.hpp>

#include "common/status.h"
#include "obscurance/obscurance_rays.h"
#include "scene/scene.h"

namespace visq::obscurance {

class InstancedRayScene {
 public:
  // objects[k]: the scene triangles of dynamic object k, at their pose in
  // `scene`; every other triangle is static.
  [[nodiscard]] static StatusOr<std::unique_ptr<InstancedRayScene>> Create(
      const Scene& scene, const std::vector<std::vector<uint32_t>>& objects);
  ~InstancedRayScene();
  InstancedRayScene(const InstancedRayScene&) = delete;
  InstancedRayScene& operator=(const InstancedRayScene&) = delete;

  // `delta` maps object k's pose at Create to its pose now (world space).
  void SetTransform(size_t object, const glm::dmat4& delta);
  // Commits the transforms set since the last commit.
  void Commit();
  // A second pose of object k, alone, for HitsProbe: where the object will
  // be, while the scene still holds it where it was.
  void SetProbeTransform(size_t object, const glm::dmat4& delta);

  struct Hit {
    bool hit = false;
    double t = 0;
    uint32_t triangle = 0;  // scene triangle
    int32_t object = -1;    // -1: static geometry
  };
  // Closest hit with t in (t_min, tmax]; `direction` unit length. t_min
  // skips the surface the ray leaves (a fixed 1e-6 of the scene extent).
  Hit Closest(const glm::dvec3& origin, const glm::dvec3& direction, double tmax) const;
  // Whether object k alone (other geometry ignored) meets the ray in (t_min, tmax].
  bool HitsObject(size_t object, const glm::dvec3& origin, const glm::dvec3& direction, double tmax) const;
  // Whether object k alone at its probe pose meets the ray in (t_min, tmax].
  bool HitsProbe(size_t object, const glm::dvec3& origin, const glm::dvec3& direction, double tmax) const;

  // Closest for many rays at once, traced as streams (rtcIntersect1M), which
  // Embree traverses in SIMD packets. hits[i] for rays[i]; hits.size() ==
  // rays.size(). A packet rounds a grazing ray through an instance transform
  // a little differently from a single ray, so a few hits can differ from
  // Closest's.
  void ClosestStream(std::span<const PatchRay> rays, double tmax, std::span<Hit> hits) const;

  size_t object_count() const;

  struct Impl;

 private:
  explicit InstancedRayScene(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace visq::obscurance
