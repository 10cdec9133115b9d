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

[[nodiscard]] StatusOr<gpu::VolumetricResult> RunVolumetricShadow(Engine& engine, const VolumetricQuery& query);

}  // namespace visq
