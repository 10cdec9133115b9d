// GPU obscurance bake by depth peeling (Méndez-Feliu, Sbert et al., section
// 4): for each direction of the sequence, an orthographic bundle of parallel
// rays over the scene, peeled layer by layer until no fragment is left; the
// transfer between consecutive layers is summed per patch (atlas texel) in
// 64-bit fixed point on the GPU, per patch and again per triangle (so that
// a triangle's W comes from its own samples, not from texels it shares with
// its neighbours), with the sum over directions of each one's squared
// per-direction sample count (the effective number of directions behind its
// estimate). Only the final sums are read back.
//
// The bake runs as one GpuWorker job per direction (priority kBatch by
// default), so interactive queries overtake it and cancellation takes effect
// between directions. Sums are integers: the same seed gives the same bits,
// and partial bakes over disjoint direction ranges merge exactly
// (visq/obscurance_partial.h).
#pragma once

#include <atomic>
#include <cstdint>
#include <functional>
#include <span>
#include <vector>

#include "common/status.h"
#include "obscurance/obscurance_atlas.h"
#include "obscurance/obscurance_bake_report.h"
#include "obscurance/obscurance_model.h"
#include "visq/obscurance_partial.h"
#include "scene/scene.h"
#include "visq/gpu/camera.h"
#include "visq/gpu/gpu_scene.h"
#include "visq/gpu/gpu_worker.h"

namespace visq::gpu {

// What a bake reports and what a preview returns are lib/obscurance's
// (obscurance_bake_report.h): the core and the transport name them without
// naming gpu/.
using obscurance::ObscuranceBakeStats;
using obscurance::ObscurancePreviewImage;
using obscurance::ObscuranceProgress;

struct ObscuranceBakeOptions {
  // Its priority, and its stop token: asked between steps.
  JobOptions job{kBatch};
  // A direction is peeled in GL jobs (steps) of about this long, each
  // whole layers or pieces of one, so that a stop and other calls reach the
  // GL thread between them. 0: a direction is one job.
  double step_target_ms = 25.0;
  // Called on the calling thread after every direction.
  std::function<void(const ObscuranceProgress&)> progress;
  // Stops peeling a direction after this many layers (a guard; reported).
  uint32_t max_layers = 4096;
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

// Preview: the scene seen from a pinhole camera with per-texel values (W or
// intensity of a bake) applied, for people to look at before they read
// numbers. Rasterized with a depth test; each fragment samples the values
// bilinearly at its interpolated atlas coordinates.
inline constexpr uint32_t kMaxObscurancePreviewSize = 4096;  // per side; RESOURCE_EXHAUSTED beyond

struct ObscurancePreviewRequest {
  PinholeCamera camera;
  Bounds scene_bounds;  // of the scene `gpu_scene` holds: the near and far planes
  uint32_t atlas_width = 0, atlas_height = 0;
  // The atlas's corner coordinates in texels, 3 per triangle of gpu_scene
  // (ObscuranceAtlas::corner_uv), and RGB values per texel (y * width + x).
  // Both must outlive the call.
  std::span<const glm::vec2> corner_uv;
  std::span<const glm::vec3> texel_values;
  JobOptions job{kInteractive};
};

// One GL job: INVALID_ARGUMENT / RESOURCE_EXHAUSTED for a bad camera
// (ValidatePinholeCamera) or values that do not fit the scene and atlas,
// before any GPU work.
[[nodiscard]] StatusOr<ObscurancePreviewImage> RenderObscurancePreview(GpuWorker& worker, const GpuScene& gpu_scene,
                                                                       const ObscurancePreviewRequest& request);

}  // namespace visq::gpu
