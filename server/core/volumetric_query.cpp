#include "core/volumetric_query.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <optional>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "common/check.h"
#include "common/job_timing.h"
#include "core/engine.h"

namespace visq::core {
namespace {

// The differences between two images of one view, over pixels
// from value `first_value` of the finer one on.
struct DifferenceSums {
  double max_abs = 0, abs_sum = 0, fine_sum = 0;
  void Add(const std::vector<float>& fine, size_t first_value, const std::vector<float>& coarse) {
    for (size_t i = 0; i < fine.size(); ++i) {
      const double difference = std::abs(double(fine[i]) - double(coarse[first_value + i]));
      max_abs = std::max(max_abs, difference);
      abs_sum += difference;
      fine_sum += std::abs(double(fine[i]));
    }
  }
};

// The estimate from the last two differences: `fine` between I(N) and
// I(N / 2), `earlier` (when there is one) between I(N / 2) and I(N / 4).
VolumetricErrorEstimate EstimateOf(const DifferenceSums& fine, const std::optional<DifferenceSums>& earlier,
                                   uint32_t coarse_map_size) {
  VolumetricErrorEstimate e;
  e.coarse_map_size = coarse_map_size;
  e.max_difference = fine.max_abs;
  double ratio = 0.5;
  if (earlier) {
    e.coarser_map_size = coarse_map_size / 2;
    // Two coarser images that agree exactly say nothing of the order: taken
    // as not converging yet (1), which the clamp makes the slowest allowed.
    e.measured_ratio = earlier->abs_sum > 0 ? fine.abs_sum / earlier->abs_sum : (fine.abs_sum > 0 ? 1.0 : 0.0);
    ratio = e.measured_ratio;
  }
  e.convergence_ratio = std::clamp(ratio, 0.5, 0.75);
  const double factor = VolumetricTailFactor(e.convergence_ratio);
  e.max_pixel_error = fine.max_abs * factor;
  e.relative_l1_error = fine.fine_sum > 0 ? factor * fine.abs_sum / fine.fine_sum : 0.0;
  return e;
}

// Sends a whole image to a band sink, a band of rows at a time.
Status SendInBands(const gpu::VolumetricResult& image, const gpu::VolumetricBandSink& sink) {
  constexpr size_t kBandRows = 256;
  gpu::VolumetricResult figures = image;
  figures.inscattering.clear();
  figures.combined.clear();
  const size_t width = image.width;
  for (size_t row = 0; row < image.height; row += kBandRows) {
    const size_t rows = std::min<size_t>(kBandRows, image.height - row);
    gpu::VolumetricBand band;
    band.first = row * width;
    const auto begin = image.inscattering.begin() + std::ptrdiff_t(3 * row * width);
    band.inscattering.assign(begin, begin + std::ptrdiff_t(3 * rows * width));
    if (!image.combined.empty()) {
      const auto c = image.combined.begin() + std::ptrdiff_t(3 * row * width);
      band.combined.assign(c, c + std::ptrdiff_t(3 * rows * width));
    }
    VISQ_RETURN_IF_ERROR(sink(figures, band));
  }
  return absl::OkStatus();
}

}  // namespace

StatusOr<VolumetricAnswer> RunVolumetricShadow(Engine& engine, const VolumetricQuery& query,
                                               const gpu::VolumetricBandSink& sink) {
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<const ResidentScene> resident,
                        engine.SceneForQuery(query.scene, query.scene_version));
  gpu::VolumetricParams p = query.params;
  if (query.target) {
    VISQ_RETURN_IF_ERROR(ValidateAccuracyTarget(*query.target));
    if (!(query.target->max_error > 0) && !(query.target->time_budget_ms > 0))
      return absl::InvalidArgumentError("target: give max_error or time_budget_ms");
    if (query.target->confidence >= 1.0)
      return absl::InvalidArgumentError(
          "target.confidence: 1 asks for a worst-case bound; volumetric shadows state an error estimate");
    if (query.target->guarantee == AccuracyTarget::Guarantee::kRigorous)
      return absl::InvalidArgumentError(
          "target.guarantee: volumetric shadows state an error estimate, not a bound; leave it unset or ESTIMATE");
    p.shadow_map_size = 256;
  }
  // Validate before the GPU upload: a bad request costs nothing.
  VISQ_RETURN_IF_ERROR(gpu::ValidateVolumetricParams(p));
  p.job = query.call.Job();
  const bool two_images = query.estimate_error || query.target;
  // A band's read-back (16 bytes a pixel) and RGB arrays, then the whole
  // image's arrays or, streamed, what the stream's writer may hold unsent
  // (with an estimate or a target, the images compared are whole); and the
  // shadow map's.
  const uint64_t pixels = uint64_t{p.camera.width} * p.camera.height;
  const uint64_t rgb_bytes = 12 * (p.combined_image ? 2 : 1);
  const uint64_t band_pixels = std::min<uint64_t>(pixels, uint64_t{p.max_pixels_per_job} + 8 * p.camera.width);
  const uint64_t image_bytes = pixels * rgb_bytes;
  const uint32_t largest_map = query.target ? gpu::kMaxVolumetricShadowMapSize : p.shadow_map_size;
  const uint64_t map_texels = uint64_t{largest_map} * largest_map;
  const uint64_t bytes = band_pixels * (16 + rgb_bytes) + map_texels * 8 +
                         (two_images ? 3 * image_bytes
                                     : (sink ? std::min(image_bytes, kStreamedAnswerQueueBytes) : 2 * image_bytes));
  VISQ_ASSIGN_OR_RETURN(WorkMemoryBudget::Reservation memory,
                        engine.work_budget().Reserve(bytes, "camera.width x camera.height, shadow_map_size", p.job));
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<gpu::GpuScene> gpu_scene, engine.GpuSceneOf(*resident, query.call));
  auto render = [&](uint32_t map_size, const gpu::VolumetricBandSink& to) {
    gpu::VolumetricParams at = p;
    at.shadow_map_size = map_size;
    return gpu::RenderVolumetricShadows(engine.gpu(), *gpu_scene, *resident->scene, at, to);
  };

  VolumetricAnswer answer;
  // Only a sink given to a render is timed: the bands sent after a target's
  // renders are outside every render's time.
  const gpu::VolumetricBandSink timed_sink = TimedBandSink(sink, &answer.delivery_ms);
  if (!two_images) {
    VISQ_ASSIGN_OR_RETURN(answer.result, render(p.shadow_map_size, timed_sink));
    answer.maps_rendered = {p.shadow_map_size};
    return answer;
  }
  // The coarser images first: I(N / 4) only to measure how fast the
  // difference falls (VolumetricErrorEstimate), then I(N / 2), each compared
  // with the one before and dropped once compared.
  const uint32_t first_coarse = std::max(gpu::kMinVolumetricShadowMapSize, p.shadow_map_size / 2);
  const uint32_t first_coarser = first_coarse / 2;
  std::optional<DifferenceSums> earlier;
  gpu::VolumetricResult coarse;
  if (first_coarse < p.shadow_map_size && first_coarser >= gpu::kMinVolumetricShadowMapSize) {
    VISQ_ASSIGN_OR_RETURN(gpu::VolumetricResult coarser, render(first_coarser, {}));
    answer.maps_rendered.push_back(first_coarser);
    answer.other_renders_ms += coarser.timings.total_ms;
    VISQ_ASSIGN_OR_RETURN(coarse, render(first_coarse, {}));
    earlier.emplace().Add(coarse.inscattering, 0, coarser.inscattering);
  } else {
    VISQ_ASSIGN_OR_RETURN(coarse, render(first_coarse, {}));
  }
  answer.maps_rendered.push_back(first_coarse);
  answer.other_renders_ms += coarse.timings.total_ms;

  if (!query.target) {
    // The answer streams as it is made, each band compared on its way.
    DifferenceSums sums;
    auto comparing = [&](const gpu::VolumetricResult& figures, const gpu::VolumetricBand& band) -> Status {
      sums.Add(band.inscattering, 3 * band.first, coarse.inscattering);
      return timed_sink ? timed_sink(figures, band) : absl::OkStatus();
    };
    VISQ_ASSIGN_OR_RETURN(answer.result, render(p.shadow_map_size, comparing));
    answer.maps_rendered.push_back(p.shadow_map_size);
    answer.estimate = EstimateOf(sums, earlier, first_coarse);
    return answer;
  }

  // A target: double the map until the estimate meets it, the cap, or the
  // time budget (the next map costs at least the last one).
  const auto start = std::chrono::steady_clock::now();
  uint32_t size = p.shadow_map_size;
  while (true) {
    const auto render_start = std::chrono::steady_clock::now();
    VISQ_ASSIGN_OR_RETURN(gpu::VolumetricResult fine, render(size, {}));
    answer.maps_rendered.push_back(size);
    DifferenceSums sums;
    sums.Add(fine.inscattering, 0, coarse.inscattering);
    answer.estimate = EstimateOf(sums, earlier, size / 2);
    const double last_ms = MillisecondsSince(render_start);
    const bool met = query.target->max_error > 0 && answer.estimate->max_pixel_error <= query.target->max_error;
    const bool out_of_time = query.target->time_budget_ms > 0 &&
                             MillisecondsSince(start) + 2.0 * last_ms > query.target->time_budget_ms;
    if (met || size >= gpu::kMaxVolumetricShadowMapSize || out_of_time) {
      answer.result = std::move(fine);
      break;
    }
    answer.other_renders_ms += fine.timings.total_ms;
    coarse = std::move(fine);
    earlier = sums;
    size *= 2;
  }
  if (sink) {
    VISQ_RETURN_IF_ERROR(SendInBands(answer.result, sink));
    answer.result.inscattering.clear();
    answer.result.combined.clear();
  }
  return answer;
}

