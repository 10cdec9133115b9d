// Hidden-sample maps and patch-to-patch visibility as core queries, by the
// GPU algorithm (RASTER, gpu/hidden_sample_map) or by Embree casting exactly
// the same segments (RAYCAST, the reference).
#pragma once

#include <string>

#include "common/status.h"
#include "visq/gpu/hidden_sample_map.h"

namespace visq {

class Engine;

enum class VisibilityMethod { kRaster, kRaycast };

// Beyond this many bits (texels x samples) a request is RESOURCE_EXHAUSTED:
// 4 Gbit, e.g. 2048 x 2048 texels x 1024 samples.
inline constexpr uint64_t kMaxHiddenSampleBits = 1ull << 32;

struct HiddenSampleMapQuery {
  std::string scene;
  uint64_t scene_version = 0;
  gpu::HiddenSampleMapRequest request;
  VisibilityMethod method = VisibilityMethod::kRaster;
  gpu::JobOptions job;
};

struct PatchVisibilityQuery {
  std::string scene;
  uint64_t scene_version = 0;
  gpu::PatchVisibilityRequest request;
  VisibilityMethod method = VisibilityMethod::kRaster;
  gpu::JobOptions job;
};

[[nodiscard]] StatusOr<gpu::HiddenSampleMapResult> RunHiddenSampleMap(Engine& engine, const HiddenSampleMapQuery& query);
[[nodiscard]] StatusOr<gpu::PatchVisibilityResult> RunPatchVisibility(Engine& engine, const PatchVisibilityQuery& query);

}  // namespace visq
