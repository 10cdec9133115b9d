#include "core/voxel_query.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <functional>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "common/job_timing.h"
#include "core/engine.h"
#include "glm/geometric.hpp"
#include "voxel_reference/transmittance_by_rays.h"

namespace visq::core {
namespace {

// Every node named, by name; INVALID_ARGUMENT for a name not in the scene.
StatusOr<std::vector<uint32_t>> NodeIndices(const Scene& scene, const std::string& name, const char* field) {
  std::vector<uint32_t> found;
  for (uint32_t i = 0; i < scene.nodes.size(); ++i)
    if (scene.nodes[i].name == name) found.push_back(i);
  if (found.empty()) return absl::InvalidArgumentError(absl::StrCat(field, ": no node named '", name, "'"));
  return found;
}

// One voxelization's working memory before its answer: a band's grids
// (surface, front and back for a solid) and read-back, and with local
// precision every column's near and far.
uint64_t VoxelizeBandBytes(uint64_t width, uint64_t height, uint64_t slices, uint64_t max_columns_per_job,
                           bool local) {
  const uint64_t column_bytes = ((slices + 31) / 32) * 4;
  const uint64_t band_columns = std::min<uint64_t>(width * height, std::max<uint64_t>(max_columns_per_job, width));
  return band_columns * (3 * column_bytes + 16 + 8) + (local ? width * height * 8 : 0);
}

}  // namespace

StatusOr<gpu::VoxelizeParams> ResolveVoxelizeQuery(VoxelizeQuery query, const Scene& scene) {
  if (query.box) {
    query.params.box = *query.box;
  } else {
    if (query.depth_axis < 0 || query.depth_axis > 2)
      return absl::InvalidArgumentError(absl::StrCat("depth_axis: ", query.depth_axis, " not in {0, 1, 2}"));
    query.params.box = gpu::AxisAlignedSlicemapBox(scene.bounds, query.depth_axis, 0.0);
  }
  for (const std::string& name : query.nodes) {
    VISQ_ASSIGN_OR_RETURN(std::vector<uint32_t> nodes, NodeIndices(scene, name, "nodes"));
    for (uint32_t n : nodes)
      if (scene.nodes[n].triangle_count > 0)
        query.params.triangles.push_back({scene.nodes[n].first_triangle, scene.nodes[n].triangle_count});
  }
  if (!query.nodes.empty() && query.params.triangles.empty())
    return absl::InvalidArgumentError("nodes: the named nodes hold no triangles");
  VISQ_RETURN_IF_ERROR(gpu::ValidateVoxelizeParams(query.params, static_cast<uint32_t>(scene.TriangleCount())));
  return std::move(query.params);
}

StatusOr<gpu::TransmittanceParams> ResolveTransmittanceQuery(TransmittanceQuery query, const Scene& scene) {
  for (size_t i = 0; i < query.absorbers.size(); ++i) {
    const auto& [name, absorption] = query.absorbers[i];
    VISQ_ASSIGN_OR_RETURN(std::vector<uint32_t> nodes,
                          NodeIndices(scene, name, absl::StrCat("absorbers[", i, "].node").c_str()));
    for (uint32_t n : nodes) query.params.nodes.push_back({n, absorption});
  }
  VISQ_RETURN_IF_ERROR(gpu::ValidateTransmittanceParams(query.params, scene));
  return std::move(query.params);
}

StatusOr<VoxelizeAnswer> RunVoxelize(Engine& engine, const VoxelizeQuery& query, const gpu::VoxelizeBandSink& sink) {
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<const ResidentScene> resident,
                        engine.SceneForQuery(query.scene, query.scene_version));
  VISQ_ASSIGN_OR_RETURN(gpu::VoxelizeParams params, ResolveVoxelizeQuery(query, *resident->scene));
  params.job = query.call.Job();
  // One band's grids (surface, front and back for a solid) and read-back,
  // and then the whole grid with its copy in messages, or, streamed, what
  // the stream's writer may hold unsent.
  const uint64_t column_bytes = ((uint64_t(params.slices) + 31) / 32) * 4;
  const uint64_t grid_bytes = uint64_t(params.width) * params.height * column_bytes;
  const uint64_t band_bytes = VoxelizeBandBytes(params.width, params.height, params.slices, params.max_columns_per_job,
                                                params.precision == gpu::SlicePrecision::kLocal);
  const uint64_t bytes = band_bytes + (sink ? std::min(grid_bytes, kStreamedAnswerQueueBytes) : 2 * grid_bytes);
  VISQ_ASSIGN_OR_RETURN(WorkMemoryBudget::Reservation memory,
                        engine.work_budget().Reserve(bytes, "width x height x slices", params.job));
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<gpu::GpuScene> gpu_scene, engine.GpuSceneOf(*resident, query.call));
  VoxelizeAnswer answer;
  VISQ_ASSIGN_OR_RETURN(answer.result, gpu::Voxelize(engine.gpu(), *gpu_scene, params,
                                                     TimedBandSink(sink, &answer.delivery_ms)));
  return answer;
}

