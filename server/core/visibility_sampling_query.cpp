#include "core/visibility_sampling_query.h"

#include <bit>
#include <chrono>

#include "core/engine.h"

namespace visq {
namespace {

double MillisecondsSince(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
}

Status CheckSize(const gpu::HiddenSampleMapRequest& request) {
  const uint64_t bits = uint64_t(std::max(request.receiver.width, 0)) * uint64_t(std::max(request.receiver.height, 0)) *
                        uint64_t(std::max(request.source.sample_count, 0));
  if (bits > kMaxHiddenSampleBits)
    return absl::ResourceExhaustedError(absl::StrCat("receiver texels x samples: ", bits, " bits exceeds the cap of ",
                                                     kMaxHiddenSampleBits, " bits per request"));
  return absl::OkStatus();
}

// The reference: Embree casts, for every texel and sample, the segment the
// GPU path tests (same endpoints, from the module's own functions).
StatusOr<gpu::HiddenSampleMapResult> RaycastHiddenSampleMap(Engine& engine, const ResidentScene& resident,
                                                            const gpu::HiddenSampleMapRequest& request) {
  VISQ_RETURN_IF_ERROR(gpu::ValidateHiddenSampleMapRequest(request));
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<raycast::EmbreeScene> embree, engine.EmbreeSceneOf(resident));
  const auto start = std::chrono::steady_clock::now();
  VISQ_ASSIGN_OR_RETURN(gpu::SourceSamples samples, gpu::ComputeSourceSamples(request.source));
  gpu::HiddenSampleMapResult result;
  const int width = request.receiver.width, height = request.receiver.height;
  const int n = static_cast<int>(samples.world.size());
  if (n == 0) return absl::InvalidArgumentError("source: no sample lies inside the polygon");
  const int words = (n + 31) / 32;
  result.width = width;
  result.height = height;
  result.sample_count = n;
  result.words_per_texel = words;
  result.visible_fraction.resize(size_t(width) * height);
  const bool colored = !samples.color.empty();
  if (colored) result.visible_rgb.resize(size_t(width) * height);
  std::vector<uint32_t> bits(size_t(width) * height * words, 0u);

  // Rows of texels at a time, so memory stays bounded for large maps.
  const int rows_per_batch = std::max(1, (1 << 20) / std::max(1, width * n));
  std::vector<raycast::Segment> segments;
  for (int y0 = 0; y0 < height; y0 += rows_per_batch) {
    const int y1 = std::min(height, y0 + rows_per_batch);
    segments.clear();
    for (int y = y0; y < y1; ++y)
      for (int x = 0; x < width; ++x) {
        const glm::dvec3 p = gpu::ReceiverSamplePosition(request.receiver, x, y);
        for (int i = 0; i < n; ++i) segments.push_back({p, gpu::SourceSampleSeenFrom(request, samples, i, x, y)});
      }
    VISQ_ASSIGN_OR_RETURN(std::vector<uint8_t> blocked, embree->Occluded(segments));
    size_t k = 0;
    for (int y = y0; y < y1; ++y)
      for (int x = 0; x < width; ++x) {
        const size_t j = size_t(y) * width + x;
        for (int i = 0; i < n; ++i, ++k)
          if (blocked[k]) bits[j * words + i / 32] |= 1u << (i % 32);
      }
  }
  // Bit counting, and colors of the unblocked samples.
  for (size_t j = 0; j < result.visible_fraction.size(); ++j) {
    int hidden = 0;
    for (int w = 0; w < words; ++w) hidden += std::popcount(bits[j * words + w]);
    result.visible_fraction[j] = float(n - hidden) / float(n);
    if (colored) {
      glm::vec3 rgb(0.0f);
      for (int i = 0; i < n; ++i)
        if (!((bits[j * words + i / 32] >> (i % 32)) & 1u)) rgb += samples.color[i];
      result.visible_rgb[j] = rgb / float(n);
    }
  }
  if (request.options.want_bitmasks) result.blocked_bits = std::move(bits);
  result.error.confidence = request.options.confidence;
  result.error.sampling = gpu::SamplingErrorBound(n, request.options.confidence);
  result.error.lookup_max = 0.0;
  result.timing.run_ms = MillisecondsSince(start);
  result.passes = 0;
  result.samples = std::move(samples);
  return result;
}

}  // namespace

StatusOr<gpu::HiddenSampleMapResult> RunHiddenSampleMap(Engine& engine, const HiddenSampleMapQuery& query) {
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<const ResidentScene> resident,
                        engine.FindScene(query.scene, query.scene_version));
  VISQ_RETURN_IF_ERROR(gpu::ValidateHiddenSampleMapRequest(query.request));
  VISQ_RETURN_IF_ERROR(CheckSize(query.request));
  if (query.method == VisibilityMethod::kRaycast) return RaycastHiddenSampleMap(engine, *resident, query.request);
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<gpu::GpuScene> gpu_scene, engine.GpuSceneOf(*resident));
  VISQ_ASSIGN_OR_RETURN(gpu::HiddenSampleMapper * mapper, engine.hidden_sample_mapper());
  return mapper->Compute(*gpu_scene, query.request, query.job);
}

StatusOr<gpu::PatchVisibilityResult> RunPatchVisibility(Engine& engine, const PatchVisibilityQuery& query) {
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<const ResidentScene> resident,
                        engine.FindScene(query.scene, query.scene_version));
  VISQ_ASSIGN_OR_RETURN(gpu::HiddenSampleMapRequest map, gpu::PatchVisibilityAsHiddenSampleMap(query.request));
  VISQ_RETURN_IF_ERROR(gpu::ValidateHiddenSampleMapRequest(map));
  VISQ_RETURN_IF_ERROR(CheckSize(map));
  if (query.method == VisibilityMethod::kRaycast) {
    VISQ_ASSIGN_OR_RETURN(gpu::HiddenSampleMapResult result, RaycastHiddenSampleMap(engine, *resident, map));
    return gpu::SummarizePatchVisibility(query.request, result);
  }
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<gpu::GpuScene> gpu_scene, engine.GpuSceneOf(*resident));
  VISQ_ASSIGN_OR_RETURN(gpu::HiddenSampleMapper * mapper, engine.hidden_sample_mapper());
  return mapper->PatchVisibility(*gpu_scene, query.request, query.job);
}

}  // namespace visq
