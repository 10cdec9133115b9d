#include "core/volumetric_query.h"

#include <algorithm>

#include "core/engine.h"

namespace visq {

StatusOr<gpu::VolumetricResult> RunVolumetricShadow(Engine& engine, const VolumetricQuery& query,
                                                    const gpu::VolumetricBandSink& sink) {
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<const ResidentScene> resident,
                        engine.FindScene(query.scene, query.scene_version));
  // Validate before the GPU upload: a bad request costs nothing.
  VISQ_RETURN_IF_ERROR(gpu::ValidateVolumetricParams(query.params));
  gpu::VolumetricParams p = query.params;
  p.job = query.call.Job();
  // A band's read-back (16 bytes a pixel) and RGB arrays, then the whole
  // image's arrays or, streamed, what the stream's writer may hold unsent;
  // and the shadow map's.
  const uint64_t pixels = uint64_t{p.camera.width} * p.camera.height;
  const uint64_t rgb_bytes = 12 * (p.combined_image ? 2 : 1);
  const uint64_t band_pixels = std::min<uint64_t>(pixels, uint64_t{p.max_pixels_per_job} + 8 * p.camera.width);
  const uint64_t image_bytes = pixels * rgb_bytes;
  const uint64_t map_texels = uint64_t{p.shadow_map_size} * p.shadow_map_size;
  const uint64_t bytes = band_pixels * (16 + rgb_bytes) + map_texels * 8 +
                         (sink ? std::min(image_bytes, kStreamedAnswerQueueBytes) : 2 * image_bytes);
  VISQ_ASSIGN_OR_RETURN(WorkMemoryBudget::Reservation memory,
                        engine.work_budget().Reserve(bytes, "camera.width x camera.height, shadow_map_size", p.job));
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<gpu::GpuScene> gpu_scene, engine.GpuSceneOf(*resident));
  return gpu::RenderVolumetricShadows(engine.gpu(), *gpu_scene, *resident->scene, p, sink);
}

}  // namespace visq