namespace {

// What one method's run holds before its answer is sent, and the request's
// fields that make it grow.
// The absorbing nodes' triangles: what stabbing's BVH holds.
uint64_t AbsorbingTriangles(const Scene& scene, const gpu::TransmittanceParams& params) {
  uint64_t triangles = 0;
  for (const voxel_reference::AbsorbingNode& n : params.nodes) triangles += scene.nodes[n.node].triangle_count;
  return triangles;
}

struct WorkBytes {
  uint64_t bytes = 0;
  const char* what = "";
};
WorkBytes TransmittanceWorkBytes(const Scene& scene, const gpu::TransmittanceParams& params,
                                 TransmittanceMethod method) {
  const uint64_t points = params.points.size() + uint64_t{params.patch.nu} * params.patch.nv;
  if (method == TransmittanceMethod::kRayStabbing) {
    // Per query point its position, its walk along the line (a count and an
    // entry per coefficient group), a ray and a hit while it crosses, its
    // answers and their copy in the response; per absorbing triangle its
    // copy and Embree's share of a BVH, while a scene's first call builds it
    // (then kept, in the scene's memory: AbsorberRaysCache).
    return {points * 512 + AbsorbingTriangles(scene, params) * 256 + (uint64_t{1} << 20),
            "points, receiver_width x receiver_height"};
  }
  // Per query point its position (the explicit points copied, the
  // receiver's texels added), its five answers (17 bytes) and their copy in
  // the response; one group's solid voxelization at a time (a band, and the
  // whole solid and surface grids with every column's ambiguity). A 4096^2
  // receiver is about 1 GB.
  const uint64_t size = params.resolution;
  const uint64_t grid_bytes = size * size * (((uint64_t{params.slices} + 31) / 32) * 4);
  return {points * (sizeof(glm::dvec3) + 2 * (4 * sizeof(float) + 1)) +
              VoxelizeBandBytes(size, size, params.slices, gpu::kDefaultSlicemapColumnsPerJob, true) + 2 * grid_bytes +
              size * size / 8 + (uint64_t{1} << 20),
          "points, receiver_width x receiver_height, resolution x slices"};
}

// One method's run of resolved parameters: its working memory reserved
// first (into *hold where given, to outlive the call), then the work.
StatusOr<gpu::TransmittanceResult> TransmittanceBy(Engine& engine, const ResidentScene& resident,
                                                   const gpu::TransmittanceParams& params, TransmittanceMethod method,
                                                   const CallOptions& call, WorkMemoryBudget::Reservation* hold) {
  const WorkBytes needs = TransmittanceWorkBytes(*resident.scene, params, method);
  VISQ_ASSIGN_OR_RETURN(WorkMemoryBudget::Reservation memory,
                        engine.work_budget().Reserve(needs.bytes, needs.what, params.job));
  if (hold != nullptr) *hold = std::move(memory);
  if (method == TransmittanceMethod::kRayStabbing) {
    std::vector<uint32_t> nodes;
    for (const voxel_reference::AbsorbingNode& n : params.nodes) nodes.push_back(n.node);
    VISQ_ASSIGN_OR_RETURN(std::shared_ptr<const voxel_reference::AbsorberRays> absorbers,
                          resident.absorber_rays.Get(*resident.scene, std::move(nodes), params.job.stop));
    return voxel_reference::TransmittanceByRays(*resident.scene, params, absorbers.get());
  }
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<gpu::GpuScene> gpu_scene, engine.GpuSceneOf(resident, call));
  return gpu::Transmittance(engine.gpu(), *resident.scene, *gpu_scene, params);
}

// The slicemap's work: light-view texels times solid passes' words, per
// absorption value (one solid slicemap each); the points' lookups apart.
double SlicemapWork(const gpu::TransmittanceParams& params) {
  std::vector<double> coefficients;
  for (const voxel_reference::AbsorbingNode& n : params.nodes) coefficients.push_back(n.absorption);
  std::sort(coefficients.begin(), coefficients.end());
  const double groups = double(std::unique(coefficients.begin(), coefficients.end()) - coefficients.begin());
  return double(params.resolution) * params.resolution * std::ceil(params.slices / 32.0) * groups;
}

