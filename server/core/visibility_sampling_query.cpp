#include "core/visibility_sampling_query.h"

#include <algorithm>
#include <atomic>
#include <bit>
#include <chrono>
#include <cmath>
#include <functional>
#include <limits>
#include <set>
#include <span>
#include <tuple>
#include <utility>
#include <vector>

#include <spdlog/spdlog.h>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_replace.h"
#include "common/check.h"
#include "common/job_timing.h"
#include "common/normal_estimate.h"
#include "common/parallel.h"
#include "core/accuracy_statement.h"
#include "core/engine.h"
#include "core/exact_prediction.h"
#include "core/light_visibility_query.h"
#include "sampling/count_intervals.h"

namespace visq::core {
namespace {

Status ValidateSize(const sampling::HiddenSampleMapRequest& request) {
  const uint64_t bits = uint64_t(std::max(request.receiver.width, 0)) * uint64_t(std::max(request.receiver.height, 0)) *
                        uint64_t(std::max(request.source.sample_count, 0));
  if (bits > kMaxHiddenSampleBits)
    return absl::ResourceExhaustedError(absl::StrCat("receiver texels x samples: ", bits, " bits exceeds the cap of ",
                                                     kMaxHiddenSampleBits, " bits per request"));
  return absl::OkStatus();
}

// Whether each of `count` segments is blocked: Embree's on the CPU threads
// (RAYCAST) or the same FloatSegments on the GPU (GPU_RAYCAST).
using SegmentOcclusion = std::function<StatusOr<std::vector<uint8_t>>(
    size_t count, const std::function<raycast::Segment(size_t)>& segment_at)>;

StatusOr<SegmentOcclusion> OcclusionTracer(Engine& engine, const ResidentScene& resident,
                                           const sampling::HiddenSampleMapRequest& request, const CallOptions& call,
                                           VisibilityMethod method) {
  const gpu::JobOptions job = call.Job();
  // Either holds float32 positions relative to an origin, like the raster
  // path: the scene's centre, or the query's own region when it lies far
  // from it.
  if (method == VisibilityMethod::kGpuRaycast) {
    VISQ_ASSIGN_OR_RETURN(std::shared_ptr<gpu::RayScene> rays, engine.RaySceneFor(resident, request, call));
    return SegmentOcclusion([rays, job](size_t count, const std::function<raycast::Segment(size_t)>& segment_at) {
      gpu::RayTraceOptions options;
      options.job = job;
      return rays->Occluded(count, segment_at, options);
    });
  }
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<raycast::EmbreeScene> embree, engine.EmbreeSceneFor(resident, request, call));
  return SegmentOcclusion([embree, job](size_t count, const std::function<raycast::Segment(size_t)>& segment_at) {
    raycast::TraceOptions trace;
    trace.stop = job.stop;
    return embree->Occluded(count, segment_at, trace);
  });
}

// The reference: Embree (or the GPU's rays) casts, for every texel and
// sample, the segment the raster path tests (same endpoints, from the
// module's own functions).
StatusOr<sampling::HiddenSampleMapResult> RaycastHiddenSampleMap(Engine& engine, const ResidentScene& resident,
                                                                 const sampling::HiddenSampleMapRequest& request,
                                                                 const CallOptions& call, VisibilityMethod method,
                                                                 const sampling::HiddenSampleMapBandSink& sink = {}) {
  VISQ_RETURN_IF_ERROR(sampling::ValidateHiddenSampleMapRequest(request));
  VISQ_ASSIGN_OR_RETURN(const SegmentOcclusion occluded, OcclusionTracer(engine, resident, request, call, method));
  const auto start = std::chrono::steady_clock::now();
  VISQ_ASSIGN_OR_RETURN(sampling::SourceSamples samples, sampling::ComputeSourceSamples(request.source));
  sampling::HiddenSampleMapResult result;
  const int width = request.receiver.width, height = request.receiver.height;
  const int n = static_cast<int>(samples.world.size());
  if (n == 0) return absl::InvalidArgumentError("source: no sample lies inside the polygon");
  const int words = (n + 31) / 32;
  result.width = width;
  result.height = height;
  result.sample_count = n;
  result.words_per_texel = words;
  result.samples = std::move(samples);
  const sampling::SourceSamples& source = result.samples;
  const bool colored = !source.color.empty();

  // Bands of rows, each traced, counted and delivered before the next:
  // segments are made by the tracing threads from the receiver positions and
  // the source samples, never stored, and no band holds more than 4M
  // segments' results.
  const int rows_per_band = std::max(1, (1 << 22) / std::max(1, width * n));
  std::vector<glm::dvec3> receiver_points;
  std::vector<uint32_t> bits;
  sampling::HiddenSampleMapBand band;
  double delivery_ms = 0;
  for (int y0 = 0; y0 < height; y0 += rows_per_band) {
    const int y1 = std::min(height, y0 + rows_per_band);
    const size_t band_texels = size_t(y1 - y0) * width;
    band.first = size_t(y0) * width;
    receiver_points.resize(band_texels);
    for (int y = y0; y < y1; ++y)
      for (int x = 0; x < width; ++x)
        receiver_points[size_t(y - y0) * width + x] = sampling::ReceiverSamplePosition(request.receiver, x, y);
    StatusOr<std::vector<uint8_t>> traced = occluded(band_texels * n, [&](size_t k) {
      const size_t t = k / n;
      const int i = static_cast<int>(k % n);
      const int x = static_cast<int>(t % width), y = y0 + static_cast<int>(t / width);
      return raycast::Segment{receiver_points[t], sampling::SourceSampleSeenFrom(request, source, i, x, y)};
    });
    VISQ_ASSIGN_OR_RETURN(std::vector<uint8_t> blocked, std::move(traced));
    bits.assign(band_texels * words, 0u);
    for (size_t k = 0; k < blocked.size(); ++k)
      if (blocked[k]) bits[(k / n) * words + (k % n) / 32] |= 1u << ((k % n) % 32);
    // Bit counting, and colours of the unblocked samples.
    band.visible_fraction.resize(band_texels);
    band.visible_rgb.resize(colored ? band_texels : 0);
    band.split_pairs.resize(band_texels);
    for (size_t t = 0; t < band_texels; ++t) {
      int hidden = 0;
      for (int w = 0; w < words; ++w) hidden += std::popcount(bits[t * words + w]);
      band.visible_fraction[t] = float(n - hidden) / float(n);
      band.split_pairs[t] = sampling::SplitPairs(std::span(bits).subspan(t * words, size_t(words)), n);
      if (colored) {
        glm::vec3 rgb(0.0f);
        for (int i = 0; i < n; ++i)
          if (!((bits[t * words + i / 32] >> (i % 32)) & 1u)) rgb += source.color[i];
        band.visible_rgb[t] = rgb / float(n);
      }
    }
    if (request.options.want_bitmasks) band.blocked_bits.swap(bits);
    sampling::BoundTexels(request, result, band);
    VISQ_RETURN_IF_ERROR(sampling::DeliverBand(result, band, TimedBandSink(sink, &delivery_ms)));
  }
  result.error.confidence = request.options.confidence;
  result.error.sampling = sampling::SamplingErrorBound(n, request.options.confidence);
  result.error.rigorous = sampling::SamplesAreIndependentStrata(request);
  result.error.lookup_max = 0.0;
  result.timing.run_ms = MillisecondsSince(start) - delivery_ms;  // the work's, as every method's
  result.passes = 0;
  return result;
}

// Shoelace: positive when the polygon winds counter-clockwise in (s, t).
double TwiceSignedArea(const std::vector<glm::dvec2>& polygon) {
  double twice_area = 0.0;
  for (size_t i = 0; i < polygon.size(); ++i) {
    const glm::dvec2& next = polygon[(i + 1) % polygon.size()];
    twice_area += polygon[i].x * next.y - next.x * polygon[i].y;
  }
  return twice_area;
}

// A map as the exact method's batch: the source (its polygon, or its
// rectangle) as a light facing the receiver, and the receiver's texel
// centres as points. No samples, so no bitmasks and no sample colours.
StatusOr<LightVisibilityQuery> ExactLightQuery(const std::string& scene, uint64_t scene_version,
                                               const sampling::HiddenSampleMapRequest& request,
                                               const CallOptions& call) {
  if (request.options.want_bitmasks)
    return absl::InvalidArgumentError(
        "want_bitmasks: the exact method has no samples, hence no bitmasks; use RASTER or RAYCAST");
  if (!request.source.sample_colors.empty() || !request.source.color_texture.empty())
    return absl::InvalidArgumentError("samples: colored lights need a sampled method (RASTER or RAYCAST)");
  const sampling::Patch& source = request.source.patch;

  // The light polygon, wound to emit towards the receiver (validation put
  // every receiver point strictly on one side of the source plane).
  LightVisibilityQuery light_query;
  light_query.scene = scene;
  light_query.scene_version = scene_version;
  light_query.call = call;
  // The map's reservation (HiddenSampleMapWorkBytes) is the batch's; a
  // planner's probe answers a lattice of a few hundred points.
  light_query.work_reserved = true;
  std::vector<glm::dvec3>& light = light_query.light.vertices;
  double winding = 1.0;
  if (request.source.polygon_uv.empty()) {
    light = {source.At(0, 0), source.At(1, 0), source.At(1, 1), source.At(0, 1)};
  } else {
    for (const glm::dvec2& uv : request.source.polygon_uv) light.push_back(source.At(uv.x, uv.y));
    winding = TwiceSignedArea(request.source.polygon_uv);
  }
  const glm::dvec3 normal = glm::cross(source.edge_u, source.edge_v);
  const bool receiver_in_front = glm::dot(request.receiver.patch.At(0.5, 0.5) - source.origin, normal) > 0.0;
  if (receiver_in_front != (winding > 0.0)) std::reverse(light.begin(), light.end());

  // The receiver points: the texel centres the sampled methods use.
  const int width = request.receiver.width, height = request.receiver.height;
  light_query.points.reserve(size_t(width) * height);
  for (int y = 0; y < height; ++y)
    for (int x = 0; x < width; ++x)
      light_query.points.push_back({sampling::ReceiverSamplePosition(request.receiver, x, y), std::nullopt, std::nullopt});
  return light_query;
}

// The exact visible fraction of the source from every receiver texel
// centre: the Plücker method of core/light_visibility_query.h.
StatusOr<sampling::HiddenSampleMapResult> ExactHiddenSampleMap(Engine& engine, const std::string& scene,
                                                               uint64_t scene_version,
                                                               const sampling::HiddenSampleMapRequest& request,
                                                               const CallOptions& call,
                                                               const sampling::HiddenSampleMapBandSink& sink = {}) {
  VISQ_ASSIGN_OR_RETURN(const LightVisibilityQuery light_query, ExactLightQuery(scene, scene_version, request, call));
  VISQ_ASSIGN_OR_RETURN(LightVisibilityAnswer answer, RunLightVisibility(engine, light_query));
  const int width = request.receiver.width, height = request.receiver.height;

  sampling::HiddenSampleMapResult result;
  result.width = width;
  result.height = height;
  // The points are answered together (they share the light's tree), so the
  // map is one band.
  sampling::HiddenSampleMapBand band;
  band.visible_fraction.reserve(answer.points.size());
  for (const auto& point : answer.points) band.visible_fraction.push_back(float(point.visible_area_fraction));
  VISQ_RETURN_IF_ERROR(sampling::DeliverBand(result, band, sink));
  // Exact but for occluders left out under the engine's shadow tolerance
  // (needles, wires): what they could hide is the bound, one-sided.
  double left_out = 0.0;
  for (const auto& point : answer.points) left_out = std::max(left_out, point.visible_area_fraction_error);
  answer.points = {};
  result.error.sampling = left_out;
  result.error.confidence = 1.0;
  result.timing.run_ms = answer.compute_ms;
  return result;
}

// What a map holds while it is made: one band of rows (its bitmasks, the
// GPU's read-back of them, its per-texel arrays and the ray caster's
// receiver points and results), and then either the whole answer (a map
// answered whole, sent one chunk message at a time) or, streamed, what its
// writer may hold unsent.
uint64_t HiddenSampleMapWorkBytes(const sampling::HiddenSampleMapRequest& request, bool streamed) {
  const uint64_t texels = uint64_t(std::max(request.receiver.width, 0)) * uint64_t(std::max(request.receiver.height, 0));
  const uint64_t words = (uint64_t(std::max(request.source.sample_count, 0)) + 31) / 32;
  const bool colored = !request.source.sample_colors.empty() || !request.source.color_texture.empty();
  // fraction, colour, lookup error, the texel's bound and estimate
  const uint64_t per_texel = 4 + (colored ? 12 : 0) + 4 + 8;
  const uint64_t bits = texels * words * 4;
  // A band's read-back stays under 64 MiB (twice the words for the Hough
  // lookup, at least 16 bytes a texel); the ray caster's bands are smaller.
  constexpr uint64_t kBandBytes = uint64_t{64} << 20;
  const uint64_t band_texels = std::min<uint64_t>(texels, kBandBytes / 16);
  const uint64_t band = std::min(bits, kBandBytes) + std::min(2 * bits, kBandBytes) + band_texels * (per_texel + 24);
  const uint64_t answer = (request.options.want_bitmasks ? bits : 0) + texels * per_texel;
  return band + (streamed ? std::min(answer, kStreamedAnswerQueueBytes) : answer) + (uint64_t{4} << 20);
}

// With `sink`, bands go to it as they are made; with `hold`, the
// reservation outlives the call: it goes with the answer.
StatusOr<sampling::HiddenSampleMapResult> HiddenSampleMapBy(Engine& engine, const ResidentScene& resident,
                                                            VisibilityMethod method,
                                                            const sampling::HiddenSampleMapRequest& request,
                                                            const CallOptions& call,
                                                            const sampling::HiddenSampleMapBandSink& sink = {},
                                                            std::shared_ptr<WorkMemoryBudget::Reservation>* hold = nullptr) {
  const gpu::JobOptions job = call.Job();
  VISQ_ASSIGN_OR_RETURN(WorkMemoryBudget::Reservation memory,
                        engine.work_budget().Reserve(HiddenSampleMapWorkBytes(request, /*streamed=*/bool(sink)),
                                                     "width x height x samples", job));
  if (hold != nullptr) *hold = std::make_shared<WorkMemoryBudget::Reservation>(std::move(memory));
  switch (method) {
    case VisibilityMethod::kRaycast:
    case VisibilityMethod::kGpuRaycast:
      return RaycastHiddenSampleMap(engine, resident, request, call, method, sink);
    case VisibilityMethod::kPluckerExact:
      return ExactHiddenSampleMap(engine, resident.name, resident.version, request, call, sink);
    case VisibilityMethod::kRaster: break;
  }
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<gpu::GpuScene> gpu_scene, engine.GpuSceneFor(resident, request, call));
  VISQ_ASSIGN_OR_RETURN(gpu::HiddenSampleMapper * mapper, engine.hidden_sample_mapper());
  return mapper->Compute(*gpu_scene, request, job, sink);
}

