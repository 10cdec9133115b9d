#include "core/obscurance_query.h"

#include <algorithm>
#include <tuple>
#include <chrono>
#include <cmath>
#include <map>
#include <set>

#include <spdlog/spdlog.h>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "common/job_timing.h"
#include "common/normal_estimate.h"
#include "core/obscurance_work.h"
#include "obscurance/obscurance_export.h"
#include "obscurance/obscurance_rays.h"

namespace visq::core {
namespace {

// The one node `query` names; INVALID_ARGUMENT naming the field otherwise.
// Adds `from` into `into` keyed by index: later values win.
template <typename Index>
void MergeKeyed(std::map<Index, glm::vec3>& into, const std::vector<Index>& keys, const std::vector<glm::vec3>& values) {
  for (size_t i = 0; i < keys.size() && i < values.size(); ++i) into[keys[i]] = values[i];
}

}  // namespace

Status ValidateObscuranceQuery(const ObscuranceQuery& query) {
  if (query.resolution == 0 || query.resolution > obscurance::kMaxAtlasResolution)
    return absl::InvalidArgumentError(absl::StrCat("resolution: ", query.resolution, " must be in [1, ",
                                                   obscurance::kMaxAtlasResolution, "]"));
  VISQ_RETURN_IF_ERROR(obscurance::ValidateParams(query.params));
  const uint64_t end = static_cast<uint64_t>(query.params.first_direction) + query.params.direction_count;
  if (query.total_directions != 0 && end > query.total_directions)
    return absl::InvalidArgumentError(absl::StrCat("total_directions: ", query.total_directions,
                                                   " is less than first_direction + direction_count = ", end));
  if (query.update_rays_per_patch == 0 || query.update_rays_per_patch > 65536)
    return absl::InvalidArgumentError(
        absl::StrCat("update_rays_per_patch: ", query.update_rays_per_patch, " must be in [1, 65536]"));
  if (IsRayEstimate(query.method)) {
    if (query.rays_per_patch == 0 || query.rays_per_patch > 65536)
      return absl::InvalidArgumentError(
          absl::StrCat("rays_per_patch: ", query.rays_per_patch, " must be in [1, 65536]"));
    if (query.params.first_direction != 0 || query.total_directions != 0 || query.partial_only)
      return absl::InvalidArgumentError("method: RAYCAST estimates a whole bake (no direction range, not partial_only)");
  }
  return absl::OkStatus();
}

double ObscuranceErrorEstimate(uint64_t directions, double confidence) {
  if (confidence >= 1.0) return 1.0;  // no worst-case figure below the trivial one
  const double d = static_cast<double>(std::max<uint64_t>(directions, 1));
  return std::min(1.0, std::sqrt(std::log(2.0 / (1.0 - confidence)) / (2.0 * d)));
}

ObscuranceCoverage CoverageOf(const ObscuranceAnswer& answer) {
  ObscuranceCoverage out;
  if (IsRayEstimate(answer.method) && answer.result) {
    // Every estimated patch got exactly rays_per_patch rays.
    for (uint8_t e : answer.result->estimated) out.estimated_texels += e;
    out.mean_samples_per_patch = answer.result->mean_samples_per_patch;
    return out;
  }
  uint64_t samples = 0;
  for (uint64_t c : answer.partial.counts)
    if (c > 0) {
      ++out.estimated_texels;
      samples += c;
    }
  if (out.estimated_texels > 0)
    out.mean_samples_per_patch = static_cast<double>(samples) / static_cast<double>(out.estimated_texels);
  return out;
}

namespace {

// The spread of the per-element half-widths of one kind (texel, triangle,
// vertex): the median and 95th percentile.
void AddElementBounds(const ObscuranceAnswer& answer, AccuracyStatement& out) {
  auto add = [&](const char* kind, const std::vector<float>& bounds, const std::vector<uint8_t>* only) {
    std::vector<float> kept;
    for (size_t i = 0; i < bounds.size(); ++i)
      if (only == nullptr || (i < only->size() && (*only)[i])) kept.push_back(bounds[i]);
    if (kept.empty()) return;
    std::sort(kept.begin(), kept.end());
    out.parameters[absl::StrCat(kind, "_bound_median")] = kept[kept.size() / 2];
    out.parameters[absl::StrCat(kind, "_bound_p95")] = kept[std::min(kept.size() - 1, kept.size() * 95 / 100)];
  };
  add("texel", answer.bounds.texel, &answer.result->estimated);
  add("triangle", answer.bounds.triangle, nullptr);
  add("vertex", answer.bounds.vertex, nullptr);
}

// Beside the bounds, where the rays' variance is known: each texel's
// estimate (ObscuranceTexelEstimates: not a bound), its median and 95th
// percentile over the estimated texels, and as the answer's estimate the
// largest among the texels that error_bound covers (resting on at least
// kCoveredShare of the `nominal` rays).
void AddTexelEstimates(const obscurance::ObscuranceResult& result, double nominal, double confidence,
                       AccuracyStatement& out) {
  const std::vector<float> estimates = obscurance::ObscuranceTexelEstimates(result, confidence);
  if (estimates.size() != result.w.size()) return;
  std::vector<double> kept;
  double covered_largest = 0.0;
  for (size_t i = 0; i < estimates.size(); ++i)
    if (estimates[i] >= 0) {
      kept.push_back(estimates[i]);
      if (result.texel_effective_samples[i] >= obscurance::kCoveredShare * nominal)
        covered_largest = std::max<double>(covered_largest, estimates[i]);
    }
  if (kept.empty()) return;
  std::sort(kept.begin(), kept.end());
  out.parameters["texel_estimate_median"] = kept[kept.size() / 2];
  out.parameters["texel_estimate_p95"] = kept[std::min(kept.size() - 1, kept.size() * 95 / 100)];
  out.estimate = covered_largest;
}

constexpr const char* kRaysBoundRule =
    "the smaller of Hoeffding's and the empirical Bernstein half-width at its rays' own sample variance (Maurer & "
    "Pontil 2009, two-sided), each at half the risk, for each texel and triangle (a vertex: the area-weighted mean "
    "of its triangles' Hoeffding half-widths)";

// error_bound and what it covers: with a result, the widest own half-width
// among the elements resting on at least a quarter of the nominal count
// (ObscuranceAnswerBoundOf), the others counted; a partial bake, which has
// no per-element figures, states the cap itself.
void SetCoveredBound(const ObscuranceAnswer& answer, double nominal, const char* unit, AccuracyStatement& out) {
  const double cap = obscurance::CoveredHalfWidth(nominal, answer.confidence);
  out.error_bound = cap;
  const bool rays = answer.result && !answer.result->texel_sample_variance.empty();
  const std::string rule = absl::StrCat(
      "at ", answer.confidence, ", ",
      rays ? kRaysBoundRule : "Hoeffding's half-width for each element's own effective number of ", rays ? "" : unit,
      rays ? "; the rays' values in [0, 1] per channel" : " with values in [0, 1] per channel",
      "; error_bound holds for every element (texel, triangle, vertex) resting on at least ", obscurance::kCoveredShare,
      " x ", nominal, " ", unit,
      " (its own bound at most ", absl::StrFormat("%.4f", cap), ")");
  if (!answer.result) {
    out.note = absl::StrCat("estimate: ", rule, "; a partial bake: elements not counted");
    return;
  }
  const obscurance::ObscuranceAnswerBound bound =
      obscurance::ObscuranceAnswerBoundOf(*answer.result, answer.bounds, nominal, answer.confidence);
  out.error_bound = bound.error_bound;
  out.parameters["texels_outside_bound"] = static_cast<double>(bound.texels.outside);
  out.parameters["triangles_outside_bound"] = static_cast<double>(bound.triangles.outside);
  out.parameters["vertices_outside_bound"] = static_cast<double>(bound.vertices.outside);
  uint64_t unsampled = 0;
  for (float e : answer.result->triangle_effective_samples) unsampled += e == 0.0f;
  out.parameters["triangles_without_samples"] = static_cast<double>(unsampled);
  AddElementBounds(answer, out);
  AddTexelEstimates(*answer.result, nominal, answer.confidence, out);
  out.note = absl::StrCat(
      "estimate: ", rule, "; outside it, with wider bounds of their own (want_errors): ", bound.texels.outside, " of ",
      bound.texels.elements, " estimated texels, ", bound.triangles.outside, " of ", bound.triangles.elements,
      " sampled triangles, ", bound.vertices.outside, " of ", bound.vertices.elements, " vertices; ", unsampled,
      " triangles got no sample (their W is their texels', with no bound); the spread of the own bounds in "
      "*_bound_median and *_bound_p95",
      rays ? absl::StrCat("; beside them an estimate, not a bound: the normal approximation's half-width at each "
                          "texel's sample variance (at ", answer.confidence, "), texel_estimate_median and "
                          "texel_estimate_p95")
           : "");
}

}  // namespace

AccuracyStatement ObscuranceStatement(const ObscuranceAnswer& answer) {
  AccuracyStatement out;
  out.confidence = answer.confidence;
  if (IsRayEstimate(answer.method)) {
    // N rays per patch, each a value in [0, 1] per channel.
    out.method = answer.method == ObscuranceMethod::kGpuRaycast ? "obscurance-gpu-raycast" : "obscurance-raycast";
    out.parameters["rays_per_patch"] = static_cast<double>(answer.rays_per_patch);
    SetCoveredBound(answer, answer.rays_per_patch, "rays", out);
    out.note += "; the rays are independent, each cosine-distributed within its own of N equal cells of the "
                "directions (stratified) from a point uniform on the patch, so Hoeffding's and Bernstein's "
                "inequalities hold for them";
  } else {
    // Per direction, a patch's value is a mean of values in [0, 1] (per
    // channel); the directions are weighed per patch by its samples.
    const uint64_t directions = answer.partial.DirectionCount();
    out.method = "obscurance-depth-peeling";
    out.parameters["directions"] = static_cast<double>(directions);
    SetCoveredBound(answer, static_cast<double>(directions), "directions", out);
    out.note += absl::StrCat(
        "; the directions are a rotated Halton sequence (usually better than independent), each weighed per element "
        "by its samples (mean ",
        absl::StrFormat("%.1f", CoverageOf(answer).mean_samples_per_patch),
        " samples per patch); rasterization of the bundles is not counted");
  }
  if (answer.plan) AddChosenPlan(*answer.plan, out);
  return out;
}

AccuracyStatement ObscuranceUpdateStatement(const ObscuranceUpdateAnswer& answer) {
  AccuracyStatement out;
  out.method = "obscurance-raycast-update";
  out.confidence = kUpdateConfidence;
  out.error_bound = ObscuranceErrorEstimate(std::max<uint32_t>(answer.rays_per_patch, 1), out.confidence);
  uint64_t texels_without = 0, triangles_without = 0;
  for (float e : answer.bounds.texel) texels_without += e >= 1.0f;
  for (float e : answer.bounds.triangle) triangles_without += e >= 1.0f;
  out.parameters["texels_without_samples"] = static_cast<double>(texels_without);
  out.parameters["triangles_without_samples"] = static_cast<double>(triangles_without);
  out.note = absl::StrCat(
      "recomputed patches: Hoeffding half-width at 95 % for ", answer.rays_per_patch,
      " independent rays per patch (values in [0, 1]; each cosine-distributed within its own of N equal cells of the "
      "directions, from a point uniform on the patch); triangles touching a changed texel by rays of their own (as "
      "many per texel of their area, 1 to 16 patches' worth); each listed element's own half-width in w_error, "
      "triangle_w_error and vertex_w_error: for a recomputed texel or triangle ", kRaysBoundRule,
      "; the bake's for those the update did not trace; 1 where W rests on no sample of its own: ",
      texels_without, " changed texels refilled from their neighbours, ", triangles_without,
      " triangles no ray reached; the other patches keep the bake's values (", answer.directions,
      " directions) bit for bit");
  return out;
}

namespace {

// A bake's GPU work runs at batch priority: interactive queries overtake it
// between directions.
gpu::ObscuranceBakeOptions BakeOptions(const ObscuranceQuery& query) {
  gpu::ObscuranceBakeOptions bake;
  bake.job = query.call.BatchJob();
  bake.progress = query.progress;
  return bake;
}

// Plans for an obscurance target: direction counts (powers of two and the
// least count meeting the error), each predicted from the measured cost per
// direction of bakes of this scene at this resolution; a scene never baked at
// it is probed with two short partial bakes (4 and 16 directions).
// The cost series of a bake's depth peeling (per direction) and of its
// ray-cast estimator (per ray a patch).
std::string DepthPeelingSeries(const ResidentScene& resident, const ObscuranceQuery& query) {
  return absl::StrCat(resident.name, "@", resident.content_hash.substr(0, 8), "/obscurance/", query.resolution, "/",
                      query.params.bundle_resolution, query.params.color_bleeding ? "/rgb" : "/w");
}
std::string RaycastSeries(const ResidentScene& resident, const ObscuranceQuery& query,
                          ObscuranceMethod method = ObscuranceMethod::kRaycast) {
  return absl::StrCat(DepthPeelingSeries(resident, query),
                      method == ObscuranceMethod::kGpuRaycast ? "/gpu-raycast" : "/raycast");
}

// The ray estimator's closest hits on the GPU (gpu/rays), for
// RayEstimateOptions::closest_hits; Embree's own when `method` is RAYCAST.
StatusOr<obscurance::ClosestHits> ClosestHitsOf(Engine& engine, const ResidentScene& resident,
                                                ObscuranceMethod method, const CallOptions& call) {
  if (method != ObscuranceMethod::kGpuRaycast) return obscurance::ClosestHits();
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<gpu::RayScene> gpu_rays, engine.RaySceneOf(resident, call));
  return obscurance::ClosestHits([gpu_rays, job = call.BatchJob()](std::span<const raycast::Ray> rays) {
    gpu::RayTraceOptions trace;
    trace.job = job;
    return gpu_rays->Intersect(rays, trace);
  });
}

// Whether a query's bake is whole, so that it becomes the scene's solution
// for UpdateObscurances.
bool IsWholeBake(const ObscuranceQuery& query, uint32_t total_directions) {
  if (query.partial_only) return false;
  return IsRayEstimate(query.method) ||
         (query.params.first_direction == 0 && query.params.direction_count == total_directions);
}

// What a bake or a ray-cast estimate holds beside its atlas
// (core/obscurance_work.h). The depth peeling: per texel and channel (plus
// the count) the GPU's sums read back and the partial's (uint64), then W
// and the intensity, and the estimated flags; per triangle its averages.
// The ray-cast estimator: its result and what it holds while it traces. A
// whole bake then builds the updater and keeps its answer until it is sent.
uint64_t ObscuranceWorkBytes(const Scene& scene, const ObscuranceQuery& query) {
  const ObscuranceWorkShape shape = ObscuranceShapeOf(scene, query.resolution, query.params);
  const uint64_t channels = shape.channels;
  uint64_t bytes = shape.texels * ((channels + 1) * (8 + 8) + 2 * 12 + 1 + 8 + 4 + 4) +
                   shape.triangles * ((channels + 1) * (8 + 8) + 12 + 8 + 4 + 4);
  if (IsRayEstimate(query.method))
    bytes = ObscuranceResultBytes(shape) + RayEstimateWorkBytes(shape, query.rays_per_patch);
  const uint32_t total = query.total_directions != 0 ? query.total_directions
                                                     : query.params.first_direction + query.params.direction_count;
  if (IsWholeBake(query, total))
    bytes += ObscuranceUpdaterBytes(shape, query.update_rays_per_patch) + ObscuranceAnswerExtraBytes(shape);
  return bytes;
}

// A probe of the ray-cast estimator with `rays` rays a patch: its estimate
// alone (no updater, no answer).
uint64_t RayProbeWorkBytes(const Scene& scene, const ObscuranceQuery& query, uint32_t rays) {
  ObscuranceQuery probe;
  probe.resolution = query.resolution;
  probe.params = query.params;
  probe.method = ObscuranceMethod::kRaycast;
  probe.rays_per_patch = rays;
  probe.partial_only = true;
  return ObscuranceWorkBytes(scene, probe);
}

// The query's atlas, built under one reservation of the work budget: the
// atlas's own bound (obscurance::AtlasWorkBytes, found from its corner
// coordinates before any fragment exists) and `then_bytes`, what the
// caller computes over it. The call's deadline and cancellation stop the
// build between rows of texels. `memory` holds the reservation.
StatusOr<obscurance::ObscuranceAtlas> BuildAtlasWithinBudget(Engine& engine, const Scene& scene,
                                                             const ObscuranceQuery& query, const CallOptions& call,
                                                             const gpu::JobOptions& job, uint64_t then_bytes,
                                                             WorkMemoryBudget::Reservation& memory) {
  obscurance::AtlasOptions options;
  options.force_build = query.force_built_atlas;
  options.reserve = [&](uint64_t atlas_bytes) -> Status {
    VISQ_ASSIGN_OR_RETURN(memory, engine.work_budget().Reserve(atlas_bytes + then_bytes,
                                                               IsRayEstimate(query.method)
                                                                   ? "resolution, rays_per_patch"
                                                                   : "resolution",
                                                               job));
    return absl::OkStatus();
  };
  options.stop = call.stop;
  return obscurance::BuildObscuranceAtlas(scene, query.resolution, options);
}

// A whole bake's ray-cast estimate with `rays` rays per patch, its atlas
// included (as the chosen run's cost is recorded): its ms.
StatusOr<double> RaycastEstimateMs(Engine& engine, const ResidentScene& resident, const ObscuranceQuery& query,
                                   ObscuranceMethod method, uint32_t rays, const CallOptions& call) {
  VISQ_ASSIGN_OR_RETURN(obscurance::ClosestHits closest_hits, ClosestHitsOf(engine, resident, method, call));
  const auto start = std::chrono::steady_clock::now();
  WorkMemoryBudget::Reservation memory;
  VISQ_ASSIGN_OR_RETURN(obscurance::ObscuranceAtlas atlas,
                        BuildAtlasWithinBudget(engine, *resident.scene, query, call, call.Job(),
                                               RayProbeWorkBytes(*resident.scene, query, rays), memory));
  obscurance::RayEstimateOptions options;
  options.rays_per_patch = rays;
  options.seed = query.params.seed;
  options.stop = call.stop;
  options.closest_hits = std::move(closest_hits);
  VISQ_RETURN_IF_ERROR(
      obscurance::EstimateObscurancesByRays(*resident.scene, atlas, query.params, options).status());
  return MillisecondsSince(start);
}

// A request naming no method, for a whole bake of D directions: depth
// peeling with D directions, or the ray-cast estimator with D rays per
// patch on Embree or on the GPU, whose covered bound is the same figure;
// the fastest here runs. The
// ray-cast estimator is probed first (a few rays a patch); the bake's
// probes (a direction, then four) get a share of its predicted time, since
// on a CPU rasterizer one direction can cost more than a whole ray-cast
// estimate.
StatusOr<PlanReport> ChooseObscuranceMethod(Engine& engine, std::shared_ptr<const ResidentScene> held,
                                            const ObscuranceQuery& query) {
  const ResidentScene& resident = *held;
  // The probes' own copy of the request, which they may run after the call
  // (in the server's idle time): without the call's stop and progress.
  auto owned = std::make_shared<ObscuranceQuery>(query);
  owned->call = {};
  owned->progress = nullptr;
  owned->scene_version = held->version;  // a probe of a version since replaced measures nothing
  const uint32_t directions = query.params.direction_count;
  const double bound = obscurance::CoveredHalfWidth(directions, 0.95);
  std::vector<EqualAnswerOption> options(engine.WeighsGpuRays() ? 3 : 2);
  for (const auto& option : {std::tuple{0, ObscuranceMethod::kRaycast, "obscurance-raycast"},
                              std::tuple{2, ObscuranceMethod::kGpuRaycast, "obscurance-gpu-raycast"}}) {
    // Named, not bound: Debian 12's clang cannot capture a structured binding.
    const size_t slot = static_cast<size_t>(std::get<0>(option));
    const ObscuranceMethod method = std::get<1>(option);
    const char* name = std::get<2>(option);
    if (slot >= options.size()) continue;
    Plan& plan = options[slot].plan;
    plan.method = name;
    plan.runs = method;
    plan.parameters["rays_per_patch"] = directions;
    plan.cost_key = RaycastSeries(resident, query, method);
    plan.work = directions;
    plan.error_bound = bound;
    for (uint32_t rays : {4u, 16u})
      options[slot].probes.push_back(
          {double(rays), 0.0, [&engine, scene = std::weak_ptr(held), owned, method, rays](const CallOptions& call)
                                  -> StatusOr<double> {
             VISQ_ASSIGN_OR_RETURN(const std::shared_ptr<const ResidentScene> held, StillHeld(scene));
             return RaycastEstimateMs(engine, *held, *owned, method, rays, call);
           }});
    options[slot].probes_outlive_the_call = true;
  }
  {
    Plan& plan = options[1].plan;
    plan.method = "obscurance-depth-peeling";
    plan.runs = ObscuranceMethod::kDepthPeeling;
    plan.parameters["directions"] = directions;
    plan.cost_key = DepthPeelingSeries(resident, query);
    plan.work = directions;
    plan.error_bound = bound;
    for (uint32_t count : {1u, 4u})
      options[1].probes.push_back({double(count), 0.0, [&engine, owned, count](const CallOptions& call) -> StatusOr<double> {
                                     ObscuranceQuery probe = *owned;
                                     probe.method = ObscuranceMethod::kDepthPeeling;
                                     probe.params.first_direction = 0;
                                     probe.params.direction_count = count;
                                     probe.total_directions = count;
                                     probe.partial_only = true;  // neither finalized nor installed for updates
                                     probe.progress = nullptr;
                                     probe.call = call;
                                     VISQ_ASSIGN_OR_RETURN(const ObscuranceAnswer answer,
                                                           RunComputeObscurances(engine, probe));
                                     return answer.atlas_ms + answer.bake_ms;
                                   }});
    options[1].probes_outlive_the_call = true;
  }
  return ChooseFastest(engine.cost_model(), std::move(options), query.call, engine.idle_explorer());
}

StatusOr<PlanReport> PlanObscurances(Engine& engine, const ResidentScene& resident, const ObscuranceQuery& query) {
  const AccuracyTarget& target = *query.target;
  const std::string series = DepthPeelingSeries(resident, query);
  PlanReport report;
  CostModel& model = engine.cost_model();
  // On the estimate, only the rays state one (a depth-peeling bake keeps
  // no per-direction values), and a plan's is at most
  // obscurance::LargestObscuranceEstimate at the covered share of its rays,
  // whatever the scene.
  const bool on_estimate = target.wants_estimate();
  if (!on_estimate && !model.Predict(series, 1.0)) {
    for (uint32_t directions : {4u, 16u}) {
      ObscuranceQuery probe = query;
      probe.target.reset();
      probe.params.first_direction = 0;
      probe.params.direction_count = directions;
      probe.total_directions = directions;
      probe.partial_only = true;  // neither finalized nor installed for updates
      probe.progress = nullptr;
      VISQ_ASSIGN_OR_RETURN(ObscuranceAnswer answer, RunComputeObscurances(engine, probe));
      model.Record(series, directions, answer.atlas_ms + answer.bake_ms);
      report.probe_ms += answer.atlas_ms + answer.bake_ms;
    }
  }
  // The ray-cast estimator: probed with 4 and 16 rays per patch, on Embree
  // and (on a GPU, where its BVH fits) on the GPU.
  std::vector<ObscuranceMethod> ray_methods = {ObscuranceMethod::kRaycast};
  if (engine.WeighsGpuRays() && engine.AdmitRayScene(resident).ok())
    ray_methods.push_back(ObscuranceMethod::kGpuRaycast);
  for (const ObscuranceMethod method : ray_methods) {
    const std::string ray_series = RaycastSeries(resident, query, method);
    if (model.Predict(ray_series, 1.0)) continue;
    VISQ_ASSIGN_OR_RETURN(obscurance::ClosestHits closest_hits, ClosestHitsOf(engine, resident, method, query.call));
    const auto atlas_start = std::chrono::steady_clock::now();
    WorkMemoryBudget::Reservation memory;
    VISQ_ASSIGN_OR_RETURN(obscurance::ObscuranceAtlas atlas,
                          BuildAtlasWithinBudget(engine, *resident.scene, query, query.call, query.call.Job(),
                                                 RayProbeWorkBytes(*resident.scene, query, 16), memory));
    const double atlas_ms = MillisecondsSince(atlas_start);
    for (uint32_t rays : {4u, 16u}) {
      const auto start = std::chrono::steady_clock::now();
      obscurance::RayEstimateOptions options;
      options.rays_per_patch = rays;
      options.seed = query.params.seed;
      options.stop = query.call.stop;
      options.closest_hits = closest_hits;
      VISQ_RETURN_IF_ERROR(
          obscurance::EstimateObscurancesByRays(*resident.scene, atlas, query.params, options).status());
      const double ms = atlas_ms + MillisecondsSince(start);
      model.Record(ray_series, rays, ms);
      report.probe_ms += ms;
    }
  }

  // Counts: powers of two and the least count meeting the error, as
  // directions of the bake or rays per patch.
  // A plan's bound is what its answer's error_bound can be at most: the
  // covered elements' cap (CoveredHalfWidth), so the count meeting the error
  // is Hoeffding's divided by the covered share.
  auto error_of = [&](uint32_t n) {
    return on_estimate ? obscurance::LargestObscuranceEstimate(std::ceil(obscurance::kCoveredShare * n),
                                                               target.confidence)
                       : obscurance::CoveredHalfWidth(n, target.confidence);
  };
  double needed = HoeffdingSamplesNeeded(target.max_error, target.confidence) / obscurance::kCoveredShare;
  if (on_estimate && target.max_error > 0) {
    const double z = TwoSidedNormalQuantile(target.confidence);
    needed = 0.25 * z * z / (target.max_error * target.max_error) / obscurance::kCoveredShare;
    while (needed < 1e9 && error_of(static_cast<uint32_t>(std::ceil(needed))) > target.max_error) needed *= 1.01;
  }
  auto add_plans = [&](ObscuranceMethod runs, const char* method, const char* parameter,
                       const std::string& plan_series, uint32_t most) {
    std::set<uint32_t> counts;
    for (uint32_t n = 8; n <= most; n *= 2) counts.insert(n);
    if (needed <= most) counts.insert(std::max(1u, static_cast<uint32_t>(std::ceil(needed))));
    for (uint32_t n : counts) {
      Plan plan;
      plan.method = method;
      plan.runs = runs;
      plan.parameters[parameter] = n;
      plan.error_bound = error_of(n);
      plan.work = n;
      plan.cost_key = plan_series;
      plan.predicted_ms = model.Predict(plan_series, plan.work).value_or(0.0);
      report.plans.push_back(std::move(plan));
    }
  };
  if (!on_estimate)
    add_plans(ObscuranceMethod::kDepthPeeling, "obscurance-depth-peeling", "directions", series,
              obscurance::kMaxDirections);
  for (const ObscuranceMethod method : ray_methods)
    add_plans(method, method == ObscuranceMethod::kGpuRaycast ? "obscurance-gpu-raycast" : "obscurance-raycast",
              "rays_per_patch", RaycastSeries(resident, query, method), 65536);
  VISQ_ASSIGN_OR_RETURN(report.chosen, ChoosePlan(report.plans, target));
  report.target = target;
  LogChosenPlan(report, query.call);
  return report;
}

}  // namespace

