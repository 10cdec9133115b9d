// The resident scene model: exactly what visibility queries need and nothing
// more. Positions are in world space in double precision, so that worlds far
// from the origin keep their detail; GPU paths re-center on the query before
// converting to float. A mesh the file places more than once is held once
// with its placements, and flattened only where a consumer asks for it.
#pragma once

#include <atomic>
#include <cmath>
#include <functional>
#include <span>
#include <memory>
#include <mutex>
#include <utility>
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

// The triangles and what each position carries, in one index space: the
// scene of record's unplaced triangles (Scene), or every triangle of the
// scene flattened to world space (Scene::Flattened).
struct TriangleArrays {
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

  size_t Bytes() const;
};

// A mesh that the file places more than once (nodes sharing a glTF mesh, or
// EXT_mesh_gpu_instancing), held once in its own coordinates: the scene of
// record keeps its placements as placements, and each structure built over
// the scene holds it once and places it as instances.
struct SceneMesh {
  std::vector<glm::dvec3> positions;  // mesh space
  std::vector<glm::uvec3> triangles;  // into positions, corners in the order the placements store them
  // Per triangle, the same at every placement.
  std::vector<uint32_t> triangle_material;
  // Per position, where the scene keeps them: lightmap UVs and texture
  // coordinates as they are, normals in mesh space as the file gave them
  // (placed: UnitNormal(inverseTranspose(dmat3(world)), normal)).
  std::vector<glm::vec2> lightmap_uvs;
  std::vector<glm::vec3> normals;
  std::vector<std::vector<glm::vec2>> texcoords;
};

// One placement of a SceneMesh: the scene's triangles [first_triangle,
// first_triangle + mesh.triangles.size()) and, flattened, its positions
// [first_position, first_position + mesh.positions.size()), with
//   flattened triangle first_triangle + i == mesh.triangles[i] + first_position
//   flattened position first_position + j == PlacePoint(world, mesh.positions[j])  (bit for bit)
// Ordered by first_triangle and disjoint; the scene of record holds the
// triangles of no placement (unplaced) in its own arrays, in order.
struct MeshPlacement {
  uint32_t mesh = 0;  // into Scene::meshes
  uint32_t first_triangle = 0;
  uint32_t first_position = 0;
  glm::dmat4 world{1.0};
  uint32_t node = 0;  // into Scene::nodes: every triangle of the placement's
  // The unplaced triangles and positions before this placement (indices
  // into the scene of record's arrays where the placement would stand).
  uint32_t unplaced_triangles_before = 0;
  uint32_t unplaced_positions_before = 0;
};

// A normal carried to world space by `normal_matrix` (the inverse transpose
// of the placement's 3x3), unit again; one of no direction stays zero.
inline glm::vec3 UnitNormal(const glm::dmat3& normal_matrix, const glm::vec3& normal) {
  const glm::dvec3 turned = normal_matrix * glm::dvec3(normal);
  const double length = glm::length(turned);
  return length > 0.0 && std::isfinite(length) ? glm::vec3(turned / length) : glm::vec3(0.0f);
}

struct Scene;

// The whole scene flattened, built on the first request and kept: a copy
// of a scene starts without it, and an edit of the record drops it.
class LazyFlattened {
 public:
  LazyFlattened() : state_(std::make_unique<State>()) {}
  LazyFlattened(const LazyFlattened&) : LazyFlattened() {}
  LazyFlattened& operator=(const LazyFlattened&) {
    state_ = std::make_unique<State>();
    return *this;
  }
  LazyFlattened(LazyFlattened&& other) noexcept : state_(std::exchange(other.state_, std::make_unique<State>())) {}
  LazyFlattened& operator=(LazyFlattened&& other) noexcept {
    state_ = std::exchange(other.state_, std::make_unique<State>());
    return *this;
  }
  // Flattens `record` on the first call, whichever thread asks first; the
  // others wait for it.
  const Scene& Get(const Scene& record) const;
  // The flattened scene's bytes, 0 before it is built; never waits.
  size_t Bytes() const;
  bool Built() const { return state_->built.load(std::memory_order_acquire); }