// Patch visibility from a map of the receiver grid: the sampled methods'
// bits give every figure; the exact method gives the receiver samples'
// fractions and their mean (no source samples, no pairs).
StatusOr<sampling::PatchVisibilityResult> PatchVisibilityBy(Engine& engine, const ResidentScene& resident,
                                                       VisibilityMethod method,
                                                       const sampling::PatchVisibilityRequest& request,
                                                       const CallOptions& call) {
  const gpu::JobOptions job = call.Job();
  VISQ_ASSIGN_OR_RETURN(sampling::HiddenSampleMapRequest map, sampling::PatchVisibilityAsHiddenSampleMap(request));
  VISQ_RETURN_IF_ERROR(sampling::ValidateHiddenSampleMapRequest(map));
  VISQ_RETURN_IF_ERROR(ValidateSize(map));
  VISQ_ASSIGN_OR_RETURN(WorkMemoryBudget::Reservation memory,
                        engine.work_budget().Reserve(HiddenSampleMapWorkBytes(map, /*streamed=*/false),
                                                     "source_columns x source_rows x receiver_columns x receiver_rows",
                                                     job));
  if (method == VisibilityMethod::kRaster) {
    VISQ_ASSIGN_OR_RETURN(std::shared_ptr<gpu::GpuScene> gpu_scene, engine.GpuSceneFor(resident, map, call));
    VISQ_ASSIGN_OR_RETURN(gpu::HiddenSampleMapper * mapper, engine.hidden_sample_mapper());
    return mapper->PatchVisibility(*gpu_scene, request, job);
  }
  if (method == VisibilityMethod::kRaycast || method == VisibilityMethod::kGpuRaycast) {
    VISQ_ASSIGN_OR_RETURN(sampling::HiddenSampleMapResult result,
                          RaycastHiddenSampleMap(engine, resident, map, call, method));
    return sampling::SummarizePatchVisibility(request, result);
  }
  if (request.unblocked_limit > 0)
    return absl::InvalidArgumentError("unblocked_limit: the exact method has no sample pairs; use RASTER or RAYCAST");
  map.options.want_bitmasks = false;  // the sampled paths count pairs from them
  VISQ_ASSIGN_OR_RETURN(sampling::HiddenSampleMapResult exact,
                        ExactHiddenSampleMap(engine, resident.name, resident.version, map, call));
  sampling::PatchVisibilityResult out;
  out.receiver_visible = std::move(exact.visible_fraction);
  double sum = 0.0;
  for (float f : out.receiver_visible) sum += f;
  out.mutual_visible_fraction = sum / double(out.receiver_visible.size());
  out.error = exact.error;
  out.timing = exact.timing;
  return out;
}