// Every point of the request, as explicit points; `count` of them, spread
// evenly over the request's order, for a probe.
gpu::TransmittanceParams WithSpreadPoints(const gpu::TransmittanceParams& params, size_t count) {
  gpu::TransmittanceParams probe = params;
  const std::vector<glm::dvec3> all = params.QueryPoints();
  probe.patch = {};
  probe.points.clear();
  count = std::min(count, all.size());
  for (size_t i = 0; i < count; ++i) probe.points.push_back(all[i * all.size() / count]);
  return probe;
}

// A request naming no method. Ray stabbing answers each point for its own
// ray, within a rounding per crossing (its ambiguous points with the whole
// interval, as the slicemap's); the slicemap for the ray through its
// texel's centre, within a voxel per crossing: stabbing's interval is at
// least as tight, on the ray the user asked about, so either may answer and
// the faster here runs. Stabbing is probed first, on a few of the points;
// the slicemap then on a few points, within a share of stabbing's predicted
// time (on a CPU rasterizer its first voxelization can cost more than every
// point's rays).
StatusOr<PlanReport> ChooseTransmittanceMethod(Engine& engine, const ResidentScene& resident,
                                               const gpu::TransmittanceParams& params, const CallOptions& call) {
  std::string absorbers;
  for (const voxel_reference::AbsorbingNode& n : params.nodes) absorbers += absl::StrCat(n.node, ":", n.absorption, ",");
  const std::string series = absl::StrCat(resident.name, "@", resident.content_hash.substr(0, 8), "/transmittance/",
                                          params.light.kind == voxel_reference::TransmittanceLightKind::kPoint ? "point" : "directional",
                                          "/", absl::StrFormat("%016x", std::hash<std::string>()(absorbers)));
  const double points = double(params.points.size()) + double(params.patch.nu) * params.patch.nv;
  std::vector<EqualAnswerOption> options(2);
  {
    Plan& plan = options[0].plan;
    plan.method = "transmittance-ray-stabbing";
    plan.runs = TransmittanceMethod::kRayStabbing;
    plan.cost_key = series + "/ray-stabbing";
    // Two parts: the absorbers' BVH (58 ms behind the bunny on this 2-core
    // machine, built on a scene's first call and kept: AbsorberRaysCache),
    // and each point's crossings. Taken as one rate per point, two probes of
    // 16 and 128 points predicted the bunny's 96^2 receiver at 7.7 s where it
    // took 75 ms.
    plan.work = std::max(1.0, double(AbsorbingTriangles(*resident.scene, params)));
    plan.extra_work = points;
    for (const size_t count : {size_t{16}, size_t{128}}) {
      options[0].probes.push_back(
          {plan.work, double(std::min<double>(count, points)),
           [&engine, &resident, &params, count](const CallOptions& probe_call) -> StatusOr<double> {
             gpu::TransmittanceParams probe = WithSpreadPoints(params, count);
             probe.job = probe_call.Job();
             const auto start = std::chrono::steady_clock::now();
             VISQ_RETURN_IF_ERROR(
                 TransmittanceBy(engine, resident, probe, TransmittanceMethod::kRayStabbing, probe_call, nullptr)
                     .status());
             return MillisecondsSince(start);
           }});
    }
  }
  {
    Plan& plan = options[1].plan;
    plan.method = "transmittance-slicemap";
    plan.runs = TransmittanceMethod::kSlicemap;
    plan.parameters["resolution"] = params.resolution;
    plan.parameters["slices"] = params.slices;
    plan.cost_key = series + "/slicemap";
    plan.work = SlicemapWork(params);
    plan.extra_work = points;
    // Its probes voxelize at the request's resolution and slices, for a few
    // of its points: the voxelization is most of its cost (on llvmpipe a
    // 256^3 bunny takes 65 ms for 16 points, 74 ms for 262,144), and a
    // smaller one measured its fixed costs as a rate, which extrapolated
    // 100x too high.
    for (const size_t count : {size_t{16}, size_t{128}}) {
      gpu::TransmittanceParams probe = WithSpreadPoints(params, count);
      const double probe_points = double(probe.points.size());
      options[1].probes.push_back(
          {plan.work, probe_points,
           [&engine, &resident, probe](const CallOptions& probe_call) mutable -> StatusOr<double> {
             probe.job = probe_call.Job();
             const auto start = std::chrono::steady_clock::now();
             VISQ_RETURN_IF_ERROR(
                 TransmittanceBy(engine, resident, probe, TransmittanceMethod::kSlicemap, probe_call, nullptr).status());
             return MillisecondsSince(start);
           }});
    }
  }
  return ChooseFastest(engine.cost_model(), std::move(options), call);
}

}  // namespace

