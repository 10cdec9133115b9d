// Slicemap voxelization and transmittance as core queries: node names to
// triangle ranges, the scene's default box, caps.
#pragma once

#include <optional>
#include <string>
#include <vector>

#include "core/accuracy_statement.h"
#include "core/call_options.h"
#include "core/work_budget.h"
#include "common/status.h"
#include "visq/gpu/slicemap.h"

namespace visq::core {

class Engine;

struct VoxelizeQuery {
  std::string scene;
  uint64_t scene_version = 0;
  gpu::VoxelizeParams params;        // box filled from the scene when `box` is unset
  CallOptions call;  // the core sets params.job from it
  std::optional<gpu::SlicemapBox> box;
  int depth_axis = 1;
  std::vector<std::string> nodes;
};

struct TransmittanceQuery {
  std::string scene;
  uint64_t scene_version = 0;
  gpu::TransmittanceParams params;
  CallOptions call;  // the core sets params.job from it
  std::vector<std::pair<std::string, double>> absorbers;  // node name, absorption
};

// The query's parameters with names resolved against the scene and every
// check made: what is refused before any GPU work (the request-validation
// fuzz target calls these alone).
[[nodiscard]] StatusOr<gpu::VoxelizeParams> ResolveVoxelizeQuery(VoxelizeQuery query, const Scene& scene);
[[nodiscard]] StatusOr<gpu::TransmittanceParams> ResolveTransmittanceQuery(TransmittanceQuery query,
                                                                           const Scene& scene);

// With `sink`, each band of image rows goes to it as soon as it is made and
// the result holds the figures only (gpu::Voxelize).
[[nodiscard]] StatusOr<gpu::VoxelizeResult> RunVoxelize(Engine& engine, const VoxelizeQuery& query,
                                                        gpu::SlicemapBox* box_used,
                                                        const gpu::VoxelizeBandSink& sink = {});
// Reserves its working memory (--max-work-bytes) before it starts; with
// `hold`, the reservation outlives the call, to cover the answer's copy in
// a response until it is sent.
[[nodiscard]] StatusOr<gpu::TransmittanceResult> RunTransmittance(Engine& engine, const TransmittanceQuery& query,
                                                                  WorkMemoryBudget::Reservation* hold = nullptr);

// "conservative" or "standard"; "local" or "uniform".
const char* RasterizationName(gpu::Rasterization rasterization);
const char* SlicePrecisionName(gpu::SlicePrecision precision);

// A grid's promise (from its figures, so it can go with the first band):
// conservative rasterization puts every surface point within one voxel of
// a set voxel; standard rasterization bounds nothing.
AccuracyStatement VoxelizeStatement(const gpu::VoxelizeResult& figures, const gpu::SlicemapBox& box);

// Transmittance: the optical depth's worst per-point bound, from the
// slicemap's own error model.
AccuracyStatement TransmittanceStatement(const gpu::TransmittanceResult& result);

}  // namespace visq::core
