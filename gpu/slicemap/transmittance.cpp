// Transmittance shadow maps (Eisemann & Décoret 2006, section 6): the
// optical depth from a light to points through absorbing nodes, counted
// along each light-view column of a solid, local-precision slicemap per
// group of absorbers with one coefficient (the voxelization of slicemap.cpp).
#include <algorithm>
#include <bit>
#include <chrono>
#include <cmath>
#include <limits>
#include <map>
#include <set>
#include <vector>

#include "common/job_timing.h"
#include "slicemap_passes.h"
#include "visq/gpu/slicemap.h"

namespace visq::gpu {

using namespace slicemap_internal;

namespace {

using Clock = std::chrono::steady_clock;

// The light's view of the absorbers: an orthographic box along a directional
// light, or a frustum around the absorbers' bounding sphere for a point
// light, with slices in distance from the light.
struct LightFrame {
  bool perspective = false;
  OrientedBox box;  // directional
  // point light
  glm::dvec3 light{0.0}, u{0.0}, v{0.0}, w{0.0};
  double focal = 1.0;      // ndc = focal * (x, y) / z in the light's frame
  double r0 = 0.0, r1 = 1.0;  // distance range the slices split
};

void Orthonormal(const glm::dvec3& w, glm::dvec3& u, glm::dvec3& v) {
  const glm::dvec3 pick = std::abs(w.x) < 0.9 ? glm::dvec3(1, 0, 0) : glm::dvec3(0, 1, 0);
  u = glm::normalize(glm::cross(pick, w));
  v = glm::cross(w, u);
}

ViewSetup PerspectiveView(const LightFrame& frame, const glm::dvec3& anchor) {
  // clip = (f x_e, f y_e, A z_e + B, z_e) with e = ((p - L).u, (p - L).v, (p - L).w).
  const glm::dvec3 light_rel = frame.light - anchor;
  const double n = 0.5 * frame.r0 + 1e-9 * frame.r1, f = 1.01 * frame.r1;
  const double a = (f + n) / (f - n), b = -2.0 * f * n / (f - n);
  glm::dmat4 m(0.0);
  const glm::dvec3 rows[3] = {frame.focal * frame.u, frame.focal * frame.v, a * frame.w};
  for (int row = 0; row < 3; ++row) {
    for (int col = 0; col < 3; ++col) m[col][row] = rows[row][col];
    m[3][row] = -glm::dot(rows[row], light_rel);
  }
  m[3][2] += b;
  for (int col = 0; col < 3; ++col) m[col][3] = frame.w[col];
  m[3][3] = -glm::dot(frame.w, light_rel);
  ViewSetup view;
  view.clip_from_anchor = glm::mat4(m);
  view.perspective = true;
  view.light = glm::vec3(light_rel);
  view.radial = glm::vec2(static_cast<float>(frame.r0), static_cast<float>(1.0 / (frame.r1 - frame.r0)));
  return view;
}

// Where a point falls in the light's view.
struct ColumnHit {
  bool inside_image = false;
  uint32_t x = 0, y = 0;
  double depth = 0;           // fraction of the view depth (distance range for point lights)
  double lateral_offset = 0;  // to the texel-center ray, world units
};

ColumnHit Locate(const LightFrame& frame, uint32_t size, const glm::dvec3& p) {
  ColumnHit hit;
  double ndc_x, ndc_y;
  if (!frame.perspective) {
    const glm::dvec3 d = p - frame.box.center;
    ndc_x = glm::dot(d, frame.box.axis_u) / frame.box.half_extent.x;
    ndc_y = glm::dot(d, frame.box.axis_v) / frame.box.half_extent.y;
    hit.depth = glm::dot(d, frame.box.axis_w) / (2.0 * frame.box.half_extent.z) + 0.5;
  } else {
    const glm::dvec3 d = p - frame.light;
    const double z = glm::dot(d, frame.w);
    if (z <= 0.0) return hit;  // behind the light: no absorber in between
    ndc_x = frame.focal * glm::dot(d, frame.u) / z;
    ndc_y = frame.focal * glm::dot(d, frame.v) / z;
    hit.depth = (glm::length(d) - frame.r0) / (frame.r1 - frame.r0);
  }
  const double tx = (ndc_x * 0.5 + 0.5) * size, ty = (ndc_y * 0.5 + 0.5) * size;
  if (!(tx >= 0.0 && tx < size && ty >= 0.0 && ty < size)) return hit;
  hit.inside_image = true;
  hit.x = static_cast<uint32_t>(tx);
  hit.y = static_cast<uint32_t>(ty);
  const double cx = hit.x + 0.5, cy = hit.y + 0.5;
  if (!frame.perspective) {
    hit.lateral_offset = std::hypot((tx - cx) * 2.0 * frame.box.half_extent.x / size,
                                    (ty - cy) * 2.0 * frame.box.half_extent.y / size);
  } else {
    const double nx = (cx / size) * 2.0 - 1.0, ny = (cy / size) * 2.0 - 1.0;
    const glm::dvec3 dir = glm::normalize(nx / frame.focal * frame.u + ny / frame.focal * frame.v + frame.w);
    const glm::dvec3 d = p - frame.light;
    hit.lateral_offset = glm::length(d - glm::dot(d, dir) * dir);
  }
  return hit;
}

}  // namespace

Status ValidateTransmittanceParams(const TransmittanceParams& params, const Scene& scene) {
  const TransmittanceLight& light = params.light;
  if (light.kind != LightKind::kPoint && light.kind != LightKind::kDirectional)
    return absl::InvalidArgumentError(fmt::format("params.light.kind: unknown value {}", static_cast<int>(light.kind)));
  if (light.kind == LightKind::kPoint && !InCoordinateRange(light.position))
    return absl::InvalidArgumentError(fmt::format("params.light.position: non-finite or beyond ±1e15 {}", Vec(light.position)));
  if (light.kind == LightKind::kDirectional && (!InCoordinateRange(light.direction) || glm::length(light.direction) < 1e-12))
    return absl::InvalidArgumentError(
        fmt::format("params.light.direction: {} must be finite and non-zero", Vec(light.direction)));
  if (params.nodes.empty()) return absl::InvalidArgumentError("params.nodes: empty (name at least one absorbing node)");
  {
    const Status size = ValidateGridSize("params.", params.resolution, params.resolution, params.slices, true,
                                         kDefaultMaxSlicemapBytes);
    if (!size.ok())  // name the field the caller set: resolution, not width/height
      return Status(size.code(), fmt::format("{} (params.resolution = {})", size.message(), params.resolution));
  }
  for (size_t i = 0; i < params.points.size(); ++i)
    if (!InCoordinateRange(params.points[i]))
      return absl::InvalidArgumentError(fmt::format("params.points[{}]: non-finite or beyond ±1e15 {}", i, Vec(params.points[i])));
  const ReceiverPatch& patch = params.patch;
  if ((patch.nu == 0) != (patch.nv == 0))
    return absl::InvalidArgumentError(
        fmt::format("params.patch: nu = {}, nv = {} (both zero for no patch, or both positive)", patch.nu, patch.nv));
  if (patch.nu > 0 && (!InCoordinateRange(patch.origin) || !InCoordinateRange(patch.u) || !InCoordinateRange(patch.v)))
    return absl::InvalidArgumentError("params.patch: non-finite or beyond ±1e15 origin, u or v");
  const uint64_t point_count = params.points.size() + uint64_t{patch.nu} * patch.nv;
  if (point_count > kMaxTransmittancePoints)
    return absl::ResourceExhaustedError(
        fmt::format("params: {} query points exceed the cap of {}", point_count, kMaxTransmittancePoints));

  std::set<double> coefficients;
  for (size_t i = 0; i < params.nodes.size(); ++i) {
    const AbsorbingNode& n = params.nodes[i];
    if (n.node >= scene.nodes.size())
      return absl::InvalidArgumentError(
          fmt::format("params.nodes[{}].node: {} (the scene has {} nodes)", i, n.node, scene.nodes.size()));
    if (!std::isfinite(n.absorption) || n.absorption < 0.0)
      return absl::InvalidArgumentError(
          fmt::format("params.nodes[{}].absorption: {} (must be finite and >= 0)", i, n.absorption));
    coefficients.insert(n.absorption);
  }
  if (coefficients.size() > kMaxTransmittanceGroups)
    return absl::ResourceExhaustedError(fmt::format("params.nodes: {} distinct absorption values exceed the cap of {}",
                                                    coefficients.size(), kMaxTransmittanceGroups));
  return absl::OkStatus();
}

namespace {

// The absorbing nodes grouped by coefficient, each group's triangles as
// contiguous ranges; `bounds` receives the bounds of them all.
using AbsorberGroup = std::pair<double, std::vector<TriangleRange>>;
std::vector<AbsorberGroup> AbsorberGroups(const TransmittanceParams& params, const Scene& scene, Bounds& bounds) {
  std::map<double, std::vector<uint32_t>> groups;  // sigma -> node ids
  for (const AbsorbingNode& n : params.nodes) groups[n.absorption].push_back(n.node);
  std::vector<AbsorberGroup> group_ranges;
  for (const auto& [sigma, node_ids] : groups) {
    std::vector<bool> wanted(scene.nodes.size(), false);
    for (uint32_t id : node_ids) wanted[id] = true;
    std::vector<TriangleRange> ranges;
    for (uint32_t t = 0; t < scene.TriangleCount(); ++t) {
      if (!wanted[scene.NodeOf(t)]) continue;
      for (int c = 0; c < 3; ++c) bounds.Extend(scene.Vertex(t, c));
      if (!ranges.empty() && ranges.back().first + ranges.back().count == t)
        ++ranges.back().count;
      else
        ranges.push_back({t, 1});
    }
    group_ranges.emplace_back(sigma, std::move(ranges));
  }
  return group_ranges;
}

// The light's view of the absorbers: an orthographic box along a
// directional light, a perspective cone from a point light.
StatusOr<LightFrame> FrameAroundAbsorbers(const TransmittanceLight& light, const Bounds& bounds) {
  LightFrame frame;
  if (light.kind == LightKind::kDirectional) {
    glm::dvec3 u, v;
    const glm::dvec3 w = glm::normalize(light.direction);
    Orthonormal(w, u, v);
    glm::dvec3 lo(std::numeric_limits<double>::infinity()), hi(-std::numeric_limits<double>::infinity());
    for (int corner = 0; corner < 8; ++corner) {
      const glm::dvec3 p((corner & 1) ? bounds.max.x : bounds.min.x, (corner & 2) ? bounds.max.y : bounds.min.y,
                         (corner & 4) ? bounds.max.z : bounds.min.z);
      const glm::dvec3 q(glm::dot(p, u), glm::dot(p, v), glm::dot(p, w));
      lo = glm::min(lo, q);
      hi = glm::max(hi, q);
    }
    const double pad = 1e-3 * glm::length(hi - lo) + 1e-9;
    const glm::dvec3 mid = 0.5 * (lo + hi);
    frame.box.center = mid.x * u + mid.y * v + mid.z * w;
    frame.box.axis_u = u;
    frame.box.axis_v = v;
    frame.box.axis_w = w;
    frame.box.half_extent = 0.5 * (hi - lo) + glm::dvec3(pad);
  } else {
    frame.perspective = true;
    frame.light = light.position;
    const glm::dvec3 center = bounds.Center();
    const double radius = 0.5 * glm::length(bounds.Extent()) * (1.0 + 1e-3) + 1e-9;
    const double distance = glm::length(center - light.position);
    if (distance <= radius * 1.0001)
      return absl::FailedPreconditionError(fmt::format(
          "params.light.position {}: the point light is inside the absorbers' bounding sphere (center {}, radius {}); "
          "one light view cannot see them all",
          Vec(light.position), Vec(center), radius));
    frame.w = (center - light.position) / distance;
    Orthonormal(frame.w, frame.u, frame.v);
    const double sin_half = radius / distance;
    frame.focal = std::sqrt(1.0 - sin_half * sin_half) / sin_half;  // 1 / tan(half angle)
    frame.r0 = distance - radius;
    frame.r1 = distance + radius;
  }
  return frame;
}

// Bit counting for one group: full slices before each point's slice, plus
// the covered fraction of its own slice (the slides' "value truncation by
// position"), added to the points' optical depths and their errors.
void AddOpticalDepths(double sigma, const VoxelizeResult& voxels, const SlicemapGrid& surface, const LightFrame& frame,
                      uint32_t size, double depth_range, const std::vector<glm::dvec3>& points,
                      TransmittanceResult& result) {
  const SlicemapGrid& grid = voxels.grid;
  const uint32_t wpc = grid.words_per_column;
  std::vector<bool> ambiguous_column(size_t{size} * size, false);
  for (uint32_t column : voxels.ambiguous_column_list) ambiguous_column[column] = true;
  for (size_t i = 0; i < points.size(); ++i) {
    const ColumnHit hit = Locate(frame, size, points[i]);
    if (!hit.inside_image) continue;
    const size_t column = size_t{hit.y} * size + hit.x;
    result.lateral_offset[i] = static_cast<float>(std::max<double>(result.lateral_offset[i], hit.lateral_offset));
    const double near = voxels.column_near[column], far = voxels.column_far[column];
    if (near > far) continue;  // no absorber in this column
    const double slice_length = (far - near) * depth_range / grid.slices;
    result.max_voxel_length = std::max(result.max_voxel_length, slice_length);
    const double position = (hit.depth - near) / (far - near) * grid.slices;
    if (position <= 0.0) continue;
    if (ambiguous_column[column]) {
      // The column's in/out order did not resolve (open, overlapping or
      // nested absorbers): its voxels say nothing of the inside. The path
      // inside lies anywhere between none and all of the column's length
      // up to the point; the answer is the upper end, as everywhere.
      const double upper = sigma * std::min<double>(position, grid.slices) * slice_length;
      result.optical_depth[i] += static_cast<float>(upper);
      result.optical_depth_error[i] += static_cast<float>(upper);
      result.ambiguous[i] = 1;
      continue;
    }
    const uint32_t whole = static_cast<uint32_t>(std::min<double>(std::floor(position), grid.slices));
    const double fraction = whole < grid.slices ? position - whole : 0.0;
    const uint32_t* solid_column = &grid.bits[column * wpc];
    const uint32_t* surface_column = &surface.bits[column * wpc];
    double occupied = 0.0, shell = 0.0;
    for (uint32_t w = 0; w < whole / 32; ++w) {
      occupied += std::popcount(solid_column[w]);
      shell += std::popcount(surface_column[w]);
    }
    if (whole % 32 != 0) {
      const uint32_t mask = (1u << (whole % 32)) - 1u;
      occupied += std::popcount(solid_column[whole / 32] & mask);
      shell += std::popcount(surface_column[whole / 32] & mask);
    }
    if (whole < grid.slices) {
      if ((solid_column[whole / 32] >> (whole % 32)) & 1u) occupied += fraction;
      if ((surface_column[whole / 32] >> (whole % 32)) & 1u) shell += fraction;
    }
    result.optical_depth[i] += static_cast<float>(sigma * occupied * slice_length);
    result.optical_depth_error[i] += static_cast<float>(sigma * shell * slice_length);
  }
}

}  // namespace

StatusOr<TransmittanceResult> Transmittance(GpuWorker& worker, const Scene& scene, const GpuScene& gpu_scene,
                                            const TransmittanceParams& params) {
  const auto start = Clock::now();
  VISQ_RETURN_IF_ERROR(ValidateTransmittanceParams(params, scene));
  const TransmittanceLight& light = params.light;

  // Absorbers grouped by coefficient: one solid slicemap per group.
  Bounds bounds;
  const std::vector<AbsorberGroup> group_ranges = AbsorberGroups(params, scene, bounds);

  const std::vector<glm::dvec3> points = params.QueryPoints();
  TransmittanceResult result;
  result.AllTransmitting(points.size());
  if (bounds.Empty()) {
    result.error_statement = "the absorbing nodes have no triangles: nothing absorbs";
    result.timings.total_ms = MillisecondsSince(start);
    return result;
  }

  // The light's frame around the absorbers.
  const uint32_t size = params.resolution;
  VISQ_ASSIGN_OR_RETURN(const LightFrame frame, FrameAroundAbsorbers(light, bounds));
  const ViewSetup view =
      frame.perspective ? PerspectiveView(frame, gpu_scene.anchor()) : OrthographicView(frame.box, gpu_scene.anchor());
  const double depth_range =
      frame.perspective ? frame.r1 - frame.r0 : 2.0 * frame.box.half_extent.z;
  result.max_texel_size = frame.perspective ? 2.0 * frame.r1 / frame.focal / size
                                            : 2.0 * std::max(frame.box.half_extent.x, frame.box.half_extent.y) / size;

  // One solid, local-precision slicemap per group; count along each column.
  for (const auto& [sigma, ranges] : group_ranges) {
    PassConfig config;
    config.width = size;
    config.height = size;
    config.slices = params.slices;
    config.mode = VoxelizeMode::kSolid;
    config.precision = SlicePrecision::kLocal;
    config.triangles = ranges;
    config.job = params.job;
    SlicemapGrid surface;
    VISQ_ASSIGN_OR_RETURN(VoxelizeResult voxels, VoxelizeView(worker, gpu_scene, view, config, /*sink=*/{}, &surface));
    result.ambiguous_columns += voxels.ambiguous_columns;
    SlicemapTimings& t = result.timings;
    t.queue_ms += voxels.timings.queue_ms;
    t.setup_ms += voxels.timings.setup_ms;
    t.depth_ms += voxels.timings.depth_ms;
    t.voxelize_ms += voxels.timings.voxelize_ms;
    t.readback_ms += voxels.timings.readback_ms;
    t.resolve_ms += voxels.timings.resolve_ms;

    const auto count_start = Clock::now();
    AddOpticalDepths(sigma, voxels, surface, frame, size, depth_range, points, result);
    result.timings.resolve_ms += MillisecondsSince(count_start);
  }
  for (size_t i = 0; i < points.size(); ++i) result.transmittance[i] = std::exp(-result.optical_depth[i]);

  size_t ambiguous_points = 0;
  for (uint8_t a : result.ambiguous) ambiguous_points += a;
  result.error_statement = fmt::format(
      "optical depth = sigma x occupied length along the point's light-view column, in voxels up to {:.4g} long "
      "(texels up to {:.4g} wide at the absorbers). The bound is for the column's centre ray, up to the point's "
      "depth: along that ray the exact optical depth lies in [optical_depth - optical_depth_error, optical_depth] "
      "(surface voxels count whole, so each surface crossing can add up to one voxel length). The point's own ray "
      "lies lateral_offset from it: where the absorbers' thickness varies within that distance, the point's own "
      "value can lie outside the interval. {} columns were ambiguous (open, overlapping or nested absorbers); the "
      "{} points behind one are flagged in `ambiguous` and state the whole interval [0, their column's length up "
      "to them x sigma].",
      result.max_voxel_length, result.max_texel_size, result.ambiguous_columns, ambiguous_points);
  result.timings.total_ms = MillisecondsSince(start);
  return result;
}

}  // namespace visq::gpu