StatusOr<TransmittanceAnswer> RunTransmittance(Engine& engine, const TransmittanceQuery& query,
                                               WorkMemoryBudget::Reservation* hold) {
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<const ResidentScene> resident,
                        engine.SceneForQuery(query.scene, query.scene_version));
  // Resolved and validated before the GPU upload: a bad request costs nothing.
  VISQ_ASSIGN_OR_RETURN(gpu::TransmittanceParams params, ResolveTransmittanceQuery(query, *resident->scene));
  params.job = query.call.Job();
  TransmittanceAnswer answer;
  TransmittanceMethod method = TransmittanceMethod::kSlicemap;
  // A method whose run cannot fit the work budget is not weighed: its probes
  // would cost time for nothing. Neither: the smaller's refusal, at once.
  const uint64_t capacity = engine.work_budget().capacity();
  const WorkBytes stabbing = TransmittanceWorkBytes(*resident->scene, params, TransmittanceMethod::kRayStabbing);
  const WorkBytes slicemap = TransmittanceWorkBytes(*resident->scene, params, TransmittanceMethod::kSlicemap);
  if (query.method) {
    method = *query.method;
  } else if (stabbing.bytes > capacity || slicemap.bytes > capacity) {
    method = stabbing.bytes <= slicemap.bytes ? TransmittanceMethod::kRayStabbing : TransmittanceMethod::kSlicemap;
  } else {
    VISQ_ASSIGN_OR_RETURN(PlanReport report, ChooseTransmittanceMethod(engine, *resident, params, query.call));
    method = std::get<TransmittanceMethod>(report.chosen_plan().runs);
    answer.plan = std::move(report);
  }
  const auto start = std::chrono::steady_clock::now();
  VISQ_ASSIGN_OR_RETURN(answer.result, TransmittanceBy(engine, *resident, params, method, query.call, hold));
  if (answer.plan) {
    // The chosen run teaches the model too.
    const Plan& plan = answer.plan->chosen_plan();
    engine.cost_model().Record(plan.cost_key, plan.work, MillisecondsSince(start), plan.extra_work);
  }
  return answer;
}

const char* RasterizationName(gpu::Rasterization rasterization) {
  return rasterization == gpu::Rasterization::kConservative ? "conservative" : "standard";
}

const char* SlicePrecisionName(gpu::SlicePrecision precision) {
  return precision == gpu::SlicePrecision::kLocal ? "local" : "uniform";
}

AccuracyStatement VoxelizeStatement(const gpu::VoxelizeResult& figures) {
  const gpu::SlicemapGrid& grid = figures.grid;
  const voxel_reference::OrientedBox& box = figures.box;
  const glm::dvec3 voxel(2.0 * box.half_extent.x / grid.width, 2.0 * box.half_extent.y / grid.height,
                         2.0 * box.half_extent.z / grid.slices);
  AccuracyStatement out;
  out.method =
      absl::StrCat("slicemap-", RasterizationName(figures.rasterization), "-", SlicePrecisionName(figures.precision));
  const std::string voxel_size = absl::StrCat(voxel.x, " x ", voxel.y, " x ", voxel.z);
  const char* precision_words =
      figures.precision == gpu::SlicePrecision::kLocal ? "; local precision: slices span each column's near..far" : "";
  if (figures.rasterization == gpu::Rasterization::kConservative) {
    out.error_bound = glm::length(voxel);
    out.confidence = 1.0;
    out.note = absl::StrCat("every voxel a triangle touches is set, and some neighbours may be: each surface point is "
                            "within one voxel (",
                            voxel_size, "; error_bound is its diagonal) of a set voxel", precision_words);
    return out;
  }
  // Standard rasterization samples texel centres: a triangle thinner than a
  // texel, or seen edge-on, may set no voxel at all, so no distance bounds
  // what is missed.
  out.note = absl::StrCat("no numeric bound: standard rasterization samples texel centres and misses triangles "
                          "thinner than a texel or seen edge-on; set voxels are within one voxel (",
                          voxel_size, ") of the surface. Ask for conservative for a bound", precision_words);
  return out;
}

AccuracyStatement TransmittanceStatement(const TransmittanceAnswer& answer) {
  const gpu::TransmittanceResult& result = answer.result;
  AccuracyStatement out;
  out.method = result.method;
  float worst = 0;
  for (float e : result.optical_depth_error) worst = std::max(worst, e);
  out.error_bound = worst;
  out.confidence = 1.0;
  out.note = result.error_statement;
  if (answer.plan) AddChosenPlan(*answer.plan, out);
  return out;
}

}  // namespace visq::core
