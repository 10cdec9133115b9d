#include "scene/scene.h"
#include "scene/placement_checks.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include <glm/gtc/matrix_inverse.hpp>

#include "common/check.h"

namespace visq {

bool PlacementKeepsFloatPrecision(const glm::dmat4& world, double mesh_magnitude, const glm::dvec3& origin,
                                  double extent) {
  const glm::dmat3 linear(world);
  const glm::dmat3 gram = glm::transpose(linear) * linear;
  // Gershgorin bounds the largest eigenvalue of the Gram matrix; with the
  // smallest at least det / largest^2, cond^2 <= largest^3 / det.
  double largest = 0.0;
  for (int r = 0; r < 3; ++r)
    largest = std::max(largest, std::abs(gram[0][r]) + std::abs(gram[1][r]) + std::abs(gram[2][r]));
  const double det = glm::determinant(gram);
  if (!(det > 0.0) || !(largest * largest * largest <= 4.0 * det)) return false;
  const glm::dvec3 translation = glm::dvec3(world[3]) - origin;
  const double offset = std::max({std::abs(translation.x), std::abs(translation.y), std::abs(translation.z)});
  return offset <= extent && mesh_magnitude * std::sqrt(largest) <= extent;
}

std::vector<double> MeshMagnitudes(const Scene& scene) {
  std::vector<double> magnitude(scene.meshes.size(), 0.0);
  for (size_t m = 0; m < scene.meshes.size(); ++m)
    for (const glm::dvec3& p : scene.meshes[m].positions)
      magnitude[m] = std::max({magnitude[m], std::abs(p.x), std::abs(p.y), std::abs(p.z)});
  return magnitude;
}

size_t TriangleArrays::Bytes() const {
  size_t bytes = positions.capacity() * sizeof(glm::dvec3) + triangles.capacity() * sizeof(glm::uvec3) +
                 triangle_material.capacity() * sizeof(uint32_t) + triangle_node.capacity() * sizeof(uint32_t) +
                 lightmap_uvs.capacity() * sizeof(glm::vec2) + normals.capacity() * sizeof(glm::vec3) +
                 texcoords.capacity() * sizeof(std::vector<glm::vec2>);
  for (const auto& set : texcoords) bytes += set.capacity() * sizeof(glm::vec2);
  return bytes;
}

size_t Scene::CpuBytes() const {
  size_t bytes = TriangleArrays::Bytes();
  for (const auto& m : materials) bytes += sizeof(Material) + m.name.capacity();
  for (const auto& n : nodes) bytes += sizeof(SceneNode) + n.name.capacity();
  for (const auto& m : meshes) {
    bytes += sizeof(SceneMesh) + m.positions.capacity() * sizeof(glm::dvec3) +
             m.triangles.capacity() * sizeof(glm::uvec3) + m.triangle_material.capacity() * sizeof(uint32_t) +
             m.lightmap_uvs.capacity() * sizeof(glm::vec2) + m.normals.capacity() * sizeof(glm::vec3);
    for (const auto& set : m.texcoords) bytes += sizeof(set) + set.capacity() * sizeof(glm::vec2);
  }
  bytes += placements.capacity() * sizeof(MeshPlacement);
  if (!placements.empty()) bytes += flattened_.Bytes();
  return bytes;
}

size_t Scene::TriangleCount() const {
  if (placements.empty()) return triangles.size();
  const MeshPlacement& last = placements.back();
  return triangles.size() + (last.first_triangle - last.unplaced_triangles_before) + meshes[last.mesh].triangles.size();
}

size_t Scene::PositionCount() const {
  if (placements.empty()) return positions.size();
  const MeshPlacement& last = placements.back();
  return positions.size() + (last.first_position - last.unplaced_positions_before) + meshes[last.mesh].positions.size();
}

Scene::Held Scene::Locate(size_t triangle) const {
  if (placements.empty()) return {-1, static_cast<uint32_t>(triangle)};
  // The last placement that starts at or before the triangle.
  auto after = std::upper_bound(placements.begin(), placements.end(), triangle,
                                [](size_t t, const MeshPlacement& p) { return t < p.first_triangle; });
  if (after == placements.begin()) return {-1, static_cast<uint32_t>(triangle)};
  const MeshPlacement& p = *(after - 1);
  const size_t end = p.first_triangle + meshes[p.mesh].triangles.size();
  if (triangle < end) return {after - 1 - placements.begin(), static_cast<uint32_t>(triangle - p.first_triangle)};
  return {-1, static_cast<uint32_t>(p.unplaced_triangles_before + (triangle - end))};
}

glm::dvec3 Scene::Vertex(size_t triangle, int corner) const {
  const Held held = Locate(triangle);
  if (held.placement < 0) return positions[triangles[held.index][corner]];
  const MeshPlacement& p = placements[size_t(held.placement)];
  const SceneMesh& mesh = meshes[p.mesh];
  return PlacePoint(p.world, mesh.positions[mesh.triangles[held.index][corner]]);
}

uint32_t Scene::MaterialOf(size_t triangle) const {
  const Held held = Locate(triangle);
  if (held.placement < 0) return held.index < triangle_material.size() ? triangle_material[held.index] : 0u;
  const SceneMesh& mesh = meshes[placements[size_t(held.placement)].mesh];
  return held.index < mesh.triangle_material.size() ? mesh.triangle_material[held.index] : 0u;
}

uint32_t Scene::NodeOf(size_t triangle) const {
  const Held held = Locate(triangle);
  if (held.placement < 0) return held.index < triangle_node.size() ? triangle_node[held.index] : 0u;
  return placements[size_t(held.placement)].node;
}

namespace {

// Appends to `out` the record's unplaced triangles and positions and the
// placements' in the flattened order. The record keeps its positions in
// that order too, between the placements'.
struct Flattener {
  const Scene& scene;
  TriangleArrays& out;
  bool with_materials, with_nodes;
  uint32_t record_position = 0;  // the record's positions taken so far

