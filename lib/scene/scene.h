// The resident scene model: exactly what visibility queries need and nothing
// more. Positions are flattened to world space in double precision, so that
// worlds far from the origin keep their detail; GPU paths re-center on the
// query before converting to float.
#pragma once

#include <cstdint>
#include <limits>
#include <string>
#include <vector>

#include <glm/glm.hpp>

namespace visq {

struct Bounds {
  glm::dvec3 min{std::numeric_limits<double>::infinity()};
  glm::dvec3 max{-std::numeric_limits<double>::infinity()};
  void Extend(const glm::dvec3& p) { min = glm::min(min, p); max = glm::max(max, p); }
  bool Empty() const { return min.x > max.x; }
  glm::dvec3 Center() const { return 0.5 * (min + max); }
  glm::dvec3 Extent() const { return max - min; }
};

struct Material {
  std::string name;
  glm::dvec3 reflectivity{1.0};  // glTF baseColorFactor.rgb
  glm::dvec3 emission{0.0};      // emissiveFactor * KHR_materials_emissive_strength
};

// One glTF node that carries geometry (after flattening) or is an ancestor of
// one. Triangles of a node are contiguous: [first_triangle, first + count).
struct SceneNode {
  std::string name;
  int gltf_index = -1;
  int parent = -1;              // index into Scene::nodes, -1 for a root
  glm::dmat4 world{1.0};        // node-to-world at load time
  uint32_t first_triangle = 0;  // own triangles only, not the subtree's
  uint32_t triangle_count = 0;
};

struct Scene {
  std::vector<glm::dvec3> positions;        // world space
  std::vector<glm::uvec3> triangles;        // counter-clockwise = front
  std::vector<uint32_t> triangle_material;  // index into materials
  std::vector<uint32_t> triangle_node;      // index into nodes
  std::vector<glm::vec2> lightmap_uvs;      // TEXCOORD_1 per position; empty if absent
  std::vector<Material> materials;
  std::vector<SceneNode> nodes;
  Bounds bounds;

  size_t TriangleCount() const { return triangles.size(); }
  glm::dvec3 Vertex(size_t triangle, int corner) const {
    return positions[triangles[triangle][corner]];
  }
  size_t CpuBytes() const;
};

}  // namespace visq
