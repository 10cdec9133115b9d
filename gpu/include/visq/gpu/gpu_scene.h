// A scene's triangles resident on the GPU, uploaded lazily by the first query
// that needs them. Positions are stored as float32 relative to an anchor (the
// scene's bounds center): algorithms build their transforms in double
// relative to the same anchor, so a world far from the origin loses nothing
// beyond float32 precision over the scene's own extent.
#pragma once

#include <cstdint>
#include <memory>
#include <optional>
#include <span>
#include <utility>
#include <vector>

#include <glm/glm.hpp>

#include "common/status.h"
#include "scene/scene.h"
#include "visq/gpu/gpu_worker.h"
#include "visq/gpu/triangle_clusters.h"

namespace visq::gpu {

// Part of a scene to draw, planned on the CPU (any thread) and issued on the
// GL thread by DrawScenePart (src/scene_draw.h). `commands` holds GL's
// indirect draw records: 5 uints a draw (count, instances, first index,
// base vertex, base instance) for clusters of the element buffer, 4 (count,
// instances, first corner, base instance) otherwise.
struct ScenePartDraw {
  bool everything = false;  // the whole scene, in the scene's triangle order
  bool indexed = false;
  std::vector<uint32_t> commands;
  uint64_t triangles = 0;  // drawn, placements counted
  size_t draws() const { return commands.size() / (indexed ? 5 : 4); }
};

class GpuScene {
 public:
  // Runs the upload on the GL thread and waits for it. Positions are stored
  // as float32 relative to `anchor` (default: the scene's bounds centre).
  // A mesh the scene places more than once (Scene::placements, those that
  // match their flattened triangles) is held once in its own space and drawn
  // at each placement through an affine record (src/gpu_scene_resources.h).
  [[nodiscard]] static StatusOr<std::shared_ptr<GpuScene>> Upload(GpuWorker& worker, const Scene& scene,
                                                                  std::optional<glm::dvec3> anchor = std::nullopt);
  // The GPU bytes Upload will hold for `scene`, exactly; no GL.
  static uint64_t EstimateBytes(const Scene& scene);
  ~GpuScene();  // releases the GL objects on the GL thread
  GpuScene(const GpuScene&) = delete;
  GpuScene& operator=(const GpuScene&) = delete;

  const glm::dvec3& anchor() const { return anchor_; }
  const Bounds& bounds() const { return bounds_; }  // of the positions uploaded, world space
  uint32_t triangle_count() const { return triangle_count_; }  // the scene's, placements flattened
  uint32_t held_triangle_count() const { return held_triangles_; }  // in the GPU's buffers
  uint32_t instance_count() const { return static_cast<uint32_t>(instances_.size()); }
  uint64_t gpu_bytes() const { return gpu_bytes_; }

  // Every triangle once, in the scene's order.
  ScenePartDraw Whole() const;
  // The same draw as commands on the CPU, which a draw cut into pieces needs.
  ScenePartDraw WholeAsCommands() const;
  // The clusters (TriangleClusters) of every part, unplaced triangles and
  // each placement, not wholly outside one of `planes` ((n, w) in
  // anchor-relative space, inside where n . x + w >= 0): they hold every
  // triangle a float32 evaluation of the planes at the placed corners keeps.
  // Unplaced triangles are drawn with the identity record, whose triangle
  // offset is 0: a shader drawing them must not need SceneTriangle().
  ScenePartDraw ClustersInside(std::span<const glm::vec4> planes) const;
  // The scene's triangles [first, first + count) of each range.
  ScenePartDraw TriangleRanges(std::span<const std::pair<uint32_t, uint32_t>> ranges) const;

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
  // A run of the scene's triangle order drawn with one record: unplaced
  // triangles (the identity) or one placement of a held mesh.
  struct Segment {
    uint32_t first_triangle = 0;  // the scene's
    uint32_t count = 0;
    uint32_t buffer_triangle = 0;  // where its corners start in the buffer, over 3
    uint32_t record = 0;
    int32_t mesh = -1;  // into meshes_, for a placement
  };
  // A mesh held once: its triangles in the buffer and its own clusters,
  // whose order starts at `element_triangle` of the element buffer.
  struct HeldMesh {
    TriangleClusters clusters;
    uint32_t element_triangle = 0;
    glm::dvec3 lo{0.0}, hi{0.0};  // its float corners' box, own space
  };
  struct Placed {
    uint32_t segment = 0;
    glm::dmat4 place{1.0};  // own space to anchor-relative
    glm::dvec3 lo{0.0}, hi{0.0};  // anchor-relative box
    // Per axis, |A| |x| + |t| over the mesh's box: the magnitude at which
    // the shader's float transform rounds.
    glm::dvec3 reach{0.0};
  };
  GpuWorker* worker_ = nullptr;
  std::shared_ptr<Resources> resources_;
  glm::dvec3 anchor_{0.0};
  Bounds bounds_;
  TriangleClusters clusters_;  // the unplaced triangles', from element 0
  std::vector<Segment> segments_;
  std::vector<HeldMesh> meshes_;
  std::vector<Placed> instances_;
  uint32_t triangle_count_ = 0;
  uint32_t held_triangles_ = 0;
  uint64_t gpu_bytes_ = 0;
  uint64_t generation_ = 0;
};

}  // namespace visq::gpu