const char* VolumetricMethodName(gpu::VolumetricMethod method) {
  return method == gpu::VolumetricMethod::kMinMaxTraversal ? "min-max-mipmap" : "ray-marching";
}

AccuracyStatement VolumetricStatement(const gpu::VolumetricResult& figures) {
  AccuracyStatement out;
  out.method = VolumetricMethodName(figures.method);
  const bool svd = figures.integrand == gpu::VolumetricIntegrand::kSvd;
  out.note = absl::StrCat(
      "no numeric bound against the continuous integral is stated; deterministic: the min-max traversal and ray "
      "marching integrate the same rectified shadow map and give the same image up to float summation order; the "
      "shadow boundary is resolved to the rectified map (",
      figures.rectified_rows, " rows x ", figures.rectified_columns, " columns), the ",
      std::string(gpu::VolumetricIntegrandName(figures.integrand)),
      svd ? absl::StrCat(" integrand approximates the spot light's phase x attenuation by a rank-", figures.svd_rank,
                         " SVD whose largest residual is ", figures.integrand_error,
                         " of its largest value (parameters svd_rank, integrand_error); texels cut by shadow edges or "
                         "the ray's ends, and rays nearly towards or away from the light, are exact per texel")
          : std::string(" integrand is exact per texel span (per-texel midpoint rule for attenuation with spot or "
                        "textured lights)"));
  if (svd) {
    out.parameters["svd_rank"] = figures.svd_rank;
    out.parameters["integrand_error"] = figures.integrand_error;
  }
  return out;
}

