#include "core/volumetric_query.h"

#include "core/engine.h"

namespace visq {

StatusOr<gpu::VolumetricResult> RunVolumetricShadow(Engine& engine, const VolumetricQuery& query) {
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<const ResidentScene> resident,
                        engine.FindScene(query.scene, query.scene_version));
  // Validate before the GPU upload: a bad request costs nothing.
  VISQ_RETURN_IF_ERROR(gpu::ValidateVolumetricParams(query.params));
  gpu::VolumetricParams p = query.params;
  p.job = query.call.Job();
  // The image's read-back and the answer's arrays, and the shadow map's.
  const uint64_t pixels = uint64_t{p.camera.width} * p.camera.height;
  const uint64_t map_texels = uint64_t{p.shadow_map_size} * p.shadow_map_size;
  VISQ_ASSIGN_OR_RETURN(WorkMemoryBudget::Reservation memory,
                        engine.work_budget().Reserve(pixels * (16 + 4 + (p.combined_image ? 4 : 0)) + map_texels * 8,
                                                     "camera.width x camera.height, shadow_map_size", p.job));
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<gpu::GpuScene> gpu_scene, engine.GpuSceneOf(*resident));
  return gpu::RenderVolumetricShadows(engine.gpu(), *gpu_scene, *resident->scene, p);
}

}  // namespace visq
