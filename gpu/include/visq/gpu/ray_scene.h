// Rays on the GPU: a scene's flat BVH (raycast::BuildFlatBvh) resident in
// shader storage, and occlusion segments traced against it by a compute
// shader (gpu/rays/rays_trace.comp): a stack traversal and a watertight
// triangle test (Woop, Benthin and Wald 2013). The segments are the
// FloatSegments Embree traces (raycast/float_segment.h), so the two tracers
// agree bit for bit except where a segment ties with a triangle's edge or
// plane in float arithmetic.
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <span>
#include <vector>

#include "common/status.h"
#include "raycast/embree_scene.h"
#include "raycast/flat_bvh.h"
#include "raycast/float_segment.h"
#include "visq/gpu/gpu_worker.h"

namespace visq::gpu {

struct RayTraceOptions {
  JobOptions job;
  // Segments a GL job traces at first; each next job is sized by the last
  // one's time towards target_job_ms (a call's stop and other calls' jobs
  // get the GL thread between jobs).
  uint32_t first_job_segments = 16384;
  double target_job_ms = 50.0;
};

class RayScene {
 public:
  // Uploads `bvh` on the GL thread and waits for it.
  [[nodiscard]] static StatusOr<std::shared_ptr<RayScene>> Upload(GpuWorker& worker, const raycast::FlatBvh& bvh,
                                                                  const JobOptions& job = {});
  ~RayScene();  // releases the GL objects on the GL thread
  RayScene(const RayScene&) = delete;
  RayScene& operator=(const RayScene&) = delete;

  // For each of `count` segments made by segment_at(i) (on the caller's
  // threads), whether a triangle other than its ignore_triangle blocks it,
  // with raycast::EmbreeScene::Occluded's semantics in this scene's frame.
  [[nodiscard]] StatusOr<std::vector<uint8_t>> Occluded(size_t count,
                                                        const std::function<raycast::Segment(size_t)>& segment_at,
                                                        const RayTraceOptions& options = {}) const;

  // The closest hit of each ray, t in [its origin's offset, tmax], with
  // raycast::EmbreeScene::Intersect's semantics in this scene's frame (u,
  // v: the weights of the triangle's corners 1 and 2).
  [[nodiscard]] StatusOr<std::vector<raycast::Hit>> Intersect(std::span<const raycast::Ray> rays,
                                                              const RayTraceOptions& options = {}) const;

  const glm::dvec3& origin() const { return origin_; }
  double extent() const { return extent_; }
  uint64_t gpu_bytes() const { return gpu_bytes_; }
  size_t triangle_count() const { return triangle_count_; }
  // False once the context the buffers live in was lost.
  bool IsCurrent() const;

  struct Resources;

 private:
  RayScene() = default;
  using SegmentMaker = std::function<void(size_t i, raycast::FloatSegment& segment, uint32_t& ignore)>;
  struct GpuHit;  // rays_trace.comp's closest hit
  using JobResults = std::function<void(size_t begin, size_t n, const std::vector<uint32_t>& bits,
                                        const std::vector<GpuHit>& hits)>;
  [[nodiscard]] Status Trace(size_t count, const SegmentMaker& make, bool closest, const RayTraceOptions& options,
                             const JobResults& take) const;
  GpuWorker* worker_ = nullptr;
  uint64_t generation_ = 0;
  std::shared_ptr<Resources> resources_;
  glm::dvec3 origin_{0.0};
  double extent_ = 0.0;
  uint64_t gpu_bytes_ = 0;
  size_t triangle_count_ = 0;
  uint32_t node_count_ = 0;
};

}  // namespace visq::gpu
