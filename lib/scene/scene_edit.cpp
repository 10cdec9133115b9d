#include "scene/scene_edit.h"

#include <glm/gtc/matrix_inverse.hpp>

#include "common/coordinates.h"

namespace visq {

std::vector<uint32_t> SubtreeNodes(const Scene& scene, uint32_t node) {
  std::vector<uint32_t> out;
  for (uint32_t i = 0; i < scene.nodes.size(); ++i) {
    for (int p = static_cast<int>(i); p >= 0; p = scene.nodes[p].parent)
      if (static_cast<uint32_t>(p) == node) { out.push_back(i); break; }
  }
  return out;
}

Status MoveNodeSubtree(Scene& scene, uint32_t node, const glm::dmat4& new_world) {
  if (node >= scene.nodes.size())
    return absl::InvalidArgumentError(absl::StrCat("node: ", node, " is not a node of the scene (", scene.nodes.size(),
                                                   " nodes)"));
  const glm::dmat4 delta = new_world * glm::inverse(scene.nodes[node].world);
  const std::vector<uint32_t> subtree = SubtreeNodes(scene, node);
  std::vector<uint8_t> in_subtree(scene.nodes.size(), 0);
  for (uint32_t n : subtree) in_subtree[n] = 1;
  auto moves = [&](uint32_t n) { return n < in_subtree.size() && in_subtree[n] != 0; };

  // The record's triangles of the subtree move their positions, which no
  // other triangle may use.
  std::vector<uint8_t> moved(scene.positions.size(), 0);
  for (size_t t = 0; t < scene.triangles.size(); ++t)
    if (moves(scene.triangle_node[t]))
      for (int c = 0; c < 3; ++c) moved[scene.triangles[t][c]] = 1;
  for (size_t t = 0; t < scene.triangles.size(); ++t) {
    if (moves(scene.triangle_node[t])) continue;
    for (int c = 0; c < 3; ++c) {
      if (!moved[scene.triangles[t][c]]) continue;
      // The record's triangle t is the scene's t plus the placed ones before it.
      uint64_t scene_triangle = t;
      for (const MeshPlacement& p : scene.placements)
        if (p.unplaced_triangles_before <= t) scene_triangle += scene.meshes[p.mesh].triangles.size();
      return absl::InvalidArgumentError(absl::StrCat("node: ", node, " shares a position with triangle ",
                                                     scene_triangle, " outside its subtree"));
    }
  }
  std::vector<glm::dvec3> placed(scene.positions.size());
  for (size_t i = 0; i < scene.positions.size(); ++i) {
    if (!moved[i]) continue;
    placed[i] = glm::dvec3(delta * glm::dvec4(scene.positions[i], 1.0));
    if (!InCoordinateRange(placed[i]))
      return absl::InvalidArgumentError(absl::StrCat("world_matrix: moves position ", i, " beyond ±", kMaxCoordinate));
  }
  // The subtree's placements stay placements, placed by delta after their
  // world: a moved copy of a level's prefab is still held once.
  std::vector<glm::dmat4> placement_world(scene.placements.size());
  for (size_t k = 0; k < scene.placements.size(); ++k) {
    const MeshPlacement& p = scene.placements[k];
    if (!moves(p.node)) continue;
    placement_world[k] = delta * p.world;
    for (const glm::dvec3& x : scene.meshes[p.mesh].positions)
      if (!InCoordinateRange(PlacePoint(placement_world[k], x)))
        return absl::InvalidArgumentError(absl::StrCat("world_matrix: moves placement ", k, " of mesh ", p.mesh,
                                                       " beyond ±", kMaxCoordinate));
  }

  for (size_t i = 0; i < scene.positions.size(); ++i)
    if (moved[i]) scene.positions[i] = placed[i];
  // Normals turn with the inverse transpose, so that they stay normal to
  // surfaces that a non-uniform scale stretched (a placement's are placed
  // with its world where they are read).
  if (!scene.normals.empty()) {
    const glm::dmat3 normal_matrix = glm::inverseTranspose(glm::dmat3(delta));
    for (size_t i = 0; i < scene.normals.size(); ++i)
      if (moved[i]) scene.normals[i] = UnitNormal(normal_matrix, scene.normals[i]);
  }
  for (size_t k = 0; k < scene.placements.size(); ++k)
    if (moves(scene.placements[k].node)) scene.placements[k].world = placement_world[k];
  for (uint32_t n : subtree) scene.nodes[n].world = delta * scene.nodes[n].world;
  scene.bounds = PositionBounds(scene);
  scene.DropFlattened();
  return absl::OkStatus();
}

}  // namespace visq
