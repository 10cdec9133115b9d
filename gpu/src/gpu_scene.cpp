#include "visq/gpu/gpu_scene.h"

#include <algorithm>
#include <vector>

#include "gl_check.h"
#include "gpu_scene_resources.h"

namespace visq::gpu {

StatusOr<std::shared_ptr<GpuScene>> GpuScene::Upload(GpuWorker& worker, const Scene& scene,
                                                     std::optional<glm::dvec3> anchor) {
  std::shared_ptr<GpuScene> out(new GpuScene());
  out->worker_ = &worker;
  out->anchor_ = anchor.value_or(scene.bounds.Empty() ? glm::dvec3(0.0) : scene.bounds.Center());
  out->bounds_ = scene.bounds;
  out->triangle_count_ = static_cast<uint32_t>(scene.TriangleCount());

  // Corner positions relative to the anchor, converted on this thread so the
  // GL thread only copies.
  std::vector<glm::vec3> corners;
  corners.reserve(scene.TriangleCount() * 3);
  for (size_t t = 0; t < scene.TriangleCount(); ++t)
    for (int c = 0; c < 3; ++c) corners.emplace_back(scene.Vertex(t, c) - out->anchor_);
  // The cluster hierarchy, over the very floats the GPU gets, and its order
  // as corner indices for the element buffer.
  std::vector<uint32_t> order;
  out->clusters_ = TriangleClusters::Build(corners, order);
  std::vector<uint32_t> cluster_corners;
  cluster_corners.reserve(order.size() * 3);
  for (const uint32_t t : order)
    for (uint32_t c = 0; c < 3; ++c) cluster_corners.push_back(3 * t + c);
  std::vector<uint32_t>().swap(order);

  Status status = worker.Run({}, [&]() -> Status {
    auto resources = std::make_shared<Resources>();
    // GL refuses zero-sized storage: an empty scene gets one unused element.
    const glm::vec3 no_corner(0.0f);
    const uint32_t no_material = 0;
    glNamedBufferStorage(resources->positions.id(), std::max<size_t>(corners.size(), 1) * sizeof(glm::vec3),
                         corners.empty() ? &no_corner : corners.data(), 0);
    glNamedBufferStorage(resources->triangle_materials.id(),
                         std::max<size_t>(scene.triangle_material.size(), 1) * sizeof(uint32_t),
                         scene.triangle_material.empty() ? &no_material : scene.triangle_material.data(), 0);
    const uint32_t no_index = 0;
    glNamedBufferStorage(resources->cluster_order.id(), std::max<size_t>(cluster_corners.size(), 1) * sizeof(uint32_t),
                         cluster_corners.empty() ? &no_index : cluster_corners.data(), 0);
    const GLuint vao = resources->vertex_array.id();
    glVertexArrayElementBuffer(vao, resources->cluster_order.id());
    glVertexArrayVertexBuffer(vao, 0, resources->positions.id(), 0, sizeof(glm::vec3));
    glEnableVertexArrayAttrib(vao, 0);
    glVertexArrayAttribFormat(vao, 0, 3, GL_FLOAT, GL_FALSE, 0);
    glVertexArrayAttribBinding(vao, 0, 0);
    resources->vertex_count = static_cast<GLsizei>(corners.size());
    VISQ_RETURN_IF_ERROR(CollectGlErrors("scene upload"));
    out->resources_ = std::move(resources);
    out->generation_ = CurrentContextGeneration();
    return absl::OkStatus();
  });
  VISQ_RETURN_IF_ERROR(status);
  out->gpu_bytes_ = corners.size() * sizeof(glm::vec3) + scene.triangle_material.size() * sizeof(uint32_t) +
                    cluster_corners.size() * sizeof(uint32_t);
  return out;
}

StatusOr<const GpuScene::Resources*> GpuScene::CurrentResources() const {
  if (generation_ != CurrentContextGeneration())
    return absl::InternalError("the GPU context holding this scene's buffers was lost; the next request re-uploads it");
  return resources_.get();
}

GpuScene::~GpuScene() {
  // GL objects die on the GL thread: the posted job holds the last reference.
  if (resources_ && worker_) worker_->Post([resources = std::move(resources_)]() mutable { resources.reset(); });
}

}  // namespace visq::gpu
