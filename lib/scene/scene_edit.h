// Edits of a resident scene that every query sees: today, moving a node
// with its subtree (SetNodeTransform). The obscurance update reads the same
// edit to know what moved.
#pragma once

#include <cstdint>
#include <vector>

#include <glm/glm.hpp>

#include "common/status.h"
#include "scene/scene.h"

namespace visq {

// The node and all its descendants.
std::vector<uint32_t> SubtreeNodes(const Scene& scene, uint32_t node);

// Moves node `node` and its subtree rigidly so that the node's world matrix
// becomes `new_world`: the subtree's unplaced positions and nodes' world
// matrices by delta = new_world * inverse(old world), and its placements'
// worlds to delta * world (they stay placements, at the cost of the
// subtree, not of the scene). INVALID_ARGUMENT for an unknown node, a
// position shared with triangles outside the subtree, or one moved beyond
// the coordinate range; the scene is unchanged then.
[[nodiscard]] Status MoveNodeSubtree(Scene& scene, uint32_t node, const glm::dmat4& new_world);

}  // namespace visq