StatusOr<ObscuranceAnswer> RunComputeObscurances(Engine& engine, ObscuranceQuery query) {
  std::optional<PlanReport> plan;
  if (query.target) {
    VISQ_RETURN_IF_ERROR(ValidateAccuracyTarget(*query.target));
    if (query.params.first_direction != 0 || query.total_directions != 0 || query.partial_only)
      return absl::InvalidArgumentError("target: only for a whole bake (no direction range, not partial_only)");
    query.params.direction_count = 1;  // validated now, chosen below
  }
  VISQ_RETURN_IF_ERROR(ValidateObscuranceQuery(query));
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<const ResidentScene> resident,
                        engine.SceneForQuery(query.scene, query.scene_version));
  if (!query.target && !query.method) {
    const bool whole_bake = query.params.first_direction == 0 && !query.partial_only &&
                            (query.total_directions == 0 || query.total_directions == query.params.direction_count);
    if (whole_bake) {
      VISQ_ASSIGN_OR_RETURN(plan, ChooseObscuranceMethod(engine, resident, query));
    } else {
      query.method = ObscuranceMethod::kDepthPeeling;  // partial sums are the bake's alone
    }
  }
  if (query.target) {
    VISQ_ASSIGN_OR_RETURN(plan, PlanObscurances(engine, *resident, query));
  }
  if (plan) {
    const Plan& chosen = plan->chosen_plan();
    query.method = std::get<ObscuranceMethod>(chosen.runs);
    if (IsRayEstimate(query.method))
      query.rays_per_patch = static_cast<uint32_t>(chosen.parameters.at("rays_per_patch"));
    else
      query.params.direction_count = static_cast<uint32_t>(chosen.parameters.at("directions"));
  }
  // The bake's atlas, model and updater read every triangle flattened.
  const Scene& scene = resident->scene->Flattened();
  ObscuranceAnswer answer;
  if (query.target) answer.confidence = query.target->confidence;
  answer.scene_version = resident->version;
  answer.total_directions = query.total_directions != 0 ? query.total_directions
                                                        : query.params.first_direction + query.params.direction_count;

  // The patches: TEXCOORD_1 or a built atlas, reserved together with the
  // bake's own arrays before the atlas's fragments exist.
  auto start = std::chrono::steady_clock::now();
  WorkMemoryBudget::Reservation memory;
  VISQ_ASSIGN_OR_RETURN(obscurance::ObscuranceAtlas atlas,
                        BuildAtlasWithinBudget(engine, scene, query, query.call, query.call.BatchJob(),
                                               ObscuranceWorkBytes(scene, query), memory));
  answer.width = atlas.width;
  answer.height = atlas.height;
  answer.from_lightmap_uvs = atlas.from_lightmap_uvs;
  answer.chart_count = atlas.chart_count;
  answer.texels_per_unit = atlas.texels_per_unit;
  answer.atlas_ms = MillisecondsSince(start);

  answer.method = *query.method;
  answer.ambient = obscurance::ComputeAmbient(scene, query.params.color_bleeding);
  obscurance::ObscuranceResult result;
  if (IsRayEstimate(query.method)) {
    // The estimator of eq. 6 per patch with Embree (or its rays on the
    // GPU): the same quantity as the bake, with independent per-patch rays
    // instead of shared bundles.
    VISQ_ASSIGN_OR_RETURN(obscurance::ClosestHits closest_hits,
                          ClosestHitsOf(engine, *resident, *query.method, query.call));
    start = std::chrono::steady_clock::now();
    obscurance::RayEstimateOptions options;
    options.rays_per_patch = query.rays_per_patch;
    options.seed = query.params.seed;
    options.stop = query.call.stop;
    options.closest_hits = std::move(closest_hits);
    StatusOr<obscurance::ObscuranceResult> estimate =
        obscurance::EstimateObscurancesByRays(scene, atlas, query.params, options);
    VISQ_RETURN_IF_ERROR(estimate.status());
    result = *std::move(estimate);
    answer.bake_ms = MillisecondsSince(start);
    answer.rays_per_patch = query.rays_per_patch;
    answer.total_directions = 0;
    answer.partial.fingerprint = obscurance::BakeFingerprint(scene, atlas, query.params);
    answer.partial.width = atlas.width;
    answer.partial.height = atlas.height;
    answer.partial.channels = query.params.color_bleeding ? 3 : 1;
  } else {
    // The bake: one GPU job per direction at the caller's (batch) priority.
    VISQ_ASSIGN_OR_RETURN(std::shared_ptr<gpu::GpuScene> gpu_scene, engine.GpuSceneOf(*resident, query.call));
    start = std::chrono::steady_clock::now();
    VISQ_ASSIGN_OR_RETURN(answer.partial, gpu::BakeObscurancePartial(engine.gpu(), *gpu_scene, scene, atlas,
                                                                     query.params, BakeOptions(query), &answer.stats));
    answer.bake_ms = MillisecondsSince(start);
    if (query.partial_only) return answer;

    start = std::chrono::steady_clock::now();
    VISQ_ASSIGN_OR_RETURN(result, obscurance::FinalizeObscurances(scene, atlas, query.params, answer.partial));
    answer.finalize_ms = MillisecondsSince(start);
  }

  // A whole bake becomes the scene's solution for UpdateObscurances.
  if (IsWholeBake(query, answer.total_directions)) {
    start = std::chrono::steady_clock::now();
    obscurance::UpdaterOptions options;
    options.rays_per_patch = query.update_rays_per_patch;
    options.seed = query.params.seed;
    VISQ_ASSIGN_OR_RETURN(std::unique_ptr<obscurance::ObscuranceUpdater> updater,
                          obscurance::ObscuranceUpdater::Create(scene, std::move(atlas), query.params, result, {},
                                                                options));
    std::shared_ptr<ObscuranceState> state = engine.SceneStateOf<ObscuranceState>(resident->name);
    std::lock_guard lock(state->mutex);
    // A newer bake installed meanwhile stays.
    if (!state->updater || state->solution_version <= resident->version) {
      state->updater = std::move(updater);
      // The updater's share of the reservation lives as long as it does.
      state->updater_memory = memory.KeepLasting(ObscuranceUpdaterBytes(
          ObscuranceShapeOf(scene, query.resolution, query.params), query.update_rays_per_patch));
      state->undelivered.reset();  // the bake's answer holds every texel
      state->solution_version = resident->version;
      state->rays_per_patch = query.update_rays_per_patch;
      answer.update_ready = true;
    }
    answer.updater_ms = MillisecondsSince(start);
  }
  answer.bounds = obscurance::ObscuranceBoundsOf(scene, result, answer.confidence);
  answer.result = std::move(result);
  if (plan) {
    const Plan& chosen = plan->chosen_plan();
    engine.cost_model().Record(chosen.cost_key, chosen.work, answer.atlas_ms + answer.bake_ms);
    answer.plan = std::move(plan);
  }
  answer.memory = std::move(memory);
  return answer;
}

