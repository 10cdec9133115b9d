#include "core/voxel_query.h"

#include <algorithm>

#include "absl/strings/str_cat.h"
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

StatusOr<gpu::TransmittanceResult> RunTransmittance(Engine& engine, const TransmittanceQuery& query,
                                                    WorkMemoryBudget::Reservation* hold) {
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<const ResidentScene> resident,
                        engine.SceneForQuery(query.scene, query.scene_version));
  // Resolved and validated before the GPU upload: a bad request costs nothing.
  VISQ_ASSIGN_OR_RETURN(gpu::TransmittanceParams params, ResolveTransmittanceQuery(query, *resident->scene));
  params.job = query.call.Job();
  if (query.method == TransmittanceMethod::kRayStabbing) {
    // Reserved first: per query point its position, its walk along the line
    // (a count and an entry per coefficient group), a ray and a hit while it
    // crosses, its answers and their copy in the response; per absorbing
    // triangle its copy and Embree's share of a BVH.
    uint64_t absorbing_triangles = 0;
    for (const voxel_reference::AbsorbingNode& n : params.nodes)
      absorbing_triangles += resident->scene->nodes[n.node].triangle_count;
    const uint64_t points = params.points.size() + uint64_t{params.patch.nu} * params.patch.nv;
    const uint64_t bytes = points * 512 + absorbing_triangles * 256 + (uint64_t{1} << 20);
    WorkMemoryBudget::Reservation memory;
    VISQ_ASSIGN_OR_RETURN(memory, engine.work_budget().Reserve(bytes, "points, receiver_width x receiver_height", params.job));
    if (hold != nullptr) *hold = std::move(memory);
    return voxel_reference::TransmittanceByRays(*resident->scene, params);
  }
  // Reserved before anything is made: per query point its position (the
  // explicit points copied, the receiver's texels added), its five answers
  // (17 bytes) and their copy in the response; one group's solid
  // voxelization at a time (a band, and the whole solid and surface grids
  // with every column's ambiguity). A 4096^2 receiver is about 1 GB.
  const uint64_t points = params.points.size() + uint64_t{params.patch.nu} * params.patch.nv;
  const uint64_t size = params.resolution;
  const uint64_t grid_bytes = size * size * (((uint64_t{params.slices} + 31) / 32) * 4);
  const uint64_t bytes = points * (sizeof(glm::dvec3) + 2 * (4 * sizeof(float) + 1)) +
                         VoxelizeBandBytes(size, size, params.slices, gpu::kDefaultSlicemapColumnsPerJob, true) +
                         2 * grid_bytes + size * size / 8 + (uint64_t{1} << 20);
  WorkMemoryBudget::Reservation memory;
  VISQ_ASSIGN_OR_RETURN(memory, engine.work_budget().Reserve(
                                    bytes, "points, receiver_width x receiver_height, resolution x slices", params.job));
  if (hold != nullptr) *hold = std::move(memory);
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<gpu::GpuScene> gpu_scene, engine.GpuSceneOf(*resident, query.call));
  return gpu::Transmittance(engine.gpu(), *resident->scene, *gpu_scene, params);
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

AccuracyStatement TransmittanceStatement(const gpu::TransmittanceResult& result) {
  AccuracyStatement out;
  out.method = result.method;
  float worst = 0;
  for (float e : result.optical_depth_error) worst = std::max(worst, e);
  out.error_bound = worst;
  out.confidence = 1.0;
  out.note = result.error_statement;
  return out;
}

}  // namespace visq::core