// ---------------------------------------------------------------------------
// Accuracy targets.

// A run's cost as the cost model sees it: compute time (the GL job or the
// CPU work; not the queue, which other requests cause) and the work done.
struct RunCost {
  double ms = 0.0;
  WorkUnits units;
};

double ComputeMs(const gpu::JobTiming& timing, double table_ms = 0.0) { return timing.run_ms + table_ms; }

// A plan predicted to outlast the call's deadline fails now rather than
// after the work.
Status RequirePredictionFitsDeadline(const Plan& plan, const gpu::JobOptions& job) {
  if (job.stop.deadline == SteadyTime::max()) return absl::OkStatus();
  const double left_ms = MillisecondsBetween(std::chrono::steady_clock::now(), job.stop.deadline);
  if (plan.predicted_ms <= left_ms) return absl::OkStatus();
  return absl::DeadlineExceededError(absl::StrCat("the cheapest plan for the target, ", DescribePlan(plan),
                                                  ", is predicted to take ", plan.predicted_ms,
                                                  " ms; the call's deadline leaves ", left_ms, " ms"));
}

// The sampled methods' work: receiver points x samples (rays, or
// fragments), and for RASTER its samples too, each a set of passes over
// the scene whatever the receiver's size: a probe of 4 x 4 texels costs
// little per fragment and much per pass, and extrapolating it by the
// fragments alone predicted a 64 x 64 map 3-6x too slow.
WorkUnits SampledWork(VisibilityMethod method, double points, int samples) {
  VISQ_CHECK(method != VisibilityMethod::kPluckerExact);
  if (method == VisibilityMethod::kRaster) return {points * samples, double(samples)};
  return {points * samples, 0.0};
}

StatusOr<ExactBatch> ExactBatchOf(const ResidentScene& resident, const sampling::HiddenSampleMapRequest& map,
                                  const CallOptions& call) {
  ExactBatch exact;
  VISQ_ASSIGN_OR_RETURN(exact.batch, ExactLightQuery(resident.name, resident.version, map, call));
  exact.width = map.receiver.width;
  exact.height = map.receiver.height;
  return exact;
}

// Runs a sampled `method` with `samples` per receiver point over a receiver
// reduced to at most `max_side` points a side (0: the request's own receiver).
using VisibilityRunner = std::function<StatusOr<RunCost>(VisibilityMethod method, int samples, int max_side)>;
// Whether a sampled method resolves the request with `samples` samples in
// float32 (Engine::ValidateSampledPrecision): FAILED_PRECONDITION when not.
using PrecisionCheck = std::function<Status(VisibilityMethod method, int samples)>;

sampling::SegmentTracer TracerOf(VisibilityMethod method) {
  return method == VisibilityMethod::kRaster ? sampling::SegmentTracer::kRaster : sampling::SegmentTracer::kRaycast;
}

// The share of the source rectangle inside the light's polygon: jittered
// samples outside it are dropped, so a plan must ask for more.
double PolygonShare(const sampling::SourceSpec& source) {
  if (source.polygon_uv.empty()) return 1.0;
  return std::clamp(std::abs(TwiceSignedArea(source.polygon_uv)) / 2.0, 1e-6, 1.0);
}

// What a sampled plan of N samples would state on the target's guarantee
// (`at`), and the least N predicted to meet max_error.
struct SampledErrorModel {
  std::function<double(int samples)> at;
  double samples_needed = 0.0;
};

// The bound a sampled map states at most, whatever the scene: Hoeffding's
// for the samples inside the polygon.
SampledErrorModel WorstCaseBound(const AccuracyTarget& target, double polygon_share) {
  SampledErrorModel model;
  model.at = [confidence = target.confidence, polygon_share](int samples) {
    const double inside = std::max(1.0, std::floor(samples * polygon_share));
    return std::min(1.0, sampling::SamplingErrorBound(int(inside), confidence));
  };
  model.samples_needed = HoeffdingSamplesNeeded(target.max_error, target.confidence) / polygon_share;
  return model;
}

// What a map of N jittered samples will state on the target's guarantee
// (its largest texel's bound, or estimate), predicted from the same request
// at two small sizes: `at_fewer` from kProbeSamples[0] samples, `at_more`
// from [1], each at least its `floor`. Where shadow edges cross the source,
// the split pairs grow as sqrt(N) and a texel's estimate and split-pair
// bound fall as N^-3/4; where occluders are finer than the cells (foliage, a
// grille seen from afar) most pairs split and they fall as N^-1/2 only. The
// two probes give the rate between, clamped to that range. Never above
// `worst`, what the answer can state whatever the scene. A prediction can
// miss (the probes see 16 x 16 of the request's texels): the chosen plan is
// topped up with more maps until its answer meets the target
// (HiddenSampleMapForTarget).
constexpr int kProbeSamples[2] = {256, 1024};
constexpr int kProbeSide = 16;

SampledErrorModel PredictedFromProbes(const AccuracyTarget& target, double at_fewer, double at_more,
                                      const double floor[2], const SampledErrorModel& worst) {
  const double n0 = kProbeSamples[0], n1 = kProbeSamples[1];
  const double e0 = std::max(at_fewer, floor[0]), e1 = std::max(at_more, floor[1]);
  const double rate = std::clamp(std::log(e0 / e1) / std::log(n1 / n0), 0.5, 0.75);
  SampledErrorModel model;
  model.at = [e1, n1, rate, worst = worst.at](int samples) {
    const double n = std::max(samples, 1);
    return std::min(e1 * std::pow(n1 / n, rate), worst(samples));
  };
  model.samples_needed = worst.samples_needed;
  if (target.max_error > 0)
    model.samples_needed = std::min(model.samples_needed, n1 * std::pow(e1 / target.max_error, 1.0 / rate));
  return model;
}

// The estimate a map states at most, whatever the scene: every pair split
// (z sqrt(n / 2) / n), or, for very few samples, a texel whose samples all
// agree (ln(1 / (1 - confidence)) / n; EstimateOfTexel).
SampledErrorModel WorstCaseEstimate(const AccuracyTarget& target) {
  const double z = TwoSidedNormalQuantile(target.confidence);
  const double agreeing = -std::log(1.0 - target.confidence);
  SampledErrorModel model;
  model.at = [z, agreeing](int samples) {
    const double n = std::max(samples, 1);
    return std::min(1.0, std::max(z * std::sqrt(0.5 / n), agreeing / n));
  };
  const double e = target.max_error;
  model.samples_needed = e > 0 ? std::max(0.5 * z * z / (e * e), agreeing / e) : 0.0;
  return model;
}

