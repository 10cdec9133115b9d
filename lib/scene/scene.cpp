#include "scene/scene.h"

#include <algorithm>
#include <cmath>

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

size_t Scene::CpuBytes() const {
  size_t bytes = positions.capacity() * sizeof(glm::dvec3) + triangles.capacity() * sizeof(glm::uvec3) +
                 triangle_material.capacity() * sizeof(uint32_t) +
                 triangle_node.capacity() * sizeof(uint32_t) + lightmap_uvs.capacity() * sizeof(glm::vec2) +
                 normals.capacity() * sizeof(glm::vec3) + texcoords.capacity() * sizeof(std::vector<glm::vec2>);
  for (const auto& set : texcoords) bytes += set.capacity() * sizeof(glm::vec2);
  for (const auto& m : materials) bytes += sizeof(Material) + m.name.capacity();
  for (const auto& n : nodes) bytes += sizeof(SceneNode) + n.name.capacity();
  for (const auto& m : meshes)
    bytes += sizeof(SceneMesh) + m.positions.capacity() * sizeof(glm::dvec3) + m.triangles.capacity() * sizeof(glm::uvec3);
  bytes += placements.capacity() * sizeof(MeshPlacement);
  return bytes;
}

bool PlacementMatchesFlattened(const Scene& scene, const MeshPlacement& placement) {
  if (placement.mesh >= scene.meshes.size()) return false;
  const SceneMesh& mesh = scene.meshes[placement.mesh];
  if (uint64_t{placement.first_triangle} + mesh.triangles.size() > scene.triangles.size() ||
      uint64_t{placement.first_position} + mesh.positions.size() > scene.positions.size())
    return false;
  for (size_t i = 0; i < mesh.triangles.size(); ++i)
    if (glm::any(glm::greaterThanEqual(mesh.triangles[i], glm::uvec3(mesh.positions.size()))) ||
        scene.triangles[placement.first_triangle + i] != mesh.triangles[i] + glm::uvec3(placement.first_position))
      return false;
  for (size_t j = 0; j < mesh.positions.size(); ++j)
    if (scene.positions[placement.first_position + j] != PlacePoint(placement.world, mesh.positions[j])) return false;
  return true;
}

Status ValidatePlacements(const Scene& scene) {
  uint64_t end_of_previous = 0;
  for (size_t k = 0; k < scene.placements.size(); ++k) {
    const MeshPlacement& placement = scene.placements[k];
    if (placement.first_triangle < end_of_previous)
      return absl::InvalidArgumentError(absl::StrCat("scene.placements[", k, "].first_triangle: ",
                                                     placement.first_triangle, " overlaps the previous placement"));
    if (!PlacementMatchesFlattened(scene, placement))
      return absl::InvalidArgumentError(absl::StrCat("scene.placements[", k,
                                                     "]: out of range, or not the flattened triangles and positions"));
    end_of_previous = uint64_t{placement.first_triangle} + scene.meshes[placement.mesh].triangles.size();
  }
  return absl::OkStatus();
}

}  // namespace visq