 private:
  struct State {
    std::once_flag once;
    std::atomic<bool> built{false};
    std::shared_ptr<const Scene> scene;
  };
  std::unique_ptr<State> state_;
};

// The scene of record: the unplaced triangles in the inherited arrays, the
// repeated meshes once, and where each is placed. Triangle indices (of
// nodes, queries' answers, structures) run over the whole scene in the
// flattened order: the unplaced and the placed ones interleaved as the file
// placed them. A scene without placements is its own flattened scene.
struct Scene : TriangleArrays {
  std::vector<Material> materials;
  std::vector<SceneNode> nodes;
  std::vector<SceneMesh> meshes;
  std::vector<MeshPlacement> placements;
  Bounds bounds;

  // Placed triangles and positions counted.
  size_t TriangleCount() const;
  size_t PositionCount() const;

  // Where triangle t (in the whole scene's order) is held: placements[placement]'s
  // mesh triangle `index`, or (placement < 0) the record's triangle `index`.
  struct Held {
    int64_t placement = -1;
    uint32_t index = 0;
  };
  Held Locate(size_t triangle) const;
  glm::dvec3 Vertex(size_t triangle, int corner) const;
  uint32_t MaterialOf(size_t triangle) const;
  uint32_t NodeOf(size_t triangle) const;

  // The scene with every triangle flattened to world space and no
  // placements, for a consumer that needs the whole scene flat (the bake's
  // atlas, the export): the record itself without placements, else built
  // once on first request and kept (counted in CpuBytes from then on).
  // Thread-safe.
  const Scene& Flattened() const;
  bool FlattenedBuilt() const { return placements.empty() || flattened_.Built(); }
  // After an edit of the record's arrays or placements.
  void DropFlattened() { flattened_ = LazyFlattened(); }

  size_t CpuBytes() const;

 private:
  LazyFlattened flattened_;
};

// Whether `placement` is in range: its mesh exists and its corners index
// the mesh's positions. (A placement of the record stands for its
// triangles by construction: HoldPlacementsOnce.)
bool PlacementInRange(const Scene& scene, const MeshPlacement& placement);

// INVALID_ARGUMENT naming the first placement that is out of range,
// overlaps another, or whose counts of unplaced triangles and positions
// before it disagree with the record.
[[nodiscard]] Status ValidatePlacements(const Scene& scene);

// A scene whose arrays hold every triangle flattened, with `placements`
// (and their meshes' positions and triangles) pointing into them, made a
// scene of record: each placement that stands for its flattened triangles
// and positions bit for bit (PlacePoint, the same materials, node and
// per-position attributes as its mesh's first placement) is taken out of
// the arrays and held by its mesh; the others are forgotten (their
// triangles stay unplaced). The loader and the scene's editors call it.
void HoldPlacementsOnce(Scene& scene);

// The inverse: every placement's triangles back in the record's arrays
// (placements kept, pointing into them again), as HoldPlacementsOnce
// takes them. Until then only the arrays describe the scene (TriangleCount
// and the per-triangle accessors do not): for an edit between the two.
void FlattenPlacements(Scene& scene);

// Some triangles flattened, for a structure that holds the rest as
// instances: the triangles whose `skip` is 0 (all where `skip` is empty),
// in order, over the world positions they use.
struct FlattenedPart {
  std::vector<glm::dvec3> positions;
  std::vector<glm::uvec3> triangles;     // into positions
  std::vector<uint32_t> scene_triangle;  // each one's index in the scene
};
FlattenedPart FlattenPart(const Scene& scene, const std::vector<uint8_t>& skip);

// The bounds of every position, placed ones included.
Bounds PositionBounds(const Scene& scene);

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