// The candidate plans for a visible-fraction answer over `points` receiver
// points, each predicted by the cost model after probing the methods this
// scene has not run yet, and the choice among them.
StatusOr<PlanReport> PlanVisibility(Engine& engine, const std::string& series_base, const AccuracyTarget& target,
                                    double points, const std::function<StatusOr<ExactBatch>()>& exact_batch,
                                    const SampledErrorModel& error_of, bool exact_possible,
                                    int max_samples,
                                    const gpu::JobOptions& job, const VisibilityRunner& run,
                                    const PrecisionCheck& resolves) {
  std::vector<VisibilityMethod> methods = {VisibilityMethod::kRaster, VisibilityMethod::kRaycast};
  if (engine.WeighsGpuRays()) methods.push_back(VisibilityMethod::kGpuRaycast);
  if (exact_possible) methods.push_back(VisibilityMethod::kPluckerExact);

  // Sample counts: powers of two, and the least count meeting the error
  // (beyond one map's 4096, a whole number of maps).
  std::set<int> counts;
  for (int n = 32; n <= max_samples; n *= 2) counts.insert(n);
  const double needed = error_of.samples_needed;
  if (needed <= max_samples) {
    const int step = needed <= sampling::kMaxHiddenSampleMapSamples ? 32 : sampling::kMaxHiddenSampleMapSamples;
    counts.insert(std::min(max_samples, std::max(32, int(std::ceil(needed / step)) * step)));
  }

  PlanReport report;
  CostModel& model = engine.cost_model();
  for (VisibilityMethod method : methods) {
    const std::string name = VisibilityMethodName(method, sampling::LookupMode::kExact);
    const std::string series = absl::StrCat(series_base, "/", name);
    // A sampled method that cannot resolve this request in float32 even
    // with its fewest samples is left out, probed or not.
    auto precise = [&](int samples) -> StatusOr<bool> {
      if (method == VisibilityMethod::kPluckerExact) return true;
      const Status status = resolves(method, samples);
      if (status.code() == absl::StatusCode::kFailedPrecondition) return false;
      VISQ_RETURN_IF_ERROR(status);
      return true;
    };
    VISQ_ASSIGN_OR_RETURN(const bool usable_at_all, precise(*counts.begin()));
    if (!usable_at_all) continue;
    if (method == VisibilityMethod::kPluckerExact) {
      // The exact method is probed on every request (PredictExactByProbes),
      // after the sampled ones, within a share of the cheapest sampled plan
      // that meets the target: a request where it is slow pays at most that
      // share to learn so; one where it is chosen finds what the probes
      // built and stored.
      double best_sampled_ms = std::numeric_limits<double>::infinity();
      for (const Plan& p : report.plans) {
        const bool meets = (target.max_error <= 0.0 || p.error_bound <= target.max_error) &&
                           (target.time_budget_ms <= 0.0 || p.predicted_ms <= target.time_budget_ms);
        if (meets) best_sampled_ms = std::min(best_sampled_ms, p.predicted_ms);
      }
      if (target.time_budget_ms > 0.0) best_sampled_ms = std::min(best_sampled_ms, target.time_budget_ms);
      const double budget_ms = std::isfinite(best_sampled_ms)
                                   ? std::max(kSmallestProbeBudgetMs, kProbeShareOfBest * best_sampled_ms)
                                   : best_sampled_ms;
      VISQ_RETURN_IF_ERROR(job.stop.Check("choosing a method"));
      VISQ_ASSIGN_OR_RETURN(const ExactBatch batch, exact_batch());
      CallOptions call;
      call.stop = job.stop;
      VISQ_ASSIGN_OR_RETURN(const ExactPrediction predicted, PredictExactByProbes(engine, batch, budget_ms, call));
      report.probe_ms += predicted.probe_ms;
      Plan plan;
      plan.method = name;
      plan.runs = method;
      plan.cost_key = series;
      plan.error_bound = 0.0;
      plan.work = predicted.units.work;
      plan.extra_work = predicted.units.extra;
      plan.predicted_ms = predicted.ms;
      // A probe cut at its budget (a share of the cheapest sampled plan)
      // extrapolates what it answered: the method costs at least that.
      if (predicted.cut) plan.parameters["probe_cut"] = 1.0;
      report.plans.push_back(std::move(plan));
      continue;
    }
    // A sampled method never run on this scene: small runs of this very
    // request give the model a fixed cost and a rate; the second, larger
    // run only when the first was cheap.
    if (!model.Predict(series, 1.0)) {
      const std::pair<int, int> probes[] = {{4, 32}, {16, 256}};
      constexpr double kSecondProbeBelowMs = 200.0;
      bool usable = true;
      for (const auto& [side, samples] : probes) {
        VISQ_RETURN_IF_ERROR(job.stop.Check("choosing a method"));
        StatusOr<RunCost> cost = run(method, samples, side);
        // A method that cannot answer this request honestly (a sampled one
        // far from the scene's float32 anchor) is left out of the plans.
        if (cost.status().code() == absl::StatusCode::kFailedPrecondition) {
          usable = false;
          break;
        }
        if (!cost.ok()) return cost.status();
        model.Record(series, cost->units.work, cost->ms, cost->units.extra);
        report.probe_ms += cost->ms;
        if (cost->ms >= kSecondProbeBelowMs) break;
      }
      if (!usable) continue;
    }
    auto add_plan = [&](int samples) -> Status {
      VISQ_ASSIGN_OR_RETURN(const bool resolved, precise(samples));
      if (!resolved) return absl::OkStatus();
      Plan plan;
      plan.method = name;
      plan.runs = method;
      plan.cost_key = series;
      if (method == VisibilityMethod::kPluckerExact) {
        plan.error_bound = engine.light_shadow_tolerance();
      } else {
        plan.parameters["samples"] = samples;
        plan.error_bound = error_of.at(samples);
      }
      const WorkUnits units = SampledWork(method, points, samples);
      plan.work = units.work;
      plan.extra_work = units.extra;
      plan.predicted_ms = model.Predict(series, plan.work, plan.extra_work).value_or(0.0);
      report.plans.push_back(std::move(plan));
      return absl::OkStatus();
    };
    if (method == VisibilityMethod::kPluckerExact) {
      VISQ_RETURN_IF_ERROR(add_plan(0));
    } else {
      for (int n : counts) VISQ_RETURN_IF_ERROR(add_plan(n));
    }
  }
  VISQ_ASSIGN_OR_RETURN(report.chosen, ChoosePlan(report.plans, target));
  VISQ_RETURN_IF_ERROR(RequirePredictionFitsDeadline(report.chosen_plan(), job));
  report.target = target;
  return report;
}

// The cost model's series for a scene's query kind: per scene content, so a
// replaced scene starts afresh.
std::string SeriesBase(const ResidentScene& resident, const char* kind) {
  return absl::StrCat(resident.name, "@", resident.content_hash.substr(0, 8), "/", kind);
}

// The request reduced for a probe: at most max_side texels a side.
sampling::ReceiverSpec ReducedReceiver(const sampling::ReceiverSpec& receiver, int max_side) {
  if (max_side <= 0) return receiver;
  sampling::ReceiverSpec reduced = receiver;
  reduced.width = std::min(receiver.width, max_side);
  reduced.height = std::min(receiver.height, max_side);
  reduced.heightfield.clear();  // its length follows the texel count; the cost does not depend on it
  return reduced;
}

// Whether a map may take more samples than one map holds (SeveralMaps):
// only jittered samples vary between maps, and only visible fractions add
// up (no bitmasks or colours; no polygon's cut or Hough lookup, which make
// each map's count its own).
Status ValidateSeveralMaps(const sampling::HiddenSampleMapRequest& request) {
  const int n = request.source.sample_count;
  auto refuse = [&](const char* why) {
    return absl::ResourceExhaustedError(absl::StrCat("samples.count: ", n, " exceeds one map's ",
                                                     sampling::kMaxHiddenSampleMapSamples, ", and ", why));
  };
  if (n > kMaxPlannedSamples)
    return absl::ResourceExhaustedError(absl::StrCat("samples.count: ", n, " exceeds the cap of ", kMaxPlannedSamples));
  if (request.source.pattern != sampling::SamplePattern::kJittered)
    return refuse("only JITTERED samples can be spread over several maps");
  if (request.options.want_bitmasks) return refuse("want_bitmasks needs one map");
  if (!request.source.sample_colors.empty() || !request.source.color_texture.empty())
    return refuse("coloured lights need one map");
  if (!request.source.polygon_uv.empty()) return refuse("a polygon needs one map");
  if (request.options.lookup != sampling::LookupMode::kExact) return refuse("the HOUGH lookup needs one map");
  return absl::OkStatus();
}

