// Embree 3 CPU ray casting over a visq::Scene: the reference for every sampled
// visibility method (shadow rays, obscurance bakes).
//
// Precision. Embree works in float32, and scene coordinates are world-space
// doubles that may sit 1e6 units from the origin, where a float's spacing is
// 0.06. The scene is therefore uploaded relative to an origin (the bounds
// center by default, or one the caller gives, e.g. the center of the region
// being queried), and every query is moved into that frame in double before
// it is rounded to float. Answers then keep float precision relative to the
// scene extent, not to the absolute coordinates.
//
// Ignored triangles (a receiver's own surface). The scene is built with
// RTC_SCENE_FLAG_CONTEXT_FILTER_FUNCTION and a call that ignores something
// installs a filter in its RTCIntersectContext that rejects those hits (by
// the ray's own id, or a sorted batch-wide list). Calls that ignore nothing
// pass no filter and pay nothing; per-query scenes would cost a BVH build
// per receiver.
//
// Threads. Batches are split into contiguous chunks, one per std::thread
// worker; each chunk is traced in streams of rays with rtcOccluded1M /
// rtcIntersect1M. Embree scenes are safe for concurrent traversal once
// committed, so workers share one RTCScene.
#pragma once

#include <atomic>
#include <cstdint>
#include <functional>
#include <limits>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include <glm/glm.hpp>

#include "common/status.h"
#include "common/stop_token.h"
#include "scene/scene.h"

// Embree's handle types, declared here so that embree headers stay private.
struct RTCDeviceTy;
struct RTCSceneTy;

namespace visq::raycast {

// The configuration every Embree device in visq is created with: its BVH
// builds run on as many threads as the process may use CPUs (its cgroup's
// quota, its affinity mask; resource_limits::ProcessCpuLimit), where
// Embree's default is every core of the machine, 64 threads throttled on a
// quota of 2.
std::string EmbreeDeviceConfig();

inline constexpr uint32_t kNoTriangle = std::numeric_limits<uint32_t>::max();

// An open segment (p, q) in world coordinates. `ignore_triangle` names one
// triangle that never blocks this segment (the receiver's own surface), or
// kNoTriangle.
struct Segment {
  glm::dvec3 p{0.0};
  glm::dvec3 q{0.0};
  uint32_t ignore_triangle = kNoTriangle;
};

// A ray origin + t * direction, t in (0, tmax]; `direction` need not be unit
// length, distances come back in units of t.
struct Ray {
  glm::dvec3 origin{0.0};
  glm::dvec3 direction{0.0, 0.0, 1.0};
  double tmax = std::numeric_limits<double>::infinity();
  uint32_t ignore_triangle = kNoTriangle;
};

struct Hit {
  bool hit = false;
  double t = 0.0;                  // along Ray::direction
  uint32_t triangle = kNoTriangle;  // index into Scene::triangles
  double u = 0.0, v = 0.0;         // barycentrics of corners 1 and 2
};

struct TraceOptions {
  int threads = 0;  // 0: the caller and every thread of the process's pool (common/parallel.h)
  // Triangles that block no ray of the batch (sorted or not; any size).
  std::span<const uint32_t> ignore_triangles;
  // Asked between streams of rays: once it says stop, the trace stops and
  // returns its CANCELLED or DEADLINE_EXCEEDED.
  StopToken stop;
};

// Embree's BVH build quality. On the shared scenes (tests/bench/structure_bench.cpp,
// 4 runs on a shared 2-core machine) MEDIUM builds 2.2-5x faster than HIGH.
// It traces coherent shadow segments as fast or faster on the "ajar" room
// and the bunny, and 1-15 % slower on Sponza (7 % on average); closest hits
// 10-23 % slower on Sponza, whose large thin triangles HIGH's spatial splits
// serve better. So HIGH stays the default, and callers that cast shadow
// segments and must build fast (a level's first query) ask for MEDIUM.
enum class BuildQuality { kMedium, kHigh };

struct EmbreeSceneOptions {
  // Meshes the scene places more than once (Scene::placements) are built
  // once and traced as Embree instances where the instance transform keeps
  // the precision of the flattened upload (InstanceKeepsPrecision in the
  // .cpp) and the mesh has two such placements at least; false flattens
  // everything.
  bool instance_meshes = true;
  // Placements with the same world transform traced as one instance where
  // that holds each mesh once (see Instancing in the .cpp); false: one
  // instance per placement (for benchmarks to compare).
  bool group_placements = true;
  // The frame origin for the float32 upload; default: scene bounds center.
  std::optional<glm::dvec3> origin;
  BuildQuality quality = BuildQuality::kHigh;
  // Create's own scene, shared: Embree then reads the scene's triangle
  // indices in place instead of copying them (12 bytes a triangle), and the
  // EmbreeScene keeps the scene alive. Ignored when it is another object.
  std::shared_ptr<const Scene> shared_scene;
  // Asked while the BVH is built: once it says stop, the build stops and
  // Create returns CANCELLED (a server shutting down does not wait for a
  // build of millions of triangles).
  StopToken stop;
};

class EmbreeScene {
 public:
  [[nodiscard]] static StatusOr<EmbreeScene> Create(const Scene& scene,
                                                    const EmbreeSceneOptions& options = {});
  EmbreeScene(EmbreeScene&& other) noexcept;
  EmbreeScene& operator=(EmbreeScene&& other) noexcept;
  EmbreeScene(const EmbreeScene&) = delete;
  EmbreeScene& operator=(const EmbreeScene&) = delete;
  ~EmbreeScene();