StatusOr<ObscuranceUpdateAnswer> RunUpdateObscurances(Engine& engine, const ObscuranceUpdateQuery& query) {
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<const ResidentScene> resident,
                        engine.SceneForQuery(query.scene, query.scene_version));
  std::shared_ptr<ObscuranceState> state = engine.SceneStateOf<ObscuranceState>(resident->name);
  std::lock_guard lock(state->mutex);
  if (!state->updater)
    return absl::FailedPreconditionError(absl::StrCat("scene '", resident->name,
                                                      "' has no full ComputeObscurances bake to update"));
  // The scene's edits since the solution must lead, each from the version
  // the last one made (versions are not consecutive: they come from the
  // repository's counter), to the resident version; a reload or replace
  // clears the log and so breaks the chain.
  std::vector<SceneEdit> todo;
  uint64_t version = state->solution_version;
  for (const SceneEdit& m : engine.EditsBetween(resident->name, state->solution_version, resident->version)) {
    if (m.from_version != version) break;
    todo.push_back(m);
    version = m.version;
  }
  if (version != resident->version)
    return absl::FailedPreconditionError(absl::StrCat(
        "scene '", resident->name, "' is at version ", resident->version, "; the bake matches version ",
        state->solution_version, " and the recorded node moves reach only version ", version,
        " (the scene was reloaded or replaced): bake again"));

  if (query.want_full_w && state->updater->result().w.size() * 3 > kMaxFullUpdateFloats)
    return absl::ResourceExhaustedError(absl::StrCat("want_full_w: ", state->updater->result().w.size() * 3,
                                                     " floats exceed the cap of ", kMaxFullUpdateFloats,
                                                     "; use the changed texels"));

  ObscuranceUpdateAnswer answer;
  // What the moves' merged changes, the answer and the candidate search
  // may hold, reserved before the first move: at most every texel,
  // triangle and vertex changed.
  {
    const obscurance::ObscuranceResult& solution = state->updater->result();
    obscurance::ObscuranceParams params;  // the index's cells are the updater's own, already reserved
    const ObscuranceWorkShape shape = ObscuranceShapeOf(state->updater->scene(), solution.width, params);
    VISQ_ASSIGN_OR_RETURN(answer.memory,
                          engine.work_budget().Reserve(ObscuranceUpdateCallBytes(shape, state->rays_per_patch),
                                                       "scene (its bake's atlas)", query.call.Job()));
  }
  answer.rays_per_patch = state->rays_per_patch;
  const auto start = std::chrono::steady_clock::now();
  // What an earlier update applied but could not deliver comes first.
  ObscuranceState::Undelivered changes;
  if (state->undelivered) changes = *std::move(state->undelivered);
  else changes.from_version = state->solution_version;
  state->undelivered.reset();
  answer.from_version = changes.from_version;
  answer.moves_applied = changes.moves;
  answer.update = changes.counts;
  std::map<uint32_t, glm::vec3>& w = changes.w;
  std::map<uint32_t, glm::vec3>& intensity = changes.intensity;
  std::map<uint32_t, glm::vec3>& triangle_w = changes.triangle_w;
  std::map<uint32_t, glm::vec3>& vertex_w = changes.vertex_w;
  for (const SceneEdit& m : todo) {
    if (Status wanted = query.call.stop.Check("obscurance update: between moves"); !wanted.ok()) {
      changes.moves = answer.moves_applied;
      changes.counts = answer.update;
      state->undelivered = std::move(changes);
      return wanted;
    }
    StatusOr<obscurance::ObscuranceUpdate> update = state->updater->MoveNode(m.node, m.world);
    if (!update.ok()) {
      // The updater may be half-moved: it can no longer be trusted.
      state->updater.reset();
      state->undelivered.reset();
      return absl::InternalError(absl::StrCat("update for the move of node ", m.node, " (version ", m.version,
                                              ") failed: ", update.status().message(), "; bake again"));
    }
    MergeKeyed(w, update->texels, update->w);
    MergeKeyed(intensity, update->texels, update->intensity);
    MergeKeyed(triangle_w, update->triangles, update->triangle_w);
    MergeKeyed(vertex_w, update->vertices, update->vertex_w);
    obscurance::ObscuranceUpdate& sum = answer.update;
    sum.influenced_before += update->influenced_before;
    sum.influenced_after += update->influenced_after;
    sum.own_patches += update->own_patches;
    sum.candidates += update->candidates;
    sum.recomputed += update->recomputed;
    sum.rays += update->rays;
    state->solution_version = m.version;
    ++answer.moves_applied;
  }
  for (const auto& [texel, value] : w) {
    answer.update.texels.push_back(texel);
    answer.update.w.push_back(value);
    answer.update.intensity.push_back(intensity[texel]);
  }
  for (const auto& [triangle, value] : triangle_w) {
    answer.update.triangles.push_back(triangle);
    answer.update.triangle_w.push_back(value);
  }
  for (const auto& [vertex, value] : vertex_w) {
    answer.update.vertices.push_back(vertex);
    answer.update.vertex_w.push_back(value);
  }
  answer.compute_ms = MillisecondsSince(start);
  answer.update.milliseconds = answer.compute_ms;
  answer.scene_version = state->solution_version;
  const obscurance::ObscuranceResult& result = state->updater->result();
  answer.width = result.width;
  answer.height = result.height;
  answer.mean_samples_per_patch = result.mean_samples_per_patch;
  answer.directions = result.directions;
  answer.bounds = obscurance::ObscuranceBoundsOfListed(state->updater->scene(), result, kUpdateConfidence,
                                                       answer.update.texels, answer.update.triangles,
                                                       answer.update.vertices);
  if (query.want_full_w) answer.full_w = result.w;
  return answer;
}