// Maps of `per_map` jittered samples each, each with its own seed, summed:
// every cell of the pattern then holds as many independent uniform samples
// as there are maps. The visible counts add up; the sum is still
// Poisson-binomial, so the per-texel bounds hold at the total count, and the
// split pairs add up as well. Each map's bands are added as they come. After
// `first_maps` maps, and after each later round (as many maps again as are
// summed, up to `most_maps`), the sum's statement is made and `enough` asked
// whether it will do; the sum that does, or the last, is delivered as one
// band.
StatusOr<sampling::HiddenSampleMapResult> SummedMaps(
    Engine& engine, const ResidentScene& resident, VisibilityMethod method, sampling::HiddenSampleMapRequest request,
    int per_map, int first_maps, int most_maps,
    const std::function<bool(const sampling::HiddenSampleMapResult& stated)>& enough, const CallOptions& call,
    const sampling::HiddenSampleMapBandSink& sink) {
  VISQ_CHECK_LE(1, first_maps);
  VISQ_CHECK_LE(first_maps, most_maps);
  request.source.sample_count = per_map;
  request.options.want_bitmasks = false;
  VISQ_RETURN_IF_ERROR(ValidateSize(request));
  const size_t texels = size_t(request.receiver.width) * request.receiver.height;
  std::vector<uint32_t> visible(texels, 0);
  std::vector<int32_t> split_pairs(texels, 0);
  bool every_band_split = true;
  const auto add_band = [&](const sampling::HiddenSampleMapResult& one, const sampling::HiddenSampleMapBand& band) {
    VISQ_CHECK_EQ(one.sample_count, per_map);  // no polygon: every sample counts
    VISQ_CHECK_LE(band.first + band.texels(), texels);
    for (size_t j = 0; j < band.texels(); ++j)
      visible[band.first + j] += static_cast<uint32_t>(std::lround(double(band.visible_fraction[j]) * per_map));
    if (band.split_pairs.size() != band.texels()) every_band_split = false;
    else
      for (size_t j = 0; j < band.texels(); ++j) split_pairs[band.first + j] += band.split_pairs[j];
    return absl::OkStatus();
  };
  sampling::HiddenSampleMapResult sum;
  const uint64_t first_seed = request.source.seed;
  sampling::HiddenSampleMapRequest as_one = request;
  // The sum of `maps` maps as one band, bounded at the total count.
  const auto summed_band = [&](int maps) {
    const int total = maps * per_map;
    sum.sample_count = total;
    sum.samples.requested = total;
    sum.error = sampling::ErrorBound();
    sum.error.confidence = request.options.confidence;
    sum.error.sampling = sampling::SamplingErrorBound(total, sum.error.confidence);
    sum.error.rigorous = sampling::SamplesAreIndependentStrata(request);
    sampling::HiddenSampleMapBand band;
    band.visible_fraction.resize(texels);
    for (size_t j = 0; j < texels; ++j) band.visible_fraction[j] = float(double(visible[j]) / total);
    if (every_band_split) {
      band.split_pairs = split_pairs;
      band.split_pair_maps = maps;
    }
    as_one.source.sample_count = total;
    sampling::BoundTexels(as_one, sum, band);
    return band;
  };
  int maps = 0, round_end = first_maps;
  while (true) {
    for (; maps < round_end; ++maps) {
      request.source.seed = first_seed + uint64_t(maps) * 0x9E3779B97F4A7C15ull;
      VISQ_ASSIGN_OR_RETURN(sampling::HiddenSampleMapResult one,
                            HiddenSampleMapBy(engine, resident, method, request, call, add_band));
      if (maps == 0) {
        sum.width = one.width;
        sum.height = one.height;
      }
      sum.samples.uv.insert(sum.samples.uv.end(), one.samples.uv.begin(), one.samples.uv.end());
      sum.samples.world.insert(sum.samples.world.end(), one.samples.world.begin(), one.samples.world.end());
      sum.timing.queue_ms += one.timing.queue_ms;
      sum.timing.run_ms += one.timing.run_ms;
      sum.table_ms += one.table_ms;
      sum.passes += one.passes;
    }
    sampling::HiddenSampleMapBand band = summed_band(maps);
    if (maps >= most_maps || enough(sum)) {
      VISQ_RETURN_IF_ERROR(sampling::DeliverBand(sum, band, sink));
      return sum;
    }
    round_end = std::min(most_maps, 2 * maps);
  }
}

// A map of `samples` jittered samples beyond one map's 4096: ceil(samples /
// 4096) maps of equal counts (SummedMaps).
StatusOr<sampling::HiddenSampleMapResult> SeveralMaps(Engine& engine, const ResidentScene& resident,
                                                      VisibilityMethod method, sampling::HiddenSampleMapRequest request,
                                                      int samples, const CallOptions& call,
                                                      const sampling::HiddenSampleMapBandSink& sink) {
  const int maps = (samples + sampling::kMaxHiddenSampleMapSamples - 1) / sampling::kMaxHiddenSampleMapSamples;
  const int per_map = (samples + maps - 1) / maps;
  return SummedMaps(engine, resident, method, std::move(request), per_map, maps, maps,
                    [](const sampling::HiddenSampleMapResult&) { return true; }, call, sink);
}

StatusOr<HiddenSampleMapAnswer> HiddenSampleMapForTarget(Engine& engine, const ResidentScene& resident,
                                                         const HiddenSampleMapQuery& query,
                                                         const sampling::HiddenSampleMapBandSink& sink) {
  const AccuracyTarget& target = *query.target;
  const sampling::HiddenSampleMapRequest& request = query.request;
  if (request.source.pattern == sampling::SamplePattern::kCustom)
    return absl::InvalidArgumentError("target: a CUSTOM pattern fixes the samples; give samples.count instead");
  const bool colored = !request.source.sample_colors.empty() || !request.source.color_texture.empty();
  if (!request.source.sample_colors.empty())
    return absl::InvalidArgumentError("target: per-sample colours fix the samples; give samples.count instead");
  const bool exact_possible = !request.options.want_bitmasks && !colored;

  auto with_samples = [&](int samples, int max_side) {
    sampling::HiddenSampleMapRequest sized = request;
    sized.source.sample_count = std::min(samples, sampling::kMaxHiddenSampleMapSamples);
    sized.receiver = ReducedReceiver(request.receiver, max_side);
    sized.options.confidence = target.confidence < 1.0 ? target.confidence : sized.options.confidence;
    return sized;
  };
  // Probes are answered whole; only the chosen plan's map goes to the sink.
  // Beyond 4096 samples, several maps with independent jitter.
  auto run = [&](VisibilityMethod method, int samples, int max_side,
                 const sampling::HiddenSampleMapBandSink& bands = {}) -> StatusOr<sampling::HiddenSampleMapResult> {
    sampling::HiddenSampleMapRequest sized = with_samples(std::max(samples, 1), max_side);
    if (samples > sampling::kMaxHiddenSampleMapSamples)
      return SeveralMaps(engine, resident, method, sized, samples, query.call, bands);
    VISQ_RETURN_IF_ERROR(ValidateSize(sized));
    return HiddenSampleMapBy(engine, resident, method, sized, query.call, bands);
  };
  auto cost_of = [&](VisibilityMethod method, int samples, int max_side) -> StatusOr<RunCost> {
    VISQ_ASSIGN_OR_RETURN(sampling::HiddenSampleMapResult result, run(method, samples, max_side));
    return RunCost{ComputeMs(result.timing, result.table_ms),
                   SampledWork(method, double(result.width) * result.height, samples)};
  };

  const auto resolves = [&](VisibilityMethod method, int samples) -> Status {
    if (method == VisibilityMethod::kGpuRaycast) VISQ_RETURN_IF_ERROR(engine.AdmitRayScene(resident));
    return engine.ValidateSampledPrecision(resident, with_samples(samples, 0), TracerOf(method), query.call);
  };
  // Jittered visible fractions can be topped up with more maps (SummedMaps),
  // so their plans are weighed by the bound, or estimate, that this
  // request's own samples predict (PredictedFromProbes), and the answer is
  // topped up where the prediction missed. Other requests are weighed by
  // the worst case, which their answer never exceeds.
  const bool several_maps = ValidateSeveralMaps(request).ok();
  if (target.wants_estimate() && !sampling::SamplesAreIndependentStrata(request))
    return absl::InvalidArgumentError(
        "target.guarantee: ESTIMATE needs JITTERED samples without a polygon or decorrelation (one independent "
        "sample in each of N equal cells, whose split pairs estimate the variance); ask for RIGOROUS");
  SampledErrorModel error_of = target.wants_estimate() ? WorstCaseEstimate(target)
                                                       : WorstCaseBound(target, PolygonShare(request.source));
  const std::string series_base = SeriesBase(resident, "hidden_sample_map");
  double probe_ms = 0.0;
  if (target.max_error > 0 && (several_maps || target.wants_estimate())) {
    // Two small maps of this request, by the cheaper method on a CPU that
    // resolves it (both give the same bits); their times teach the cost
    // model that method too.
    VisibilityMethod probe_method = VisibilityMethod::kRaycast;
    const Status raycast_resolves = resolves(probe_method, kProbeSamples[1]);
    if (raycast_resolves.code() == absl::StatusCode::kFailedPrecondition) probe_method = VisibilityMethod::kRaster;
    else VISQ_RETURN_IF_ERROR(raycast_resolves);
    double at[2] = {0.0, 0.0};
    double floor[2] = {0.0, 0.0};
    const double z = TwoSidedNormalQuantile(target.confidence);
    for (int i = 0; i < 2; ++i) {
      VISQ_RETURN_IF_ERROR(query.call.stop.Check("choosing a method"));
      VISQ_ASSIGN_OR_RETURN(const sampling::HiddenSampleMapResult probe,
                            run(probe_method, kProbeSamples[i], kProbeSide));
      const double ms = ComputeMs(probe.timing, probe.table_ms);
      const WorkUnits units = SampledWork(probe_method, double(probe.width) * probe.height, kProbeSamples[i]);
      engine.cost_model().Record(absl::StrCat(series_base, "/", VisibilityMethodName(probe_method,
                                                                                      request.options.lookup)),
                                 units.work, ms, units.extra);
      probe_ms += ms;
      if (target.wants_estimate()) {
        at[i] = probe.error.has_estimate ? probe.error.estimate_max : 1.0;
        floor[i] = z / kProbeSamples[i];  // one split pair: a probe that saw no penumbra says little
      } else {
        at[i] = probe.error.total();
      }
    }
    error_of = PredictedFromProbes(target, at[0], at[1], floor, error_of);
  }

  const double texels = double(request.receiver.width) * request.receiver.height;
  const int max_samples = several_maps ? kMaxPlannedSamples : sampling::kMaxHiddenSampleMapSamples;
  VISQ_ASSIGN_OR_RETURN(PlanReport report, PlanVisibility(engine, series_base, target, texels,
                                                          [&] { return ExactBatchOf(resident, with_samples(1, 0), query.call); },
                                                          error_of, exact_possible,
                                                          max_samples, query.call.Job(), cost_of, resolves));
  report.probe_ms += probe_ms;
  LogChosenPlan(report, query.call);
  const Plan& plan = report.chosen_plan();
  HiddenSampleMapAnswer answer;
  answer.method = std::get<VisibilityMethod>(plan.runs);
  const int samples = plan.parameters.contains("samples") ? int(plan.parameters.at("samples")) : 0;
  if (answer.method != VisibilityMethod::kPluckerExact && several_maps && target.max_error > 0) {
    // The plan's maps, then as many again while the answer misses the
    // target, up to the planner's cap.
    const int maps = (samples + sampling::kMaxHiddenSampleMapSamples - 1) / sampling::kMaxHiddenSampleMapSamples;
    const int per_map = (samples + maps - 1) / maps;
    const auto meets = [&](const sampling::HiddenSampleMapResult& stated) {
      const double value = target.wants_estimate() ? (stated.error.has_estimate ? stated.error.estimate_max : 1.0)
                                                   : stated.error.total();
      return value <= target.max_error;
    };
    constexpr int kMostTopUp = 16;  // at most 16x the planned samples: the bound falls 4-8x
    const int most_maps = std::max(maps, std::min(kMostTopUp * maps, kMaxPlannedSamples / per_map));
    VISQ_ASSIGN_OR_RETURN(answer.result, SummedMaps(engine, resident, answer.method, with_samples(per_map, 0),
                                                    per_map, maps, most_maps, meets, query.call, sink));
  } else {
    VISQ_ASSIGN_OR_RETURN(answer.result, run(answer.method, samples, 0, sink));
  }
  // The model learns what ran: a topped-up plan ran more samples.
  const WorkUnits ran = answer.method == VisibilityMethod::kPluckerExact
                            ? WorkUnits{plan.work, plan.extra_work}
                            : SampledWork(answer.method, texels, answer.result.sample_count);
  engine.cost_model().Record(plan.cost_key, ran.work, ComputeMs(answer.result.timing, answer.result.table_ms),
                             ran.extra);

  answer.plan = std::move(report);
  return answer;
}

