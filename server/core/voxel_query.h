// Slicemap voxelization and transmittance as core queries: node names to
// triangle ranges, the scene's default box, caps.
#pragma once

#include <optional>
#include <string>
#include <vector>

#include "core/accuracy_planner.h"
#include "core/accuracy_statement.h"
#include "core/call_options.h"
#include "core/query_methods.h"
#include "core/work_budget.h"
#include "common/status.h"
#include "visq/gpu/slicemap.h"
#include "core/work_timing.h"

namespace visq::core {

class Engine;

struct VoxelizeQuery {
  std::string scene;
  uint64_t scene_version = 0;
  voxel_reference::VoxelizeParams params;        // box filled from the scene when `box` is unset
  CallOptions call;  // the core sets params.job from it
  std::optional<voxel_reference::OrientedBox> box;
  int depth_axis = 1;
  std::vector<std::string> nodes;
};

struct TransmittanceQuery {
  std::string scene;
  uint64_t scene_version = 0;
  voxel_reference::TransmittanceParams params;
  CallOptions call;  // the core sets params.job from it
  std::vector<std::pair<std::string, double>> absorbers;  // node name, absorption
  // None: the server runs the faster here of the two (ChooseFastest): ray
  // stabbing answers each point's own ray at least as tightly as the
  // slicemap answers its texel's centre ray.
  std::optional<TransmittanceMethod> method = TransmittanceMethod::kSlicemap;
};

struct TransmittanceAnswer {
  voxel_reference::TransmittanceResult result;
  // The server's choice, where the query named no method.
  std::optional<PlanReport> plan;
};

// The query's parameters with names resolved against the scene and every
// check made: what is refused before any GPU work (the request-validation
// fuzz target calls these alone).
[[nodiscard]] StatusOr<voxel_reference::VoxelizeParams> ResolveVoxelizeQuery(VoxelizeQuery query, const Scene& scene);
[[nodiscard]] StatusOr<voxel_reference::TransmittanceParams> ResolveTransmittanceQuery(TransmittanceQuery query,
                                                                                       const Scene& scene);

struct VoxelizeAnswer {
  voxel_reference::VoxelizeResult result;
  double delivery_ms = 0;  // in the sink: the stream's writes, not the work's
};

// With `sink`, each band of image rows goes to it as soon as it is made and
// the result holds the figures only (gpu::Voxelize).
[[nodiscard]] StatusOr<VoxelizeAnswer> RunVoxelize(Engine& engine, const VoxelizeQuery& query,
                                                   const voxel_reference::VoxelizeBandSink& sink = {});
// Reserves its working memory (--max-work-bytes) before it starts; with
// `hold`, the reservation outlives the call, to cover the answer's copy in
// a response until it is sent.
// A voxelization's or a transmittance's GL jobs: their wait, and the rest
// of their time but its bands' delivery.
inline WorkTiming WorkTimingOf(const VoxelizeAnswer& a) {
  const voxel_reference::SlicemapTimings& t = a.result.timings;
  return {t.queue_ms, t.total_ms - t.queue_ms - a.delivery_ms};
}
inline WorkTiming WorkTimingOf(const voxel_reference::TransmittanceResult& r) {
  return {r.timings.queue_ms, r.timings.total_ms - r.timings.queue_ms};
}
inline WorkTiming WorkTimingOf(const TransmittanceAnswer& a) { return WorkTimingOf(a.result); }

[[nodiscard]] StatusOr<TransmittanceAnswer> RunTransmittance(
    Engine& engine, const TransmittanceQuery& query, WorkMemoryBudget::Reservation* hold = nullptr);

// "conservative" or "standard"; "local" or "uniform".
const char* RasterizationName(voxel_reference::Rasterization rasterization);
const char* SlicePrecisionName(voxel_reference::SlicePrecision precision);

// A grid's promise (from its figures, so it can go with the first band):
// conservative rasterization puts every surface point within one voxel of
// a set voxel; standard rasterization bounds nothing.
AccuracyStatement VoxelizeStatement(const voxel_reference::VoxelizeResult& figures);

// Transmittance: the optical depth's worst per-point bound, from the
// method's own error model, and the server's choice where it made one.
AccuracyStatement TransmittanceStatement(const TransmittanceAnswer& answer);

}  // namespace visq::core