// FAILED_PRECONDITION unless the scene has a whole-bake solution that
// matches its version. Under the state's lock.
Status RequireCurrentSolution(const ResidentScene& resident, const ObscuranceState& state, const char* purpose) {
  if (!state.updater)
    return absl::FailedPreconditionError(absl::StrCat("scene '", resident.name,
                                                      "' has no whole-bake obscurance solution to ", purpose,
                                                      ": run ComputeObscurances first (a whole bake, not partial_only)"));
  if (state.solution_version != resident.version)
    return absl::FailedPreconditionError(absl::StrCat(
        "scene '", resident.name, "' is at version ", resident.version, " but its obscurance solution matches version ",
        state.solution_version, ": run UpdateObscurances to apply the node moves since (or bake again)"));
  return absl::OkStatus();
}

StatusOr<ObscurancePreviewAnswer> RunRenderObscurancePreview(Engine& engine, const ObscurancePreviewQuery& query) {
  VISQ_RETURN_IF_ERROR(gpu::ValidatePinholeCamera(query.camera, gpu::kMaxObscurancePreviewSize));
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<const ResidentScene> resident,
                        engine.SceneForQuery(query.scene, query.scene_version));
  ObscurancePreviewAnswer answer;
  answer.quantity = query.quantity;

  // What the picture holds, reserved before anything is copied: the copies
  // of the atlas's corners and values and their GL buffer and texture (on
  // a CPU rasterizer, in this process), and per pixel the RGBA32F target
  // and its float depth, the RGBA read-back and the answer's RGB and
  // coverage, kept until sent. At 4096^2 about 0.8 GB.
  {
    uint64_t corners = 0, texels = 0;
    {
      std::shared_ptr<ObscuranceState> state = engine.SceneStateOf<ObscuranceState>(resident->name);
      std::lock_guard lock(state->mutex);
      if (state->updater) {
        corners = state->updater->atlas().corner_uv.size();
        texels = uint64_t{state->updater->result().width} * state->updater->result().height;
      }
    }
    const uint64_t pixels = uint64_t{query.camera.width} * query.camera.height;
    const uint64_t bytes = corners * 2 * sizeof(glm::vec2) + texels * (sizeof(glm::vec3) + 16) +
                           pixels * (16 + 4 + 16 + 12 + 1) + (uint64_t{1} << 20);
    VISQ_ASSIGN_OR_RETURN(answer.memory, engine.work_budget().Reserve(bytes, "width x height", query.call.Job()));
  }

  // The solution, copied under the state's lock so that moves and updates
  // may go on while the GPU draws.
  const auto start = std::chrono::steady_clock::now();
  std::vector<glm::vec2> corner_uv;
  std::vector<glm::vec3> values;
  uint32_t width = 0, height = 0;
  {
    std::shared_ptr<ObscuranceState> state = engine.SceneStateOf<ObscuranceState>(resident->name);
    std::lock_guard lock(state->mutex);
    // Re-read under the lock: a move may have landed in between.
    VISQ_ASSIGN_OR_RETURN(resident, engine.SceneForQuery(query.scene, query.scene_version));
    VISQ_RETURN_IF_ERROR(RequireCurrentSolution(*resident, *state, "preview"));
    const obscurance::ObscuranceResult& result = state->updater->result();
    const obscurance::ObscuranceAtlas& atlas = state->updater->atlas();
    corner_uv = atlas.corner_uv;
    values = query.quantity == ObscurancePreviewQuery::Quantity::kW ? result.w : result.intensity;
    width = result.width;
    height = result.height;
    answer.solution_version = state->solution_version;
  }
  answer.copy_ms = MillisecondsSince(start);
  answer.scene_version = resident->version;

  // The picture: one interactive GPU job.
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<gpu::GpuScene> gpu_scene, engine.GpuSceneOf(*resident, query.call));
  gpu::ObscurancePreviewRequest request;
  request.camera = query.camera;
  request.scene_bounds = resident->scene->bounds;
  request.atlas_width = width;
  request.atlas_height = height;
  request.corner_uv = corner_uv;
  request.texel_values = values;
  request.job = query.call.Job();
  VISQ_ASSIGN_OR_RETURN(answer.image, gpu::RenderObscurancePreview(engine.gpu(), *gpu_scene, request));
  return answer;
}