StatusOr<PatchVisibilityAnswer> PatchVisibilityForTarget(Engine& engine, const ResidentScene& resident,
                                                         const PatchVisibilityQuery& query) {
  const AccuracyTarget& target = *query.target;
  const sampling::PatchVisibilityRequest& request = query.request;
  const bool exact_possible = request.unblocked_limit == 0;
  if (target.wants_estimate())
    return absl::InvalidArgumentError(
        "target.guarantee: ESTIMATE needs samples whose variance the answer can estimate, and PatchVisibility's "
        "source grid is regular; ask for RIGOROUS, or a HiddenSampleMap of JITTERED samples");

  // A plan's sample count becomes the most nearly square source grid with
  // at least that many cells.
  auto sized = [&](int samples, int max_side) {
    sampling::PatchVisibilityRequest out = request;
    out.source_columns = std::max(1, int(std::ceil(std::sqrt(double(std::max(samples, 1))))));
    out.source_rows = std::max(1, (std::max(samples, 1) + out.source_columns - 1) / out.source_columns);
    if (max_side > 0) {
      out.receiver_columns = std::min(request.receiver_columns, max_side);
      out.receiver_rows = std::min(request.receiver_rows, max_side);
    }
    return out;
  };
  // The exact method's batch on a grid: that of its map (PatchVisibilityBy).
  auto exact_batch_of = [&]() -> StatusOr<ExactBatch> {
    VISQ_ASSIGN_OR_RETURN(sampling::HiddenSampleMapRequest map, sampling::PatchVisibilityAsHiddenSampleMap(request));
    map.options.want_bitmasks = false;
    return ExactBatchOf(resident, map, query.call);
  };
  auto cost_of = [&](VisibilityMethod method, int samples, int max_side) -> StatusOr<RunCost> {
    const sampling::PatchVisibilityRequest probe = sized(samples, max_side);
    VISQ_ASSIGN_OR_RETURN(sampling::PatchVisibilityResult result, PatchVisibilityBy(engine, resident, method, probe, query.call));
    return RunCost{ComputeMs(result.timing), SampledWork(method, double(probe.receiver_columns) * probe.receiver_rows,
                                                         probe.source_columns * probe.source_rows)};
  };

  const double points = double(request.receiver_columns) * request.receiver_rows;
  VISQ_ASSIGN_OR_RETURN(PlanReport report, PlanVisibility(engine, SeriesBase(resident, "patch_visibility"), target,
                                                          points, exact_batch_of,
                                                          WorstCaseBound(target, 1.0), exact_possible,
                                                          sampling::kMaxHiddenSampleMapSamples, query.call.Job(), cost_of,
                                                          [&](VisibilityMethod method, int samples) -> Status {
                                                            VISQ_ASSIGN_OR_RETURN(
                                                                sampling::HiddenSampleMapRequest map,
                                                                sampling::PatchVisibilityAsHiddenSampleMap(sized(samples, 0)));
                                                            return engine.ValidateSampledPrecision(resident, map,
                                                                                                TracerOf(method),
                                                                                                query.call);
                                                          }));
  LogChosenPlan(report, query.call);
  Plan& plan = report.plans[report.chosen];
  PatchVisibilityAnswer answer;
  answer.method = std::get<VisibilityMethod>(plan.runs);
  sampling::PatchVisibilityRequest chosen = request;
  if (answer.method != VisibilityMethod::kPluckerExact) {
    chosen = sized(int(plan.parameters.at("samples")), 0);
    plan.parameters["source_columns"] = chosen.source_columns;
    plan.parameters["source_rows"] = chosen.source_rows;
  }
  VISQ_ASSIGN_OR_RETURN(answer.result, PatchVisibilityBy(engine, resident, answer.method, chosen, query.call));
  engine.cost_model().Record(plan.cost_key, plan.work, ComputeMs(answer.result.timing), plan.extra_work);
  // The grid's bound restated at the target's confidence, as the plan was
  // weighed (the map itself is built at the default one).
  if (answer.method != VisibilityMethod::kPluckerExact && target.confidence < 1.0) {
    answer.result.error.confidence = target.confidence;
    answer.result.error.sampling =
        sampling::SamplingErrorBound(chosen.source_columns * chosen.source_rows, target.confidence);
  }
  answer.plan = std::move(report);
  return answer;
}

// ---------------------------------------------------------------------------
// A request with its own samples and no method: the server's choice.

// RASTER with the EXACT lookup and RAYCAST give the same bits (up to float
// ties on triangle edges), so the server runs the one this scene's cost
// model predicts faster on this device. RAYCAST comes first: its probe of
// a few receiver points costs a few thousand rays, so it is always measured,
// and RASTER's probe (whole passes over the scene, slow on a CPU
// rasterizer) then gets a share of RAYCAST's predicted time.
// `run(method, side, call)` runs the request reduced to at most side x side
// receiver points and returns its compute ms; it owns what it runs on (the
// scene, a copy of the request), so that a probe too large for this
// request's share can run later, in the server's idle time.
// `points(side)` counts the points.
using SampledProbeRun = std::function<StatusOr<double>(VisibilityMethod, int side, const CallOptions&)>;
StatusOr<PlanReport> ChooseSampledMethod(Engine& engine, const std::string& series_base, sampling::LookupMode lookup,
                                         int samples, const std::function<double(int side)>& points,
                                         std::shared_ptr<const SampledProbeRun> run, const PrecisionCheck& resolves,
                                         const CallOptions& call) {
  std::vector<VisibilityMethod> methods = {VisibilityMethod::kRaster};
  if (lookup == sampling::LookupMode::kExact) {
    methods.insert(methods.begin(), VisibilityMethod::kRaycast);
    if (engine.WeighsGpuRays()) methods.push_back(VisibilityMethod::kGpuRaycast);
  }
  std::vector<EqualAnswerOption> options;
  for (VisibilityMethod method : methods) {
    const Status precise = resolves(method, samples);
    if (precise.code() == absl::StatusCode::kFailedPrecondition) continue;  // not honest for this request
    VISQ_RETURN_IF_ERROR(precise);
    EqualAnswerOption option;
    Plan& plan = option.plan;
    plan.method = VisibilityMethodName(method, lookup);
    plan.runs = method;
    plan.cost_key = absl::StrCat(series_base, "/", plan.method);
    plan.parameters["samples"] = samples;
    const WorkUnits whole = SampledWork(method, points(0), samples);
    plan.work = whole.work;
    plan.extra_work = whole.extra;
    for (int side : {4, 16}) {
      const WorkUnits units = SampledWork(method, points(side), samples);
      option.probes.push_back({units.work, units.extra, [run, method, side](const CallOptions& probe_call) {
                                 return (*run)(method, side, probe_call);
                               }});
    }
    option.probes_outlive_the_call = true;
    options.push_back(std::move(option));
  }
  if (options.empty())
    return absl::FailedPreconditionError(
        "method: no sampled method resolves this request in float32 (see the scene's anchor); name PLUCKER_EXACT");
  return ChooseFastest(engine.cost_model(), std::move(options), call, engine.idle_explorer());
}

