// GPU obscurance bake by depth peeling (Méndez-Feliu, Sbert et al., section
// 4): for each direction of the sequence, an orthographic bundle of parallel
// rays over the scene, peeled layer by layer until no fragment is left; the
// transfer between consecutive layers is summed per patch (atlas texel) in
// 64-bit fixed point on the GPU. Only the final sums are read back.
//
// The bake runs as one GpuWorker job per direction (priority kBatch by
// default), so interactive queries overtake it and cancellation takes effect
// between directions. Sums are integers: the same seed gives the same bits,
// and partial bakes over disjoint direction ranges merge exactly
// (obscurance/obscurance_partial.h).
#pragma once

#include <atomic>
#include <cstdint>
#include <functional>

#include "common/status.h"
#include "obscurance/obscurance_atlas.h"
#include "obscurance/obscurance_model.h"
#include "obscurance/obscurance_partial.h"
#include "scene/scene.h"
#include "visq/gpu/gpu_scene.h"
#include "visq/gpu/gpu_worker.h"

namespace visq::gpu {

struct ObscuranceProgress {
  uint32_t directions_done = 0;
  uint32_t directions_total = 0;
  double elapsed_seconds = 0;
  double estimated_seconds_left = 0;
  uint32_t layers_last_direction = 0;
};

struct ObscuranceBakeOptions {
  int priority = kBatch;
  SteadyTime deadline = SteadyTime::max();
  const std::atomic<bool>* cancelled = nullptr;  // checked between directions
  // Called on the calling thread after every direction.
  std::function<void(const ObscuranceProgress&)> progress;
  // Stops peeling a direction after this many layers (a guard; reported).
  uint32_t max_layers = 4096;
};

struct ObscuranceBakeStats {
  uint64_t layers = 0;       // over all directions
  uint32_t max_layers = 0;   // of one direction
  uint32_t truncated_directions = 0;  // that hit max_layers
  uint32_t bundle_resolution = 0;
  double seconds = 0;
};

// Bakes directions [params.first_direction, + params.direction_count) of the
// sequence for `scene` (which `gpu_scene` must hold) over `atlas`. The
// partial's fingerprint is BakeFingerprint(scene, atlas, params).
[[nodiscard]] StatusOr<obscurance::ObscurancePartial> BakeObscurancePartial(
    GpuWorker& worker, const GpuScene& gpu_scene, const Scene& scene, const obscurance::ObscuranceAtlas& atlas,
    const obscurance::ObscuranceParams& params, const ObscuranceBakeOptions& options = {},
    ObscuranceBakeStats* stats = nullptr);

// BakeObscurancePartial + FinalizeObscurances.
[[nodiscard]] StatusOr<obscurance::ObscuranceResult> BakeObscurances(
    GpuWorker& worker, const GpuScene& gpu_scene, const Scene& scene, const obscurance::ObscuranceAtlas& atlas,
    const obscurance::ObscuranceParams& params, const ObscuranceBakeOptions& options = {},
    ObscuranceBakeStats* stats = nullptr);

}  // namespace visq::gpu
