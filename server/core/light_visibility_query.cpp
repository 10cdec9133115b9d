#include "core/light_visibility_query.h"

#include <chrono>
#include <cmath>

#include "core/engine.h"

namespace visq {
namespace {

bool Finite(const glm::dvec3& v) { return std::isfinite(v.x) && std::isfinite(v.y) && std::isfinite(v.z); }

}  // namespace

Status CheckLightVisibilityQuery(const LightVisibilityQuery& query, const Scene& scene) {
  if (query.points.empty()) return absl::InvalidArgumentError("points: empty");
  if (query.points.size() > kMaxLightVisibilityPoints)
    return absl::ResourceExhaustedError(absl::StrCat("points: ", query.points.size(), " exceeds the cap of ",
                                                     kMaxLightVisibilityPoints,
                                                     " per request (use LightVisibilityStream)"));
  if (query.light.vertices.size() > kMaxLightVertices)
    return absl::ResourceExhaustedError(absl::StrCat("light.vertices: ", query.light.vertices.size(),
                                                     " exceeds the cap of ", kMaxLightVertices));
  VISQ_RETURN_IF_ERROR(exact::ValidateAreaLight(query.light));  // after the vertex cap: it is quadratic
  if (!std::isfinite(query.light.radiance) || query.light.radiance < 0)
    return absl::InvalidArgumentError(absl::StrCat("radiance: ", query.light.radiance, " is not a finite value >= 0"));
  for (size_t i = 0; i < query.points.size(); ++i) {
    const auto& p = query.points[i];
    if (!Finite(p.position)) return absl::InvalidArgumentError(absl::StrCat("points[", i, "].position: NaN or Inf"));
    if (p.normal && (!Finite(*p.normal) || glm::dot(*p.normal, *p.normal) == 0.0))
      return absl::InvalidArgumentError(absl::StrCat("points[", i, "].normal: zero, NaN or Inf"));
    if (p.receiver_triangle && *p.receiver_triangle >= scene.TriangleCount())
      return absl::InvalidArgumentError(absl::StrCat("points[", i, "].triangle: ", *p.receiver_triangle,
                                                     " out of range (", scene.TriangleCount(), " triangles)"));
  }
  if (query.receiver_region) {
    const Bounds& r = *query.receiver_region;
    if (!Finite(r.min) || !Finite(r.max) || r.min.x > r.max.x || r.min.y > r.max.y || r.min.z > r.max.z)
      return absl::InvalidArgumentError("receiver_region: min must be finite and <= max");
    for (size_t i = 0; i < query.points.size(); ++i) {
      const glm::dvec3& q = query.points[i].position;
      if (glm::any(glm::lessThan(q, r.min)) || glm::any(glm::greaterThan(q, r.max)))
        return absl::InvalidArgumentError(absl::StrCat("points[", i, "]: outside receiver_region"));
    }
  }
  return absl::OkStatus();
}

Bounds SnappedReceiverRegion(const std::vector<exact::QueryPoint>& points, const Bounds& scene_bounds) {
  Bounds batch;
  for (const auto& p : points) batch.Extend(p.position);
  const glm::dvec3 extent = scene_bounds.Empty() ? glm::dvec3(1.0) : scene_bounds.Extent();
  const double cell = std::max({extent.x, extent.y, extent.z, 1e-300}) / 16.0;
  const glm::dvec3 origin = scene_bounds.Empty() ? glm::dvec3(0.0) : scene_bounds.min;
  Bounds snapped;
  // Snap in cell units relative to the scene's corner; a point exactly on a
  // grid plane gets the cell on both sides, so it is never on the boundary.
  snapped.min = origin + glm::floor((batch.min - origin) / cell - 0.5) * cell;
  snapped.max = origin + glm::ceil((batch.max - origin) / cell + 0.5) * cell;
  return snapped;
}

StatusOr<LightVisibilityAnswer> RunLightVisibility(Engine& engine, const LightVisibilityQuery& query) {
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<const ResidentScene> resident,
                        engine.FindScene(query.scene, query.scene_version));
  const Scene& scene = *resident->scene;
  VISQ_RETURN_IF_ERROR(CheckLightVisibilityQuery(query, scene));
  const auto start = std::chrono::steady_clock::now();

  // The tree's options: the receiver region and the excluded nodes' triangles.
  exact::TreeOptions options;
  // One tree may use the whole cache, no more: past that it stops growing.
  options.max_bytes = engine.light_cache_capacity();
  options.receiver_bounds = query.receiver_region ? *query.receiver_region
                                                  : SnappedReceiverRegion(query.points, scene.bounds);
  for (const std::string& node_name : query.exclude_nodes) {
    bool found = false;
    for (const SceneNode& node : scene.nodes) {
      if (node.name != node_name) continue;
      found = true;
      for (uint32_t t = node.first_triangle; t < node.first_triangle + node.triangle_count; ++t)
        options.exclude_triangles.push_back(t);
    }
    if (!found) return absl::InvalidArgumentError(absl::StrCat("exclude_nodes: no node named '", node_name, "'"));
  }

  const exact::CacheKey key{resident->name, resident->version, exact::HashLight(query.light, options)};
  bool created = false;
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<exact::LightVisibilityTree> tree,
                        engine.light_cache().GetOrCreate(key, [&]() -> StatusOr<std::unique_ptr<exact::LightVisibilityTree>> {
                          created = true;
                          VISQ_ASSIGN_OR_RETURN(std::shared_ptr<const exact::SceneTriangleIndex> index,
                                                engine.TriangleIndexOf(*resident));
                          return exact::LightVisibilityTree::Create(query.light, scene, options, index.get());
                        }));
  (created ? engine.light_tree_misses : engine.light_tree_hits).fetch_add(1);
  VISQ_ASSIGN_OR_RETURN(std::vector<exact::PointVisibility> points,
                        tree->QueryBatch(query.points, /*threads=*/0, query.want_polygons, query.deadline));

  LightVisibilityAnswer answer;
  answer.points = std::move(points);
  answer.tree = tree->Stats();
  answer.tree_reused = !created;
  answer.receiver_region = *options.receiver_bounds;
  answer.compute_ms =
      std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
  return answer;
}

}  // namespace visq