StatusOr<PlanReport> ChooseHiddenSampleMapMethod(Engine& engine, std::shared_ptr<const ResidentScene> held,
                                                 const sampling::HiddenSampleMapRequest& request,
                                                 const CallOptions& call) {
  const ResidentScene& resident = *held;
  const int samples = request.source.sample_count;
  auto run = std::make_shared<const SampledProbeRun>(
      [&engine, scene = std::weak_ptr(held), request, samples](VisibilityMethod method, int side,
                                                               const CallOptions& probe_call) -> StatusOr<double> {
        VISQ_ASSIGN_OR_RETURN(const std::shared_ptr<const ResidentScene> held, StillHeld(scene));
        sampling::HiddenSampleMapRequest probe = request;
        probe.receiver = ReducedReceiver(request.receiver, side);
        StatusOr<sampling::HiddenSampleMapResult> result =
            samples > sampling::kMaxHiddenSampleMapSamples
                ? SeveralMaps(engine, *held, method, probe, samples, probe_call, {})
                : HiddenSampleMapBy(engine, *held, method, probe, probe_call);
        if (!result.ok()) return result.status();
        return ComputeMs(result->timing, result->table_ms);
      });
  auto points = [&](int side) {
    const sampling::ReceiverSpec receiver = ReducedReceiver(request.receiver, side);
    return double(receiver.width) * receiver.height;
  };
  auto resolves = [&](VisibilityMethod method, int) -> Status {
    if (method == VisibilityMethod::kGpuRaycast) VISQ_RETURN_IF_ERROR(engine.AdmitRayScene(resident));
    sampling::HiddenSampleMapRequest one_map = request;
    one_map.source.sample_count = std::min(samples, sampling::kMaxHiddenSampleMapSamples);
    return engine.ValidateSampledPrecision(resident, one_map, TracerOf(method), call);
  };
  return ChooseSampledMethod(engine, SeriesBase(resident, "hidden_sample_map"), request.options.lookup, samples,
                             points, run, resolves, call);
}

sampling::PatchVisibilityRequest WithReceiverSide(const sampling::PatchVisibilityRequest& request, int side) {
  sampling::PatchVisibilityRequest out = request;
  if (side > 0) {
    out.receiver_columns = std::min(request.receiver_columns, side);
    out.receiver_rows = std::min(request.receiver_rows, side);
  }
  return out;
}

StatusOr<PlanReport> ChoosePatchVisibilityMethod(Engine& engine, std::shared_ptr<const ResidentScene> held,
                                                 const sampling::PatchVisibilityRequest& request,
                                                 const CallOptions& call) {
  const ResidentScene& resident = *held;
  auto sized = [&](int side) { return WithReceiverSide(request, side); };
  auto run = std::make_shared<const SampledProbeRun>(
      [&engine, scene = std::weak_ptr(held), request](VisibilityMethod method, int side,
                                                      const CallOptions& probe_call) -> StatusOr<double> {
        VISQ_ASSIGN_OR_RETURN(const std::shared_ptr<const ResidentScene> held, StillHeld(scene));
        VISQ_ASSIGN_OR_RETURN(const sampling::PatchVisibilityResult result,
                              PatchVisibilityBy(engine, *held, method, WithReceiverSide(request, side), probe_call));
        return ComputeMs(result.timing);
      });
  auto points = [&](int side) {
    const sampling::PatchVisibilityRequest r = sized(side);
    return double(r.receiver_columns) * r.receiver_rows;
  };
  auto resolves = [&](VisibilityMethod method, int) -> Status {
    if (method == VisibilityMethod::kGpuRaycast) VISQ_RETURN_IF_ERROR(engine.AdmitRayScene(resident));
    VISQ_ASSIGN_OR_RETURN(const sampling::HiddenSampleMapRequest map, sampling::PatchVisibilityAsHiddenSampleMap(request));
    return engine.ValidateSampledPrecision(resident, map, TracerOf(method), call);
  };
  return ChooseSampledMethod(engine, SeriesBase(resident, "patch_visibility"), request.lookup,
                             request.source_columns * request.source_rows, points, run, resolves, call);
}

// The chosen method's run teaches the model too.
void RecordChosenRun(Engine& engine, const PlanReport& report, double compute_ms) {
  const Plan& plan = report.chosen_plan();
  engine.cost_model().Record(plan.cost_key, plan.work, compute_ms, plan.extra_work);
}

}  // namespace

std::string VisibilityMethodName(VisibilityMethod method, sampling::LookupMode lookup) {
  switch (method) {
    case VisibilityMethod::kRaycast: return "raycast";
    case VisibilityMethod::kGpuRaycast: return "gpu-raycast";
    case VisibilityMethod::kPluckerExact: return "plucker-exact";
    case VisibilityMethod::kRaster: break;
  }
  return lookup == sampling::LookupMode::kExact ? "raster-exact-lookup" : "raster-hough-lookup";
}

namespace {

// The request as it will run: without samples (a target, or the exact
// method) the count is the planner's to choose, so one stands in for it.
sampling::HiddenSampleMapRequest WithStandInCount(const HiddenSampleMapQuery& query) {
  sampling::HiddenSampleMapRequest request = query.request;
  const bool count_chosen_here = query.target || query.method == VisibilityMethod::kPluckerExact;
  if (count_chosen_here && request.source.sample_count == 0) request.source.sample_count = 1;
  return request;
}

}  // namespace

Status ValidateHiddenSampleMapQuery(const HiddenSampleMapQuery& query) {
  if (query.target) {
    VISQ_RETURN_IF_ERROR(ValidateAccuracyTarget(*query.target));
    if (query.request.source.sample_count != 0)
      return absl::InvalidArgumentError("samples.count: give either a count or a target, not both");
  }
  sampling::HiddenSampleMapRequest checked = WithStandInCount(query);
  if (checked.source.sample_count > sampling::kMaxHiddenSampleMapSamples) {
    VISQ_RETURN_IF_ERROR(ValidateSeveralMaps(checked));
    if (query.method == VisibilityMethod::kPluckerExact)
      return absl::InvalidArgumentError("samples.count: the exact method takes no samples (leave it 0)");
    checked.source.sample_count = sampling::kMaxHiddenSampleMapSamples;  // one of the maps
  }
  VISQ_RETURN_IF_ERROR(sampling::ValidateHiddenSampleMapRequest(checked));
  if (!query.target) VISQ_RETURN_IF_ERROR(ValidateSize(checked));
  return absl::OkStatus();
}

Status ValidatePatchVisibilityQuery(const PatchVisibilityQuery& query) {
  if (query.target) return ValidateAccuracyTarget(*query.target);
  VISQ_ASSIGN_OR_RETURN(sampling::HiddenSampleMapRequest map, sampling::PatchVisibilityAsHiddenSampleMap(query.request));
  VISQ_RETURN_IF_ERROR(sampling::ValidateHiddenSampleMapRequest(map));
  return ValidateSize(map);
}

namespace {

StatusOr<HiddenSampleMapAnswer> HiddenSampleMapUnstated(Engine& engine, const HiddenSampleMapQuery& query,
                                                        const sampling::HiddenSampleMapBandSink& sink) {
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<const ResidentScene> resident,
                        engine.SceneForQuery(query.scene, query.scene_version));
  if (query.target) return HiddenSampleMapForTarget(engine, *resident, query, sink);
  const sampling::HiddenSampleMapRequest checked = WithStandInCount(query);
  HiddenSampleMapAnswer answer;
  if (query.method) {
    answer.method = *query.method;
  } else {
    VISQ_ASSIGN_OR_RETURN(PlanReport report, ChooseHiddenSampleMapMethod(engine, resident, checked, query.call));
    answer.method = std::get<VisibilityMethod>(report.chosen_plan().runs);
    answer.plan = std::move(report);
  }
  if (checked.source.sample_count > sampling::kMaxHiddenSampleMapSamples) {
    VISQ_ASSIGN_OR_RETURN(answer.result, SeveralMaps(engine, *resident, answer.method, checked,
                                                     checked.source.sample_count, query.call, sink));
  } else {
    VISQ_ASSIGN_OR_RETURN(answer.result, HiddenSampleMapBy(engine, *resident, answer.method, checked, query.call,
                                                           sink, &answer.memory));
  }
  if (answer.plan) RecordChosenRun(engine, *answer.plan, ComputeMs(answer.result.timing, answer.result.table_ms));
  return answer;
}

