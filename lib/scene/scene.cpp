#include "scene/scene.h"

namespace visq {

size_t Scene::CpuBytes() const {
  size_t bytes = positions.capacity() * sizeof(glm::dvec3) + triangles.capacity() * sizeof(glm::uvec3) +
                 triangle_material.capacity() * sizeof(uint32_t) +
                 triangle_node.capacity() * sizeof(uint32_t) + lightmap_uvs.capacity() * sizeof(glm::vec2);
  for (const auto& m : materials) bytes += sizeof(Material) + m.name.capacity();
  for (const auto& n : nodes) bytes += sizeof(SceneNode) + n.name.capacity();
  return bytes;
}

}  // namespace visq
