// Scene edits as core queries: a node moved (with its subtree) makes the
// next resident version of the scene, in memory only, and joins the scene's
// edit log (Engine::MoveNode), which every query sees and which the
// obscurance updater replays.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "common/status.h"
#include "core/call_options.h"
#include "core/engine.h"

namespace visq::core {

struct NodeTransformQuery {
  std::string scene;
  uint64_t scene_version = 0;
  std::optional<std::string> node_name;
  std::optional<uint32_t> node_index;
  std::vector<double> world_matrix;  // 16, column-major
  CallOptions call;  // a call stopped before the move is made resident moves nothing
};

// INVALID_ARGUMENT for an unknown or ambiguous node, a matrix that is not 16
// finite numbers, not affine or not invertible.
[[nodiscard]] StatusOr<SceneSummary> RunSetNodeTransform(Engine& engine, const NodeTransformQuery& query);

}  // namespace visq::core