StatusOr<PatchVisibilityAnswer> PatchVisibilityUnstated(Engine& engine, const PatchVisibilityQuery& query) {
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<const ResidentScene> resident,
                        engine.SceneForQuery(query.scene, query.scene_version));
  if (query.target) return PatchVisibilityForTarget(engine, *resident, query);
  PatchVisibilityAnswer answer;
  if (query.method) {
    answer.method = *query.method;
  } else {
    VISQ_ASSIGN_OR_RETURN(PlanReport report, ChoosePatchVisibilityMethod(engine, resident, query.request, query.call));
    answer.method = std::get<VisibilityMethod>(report.chosen_plan().runs);
    answer.plan = std::move(report);
  }
  VISQ_ASSIGN_OR_RETURN(answer.result, PatchVisibilityBy(engine, *resident, answer.method, query.request, query.call));
  if (answer.plan) RecordChosenRun(engine, *answer.plan, ComputeMs(answer.result.timing));
  return answer;
}

}  // namespace

AccuracyStatement SampledVisibilityStatement(const sampling::ErrorBound& error, VisibilityMethod method,
                                             sampling::LookupMode lookup, int samples) {
  if (method == VisibilityMethod::kPluckerExact) {
    AccuracyStatement exact =
        ExactStatement(VisibilityMethodName(method, lookup),
                       "exact visible fractions (Plücker method): every side decision is an exact predicate; only "
                       "the areas are double-precision sums");
    if (error.sampling > 0.0) {
      exact.error_bound = error.sampling;
      absl::StrAppend(&exact.note,
                      "; but occluders whose shadows on the source were tiny were left out under the server's "
                      "--light-shadow-tolerance, and error_bound is what they could hide at the worst texel, "
                      "one-sided (the true fraction is at most that much below the answer)");
    }
    return exact;
  }
  AccuracyStatement out;
  out.method = VisibilityMethodName(method, lookup);
  out.parameters["samples"] = samples;
  out.error_bound = error.total();
  out.confidence = error.confidence;
  const std::string lookup_words =
      error.lookup_max > 0 ? absl::StrCat("; the Hough lookup's error (at most ", error.lookup_max,
                                          ", per texel in lookup_error) is included")
                           : std::string("; no lookup error (same bits as casting the same segments)");
  if (error.has_per_texel) {
    out.note = absl::StrCat(
        "each texel's visible fraction within its own bound of the true (continuous) fraction at confidence ",
        error.confidence,
        ", from its count of visible samples (one independent sample in each of N equal-area cells: the count is "
        "Poisson-binomial, and the binomial's Clopper-Pearson limits one count wider hold for it, Hoeffding 1956)",
        error.per_texel_split_pairs
            ? "; or, where smaller, from its split pairs (cells 2i and 2i+1 whose samples disagree bound the count's "
              "variance; Bennett's inequality at that variance), the two holding together at the confidence"
            : "",
        "; error_bound is the largest texel's, texel_error gives each (want_texel_error)",
        lookup_words);
    if (error.has_estimate) {
      out.estimate = error.estimate_max;
      out.parameters["texel_estimate_median"] = error.estimate_spread.Quantile(0.5);
      out.parameters["texel_estimate_p95"] = error.estimate_spread.Quantile(0.95);
      absl::StrAppend(&out.note,
                      "; beside the bounds an estimate, not a bound: the normal approximation's half-width at the "
                      "variance each texel's split pairs estimate (at ",
                      error.confidence,
                      "), estimate the largest texel's, texel_estimate gives each (want_texel_error), "
                      "texel_estimate_median and texel_estimate_p95 their spread (rounded up, within 4 %)");
    }
    return out;
  }
  out.note = absl::StrCat(
      "visible fraction within +-", error.sampling, " of the true (continuous) fraction at confidence ",
      error.confidence,
      error.rigorous ? " (Hoeffding over one independent sample in each of N equal-area cells: a bound)"
                     : " (the Hoeffding half-width of N independent samples; these samples are regular, custom, "
                       "decorrelated or cut by a polygon, so it is an estimate, not a guarantee)",
      error.lookup_max > 0 ? absl::StrCat(", plus at most ", error.lookup_max,
                                          " from the Hough lookup (per texel in lookup_error)")
                           : std::string(", no lookup error (same bits as casting the same segments)"));
  return out;
}

StatusOr<HiddenSampleMapAnswer> RunHiddenSampleMap(Engine& engine, const HiddenSampleMapQuery& query,
                                                   const sampling::HiddenSampleMapBandSink& sink) {
  VISQ_RETURN_IF_ERROR(ValidateHiddenSampleMapQuery(query));
  VISQ_ASSIGN_OR_RETURN(HiddenSampleMapAnswer answer, HiddenSampleMapUnstated(engine, query, sink));
  answer.accuracy = SampledVisibilityStatement(answer.result.error, answer.method, query.request.options.lookup,
                                               answer.result.sample_count);
  if (answer.plan) {
    AddChosenPlan(*answer.plan, answer.accuracy);
    // A plan topped up with more maps (HiddenSampleMapForTarget) says so:
    // `samples` is what ran, `planned_samples` what was chosen.
    const Plan& chosen = answer.plan->chosen_plan();
    if (chosen.parameters.contains("samples") && answer.result.sample_count > chosen.parameters.at("samples")) {
      answer.accuracy.parameters["planned_samples"] = chosen.parameters.at("samples");
      answer.accuracy.parameters["samples"] = answer.result.sample_count;
      absl::StrAppend(&answer.accuracy.note, "; its answer missed the target at the ",
                      chosen.parameters.at("samples"), " samples planned (a prediction from two small maps of this "
                      "request), so more maps with their own jitter were added: ", answer.result.sample_count,
                      " samples in all");
    }
  }
  return answer;
}

AccuracyStatement PatchVisibilityStatement(const sampling::ErrorBound& error, VisibilityMethod method,
                                           const sampling::PatchVisibilityRequest& request, int source_samples) {
  // The statement of the source's sampling (or its exact integral), then
  // what every method answers: the receiver grid's mean, not the continuous
  // patch-to-patch fraction, whose receiver integral is not bounded.
  sampling::ErrorBound source_only = error;
  source_only.has_per_texel = false;  // one number, the grid mean, is stated
  AccuracyStatement out = SampledVisibilityStatement(source_only, method, request.lookup, source_samples);
  const std::string grid = absl::StrCat(request.receiver_columns, " x ", request.receiver_rows);
  const std::string quantity = absl::StrCat(
      "mutual_visible_fraction is the mean, over the receiver grid's ", grid,
      " cell centres, of the fraction of the source visible from each (every method answers this grid mean); ");
  const std::string receiver_words =
      "; the bound is on that grid mean only: the continuous patch-to-patch fraction differs from it by the "
      "receiver grid's quadrature error, which is not bounded (a regular grid can alias with regular occluders; "
      "compare a finer receiver grid)";
  if (method == VisibilityMethod::kPluckerExact) {
    out.note = absl::StrCat(quantity, "each point's fraction is exact (Plücker method: every side decision is an exact "
                            "predicate; only the areas are double-precision sums)",
                            out.error_bound > 0.0
                                ? ", but for occluders with tiny shadows left out under the server's "
                                  "--light-shadow-tolerance, which could hide at most error_bound (one-sided)"
                                : ", so error_bound is 0",
                            receiver_words);
    return out;
  }
  // The source statement's "true (continuous) fraction" is, here, each
  // point's exact fraction averaged over the grid.
  out.note = absl::StrCat(quantity, "each point's fraction is estimated from the source grid's ", source_samples,
                          " cell centres: ",
                          absl::StrReplaceAll(out.note, {{"the true (continuous) fraction",
                                                          "the grid mean of the points' exact fractions"}}),
                          receiver_words);
  return out;
}

StatusOr<PatchVisibilityAnswer> RunPatchVisibility(Engine& engine, const PatchVisibilityQuery& query) {
  VISQ_RETURN_IF_ERROR(ValidatePatchVisibilityQuery(query));
  VISQ_ASSIGN_OR_RETURN(PatchVisibilityAnswer answer, PatchVisibilityUnstated(engine, query));
  answer.accuracy = PatchVisibilityStatement(answer.result.error, answer.method, query.request,
                                             static_cast<int>(answer.result.source_visible.size()));
  if (answer.plan) AddChosenPlan(*answer.plan, answer.accuracy);
  return answer;
}

}  // namespace visq::core
