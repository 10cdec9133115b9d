// Hidden-sample maps and patch-to-patch visibility as core queries, by the
// GPU algorithm (RASTER, gpu/hidden_sample_map), by Embree casting exactly
// the same segments (RAYCAST, the reference for the bits), or by the exact
// Plücker method (PLUCKER_EXACT: the visible fractions themselves, no
// samples). With an AccuracyTarget the query picks among the three
// (core/accuracy_planner.h).
#pragma once

#include <optional>
#include <string>

#include "common/status.h"
#include "core/accuracy_planner.h"
#include "core/accuracy_statement.h"
#include "core/call_options.h"
#include "core/work_budget.h"
#include "visq/gpu/hidden_sample_map.h"
#include "core/work_timing.h"

namespace visq::core {

class Engine;

// "raster-exact-lookup", "raster-hough-lookup", "raycast", "plucker-exact".
std::string VisibilityMethodName(VisibilityMethod method, sampling::LookupMode lookup);

// What a sampled (or exact) visible fraction can promise: per-texel
// Clopper-Pearson limits for one independent sample per equal-area cell, a
// Hoeffding half-width otherwise (an estimate where the samples are not
// independent), plus the Hough lookup's own error.
AccuracyStatement SampledVisibilityStatement(const sampling::ErrorBound& error, VisibilityMethod method,
                                             sampling::LookupMode lookup, int samples);

// PatchVisibility's statement: SampledVisibilityStatement's for the source,
// with what every method answers said exactly (the mean over the receiver
// grid's cell centres, not the continuous patch-to-patch fraction).
AccuracyStatement PatchVisibilityStatement(const sampling::ErrorBound& error, VisibilityMethod method,
                                           const sampling::PatchVisibilityRequest& request, int source_samples);

// Beyond this many bits (texels x samples) a request is RESOURCE_EXHAUSTED:
// 4 Gbit, e.g. 2048 x 2048 texels x 1024 samples.
inline constexpr uint64_t kMaxHiddenSampleBits = 1ull << 32;

// A target's plans go up to this many samples: beyond one map's 4096, a
// whole number of maps with independent jitter (JITTERED, EXACT lookup, no
// polygon), their counts added.
inline constexpr int kMaxPlannedSamples = 16 * 4096;

struct HiddenSampleMapQuery {
  std::string scene;
  uint64_t scene_version = 0;
  sampling::HiddenSampleMapRequest request;
  // None: the server runs the fastest here of the methods that give this
  // answer (RASTER with the EXACT lookup and RAYCAST cast the same segments;
  // the HOUGH lookup is RASTER's alone).
  std::optional<VisibilityMethod> method = VisibilityMethod::kRaster;
  // Instead of request.source.sample_count and method: the planner chooses
  // the method and the count (jittered samples, or the exact method).
  std::optional<AccuracyTarget> target;
  // Send each texel's own bound (rigorous sample sets); the map's bound,
  // the largest of them, goes with every answer.
  bool want_texel_error = false;
  CallOptions call;
};

struct HiddenSampleMapAnswer {
  sampling::HiddenSampleMapResult result;
  VisibilityMethod method = VisibilityMethod::kRaster;  // what produced it
  std::optional<PlanReport> plan;                       // with a target
  AccuracyStatement accuracy;                           // over every band
  // The answer's share of the budget for work in flight: it goes with the
  // answer, once the answer has been sent.
  std::shared_ptr<WorkMemoryBudget::Reservation> memory;
};
// Its GL jobs' wait, and its run with the pattern's Hough table when built.
inline WorkTiming WorkTimingOf(const HiddenSampleMapAnswer& a) {
  return {a.result.timing.queue_ms, a.result.timing.run_ms + a.result.table_ms};
}

struct PatchVisibilityQuery {
  std::string scene;
  uint64_t scene_version = 0;
  sampling::PatchVisibilityRequest request;
  // None: the server chooses, as for maps.
  std::optional<VisibilityMethod> method = VisibilityMethod::kRaster;
  // Instead of the source grid and method (the receiver grid stays).
  std::optional<AccuracyTarget> target;
  CallOptions call;
};

struct PatchVisibilityAnswer {
  sampling::PatchVisibilityResult result;
  VisibilityMethod method = VisibilityMethod::kRaster;
  std::optional<PlanReport> plan;
  AccuracyStatement accuracy;
};
inline WorkTiming WorkTimingOf(const PatchVisibilityAnswer& a) {
  return {a.result.timing.queue_ms, a.result.timing.run_ms};
}

// Every check of a query that needs neither the scene nor the GPU: what is
// refused before any work is queued. The Run functions start with these (the
// request-validation fuzz target calls them alone).
[[nodiscard]] Status ValidateHiddenSampleMapQuery(const HiddenSampleMapQuery& query);
[[nodiscard]] Status ValidatePatchVisibilityQuery(const PatchVisibilityQuery& query);

// Without a sink the answer holds the whole map. With one, every band of
// receiver rows goes to it as soon as it is made (the first before the
// second is drawn), and the answer holds the figures only: sizes, samples,
// the bound (over every band) and the timing.
[[nodiscard]] StatusOr<HiddenSampleMapAnswer> RunHiddenSampleMap(Engine& engine, const HiddenSampleMapQuery& query,
                                                                 const sampling::HiddenSampleMapBandSink& sink = {});
[[nodiscard]] StatusOr<PatchVisibilityAnswer> RunPatchVisibility(Engine& engine, const PatchVisibilityQuery& query);

}  // namespace visq::core