  // For each segment, whether some triangle blocks the open segment (p, q).
  //
  // Semantics: the segment is traced for t in [t0, t1] of p + t (q - p) with
  // t0 = delta_p / |q - p| and t1 = 1 - delta_q / |q - p|, where delta_p =
  // 2^-17 * max(largest absolute coordinate of p in the upload frame, 1/8 of
  // the scene extent) and delta_q the same over p and q together (the ray
  // starts at p: its far end carries the rounding of the whole segment). A
  // triangle that only touches an endpoint (the receiver surface at p, the
  // light at q) therefore does not block, and a light far out in empty space
  // does not blunt the receiver's end. Why this delta:
  // the float32 upload rounds vertices by up to 2^-24 of that magnitude and
  // Embree's watertight test adds a few ulps more; 2^-17 is 128 such ulps, so
  // a triangle through an endpoint is skipped robustly, while occluders
  // closer than delta to an endpoint (1e-5 of the scene size) are missed.
  // Degenerate segments (p == q) are never blocked.
  [[nodiscard]] StatusOr<std::vector<uint8_t>> Occluded(std::span<const Segment> segments,
                                                        const TraceOptions& options = {}) const;
  // The same for `count` segments made on the fly by segment_at(i), called
  // from the tracing threads: a million segments need not be stored first
  // (56 MB, whose page faults alone cost more than tracing them).
  [[nodiscard]] StatusOr<std::vector<uint8_t>> Occluded(size_t count,
                                                        const std::function<Segment(size_t)>& segment_at,
                                                        const TraceOptions& options = {}) const;

  // Closest hit for each ray, t in [t0, tmax] with the same offset rule as
  // Occluded at the origin (t0 = delta / |direction|). Hit::t is Embree's
  // float32 distance: relative precision about 1e-7 of M.
  [[nodiscard]] StatusOr<std::vector<Hit>> Intersect(std::span<const Ray> rays,
                                                     const TraceOptions& options = {}) const;

  const glm::dvec3& origin() const { return origin_; }
  const Bounds& bounds() const { return bounds_; }  // of the positions uploaded, world space
  // Bytes Embree holds for this scene (its memory monitor callback).
  size_t memory_bytes() const { return memory_ ? static_cast<size_t>(memory_->load()) : 0; }
  size_t triangle_count() const { return triangle_count_; }
  // For each of scene.placements, whether Create traces it as an instance
  // (with `options`; the frame origin as Create chooses it): what memory
  // estimates count by.
  static std::vector<uint8_t> TracedAsInstances(const Scene& scene, const EmbreeSceneOptions& options = {});

  // The placements traced as instances, and the triangles they stand for;
  // the Embree instances they make (one per distinct world transform).
  size_t instance_count() const;
  size_t instance_group_count() const;
  size_t instanced_triangle_count() const;

  struct Instancing;  // the instanced meshes and how hits map back to scene triangles

 private:
  EmbreeScene() = default;
  void Reset();
  [[nodiscard]] Status AddInstances(const Scene& scene, const EmbreeSceneOptions& options,
                                    const std::vector<uint8_t>& traced_as_instance, std::vector<uint8_t>& instanced);

  std::shared_ptr<const Scene> shared_scene_;  // whose index buffer Embree reads, or null
  RTCDeviceTy* device_ = nullptr;
  RTCSceneTy* scene_ = nullptr;
  std::unique_ptr<std::atomic<int64_t>> memory_;  // stable address for the callback
  glm::dvec3 origin_{0.0};
  double extent_ = 0.0;
  Bounds bounds_;
  size_t triangle_count_ = 0;
  std::unique_ptr<Instancing> instancing_;  // null: every triangle in one flattened geometry
};

}  // namespace visq::raycast
