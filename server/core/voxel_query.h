// Slicemap voxelization and transmittance as core queries: node names to
// triangle ranges, the scene's default box, caps.
#pragma once

#include <optional>
#include <string>
#include <vector>

#include "common/status.h"
#include "visq/gpu/slicemap.h"

namespace visq {

class Engine;

struct VoxelizeQuery {
  std::string scene;
  uint64_t scene_version = 0;
  gpu::VoxelizeParams params;        // box filled from the scene when `box` is unset
  std::optional<gpu::SlicemapBox> box;
  int depth_axis = 1;
  std::vector<std::string> nodes;
};

struct TransmittanceQuery {
  std::string scene;
  uint64_t scene_version = 0;
  gpu::TransmittanceParams params;
  std::vector<std::pair<std::string, double>> absorbers;  // node name, absorption
};

[[nodiscard]] StatusOr<gpu::VoxelizeResult> RunVoxelize(Engine& engine, VoxelizeQuery query,
                                                        gpu::SlicemapBox* box_used);
[[nodiscard]] StatusOr<gpu::TransmittanceResult> RunTransmittance(Engine& engine, TransmittanceQuery query);

}  // namespace visq
