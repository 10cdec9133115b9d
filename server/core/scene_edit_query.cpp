#include "core/scene_edit_query.h"

#include <algorithm>
#include <cmath>

#include "absl/strings/str_cat.h"

namespace visq::core {
namespace {

StatusOr<uint32_t> NamedNode(const Scene& scene, const NodeTransformQuery& query) {
  if (query.node_index) {
    if (*query.node_index >= scene.nodes.size())
      return absl::InvalidArgumentError(absl::StrCat("node_index: ", *query.node_index, " is not a node of the scene (",
                                                     scene.nodes.size(), " nodes)"));
    return *query.node_index;
  }
  if (!query.node_name) return absl::InvalidArgumentError("node: set node_name or node_index");
  std::vector<uint32_t> found;
  for (uint32_t i = 0; i < scene.nodes.size(); ++i)
    if (scene.nodes[i].name == *query.node_name) found.push_back(i);
  if (found.empty()) return absl::InvalidArgumentError(absl::StrCat("node_name: no node named '", *query.node_name, "'"));
  if (found.size() > 1)
    return absl::InvalidArgumentError(absl::StrCat("node_name: '", *query.node_name, "' names ", found.size(),
                                                   " nodes; give node_index"));
  return found[0];
}

// 16 column-major numbers -> an affine, invertible matrix.
StatusOr<glm::dmat4> WorldMatrix(const std::vector<double>& m) {
  if (m.size() != 16)
    return absl::InvalidArgumentError(absl::StrCat("world_matrix: ", m.size(), " numbers, expected 16 (column-major)"));
  glm::dmat4 world;
  double scale = 0;
  for (int c = 0; c < 4; ++c)
    for (int r = 0; r < 4; ++r) {
      const double v = m[static_cast<size_t>(c * 4 + r)];
      if (!std::isfinite(v))
        return absl::InvalidArgumentError(absl::StrCat("world_matrix[", c * 4 + r, "]: ", v, " is not finite"));
      world[c][r] = v;
      if (c < 3 && r < 3) scale = std::max(scale, std::abs(v));
    }
  if (world[0][3] != 0 || world[1][3] != 0 || world[2][3] != 0 || world[3][3] != 1)
    return absl::InvalidArgumentError(
        absl::StrCat("world_matrix: last row (", world[0][3], ", ", world[1][3], ", ", world[2][3], ", ", world[3][3],
                     ") must be (0, 0, 0, 1): an affine transform"));
  // Relative to the matrix's own scale, so tiny but well-conditioned scenes pass.
  const double det = glm::determinant(glm::dmat3(world));
  if (!(std::abs(det) > 1e-12 * scale * scale * scale))
    return absl::InvalidArgumentError(absl::StrCat("world_matrix: not invertible (determinant ", det, ")"));
  return world;
}

}  // namespace

StatusOr<SceneSummary> RunSetNodeTransform(Engine& engine, const NodeTransformQuery& query) {
  VISQ_ASSIGN_OR_RETURN(const glm::dmat4 world, WorldMatrix(query.world_matrix));
  return engine.MoveNode(
      query.scene, query.scene_version, [&query](const Scene& scene) { return NamedNode(scene, query); }, world,
      query.call.stop);
}

}  // namespace visq::core
