// Volumetric shadows as a core query over a resident scene.
#pragma once

#include <string>

#include "core/call_options.h"
#include "common/status.h"
#include "visq/gpu/volumetric_shadows.h"

namespace visq {

class Engine;

struct VolumetricQuery {
  std::string scene;
  uint64_t scene_version = 0;
  gpu::VolumetricParams params;
  CallOptions call;  // the core sets params.job from it
};

// With `sink`, each band of image rows goes to it as the traversal makes it
// and the result holds the figures only (gpu::RenderVolumetricShadows).
[[nodiscard]] StatusOr<gpu::VolumetricResult> RunVolumetricShadow(Engine& engine, const VolumetricQuery& query,
                                                                 const gpu::VolumetricBandSink& sink = {});

}  // namespace visq
