// A scene's triangles resident on the GPU, uploaded lazily by the first query
// that needs them. Positions are stored as float32 relative to an anchor (the
// scene's bounds center): algorithms build their transforms in double
// relative to the same anchor, so a world far from the origin loses nothing
// beyond float32 precision over the scene's own extent.
#pragma once

#include <memory>
#include <optional>

#include <glm/glm.hpp>

#include "common/status.h"
#include "scene/scene.h"
#include "visq/gpu/gpu_worker.h"
#include "visq/gpu/triangle_clusters.h"

namespace visq::gpu {

class GpuScene {
 public:
  // Runs the upload on the GL thread and waits for it. Positions are stored
  // as float32 relative to `anchor` (default: the scene's bounds centre).
  [[nodiscard]] static StatusOr<std::shared_ptr<GpuScene>> Upload(GpuWorker& worker, const Scene& scene,
                                                                  std::optional<glm::dvec3> anchor = std::nullopt);
  ~GpuScene();  // releases the GL objects on the GL thread
  GpuScene(const GpuScene&) = delete;
  GpuScene& operator=(const GpuScene&) = delete;

  const glm::dvec3& anchor() const { return anchor_; }
  const Bounds& bounds() const { return bounds_; }  // of the positions uploaded, world space
  uint32_t triangle_count() const { return triangle_count_; }
  uint64_t gpu_bytes() const { return gpu_bytes_; }
  // The hierarchy over the triangles' clusters, built at upload; its order
  // is the GPU's element buffer (see src/gpu_scene_resources.h).
  const TriangleClusters& clusters() const { return clusters_; }

  // The worker's context generation the buffers were made in: a cache
  // holding this scene re-uploads when the worker's generation moved on.
  uint64_t context_generation() const { return generation_; }
  bool IsCurrent() const { return worker_ != nullptr && worker_->context_generation() == generation_; }

  // GL objects, for algorithm code inside gpu/ (defined in src/gpu_scene_resources.h).
  // Call on the GL thread; INTERNAL if the context they lived in was lost
  // (the caller's next request re-uploads).
  struct Resources;
  [[nodiscard]] StatusOr<const Resources*> CurrentResources() const;

 private:
  GpuScene() = default;
  GpuWorker* worker_ = nullptr;
  std::shared_ptr<Resources> resources_;
  glm::dvec3 anchor_{0.0};
  Bounds bounds_;
  TriangleClusters clusters_;
  uint32_t triangle_count_ = 0;
  uint64_t gpu_bytes_ = 0;
  uint64_t generation_ = 0;
};

}  // namespace visq::gpu
