// Obscurances as core queries (Méndez-Feliu, Sbert et al.): the GPU bake
// over a resident scene, node moves that make a new scene version, and the
// real-time update of the last full bake by the moves since. The algorithms
// are in lib/obscurance/ and gpu/obscurance/; this file holds the
// per-scene state that joins them to resident scenes and versions.
#pragma once

#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <vector>

#include <glm/glm.hpp>

#include "common/status.h"
#include "core/accuracy_statement.h"
#include "core/call_options.h"
#include "core/engine.h"
#include "obscurance/obscurance_atlas.h"
#include "obscurance/obscurance_model.h"
#include "visq/obscurance_partial.h"
#include "obscurance/obscurance_update.h"
#include "visq/gpu/obscurance.h"
#include "core/work_timing.h"

namespace visq::core {

// Per scene name (Engine::SceneStateOf): the updater of the last full bake.
// UpdateObscurances replays the scene's edit log (Engine::EditsBetween) from
// the version it matches.
struct ObscuranceState {
  std::mutex mutex;  // one update (or installation of a bake) at a time
  std::unique_ptr<obscurance::ObscuranceUpdater> updater;  // after a full bake
  // What the updater holds (ObscuranceUpdaterBytes), reserved by its bake
  // and kept as long as it lives.
  WorkMemoryBudget::Reservation updater_memory;
  uint64_t solution_version = 0;  // the scene version the updater's solution matches
  uint32_t rays_per_patch = 0;
  // The changes of moves an update applied before its call stopped (each
  // move is applied whole, so the solution stays consistent): the next
  // update's answer carries them, from the version the last answer reached,
  // so a client that applies the answers it gets misses no texel.
  struct Undelivered {
    uint64_t from_version = 0;
    uint32_t moves = 0;
    std::map<uint32_t, glm::vec3> w, intensity, triangle_w, vertex_w;
    obscurance::ObscuranceUpdate counts;  // the figures, summed
  };
  std::optional<Undelivered> undelivered;
};

struct ObscuranceQuery {
  std::string scene;
  uint64_t scene_version = 0;
  uint32_t resolution = 256;
  bool force_built_atlas = false;
  obscurance::ObscuranceParams params;
  uint32_t total_directions = 0;  // 0: first + count
  bool partial_only = false;
  bool want_averages = false;
  bool want_errors = false;  // the answer always has them; the transport sends them on request
  uint32_t update_rays_per_patch = 64;
  // None: for a whole bake, the server runs the faster here of the depth
  // peeling with params.direction_count directions and the ray-cast
  // estimator with as many rays per patch, whose bound is the same figure
  // (and a bound, where the bake's is an estimate); a partial bake peels.
  std::optional<ObscuranceMethod> method = ObscuranceMethod::kDepthPeeling;
  uint32_t rays_per_patch = 256;  // kRaycast
  // Instead of params.direction_count, for a whole bake: the planner picks
  // the number of directions (core/accuracy_planner.h).
  std::optional<AccuracyTarget> target;
  CallOptions call;
  // Called on the computing thread after every direction of a GPU bake.
  std::function<void(const obscurance::ObscuranceProgress&)> progress;
};

struct ObscuranceAnswer {
  uint64_t scene_version = 0;
  uint32_t total_directions = 0;
  // The atlas's description (its fragments stay on the server).
  uint32_t width = 0, height = 0;
  bool from_lightmap_uvs = false;
  uint32_t chart_count = 0;
  double texels_per_unit = 0;
  obscurance::ObscurancePartial partial;             // always
  std::optional<obscurance::ObscuranceResult> result;  // unless partial_only
  // Each W's own half-width at `confidence` (per texel, triangle, vertex),
  // with `result`.
  obscurance::ObscuranceBounds bounds;
  obscurance::AmbientModel ambient;
  obscurance::ObscuranceBakeStats stats;
  bool update_ready = false;
  double atlas_ms = 0, bake_ms = 0, finalize_ms = 0, updater_ms = 0;
  double confidence = 0.95;       // of the error figure (a target's, else 0.95)
  ObscuranceMethod method = ObscuranceMethod::kDepthPeeling;
  uint32_t rays_per_patch = 0;    // kRaycast
  std::optional<PlanReport> plan;  // with a target
  WorkMemoryBudget::Reservation memory;  // held until the answer is sent
};
// The atlas, the bake or ray estimate, the finishing and the updater's
// preparation.
inline WorkTiming WorkTimingOf(const ObscuranceAnswer& a) {
  return {0.0, a.atlas_ms + a.bake_ms + a.finalize_ms + a.updater_ms};
}

// Hoeffding's half-width for D independent directions (or rays) with values
// in [0, 1]: the bound of an update's recomputed patches, whose rays are
// independent (obscurance::GeneratePatchRays); for the bake's directions,
// a rotated Halton sequence, an estimate.
double ObscuranceErrorEstimate(uint64_t directions, double confidence);

// How many patches the bake estimated and with how many samples each, on
// average: from the partial's counts for depth peeling (so partial bakes
// have them too), from the result for the ray-cast estimator.
struct ObscuranceCoverage {
  uint64_t estimated_texels = 0;
  double mean_samples_per_patch = 0;
};
ObscuranceCoverage CoverageOf(const ObscuranceAnswer& answer);

// What W and I can promise: error_bound holds for the elements covered by
// obscurance::ObscuranceAnswerBoundOf (those resting on at least a quarter of
// the directions or rays), whose counts outside and the spread of the
// per-element half-widths (answer.bounds) are in its parameters; for the
// depth-peeling bake stated as an estimate because its directions are a
// rotated Halton sequence, for the ray-cast one as a bound (its rays are
// independent); with a target, the chosen plan.
AccuracyStatement ObscuranceStatement(const ObscuranceAnswer& answer);

// INVALID_ARGUMENT (naming the field) for bad parameters before any work.
[[nodiscard]] Status ValidateObscuranceQuery(const ObscuranceQuery& query);
// Builds the atlas, bakes on the GPU and (unless partial_only) finalizes W
// and I. A full bake ([0, total), not partial_only) becomes the scene's
// solution for UpdateObscurances.
[[nodiscard]] StatusOr<ObscuranceAnswer> RunComputeObscurances(Engine& engine, ObscuranceQuery query);

struct ObscuranceUpdateQuery {
  std::string scene;
  uint64_t scene_version = 0;
  bool want_full_w = false;
  // Checked before each move is applied.
  CallOptions call;
};

struct ObscuranceUpdateAnswer {
  uint64_t from_version = 0, scene_version = 0;
  uint32_t moves_applied = 0;
  // Merged over the moves applied: later moves' values win.
  obscurance::ObscuranceUpdate update;
  uint32_t rays_per_patch = 0;
  uint32_t width = 0, height = 0;
  // Each listed element's own half-width at kUpdateConfidence, in the
  // order of update.texels, update.triangles and update.vertices
  // (obscurance::ObscuranceBoundsOfListed): 1 where W rests on no sample of
  // its own (a texel refilled from its neighbours, a triangle no ray reached).
  obscurance::ObscuranceBounds bounds;
  std::vector<glm::vec3> full_w;  // want_full_w
  double mean_samples_per_patch = 0;  // of the bake
  uint64_t directions = 0;            // of the bake
  double compute_ms = 0;
  WorkMemoryBudget::Reservation memory;  // held until the answer is sent
};
inline WorkTiming WorkTimingOf(const ObscuranceUpdateAnswer& a) { return {0.0, a.compute_ms}; }
inline constexpr size_t kMaxFullUpdateFloats = size_t{1} << 22;
inline constexpr double kUpdateConfidence = 0.95;

// The update's: recomputed patches by their rays; the others keep the
// bake's values bit for bit.
AccuracyStatement ObscuranceUpdateStatement(const ObscuranceUpdateAnswer& answer);

// FAILED_PRECONDITION when the scene has no full bake, or when the moves
// recorded since do not lead from the bake's version to the resident one
// (the scene was reloaded or replaced).
[[nodiscard]] StatusOr<ObscuranceUpdateAnswer> RunUpdateObscurances(Engine& engine,
                                                                   const ObscuranceUpdateQuery& query);

// A preview of the scene's current solution: the scene from a pinhole camera
// with W or the intensity I applied per texel (gpu::RenderObscurancePreview).
struct ObscurancePreviewQuery {
  enum class Quantity { kW, kIntensity };
  std::string scene;
  uint64_t scene_version = 0;
  PinholeCamera camera;
  Quantity quantity = Quantity::kW;
  CallOptions call;
};

struct ObscurancePreviewAnswer {
  uint64_t scene_version = 0;
  uint64_t solution_version = 0;  // the solution drawn (equals scene_version)
  ObscurancePreviewQuery::Quantity quantity = ObscurancePreviewQuery::Quantity::kW;
  obscurance::ObscurancePreviewImage image;
  double copy_ms = 0;  // copying the solution out of the updater
  WorkMemoryBudget::Reservation memory;  // held until the answer is sent
};
inline WorkTiming WorkTimingOf(const ObscurancePreviewAnswer& a) {
  return {a.image.queue_ms, a.copy_ms + a.image.total_ms - a.image.queue_ms};
}

// INVALID_ARGUMENT / RESOURCE_EXHAUSTED for a bad camera before any GPU
// work; FAILED_PRECONDITION when the scene has no whole-bake solution, or
// the solution matches another version of the scene (moves since it not yet
// applied by UpdateObscurances).
[[nodiscard]] StatusOr<ObscurancePreviewAnswer> RunRenderObscurancePreview(Engine& engine,
                                                                         const ObscurancePreviewQuery& query);

struct ObscuranceExportQuery {
  std::string scene;
  uint64_t scene_version = 0;
  bool want_atlas_uvs = false;
  bool want_gltf = false;
  bool want_vertex_colors = false;  // with want_gltf: W per vertex as COLOR_0
  CallOptions call;
};

struct ObscuranceExportAnswer {
  uint64_t scene_version = 0;
  uint64_t solution_version = 0;  // equals scene_version
  uint32_t width = 0, height = 0;
  bool from_lightmap_uvs = false;
  uint64_t triangles = 0;
  std::vector<float> atlas_uv;  // obscurance::AtlasUvs, with want_atlas_uvs
  std::string glb;              // obscurance::BakedSceneGlb, with want_gltf
  double copy_ms = 0, export_ms = 0;
  WorkMemoryBudget::Reservation memory;  // held until the answer is sent
};
inline WorkTiming WorkTimingOf(const ObscuranceExportAnswer& a) { return {0.0, a.copy_ms + a.export_ms}; }

// INVALID_ARGUMENT when neither part is wanted; otherwise as
// RunRenderObscurancePreview.
[[nodiscard]] StatusOr<ObscuranceExportAnswer> RunExportObscurances(Engine& engine, const ObscuranceExportQuery& query);

}  // namespace visq::core