StatusOr<ObscuranceExportAnswer> RunExportObscurances(Engine& engine, const ObscuranceExportQuery& query) {
  if (!query.want_atlas_uvs && !query.want_gltf)
    return absl::InvalidArgumentError("want_atlas_uvs, want_gltf: ask for at least one of the two");
  if (query.want_vertex_colors && !query.want_gltf)
    return absl::InvalidArgumentError("want_vertex_colors: colours the glb, so needs want_gltf");
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<const ResidentScene> resident,
                        engine.SceneForQuery(query.scene, query.scene_version));
  // What the answer holds until it is sent: per corner a UV (8 bytes) and,
  // in the glTF, twice (the model's buffer, then the serialized file) at
  // most a vertex per corner (a position, a normal and a colour, 36 bytes,
  // and 8 bytes a TEXCOORD set, the atlas's included) and an index; the
  // PNG at most 3 bytes a texel (and a little more for its rows and
  // headers).
  const uint64_t triangles = resident->scene->TriangleCount();
  const uint64_t uv_sets = std::max<uint64_t>(resident->scene->texcoords.size(), 2) + 1;
  uint64_t texels = 0;
  {
    std::shared_ptr<ObscuranceState> state = engine.SceneStateOf<ObscuranceState>(resident->name);
    std::lock_guard lock(state->mutex);
    if (state->updater) texels = uint64_t{state->updater->result().width} * state->updater->result().height;
  }
  const uint64_t bytes = (query.want_atlas_uvs ? 3 * triangles * 8 : 0) +
                         (query.want_gltf ? 2 * 3 * triangles * (40 + 8 * uv_sets) + texels * 4 + (uint64_t{1} << 20) : 0);
  ObscuranceExportAnswer answer;
  VISQ_ASSIGN_OR_RETURN(answer.memory, engine.work_budget().Reserve(bytes, "scene", query.call.Job()));

  const auto start = std::chrono::steady_clock::now();
  std::vector<glm::vec2> corner_uv;
  std::vector<glm::vec3> w, vertex_w;
  {
    std::shared_ptr<ObscuranceState> state = engine.SceneStateOf<ObscuranceState>(resident->name);
    std::lock_guard lock(state->mutex);
    VISQ_ASSIGN_OR_RETURN(resident, engine.SceneForQuery(query.scene, query.scene_version));
    VISQ_RETURN_IF_ERROR(RequireCurrentSolution(*resident, *state, "export"));
    const obscurance::ObscuranceAtlas& atlas = state->updater->atlas();
    corner_uv = atlas.corner_uv;
    if (query.want_gltf) w = state->updater->result().w;
    if (query.want_vertex_colors) vertex_w = state->updater->result().vertex_w;
    answer.width = atlas.width;
    answer.height = atlas.height;
    answer.from_lightmap_uvs = atlas.from_lightmap_uvs;
    answer.solution_version = state->solution_version;
  }
  answer.copy_ms = MillisecondsSince(start);
  answer.scene_version = resident->version;
  answer.triangles = resident->scene->TriangleCount();
  VISQ_RETURN_IF_ERROR(query.call.stop.Check("ExportObscurances"));

  const auto export_start = std::chrono::steady_clock::now();
  if (query.want_atlas_uvs) answer.atlas_uv = obscurance::AtlasUvs(corner_uv, answer.width, answer.height);
  if (query.want_gltf) {
    obscurance::BakedSceneOptions options;
    options.atlas_is_lightmap_uvs = answer.from_lightmap_uvs;
    options.vertex_w = std::move(vertex_w);
    VISQ_ASSIGN_OR_RETURN(answer.glb, obscurance::BakedSceneGlb(*resident->scene, corner_uv, answer.width,
                                                                answer.height, w, std::move(options)));
  }
  answer.export_ms = MillisecondsSince(export_start);
  return answer;
}

}  // namespace visq::core
