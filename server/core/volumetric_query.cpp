#include "core/volumetric_query.h"

#include "core/engine.h"

namespace visq {

StatusOr<gpu::VolumetricResult> RunVolumetricShadow(Engine& engine, const VolumetricQuery& query) {
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<const ResidentScene> resident,
                        engine.FindScene(query.scene, query.scene_version));
  // Validate before the GPU upload: a bad request costs nothing.
  VISQ_RETURN_IF_ERROR(gpu::ValidateVolumetricParams(query.params));
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<gpu::GpuScene> gpu_scene, engine.GpuSceneOf(*resident));
  return gpu::RenderVolumetricShadows(engine.gpu(), *gpu_scene, *resident->scene, query.params);
}

}  // namespace visq
