// The resident scene model: exactly what visibility queries need and nothing
// more. Positions are flattened to world space in double precision, so that
// worlds far from the origin keep their detail; GPU paths re-center on the
// query before converting to float.
#pragma once

#include <cmath>
#include <cstdint>
#include <limits>
#include <string>
#include <vector>

#include <glm/glm.hpp>

#include "common/status.h"

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

// Where a point of a mesh lands in the world. Every flattened position is
// computed by this one expression, so that a structure that keeps a mesh
// once and places it again gets the flattened scene's doubles to the bit.
inline glm::dvec3 PlacePoint(const glm::dmat4& world, const glm::dvec3& point) {
  return glm::dvec3(world * glm::dvec4(point, 1.0));
}

// A mesh that the file places more than once (nodes sharing a glTF mesh, or
// EXT_mesh_gpu_instancing), held once in its own coordinates so that the
// structures built over the scene can hold it once and place it as
// instances. The flattened arrays stay the scene of record.
struct SceneMesh {
  std::vector<glm::dvec3> positions;  // mesh space
  std::vector<glm::uvec3> triangles;  // into positions, corners in the order the placements store them
};

// One placement of a SceneMesh. For i < mesh.triangles.size() and
// j < mesh.positions.size():
//   Scene::triangles[first_triangle + i] == mesh.triangles[i] + first_position
//   Scene::positions[first_position + j] == PlacePoint(world, mesh.positions[j])  (bit for bit)
// (ValidatePlacements checks both).
struct MeshPlacement {
  uint32_t mesh = 0;  // into Scene::meshes
  uint32_t first_triangle = 0;
  uint32_t first_position = 0;
  glm::dmat4 world{1.0};
};

// A normal carried to world space by `normal_matrix` (the inverse transpose
// of the placement's 3x3), unit again; one of no direction stays zero.
inline glm::vec3 UnitNormal(const glm::dmat3& normal_matrix, const glm::vec3& normal) {
  const glm::dvec3 turned = normal_matrix * glm::dvec3(normal);
  const double length = glm::length(turned);
  return length > 0.0 && std::isfinite(length) ? glm::vec3(turned / length) : glm::vec3(0.0f);
}

struct Scene {
  std::vector<glm::dvec3> positions;        // world space
  std::vector<glm::uvec3> triangles;        // counter-clockwise = front
  std::vector<uint32_t> triangle_material;  // index into materials
  std::vector<uint32_t> triangle_node;      // index into nodes
  std::vector<glm::vec2> lightmap_uvs;      // TEXCOORD_1 per position; empty if absent
  // What no query reads but an export writes back, so that the game mesh
  // returns to the studio's tools as it came (obscurance_export.h): NORMAL
  // per position, world space and unit (empty unless every primitive has
  // one), and TEXCOORD_0 .. TEXCOORD_{k-1} per position, the k sets (at most
  // kMaxKeptTexcoordSets) that every primitive has. A kept TEXCOORD_1 is
  // lightmap_uvs again: 8 bytes a position, against a second representation.
  std::vector<glm::vec3> normals;
  std::vector<std::vector<glm::vec2>> texcoords;
  std::vector<Material> materials;
  std::vector<SceneNode> nodes;
  // Repeated meshes and where each stands, ordered by first_triangle and
  // disjoint; triangles of no placement are unique.
  std::vector<SceneMesh> meshes;
  std::vector<MeshPlacement> placements;
  Bounds bounds;

  size_t TriangleCount() const { return triangles.size(); }
  glm::dvec3 Vertex(size_t triangle, int corner) const {
    return positions[triangles[triangle][corner]];
  }
  size_t CpuBytes() const;
};

// Whether `placement` is in range and stands for its flattened triangles
// and positions exactly (the invariant of MeshPlacement). Structures that
// instance a placement check it first and flatten one that does not.
bool PlacementMatchesFlattened(const Scene& scene, const MeshPlacement& placement);

// INVALID_ARGUMENT naming the first placement that is out of range, overlaps
// another, or differs from the flattened triangles and positions it stands
// for (the invariant of MeshPlacement).
[[nodiscard]] Status ValidatePlacements(const Scene& scene);

// Whether a structure that places a mesh with a float32 transform (Embree
// moving rays into the mesh's space, the GPU moving the mesh's corners into
// the upload's frame) keeps the flattened upload's precision. Flattened, a
// vertex is rounded once, by an ulp of its coordinate in the frame centred
// at `origin`. Placed, the float transform picks up a few ulps of |x| times
// the transform's condition number and scale, and of the translation. With
// the condition number at most 2, the translation within `extent` (the
// upload's largest extent) of `origin` and the placed mesh within `extent`
// of its own origin, that stays within about 8 ulps of the extent (Embree's
// tracing offset leaves 32; the GPU's tests resolve the scene's extent at
// float32). Other placements (strong shears or scales, meshes modelled far
// from their origin) are flattened. `mesh_magnitude`: the mesh's largest
// |coordinate| (MeshMagnitudes).
bool PlacementKeepsFloatPrecision(const glm::dmat4& world, double mesh_magnitude, const glm::dvec3& origin,
                                  double extent);
std::vector<double> MeshMagnitudes(const Scene& scene);

// The most TEXCOORD sets a scene keeps (glTF asks every viewer for two;
// DCCs write up to eight): each costs 8 bytes a position.
inline constexpr int kMaxKeptTexcoordSets = 4;

// Placements of a mesh with fewer triangles than this are flattened only:
// an instance costs a few hundred bytes in every structure.
inline constexpr uint32_t kFewestTrianglesToInstance = 16;

}  // namespace visq