  void Positions(uint32_t end) {
    for (uint32_t j = record_position; j < end; ++j) {
      out.positions.push_back(scene.positions[j]);
      if (!scene.lightmap_uvs.empty()) out.lightmap_uvs.push_back(scene.lightmap_uvs[j]);
      if (!scene.normals.empty()) out.normals.push_back(scene.normals[j]);
      for (size_t s = 0; s < scene.texcoords.size(); ++s) out.texcoords[s].push_back(scene.texcoords[s][j]);
    }
    record_position = std::max(record_position, end);
  }
  void Triangles(uint32_t first, uint32_t end, uint32_t position_shift) {
    for (uint32_t t = first; t < end; ++t) {
      out.triangles.push_back(scene.triangles[t] + glm::uvec3(position_shift));
      if (with_materials) out.triangle_material.push_back(scene.triangle_material[t]);
      if (with_nodes) out.triangle_node.push_back(scene.triangle_node[t]);
    }
  }
  void Placement(const MeshPlacement& p) {
    const SceneMesh& mesh = scene.meshes[p.mesh];
    const auto base = static_cast<uint32_t>(out.positions.size());
    for (const glm::dvec3& x : mesh.positions) out.positions.push_back(PlacePoint(p.world, x));
    if (!scene.lightmap_uvs.empty())
      out.lightmap_uvs.insert(out.lightmap_uvs.end(), mesh.lightmap_uvs.begin(), mesh.lightmap_uvs.end());
    if (!scene.normals.empty()) {
      const glm::dmat3 normal_matrix = glm::inverseTranspose(glm::dmat3(p.world));
      for (const glm::vec3& n : mesh.normals) out.normals.push_back(UnitNormal(normal_matrix, n));
    }
    for (size_t s = 0; s < scene.texcoords.size(); ++s)
      out.texcoords[s].insert(out.texcoords[s].end(), mesh.texcoords[s].begin(), mesh.texcoords[s].end());
    for (size_t i = 0; i < mesh.triangles.size(); ++i) {
      out.triangles.push_back(mesh.triangles[i] + glm::uvec3(base));
      if (with_materials) out.triangle_material.push_back(mesh.triangle_material[i]);
      if (with_nodes) out.triangle_node.push_back(p.node);
    }
  }
};

TriangleArrays FlattenAll(const Scene& scene) {
  TriangleArrays out;
  const size_t triangles = scene.TriangleCount(), positions = scene.PositionCount();
  const bool with_materials = scene.triangle_material.size() == scene.triangles.size();
  const bool with_nodes = scene.triangle_node.size() == scene.triangles.size();
  out.positions.reserve(positions);
  out.triangles.reserve(triangles);
  if (with_materials) out.triangle_material.reserve(triangles);
  if (with_nodes) out.triangle_node.reserve(triangles);
  if (!scene.lightmap_uvs.empty()) out.lightmap_uvs.reserve(positions);
  if (!scene.normals.empty()) out.normals.reserve(positions);
  out.texcoords.resize(scene.texcoords.size());
  for (auto& set : out.texcoords) set.reserve(positions);
  Flattener flat{scene, out, with_materials, with_nodes};
  uint32_t record_triangle = 0;
  for (const MeshPlacement& p : scene.placements) {
    flat.Positions(p.unplaced_positions_before);
    flat.Triangles(record_triangle, p.unplaced_triangles_before,
                   static_cast<uint32_t>(out.positions.size()) - flat.record_position);
    record_triangle = p.unplaced_triangles_before;
    flat.Placement(p);
  }
  flat.Positions(static_cast<uint32_t>(scene.positions.size()));
  flat.Triangles(record_triangle, static_cast<uint32_t>(scene.triangles.size()),
                 static_cast<uint32_t>(out.positions.size()) - flat.record_position);
  VISQ_CHECK_EQ(out.triangles.size(), triangles);
  VISQ_CHECK_EQ(out.positions.size(), positions);
  return out;
}

}  // namespace

const Scene& LazyFlattened::Get(const Scene& record) const {
  std::call_once(state_->once, [&] {
    auto flat = std::make_shared<Scene>();
    static_cast<TriangleArrays&>(*flat) = FlattenAll(record);
    flat->materials = record.materials;
    flat->nodes = record.nodes;
    flat->bounds = record.bounds;
    state_->scene = std::move(flat);
    state_->built.store(true, std::memory_order_release);
  });
  return *state_->scene;
}

size_t LazyFlattened::Bytes() const { return Built() ? state_->scene->CpuBytes() : 0; }

const Scene& Scene::Flattened() const {
  if (placements.empty()) return *this;
  return flattened_.Get(*this);
}

bool PlacementInRange(const Scene& scene, const MeshPlacement& placement) {
  if (placement.mesh >= scene.meshes.size()) return false;
  const SceneMesh& mesh = scene.meshes[placement.mesh];
  for (const glm::uvec3& t : mesh.triangles)
    if (glm::any(glm::greaterThanEqual(t, glm::uvec3(mesh.positions.size())))) return false;
  return placement.node < scene.nodes.size() || scene.nodes.empty();
}

Status ValidatePlacements(const Scene& scene) {
  uint64_t end_of_previous = 0, placed_triangles = 0, placed_positions = 0;
  uint64_t unplaced_triangles = 0, unplaced_positions = 0;
  const std::vector<uint8_t> in_range = PlacementsInRange(scene);
  for (size_t k = 0; k < scene.placements.size(); ++k) {
    const MeshPlacement& placement = scene.placements[k];
    if (!in_range[k])
      return absl::InvalidArgumentError(absl::StrCat("scene.placements[", k, "]: mesh or node out of range"));
    if (placement.first_triangle < end_of_previous)
      return absl::InvalidArgumentError(absl::StrCat("scene.placements[", k, "].first_triangle: ",
                                                     placement.first_triangle, " overlaps the previous placement"));
    if (placement.unplaced_triangles_before != placement.first_triangle - placed_triangles ||
        placement.unplaced_positions_before != placement.first_position - placed_positions ||
        placement.unplaced_triangles_before < unplaced_triangles ||
        placement.unplaced_positions_before < unplaced_positions ||
        placement.unplaced_triangles_before > scene.triangles.size() ||
        placement.unplaced_positions_before > scene.positions.size())
      return absl::InvalidArgumentError(absl::StrCat(
          "scene.placements[", k, "]: the unplaced triangles or positions before it disagree with the record"));
    const SceneMesh& mesh = scene.meshes[placement.mesh];
    unplaced_triangles = placement.unplaced_triangles_before;
    unplaced_positions = placement.unplaced_positions_before;
    placed_triangles += mesh.triangles.size();
    placed_positions += mesh.positions.size();
    end_of_previous = uint64_t{placement.first_triangle} + mesh.triangles.size();
  }
  return absl::OkStatus();
}

namespace {

// Whether the flattened `scene` (HoldPlacementsOnce's input) holds exactly
// `mesh` placed by `placement` from first_triangle and first_position:
// corners, node, materials, positions bit for bit, and each position's
// attributes as the mesh keeps them.
bool StandsForFlattened(const Scene& scene, const SceneMesh& mesh, const MeshPlacement& placement) {
  if (uint64_t{placement.first_triangle} + mesh.triangles.size() > scene.triangles.size() ||
      uint64_t{placement.first_position} + mesh.positions.size() > scene.positions.size())
    return false;
  for (size_t i = 0; i < mesh.triangles.size(); ++i) {
    const size_t t = placement.first_triangle + i;
    if (glm::any(glm::greaterThanEqual(mesh.triangles[i], glm::uvec3(mesh.positions.size()))) ||
        scene.triangles[t] != mesh.triangles[i] + glm::uvec3(placement.first_position) ||
        (t < scene.triangle_node.size() && scene.triangle_node[t] != placement.node) ||
        (t < scene.triangle_material.size() &&
         (i >= mesh.triangle_material.size() || scene.triangle_material[t] != mesh.triangle_material[i])))
      return false;
  }
  const glm::dmat3 normal_matrix = glm::inverseTranspose(glm::dmat3(placement.world));
  for (size_t j = 0; j < mesh.positions.size(); ++j) {
    const size_t v = placement.first_position + j;
    if (scene.positions[v] != PlacePoint(placement.world, mesh.positions[j])) return false;
    if (!scene.lightmap_uvs.empty() && (j >= mesh.lightmap_uvs.size() || scene.lightmap_uvs[v] != mesh.lightmap_uvs[j]))
      return false;
    if (!scene.normals.empty() &&
        (j >= mesh.normals.size() || scene.normals[v] != UnitNormal(normal_matrix, mesh.normals[j])))
      return false;
    for (size_t s = 0; s < scene.texcoords.size(); ++s)
      if (s >= mesh.texcoords.size() || j >= mesh.texcoords[s].size() || scene.texcoords[s][v] != mesh.texcoords[s][j])
        return false;
  }
  return true;
}

template <typename T>
void KeepUnmarked(std::vector<T>& values, const std::vector<uint8_t>& drop) {
  if (values.size() != drop.size()) return;
  size_t kept = 0;
  for (size_t i = 0; i < values.size(); ++i)
    if (!drop[i]) values[kept++] = std::move(values[i]);
  values.resize(kept);
  values.shrink_to_fit();
}

}  // namespace

void HoldPlacementsOnce(Scene& scene) {
  if (scene.placements.empty()) return;
  scene.DropFlattened();
  // Each mesh's materials and per-position attributes, from its first
  // placement, where the mesh does not carry them already (normals it
  // must: a world normal does not give back the file's to the bit).
  const bool with_materials = scene.triangle_material.size() == scene.triangles.size();
  for (SceneMesh& mesh : scene.meshes) {
    if (scene.normals.empty()) mesh.normals.clear();
    if (scene.lightmap_uvs.empty()) mesh.lightmap_uvs.clear();
  }
  for (const MeshPlacement& p : scene.placements) {
    if (p.mesh >= scene.meshes.size()) continue;
    SceneMesh& mesh = scene.meshes[p.mesh];
    if (uint64_t{p.first_triangle} + mesh.triangles.size() > scene.triangles.size() ||
        uint64_t{p.first_position} + mesh.positions.size() > scene.positions.size())
      continue;
    if (with_materials && mesh.triangle_material.size() != mesh.triangles.size())
      mesh.triangle_material.assign(scene.triangle_material.begin() + p.first_triangle,
                                    scene.triangle_material.begin() + p.first_triangle + mesh.triangles.size());
    if (!scene.lightmap_uvs.empty() && mesh.lightmap_uvs.size() != mesh.positions.size())
      mesh.lightmap_uvs.assign(scene.lightmap_uvs.begin() + p.first_position,
                               scene.lightmap_uvs.begin() + p.first_position + mesh.positions.size());
    if (mesh.texcoords.size() != scene.texcoords.size()) {
      mesh.texcoords.resize(scene.texcoords.size());
      for (size_t s = 0; s < scene.texcoords.size(); ++s)
        mesh.texcoords[s].assign(scene.texcoords[s].begin() + p.first_position,
                                 scene.texcoords[s].begin() + p.first_position + mesh.positions.size());
    }
  }
  // The placements that stand for their triangles, disjoint.
  std::vector<uint8_t> placed_triangle(scene.triangles.size(), 0), placed_position(scene.positions.size(), 0);
  std::vector<MeshPlacement> held;
  uint64_t end_of_previous = 0;
  for (MeshPlacement p : scene.placements) {
    if (p.mesh >= scene.meshes.size() || p.first_triangle < end_of_previous) continue;
    if (p.first_triangle < scene.triangle_node.size()) p.node = scene.triangle_node[p.first_triangle];
    const SceneMesh& mesh = scene.meshes[p.mesh];
    if (mesh.triangles.empty() || !StandsForFlattened(scene, mesh, p)) continue;
    std::fill_n(placed_triangle.begin() + p.first_triangle, mesh.triangles.size(), uint8_t{1});
    std::fill_n(placed_position.begin() + p.first_position, mesh.positions.size(), uint8_t{1});
    end_of_previous = uint64_t{p.first_triangle} + mesh.triangles.size();
    held.push_back(p);
  }
  // An unplaced triangle that uses a placement's positions (a hand-made
  // scene sharing them) keeps the whole scene flattened.
  for (size_t t = 0; t < scene.triangles.size(); ++t) {
    if (placed_triangle[t]) continue;
    for (int c = 0; c < 3; ++c)
      if (scene.triangles[t][c] < placed_position.size() && placed_position[scene.triangles[t][c]]) {
        scene.placements.clear();
        scene.meshes.clear();
        return;
      }
  }
  // The counts of unplaced triangles and positions before each placement,
  // and the unplaced triangles' corners renumbered over the kept positions.
  std::vector<uint32_t> renumbered(scene.positions.size(), UINT32_MAX);
  uint32_t next = 0;
  for (size_t j = 0; j < scene.positions.size(); ++j)
    if (!placed_position[j]) renumbered[j] = next++;
  {
    uint32_t unplaced_triangles = 0, unplaced_positions = 0;
    size_t t = 0, j = 0;
    for (MeshPlacement& p : held) {
      for (; t < p.first_triangle; ++t) unplaced_triangles += placed_triangle[t] ? 0 : 1;
      for (; j < p.first_position; ++j) unplaced_positions += placed_position[j] ? 0 : 1;
      p.unplaced_triangles_before = unplaced_triangles;
      p.unplaced_positions_before = unplaced_positions;
    }
  }
  for (size_t t = 0; t < scene.triangles.size(); ++t)
    if (!placed_triangle[t])
      for (int c = 0; c < 3; ++c) scene.triangles[t][c] = renumbered[scene.triangles[t][c]];
  KeepUnmarked(scene.triangles, placed_triangle);
  KeepUnmarked(scene.triangle_material, placed_triangle);
  KeepUnmarked(scene.triangle_node, placed_triangle);
  KeepUnmarked(scene.positions, placed_position);
  KeepUnmarked(scene.lightmap_uvs, placed_position);
  KeepUnmarked(scene.normals, placed_position);
  for (auto& set : scene.texcoords) KeepUnmarked(set, placed_position);
  // Meshes no placement keeps are dropped, the rest renumbered.
  std::vector<uint32_t> mesh_of(scene.meshes.size(), UINT32_MAX);
  std::vector<SceneMesh> meshes;
  for (MeshPlacement& p : held) {
    if (mesh_of[p.mesh] == UINT32_MAX) {
      mesh_of[p.mesh] = static_cast<uint32_t>(meshes.size());
      meshes.push_back(std::move(scene.meshes[p.mesh]));
    }
    p.mesh = mesh_of[p.mesh];
  }
  scene.meshes = std::move(meshes);
  scene.placements = std::move(held);
  scene.meshes.shrink_to_fit();
  scene.placements.shrink_to_fit();
}

void FlattenPlacements(Scene& scene) {
  if (scene.placements.empty()) return;
  TriangleArrays flat = FlattenAll(scene);
  static_cast<TriangleArrays&>(scene) = std::move(flat);
  for (MeshPlacement& p : scene.placements) {
    p.unplaced_triangles_before = 0;
    p.unplaced_positions_before = 0;
  }
  scene.DropFlattened();
}

FlattenedPart FlattenPart(const Scene& scene, const std::vector<uint8_t>& skip) {
  FlattenedPart out;
  const size_t count = scene.TriangleCount();
  std::vector<uint32_t> record_vertex(scene.positions.size(), UINT32_MAX);
  std::vector<int64_t> placement_base(scene.placements.size(), -1);
  size_t k = 0;  // the first placement that does not end at or before t
  for (size_t t = 0; t < count; ++t) {
    while (k < scene.placements.size() &&
           t >= scene.placements[k].first_triangle + scene.meshes[scene.placements[k].mesh].triangles.size())
      ++k;
    if (!skip.empty() && skip[t]) continue;
    out.scene_triangle.push_back(static_cast<uint32_t>(t));
    if (k < scene.placements.size() && t >= scene.placements[k].first_triangle) {
      // A placement's positions, all of them, on its first triangle taken.
      const MeshPlacement& p = scene.placements[k];
      const SceneMesh& mesh = scene.meshes[p.mesh];
      if (placement_base[k] < 0) {
        placement_base[k] = static_cast<int64_t>(out.positions.size());
        for (const glm::dvec3& x : mesh.positions) out.positions.push_back(PlacePoint(p.world, x));
      }
      out.triangles.push_back(mesh.triangles[t - p.first_triangle] + glm::uvec3(uint32_t(placement_base[k])));
      continue;
    }
    // An unplaced triangle: its index in the record is the unplaced ones
    // before the next placement, less those between it and that placement.
    const size_t before = k < scene.placements.size() ? scene.placements[k].unplaced_triangles_before : scene.triangles.size();
    const size_t next_start = k < scene.placements.size() ? scene.placements[k].first_triangle : count;
    glm::uvec3 corners = scene.triangles[before - (next_start - t)];
    for (int c = 0; c < 3; ++c) {
      uint32_t& v = record_vertex[corners[c]];
      if (v == UINT32_MAX) {
        v = static_cast<uint32_t>(out.positions.size());
        out.positions.push_back(scene.positions[corners[c]]);
      }
      corners[c] = v;
    }
    out.triangles.push_back(corners);
  }
  return out;
}

Bounds PositionBounds(const Scene& scene) {
  Bounds bounds = BoundsOf(scene.positions);
  std::vector<PlacedMeshBounds> placed_bounds;
  placed_bounds.reserve(scene.meshes.size());
  for (const SceneMesh& mesh : scene.meshes) placed_bounds.emplace_back(mesh.positions);
  for (const MeshPlacement& p : scene.placements) {
    const Bounds placed = placed_bounds[p.mesh].Of(p.world, scene.meshes[p.mesh].positions);
    if (!placed.Empty()) {
      bounds.Extend(placed.min);
      bounds.Extend(placed.max);
    }
  }
  return bounds;
}

std::vector<uint8_t> PlacementsInRange(const Scene& scene) {
  // Per mesh: -1 not yet checked, else whether its corners index its positions.
  std::vector<int8_t> mesh_ok(scene.meshes.size(), -1);
  std::vector<uint8_t> in_range(scene.placements.size(), 0);
  for (size_t k = 0; k < scene.placements.size(); ++k) {
    const MeshPlacement& placement = scene.placements[k];
    if (placement.mesh >= scene.meshes.size()) continue;
    int8_t& ok = mesh_ok[placement.mesh];
    if (ok < 0) {
      const SceneMesh& mesh = scene.meshes[placement.mesh];
      ok = std::none_of(mesh.triangles.begin(), mesh.triangles.end(), [&](const glm::uvec3& t) {
        return glm::any(glm::greaterThanEqual(t, glm::uvec3(mesh.positions.size())));
      });
    }
    in_range[k] = ok == 1 && (placement.node < scene.nodes.size() || scene.nodes.empty());
  }
  return in_range;
}

Bounds BoundsOf(const std::vector<glm::dvec3>& points) {
  Bounds bounds;
  for (const glm::dvec3& p : points) bounds.Extend(p);
  return bounds;
}

std::vector<Bounds> MeshBounds(const Scene& scene) {
  std::vector<Bounds> bounds;
  bounds.reserve(scene.meshes.size());
  for (const SceneMesh& mesh : scene.meshes) bounds.push_back(BoundsOf(mesh.positions));
  return bounds;
}

std::optional<Bounds> PlacedBoundsWithoutRotation(const glm::dmat4& world, const Bounds& local) {
  for (int column = 0; column < 3; ++column)
    for (int row = 0; row < 3; ++row)
      if (row != column && world[column][row] != 0.0) return std::nullopt;
  if (local.Empty()) return local;
  // Row r of the placed point is world[r][r] * x_r plus zeros plus the
  // translation, rounded as PlacePoint rounds it: monotone in x_r, rising
  // or falling with the scale's sign, so its extremes are those of the
  // local extremes placed.
  const glm::dvec3 a = PlacePoint(world, local.min), b = PlacePoint(world, local.max);
  Bounds placed;
  placed.Extend(a);
  placed.Extend(b);
  return placed;
}

namespace {

// At most this many linear parts of one mesh keep their extremes, and this
// many more are remembered as seen once.
constexpr size_t kMaxLinearPartsWithExtremes = 16;
constexpr size_t kMaxLinearPartsSeenOnce = 64;
// Magnitudes above this are placed point by point: the error bounds below
// assume that no sum overflows.
constexpr double kLargestBoundedMagnitude = 1e300;

// Twice the bound on the rounding of an affine value of four terms whose
// magnitudes sum to `magnitude` (gamma_4 = 4u / (1 - 4u) < 8u), plus the
// absolute error of subnormal results.
double RoundingBound(double magnitude) {
  constexpr double kUnitRoundoff = std::numeric_limits<double>::epsilon() / 2;
  return 8.0 * kUnitRoundoff * magnitude + 8.0 * std::numeric_limits<double>::denorm_min();
}

// How far below the largest computed L (or above the smallest) a point may
// lie and still be placed at the extreme, for a row whose linear terms'
// magnitudes sum to `linear_magnitude`, translated by `translation`.
double ExtremeMargin(double linear_magnitude, double translation) {
  return 2.0 * RoundingBound(linear_magnitude + translation) + 2.0 * RoundingBound(linear_magnitude);
}

Bounds PlacedByEveryPoint(const glm::dmat4& world, const std::vector<glm::dvec3>& positions) {
  Bounds bounds;
  for (const glm::dvec3& x : positions) bounds.Extend(PlacePoint(world, x));
  return bounds;
}

}  // namespace

PlacedMeshBounds::PlacedMeshBounds(const std::vector<glm::dvec3>& positions) : local_(BoundsOf(positions)) {
  if (!local_.Empty()) largest_magnitude_ = glm::max(glm::abs(local_.min), glm::abs(local_.max));
}

const PlacedMeshBounds::Extremes* PlacedMeshBounds::ExtremesFor(const glm::dmat3& linear,
                                                                const glm::dvec3& linear_magnitude,
                                                                const std::vector<glm::dvec3>& positions) {
  for (const Extremes& extremes : extremes_)
    if (extremes.linear == linear) return &extremes;
  const auto seen = std::find(seen_once_.begin(), seen_once_.end(), linear);
  if (seen == seen_once_.end()) {
    if (seen_once_.size() < kMaxLinearPartsSeenOnce) seen_once_.push_back(linear);
    return nullptr;
  }
  if (extremes_.size() >= kMaxLinearPartsWithExtremes) return nullptr;
  seen_once_.erase(seen);
  Extremes extremes{linear, {}, {}, {}, {}};
  std::vector<double> value(positions.size());
  for (int row = 0; row < 3; ++row) {
    for (size_t i = 0; i < positions.size(); ++i) {
      const glm::dvec3& x = positions[i];
      value[i] = linear[0][row] * x.x + linear[1][row] * x.y + linear[2][row] * x.z;
    }
    const auto [smallest, largest] = std::minmax_element(value.begin(), value.end());
    extremes.largest[row] = *largest;
    extremes.smallest[row] = *smallest;
    const double kept = ExtremeMargin(linear_magnitude[row], PlacedMeshBounds::kMaxOrderedTranslation);
    for (size_t i = 0; i < value.size(); ++i) {
      if (value[i] >= *largest - kept) extremes.top[row].push_back({value[i], static_cast<uint32_t>(i)});
      if (value[i] <= *smallest + kept) extremes.bottom[row].push_back({value[i], static_cast<uint32_t>(i)});
    }
  }
  extremes_.push_back(std::move(extremes));
  return &extremes_.back();
}

Bounds PlacedMeshBounds::Of(const glm::dmat4& world, const std::vector<glm::dvec3>& positions) {
  if (positions.empty()) return Bounds{};
  if (const std::optional<Bounds> placed = PlacedBoundsWithoutRotation(world, local_)) return *placed;
  const glm::dmat3 linear(world);
  glm::dvec3 linear_magnitude{0.0};
  for (int row = 0; row < 3; ++row)
    for (int column = 0; column < 3; ++column)
      linear_magnitude[row] += std::abs(linear[column][row]) * largest_magnitude_[column];
  const glm::dvec3 translation(world[3]);
  if (!glm::all(glm::lessThanEqual(linear_magnitude, glm::dvec3(kLargestBoundedMagnitude))) ||
      !glm::all(glm::lessThanEqual(glm::abs(translation), glm::dvec3(kMaxOrderedTranslation))))
    return PlacedByEveryPoint(world, positions);
  const Extremes* extremes = ExtremesFor(linear, linear_magnitude, positions);
  if (extremes == nullptr) return PlacedByEveryPoint(world, positions);
  ++answered_by_extremes_;
  Bounds bounds;
  for (int row = 0; row < 3; ++row) {
    const double margin = ExtremeMargin(linear_magnitude[row], std::abs(translation[row]));
    for (const Candidate& c : extremes->top[row])
      if (c.value >= extremes->largest[row] - margin)
        bounds.max[row] = std::max(bounds.max[row], PlacePoint(world, positions[c.point])[row]);
    for (const Candidate& c : extremes->bottom[row])
      if (c.value <= extremes->smallest[row] + margin)
        bounds.min[row] = std::min(bounds.min[row], PlacePoint(world, positions[c.point])[row]);
  }
  return bounds;
}

}  // namespace visq
