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

namespace {

// MoveNodeSubtree on a scene whose arrays hold every triangle (placements
// pointing into them).
Status MoveFlattenedSubtree(Scene& scene, uint32_t node, const glm::dmat4& new_world) {
  if (node >= scene.nodes.size())
    return absl::InvalidArgumentError(absl::StrCat("node: ", node, " is not a node of the scene (", scene.nodes.size(),
                                                   " nodes)"));
  const glm::dmat4 delta = new_world * glm::inverse(scene.nodes[node].world);
  const std::vector<uint32_t> subtree = SubtreeNodes(scene, node);
  std::vector<uint8_t> in_subtree(scene.nodes.size(), 0);
  for (uint32_t n : subtree) in_subtree[n] = 1;
  // Positions referenced by the subtree, and none outside it.
  std::vector<uint8_t> moved(scene.positions.size(), 0);
  for (uint32_t n : subtree)
    for (uint32_t t = scene.nodes[n].first_triangle; t < scene.nodes[n].first_triangle + scene.nodes[n].triangle_count; ++t)
      for (int c = 0; c < 3; ++c) moved[scene.triangles[t][c]] = 1;
  for (size_t t = 0; t < scene.triangles.size(); ++t)
    if (!in_subtree[scene.triangle_node[t]])
      for (int c = 0; c < 3; ++c)
        if (moved[scene.triangles[t][c]])
          return absl::InvalidArgumentError(absl::StrCat("node: ", node, " shares position ", scene.triangles[t][c],
                                                         " with triangle ", t, " outside its subtree"));
  std::vector<glm::dvec3> placed(scene.positions.size());
  for (size_t i = 0; i < scene.positions.size(); ++i) {
    if (!moved[i]) continue;
    placed[i] = glm::dvec3(delta * glm::dvec4(scene.positions[i], 1.0));
    if (!InCoordinateRange(placed[i]))
      return absl::InvalidArgumentError(absl::StrCat("world_matrix: moves position ", i, " beyond ±", kMaxCoordinate));
  }
  for (size_t i = 0; i < scene.positions.size(); ++i)
    if (moved[i]) scene.positions[i] = placed[i];
  // Normals turn with the inverse transpose, so that they stay normal to
  // surfaces that a non-uniform scale stretched.
  if (!scene.normals.empty()) {
    const glm::dmat3 normal_matrix = glm::inverseTranspose(glm::dmat3(delta));
    for (size_t i = 0; i < scene.normals.size(); ++i)
      if (moved[i]) scene.normals[i] = UnitNormal(normal_matrix, scene.normals[i]);
  }
  for (uint32_t n : subtree) scene.nodes[n].world = delta * scene.nodes[n].world;
  // A moved placement's positions are delta * (world * p), which is not
  // PlacePoint(delta * world, p) to the bit: the moved meshes stay flattened only.
  std::erase_if(scene.placements, [&](const MeshPlacement& placement) {
    return in_subtree[scene.triangle_node[placement.first_triangle]] != 0;
  });
  scene.bounds = Bounds{};
  for (const auto& p : scene.positions) scene.bounds.Extend(p);
  return absl::OkStatus();
}

}  // namespace

Status MoveNodeSubtree(Scene& scene, uint32_t node, const glm::dmat4& new_world) {
  // The placements flattened for the edit, and the ones it left in place
  // held once again (the moved ones stay flattened).
  FlattenPlacements(scene);
  const Status moved = MoveFlattenedSubtree(scene, node, new_world);
  HoldPlacementsOnce(scene);
  return moved;
}

}  // namespace visq
