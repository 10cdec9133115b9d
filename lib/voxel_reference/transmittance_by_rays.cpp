#include "voxel_reference/transmittance_by_rays.h"

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <limits>
#include <map>
#include <vector>

#include <fmt/format.h>

#include "common/job_timing.h"
#include "raycast/embree_scene.h"
#include "scene/sample_scenes.h"

namespace visq::voxel_reference {
namespace {

constexpr double kInfinity = std::numeric_limits<double>::infinity();
// Rounds after which a line still crossing is given up on (and flagged):
// thousands of surfaces on one line are not an absorber.
constexpr int kMostCrossings = 4096;

// The smallest float not below x (x >= 0): a bound stays a bound.
float FloatAtLeast(double x) {
  float f = static_cast<float>(x);
  if (static_cast<double>(f) < x) f = std::nextafter(f, std::numeric_limits<float>::infinity());
  return f;
}

// Where the line p + t u is inside `box`: [t_in, t_out], false when nowhere.
bool ClipToBox(const glm::dvec3& p, const glm::dvec3& u, const Bounds& box, double& t_in, double& t_out) {
  t_in = -kInfinity;
  t_out = kInfinity;
  for (int a = 0; a < 3; ++a) {
    if (u[a] == 0.0) {
      if (p[a] < box.min[a] || p[a] > box.max[a]) return false;
      continue;
    }
    double t0 = (box.min[a] - p[a]) / u[a], t1 = (box.max[a] - p[a]) / u[a];
    if (t0 > t1) std::swap(t0, t1);
    t_in = std::max(t_in, t0);
    t_out = std::min(t_out, t1);
  }
  return t_in <= t_out;
}

// One point's line, p + t u with t = 0 at the point and the light at
// t_light (-infinity for a directional light), and its walk through the
// crossings, nearest the light first.
struct Walk {
  glm::dvec3 p{0.0}, u{0.0};
  double t_light = 0.0;
  double t_in = 0.0, t_out = 0.0;  // the line inside the absorbers' box
  double travelled = 0.0;          // from t_in to the last crossing
  std::array<int, kMaxTransmittanceGroups> winding{};
  std::array<double, kMaxTransmittanceGroups> entered_at{}, entered_error{};
  double depth = 0.0;  // sum of sigma x the inside length within [t_light, 0]
  double error = 0.0;  // sum of sigma x the error of each crossing that bounds such a length
  bool ambiguous = false;
};

}  // namespace

size_t AbsorberRays::MemoryBytes() const {
  return nodes.size() * sizeof(uint32_t) + triangles.positions.size() * sizeof(glm::dvec3) +
         triangles.triangles.size() * (sizeof(glm::uvec3) + 2 * sizeof(uint32_t)) +
         node_of_triangle.size() * sizeof(uint32_t) + (embree ? embree->memory_bytes() : 0);
}

StatusOr<std::shared_ptr<const AbsorberRays>> BuildAbsorberRays(const Scene& scene, std::vector<uint32_t> nodes,
                                                               const StopToken& stop) {
  std::sort(nodes.begin(), nodes.end());
  nodes.erase(std::unique(nodes.begin(), nodes.end()), nodes.end());
  auto out = std::make_shared<AbsorberRays>();
  std::vector<std::array<glm::dvec3, 3>> triangles;
  for (const uint32_t n : nodes) {
    if (n >= scene.nodes.size())
      return absl::InvalidArgumentError(fmt::format("node {}: the scene has {} nodes", n, scene.nodes.size()));
    const SceneNode& node = scene.nodes[n];
    for (size_t t = node.first_triangle; t < size_t{node.first_triangle} + node.triangle_count; ++t) {
      triangles.push_back({scene.Vertex(t, 0), scene.Vertex(t, 1), scene.Vertex(t, 2)});
      out->node_of_triangle.push_back(n);
    }
  }
  out->nodes = std::move(nodes);
  if (triangles.empty()) return std::shared_ptr<const AbsorberRays>(std::move(out));
  out->triangles = SceneOfTriangles(triangles);
  raycast::EmbreeSceneOptions embree_options;
  embree_options.instance_meshes = false;
  embree_options.stop = stop;
  VISQ_ASSIGN_OR_RETURN(raycast::EmbreeScene embree, raycast::EmbreeScene::Create(out->triangles, embree_options));
  out->embree = std::make_unique<raycast::EmbreeScene>(std::move(embree));
  return std::shared_ptr<const AbsorberRays>(std::move(out));
}

StatusOr<TransmittanceResult> TransmittanceByRays(const Scene& scene, const TransmittanceParams& params,
                                                  const AbsorberRays* given) {
  const auto start = std::chrono::steady_clock::now();
  TransmittanceResult result;
  result.method = "transmittance-ray-stabbing";

  // The absorbers alone, each triangle knowing its coefficient's group.
  std::map<double, int> group_of_sigma;
  std::vector<int> group_of_node(scene.nodes.size(), -1);
  for (const AbsorbingNode& n : params.nodes) group_of_sigma.emplace(n.absorption, 0);
  std::vector<double> sigma;
  for (auto& [value, group] : group_of_sigma) {
    group = static_cast<int>(sigma.size());
    sigma.push_back(value);
  }
  if (sigma.size() > kMaxTransmittanceGroups)
    return absl::InvalidArgumentError(fmt::format("params.nodes: {} distinct absorption values (at most {})",
                                                  sigma.size(), kMaxTransmittanceGroups));
  std::vector<uint32_t> listed;
  for (size_t i = 0; i < params.nodes.size(); ++i) {
    const AbsorbingNode& n = params.nodes[i];
    if (n.node >= scene.nodes.size())
      return absl::InvalidArgumentError(
          fmt::format("params.nodes[{}].node: {} (the scene has {} nodes)", i, n.node, scene.nodes.size()));
    const int group = group_of_sigma[n.absorption];
    // One node in two coefficients' unions would be two coincident
    // surfaces on every line through it, which count as one crossing.
    if (group_of_node[n.node] >= 0 && group_of_node[n.node] != group)
      return absl::InvalidArgumentError(fmt::format(
          "params.nodes[{}]: node {} is listed with two absorption values; RAY_STABBING takes one a node", i,
          n.node));
    group_of_node[n.node] = group;
    listed.push_back(n.node);
  }
  if (params.light.kind == TransmittanceLightKind::kDirectional
          ? !(glm::length(params.light.direction) > 0.0) || !std::isfinite(glm::length(params.light.direction))
          : !std::isfinite(glm::length(params.light.position)))
    return absl::InvalidArgumentError("params.light: a finite position, or a finite non-zero direction");
  // Each absorbing node's own triangles (its range of the scene's), once
  // however often it is listed: the work follows the absorbers, not the scene.
  std::shared_ptr<const AbsorberRays> built;
  if (given == nullptr) {
    VISQ_ASSIGN_OR_RETURN(built, BuildAbsorberRays(scene, listed, params.job.stop));
    given = built.get();
  } else {
    std::sort(listed.begin(), listed.end());
    listed.erase(std::unique(listed.begin(), listed.end()), listed.end());
    if (listed != given->nodes)
      return absl::InvalidArgumentError("absorbers: built for other nodes than params.nodes lists");
  }
  const AbsorberRays& rays_of = *given;

  const std::vector<glm::dvec3> points = params.QueryPoints();
  result.AllTransmitting(points.size());
  if (rays_of.embree == nullptr) {
    result.error_statement = "the absorbing nodes have no triangles: nothing absorbs";
    result.timings.total_ms = MillisecondsSince(start);
    return result;
  }

  const Scene& absorbers = rays_of.triangles;
  const raycast::EmbreeScene& embree = *rays_of.embree;
  // The box the rays start and end outside of, a little larger than the
  // absorbers so that each line starts outside every one of them.
  Bounds box = absorbers.bounds;
  const double margin = 1e-3 * glm::length(box.Extent()) + 1e-9;
  box.min -= glm::dvec3(margin);
  box.max += glm::dvec3(margin);
  // EmbreeScene's offset at an origin within `box` (its frame is the
  // absorbers' centre): every crossing is placed within it, and hits closer
  // than it to the last one are skipped.
  const glm::dvec3 half = 0.5 * box.Extent();
  const double magnitude = std::max({half.x, half.y, half.z, glm::length(absorbers.bounds.Extent()) / 8.0});
  const double offset = std::ldexp(magnitude, -17);

  std::vector<Walk> walks(points.size());
  std::vector<size_t> active;
  for (size_t i = 0; i < points.size(); ++i) {
    Walk& w = walks[i];
    w.p = points[i];
    if (params.light.kind == TransmittanceLightKind::kDirectional) {
      w.u = glm::normalize(params.light.direction);
      w.t_light = -kInfinity;
    } else {
      const glm::dvec3 d = points[i] - params.light.position;
      const double length = glm::length(d);
      if (length == 0.0) continue;  // the point is the light: no path
      w.u = d / length;
      w.t_light = -length;
    }
    // Lines that meet the box only beyond the point or before the light
    // have nothing on their way.
    if (!ClipToBox(w.p, w.u, box, w.t_in, w.t_out) || w.t_in >= 0.0 || w.t_out <= w.t_light) continue;
    active.push_back(i);
  }

  // Each round casts every line still crossing from its last crossing on,
  // in one batch over the worker threads. A crossing is placed within
  // `error` of where it is.
  auto cross = [&](Walk& w, double t, double error, int group, bool entering) {
    if (entering) {
      if (w.winding[group]++ == 0) {
        w.entered_at[group] = t;
        w.entered_error[group] = error;
      }
      return;
    }
    if (w.winding[group] == 0) {
      w.ambiguous = true;  // out of an absorber it never entered
      return;
    }
    if (--w.winding[group] > 0) return;
    const double lo = std::max(w.entered_at[group], w.t_light), hi = std::min(t, 0.0);
    if (hi > lo) w.depth += sigma[group] * (hi - lo);
    // An end within its error of [t_light, 0] may have moved the length by
    // up to that error.
    auto counted = [&](double at, double e) { return at >= w.t_light - e && at <= e ? e : 0.0; };
    w.error += sigma[group] * (counted(w.entered_at[group], w.entered_error[group]) + counted(t, error));
  };
  raycast::TraceOptions trace;
  trace.stop = params.job.stop;
  for (int round = 0; !active.empty(); ++round) {
    VISQ_RETURN_IF_ERROR(params.job.stop.Check("transmittance rays"));
    if (round == kMostCrossings) {
      for (size_t i : active) walks[i].ambiguous = true;
      break;
    }
    std::vector<raycast::Ray> rays;
    rays.reserve(active.size());
    for (size_t i : active) {
      const Walk& w = walks[i];
      rays.push_back({w.p + (w.t_in + w.travelled) * w.u, w.u, w.t_out - w.t_in - w.travelled});
    }
    VISQ_ASSIGN_OR_RETURN(const std::vector<raycast::Hit> hits, embree.Intersect(rays, trace));
    std::vector<size_t> still;
    for (size_t k = 0; k < active.size(); ++k) {
      Walk& w = walks[active[k]];
      if (!hits[k].hit) continue;
      w.travelled += hits[k].t;
      const uint32_t t = hits[k].triangle;
      const glm::dvec3 normal = glm::cross(absorbers.Vertex(t, 1) - absorbers.Vertex(t, 0),
                                           absorbers.Vertex(t, 2) - absorbers.Vertex(t, 0));
      const double facing = glm::dot(normal, w.u);
      if (facing == 0.0) w.ambiguous = true;  // along the triangle's plane: neither in nor out
      // The float ray is off the double one by about 2^-23 of the magnitude
      // sideways, which moves a crossing along the ray by that over the
      // sine of the angle to the surface: grazing crossings are placed the
      // least well.
      const double sine = std::abs(facing) / glm::length(normal);
      const double error = offset * std::max(1.0, 0x1p-5 / std::max(sine, 1e-300));
      cross(w, w.t_in + w.travelled, error, group_of_node[rays_of.node_of_triangle[t]], facing < 0.0);
      // Past the point and every absorber left: nothing more to learn.
      const bool all_out = std::all_of(w.winding.begin(), w.winding.end(), [](int n) { return n == 0; });
      if (w.t_in + w.travelled > 0.0 && all_out) continue;
      still.push_back(active[k]);
    }
    active = std::move(still);
  }

  double sigma_sum = 0.0;
  for (double s : sigma) sigma_sum += s;
  for (size_t i = 0; i < points.size(); ++i) {
    Walk& w = walks[i];
    for (int n : w.winding) w.ambiguous = w.ambiguous || n != 0;  // a line must leave what it entered
    double upper = w.depth + w.error, width = 2.0 * w.error;
    if (w.ambiguous) {
      // The whole interval: every coefficient over the path inside the box.
      const double inside = std::max(0.0, std::min(0.0, w.t_out) - std::max(w.t_light, w.t_in));
      upper = sigma_sum * inside;
      width = upper;
      result.ambiguous[i] = 1;
      ++result.ambiguous_columns;
    }
    result.optical_depth[i] = FloatAtLeast(upper);
    result.optical_depth_error[i] = FloatAtLeast(width + (double(result.optical_depth[i]) - upper));
    result.transmittance[i] = static_cast<float>(std::exp(-double(result.optical_depth[i])));
  }
  result.error_statement = fmt::format(
      "each point's own ray from the light, cast against the absorbers (Embree, every crossing in order, inside "
      "and outside by the triangles' facing): the exact optical depth lies in [optical_depth - "
      "optical_depth_error, optical_depth], {:.3g} world units per crossing (2^-17 of the coordinates' magnitude "
      "around the absorbers; more where the ray grazes a surface); absorber parts thinner than that can be missed, "
      "and surfaces closer than that along the line count as one crossing. {} point(s) flagged ambiguous (a "
      "line that did not leave what it entered: open, two-sided or inverted absorbers) state the whole interval "
      "[0, the coefficients' sum x the path inside the absorbers' box]; absorbers that touch flag the points behind "
      "them",
      offset, result.ambiguous_columns);
  result.timings.total_ms = MillisecondsSince(start);
  return result;
}

}  // namespace visq::voxel_reference