double VolumetricTailFactor(double ratio) {
  VISQ_CHECK_LE(0.5, ratio);
  VISQ_CHECK_LT(ratio, 1.0);
  return ratio / (1.0 - ratio);
}

std::optional<AccuracyStatement> VolumetricEstimateStatement(const VolumetricAnswer& answer) {
  if (!answer.estimate) return std::nullopt;
  const VolumetricErrorEstimate& e = *answer.estimate;
  AccuracyStatement out;
  out.method = VolumetricMethodName(answer.result.method);
  out.error_bound = e.max_pixel_error;
  out.estimate = e.max_pixel_error;
  out.confidence = 0.0;
  const std::string convergence =
      e.coarser_map_size > 0
          ? absl::StrCat("the difference fell by ", absl::StrFormat("%.3f", e.measured_ratio), " (L1) from the ",
                         e.coarser_map_size, "^2 to the ", e.coarse_map_size, "^2 map's image, taken as ",
                         absl::StrFormat("%.3f", e.convergence_ratio), " (clamped to [0.5, 0.75])")
          : std::string("no quarter-size map: the difference taken to halve with the map (first order)");
  out.note = absl::StrCat(
      "an estimate, not a bound: Richardson's estimate of the error the shadow map's resolution leaves, from the "
      "same image with ", e.coarse_map_size, "^2 and smaller maps; the traversal integrates the rectified map "
      "exactly, so the error left is where the map puts shadow edges; the largest per-pixel difference from the ",
      e.coarse_map_size, "^2 image is ", e.max_difference, ", and ", convergence,
      ", so the error left is that difference times r / (1 - r)");
  out.parameters["shadow_map_size"] = answer.maps_rendered.back();
  out.parameters["coarse_shadow_map_size"] = e.coarse_map_size;
  out.parameters["coarser_shadow_map_size"] = e.coarser_map_size;
  out.parameters["max_difference"] = e.max_difference;
  out.parameters["convergence_ratio"] = e.convergence_ratio;
  out.parameters["measured_convergence_ratio"] = e.measured_ratio;
  out.parameters["relative_l1_error"] = e.relative_l1_error;
  out.parameters["maps_rendered"] = double(answer.maps_rendered.size());
  return out;
}

}  // namespace visq::core
