#include "obscurance/obscurance_update.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstddef>

#include "common/job_timing.h"
#include "common/parallel.h"
#include "obscurance/obscurance_rays.h"
#include "scene/scene_edit.h"

namespace visq::obscurance {
namespace {

// body(i) for i in [0, count) on the process's pool (`threads` > 0: on at
// most that many threads), in interleaved chunks that balance patches of
// uneven cost.
template <typename Body>
void ForEachIndex(size_t count, int threads, const Body& body) {
  ParallelFor(
      count, 32,
      [&body](size_t begin, size_t end) {
        for (size_t i = begin; i < end; ++i) body(i);
      },
      threads > 0 ? static_cast<size_t>(threads) : 0);
}

std::vector<uint32_t> SortedUnion(const std::vector<uint32_t>& a, const std::vector<uint32_t>& b) {
  std::vector<uint32_t> out;
  std::set_union(a.begin(), a.end(), b.begin(), b.end(), std::back_inserter(out));
  return out;
}

}  // namespace

ObscuranceUpdater::~ObscuranceUpdater() = default;

StatusOr<std::unique_ptr<ObscuranceUpdater>> ObscuranceUpdater::Create(Scene scene, ObscuranceAtlas atlas,
                                                                       const ObscuranceParams& params,
                                                                       ObscuranceResult baked,
                                                                       std::vector<uint32_t> dynamic_nodes,
                                                                       const UpdaterOptions& options) {
  VISQ_RETURN_IF_ERROR(ValidateParams(params));
  if (options.rays_per_patch == 0) return absl::InvalidArgumentError("rays_per_patch: 0 must be at least 1");
  if (baked.w.size() != atlas.texel_count())
    return absl::InvalidArgumentError(absl::StrCat("baked: ", baked.w.size(), " texels, atlas has ", atlas.texel_count()));
  std::unique_ptr<ObscuranceUpdater> u(new ObscuranceUpdater());
  u->scene_ = std::move(scene);
  u->atlas_ = std::move(atlas);
  u->params_ = params;
  u->options_ = options;
  u->ambient_ = ComputeAmbient(u->scene_, params.color_bleeding);
  u->result_ = std::move(baked);
  for (uint32_t node : dynamic_nodes) {
    if (node >= u->scene_.nodes.size())
      return absl::InvalidArgumentError(absl::StrCat("dynamic_nodes: node ", node, " is not a node of the scene (",
                                                     u->scene_.nodes.size(), " nodes)"));
    u->objects_.push_back(Object{node});
  }
  // Triangles per position, for the per-vertex averages.
  const Scene& s = u->scene_;
  u->vertex_begin_.assign(s.positions.size() + 1, 0);
  for (const auto& t : s.triangles)
    for (int c = 0; c < 3; ++c) ++u->vertex_begin_[t[c] + 1];
  for (size_t i = 1; i < u->vertex_begin_.size(); ++i) u->vertex_begin_[i] += u->vertex_begin_[i - 1];
  u->vertex_triangles_.resize(s.triangles.size() * 3);
  std::vector<uint32_t> cursor(u->vertex_begin_.begin(), u->vertex_begin_.end() - 1);
  for (uint32_t t = 0; t < s.triangles.size(); ++t)
    for (int c = 0; c < 3; ++c) u->vertex_triangles_[cursor[s.triangles[t][c]]++] = t;
  std::vector<uint32_t> all(u->atlas_.texel_count());
  for (uint32_t i = 0; i < all.size(); ++i) all[i] = i;
  u->patch_center_.assign(all.size(), glm::dvec3(0.0));
  u->patch_radius_.assign(all.size(), -1.0);
  u->ComputePatchBounds(all);
  VISQ_RETURN_IF_ERROR(u->Rebuild());
  return u;
}

Status ObscuranceUpdater::AddDynamicNode(uint32_t node) {
  if (node >= scene_.nodes.size())
    return absl::InvalidArgumentError(absl::StrCat("node: ", node, " is not a node of the scene (", scene_.nodes.size(),
                                                   " nodes)"));
  for (const Object& o : objects_)
    if (o.node == node) return absl::OkStatus();
  objects_.push_back(Object{node});
  return Rebuild();
}

void ObscuranceUpdater::ComputePatchBounds(const std::vector<uint32_t>& texels) {
  // A patch's world footprint: its fragments' clipped polygons mapped back
  // through each triangle's atlas-to-world map.
  for (uint32_t texel : texels) {
    const uint32_t x = texel % atlas_.width, y = texel / atlas_.width;
    glm::dvec3 lo(std::numeric_limits<double>::infinity()), hi(-std::numeric_limits<double>::infinity());
    for (uint32_t i = atlas_.texel_begin[texel]; i < atlas_.texel_begin[texel + 1]; ++i) {
      const uint32_t t = atlas_.fragments[i].triangle;
      const glm::dvec2 a = atlas_.corner_uv[3 * t], b = atlas_.corner_uv[3 * t + 1], c = atlas_.corner_uv[3 * t + 2];
      const glm::dvec3 pa = scene_.Vertex(t, 0), pb = scene_.Vertex(t, 1), pc = scene_.Vertex(t, 2);
      const double det = (b.x - a.x) * (c.y - a.y) - (b.y - a.y) * (c.x - a.x);
      if (std::abs(det) <= 1e-12) {
        for (const glm::dvec3& p : {pa, pb, pc}) { lo = glm::min(lo, p); hi = glm::max(hi, p); }
        continue;
      }
      const ClippedPolygon poly = ClipTriangleToTexel(a, b, c, x, y);
      for (int k = 0; k < poly.n; ++k) {
        const glm::dvec2 q = poly.p[k];
        const double l1 = ((q.x - a.x) * (c.y - a.y) - (q.y - a.y) * (c.x - a.x)) / det;
        const double l2 = ((b.x - a.x) * (q.y - a.y) - (b.y - a.y) * (q.x - a.x)) / det;
        const glm::dvec3 p = pa + (pb - pa) * l1 + (pc - pa) * l2;
        lo = glm::min(lo, p);
        hi = glm::max(hi, p);
      }
    }
    if (lo.x > hi.x) continue;
    patch_center_[texel] = 0.5 * (lo + hi);
    patch_radius_[texel] = 0.5 * glm::length(hi - lo);
  }
}

Status ObscuranceUpdater::Rebuild() {
  // Objects: each dynamic node's subtree triangles.
  object_of_triangle_.assign(scene_.TriangleCount(), -1);
  std::vector<std::vector<uint32_t>> triangle_lists;
  for (size_t k = 0; k < objects_.size(); ++k) {
    Object& o = objects_[k];
    o.triangles.clear();
    for (uint32_t n : SubtreeNodes(scene_, o.node))
      for (uint32_t t = scene_.nodes[n].first_triangle; t < scene_.nodes[n].first_triangle + scene_.nodes[n].triangle_count; ++t) {
        if (object_of_triangle_[t] >= 0)
          return absl::InvalidArgumentError(absl::StrCat("dynamic_nodes: node ", o.node, " overlaps the subtree of node ",
                                                         objects_[object_of_triangle_[t]].node));
        object_of_triangle_[t] = static_cast<int32_t>(k);
        o.triangles.push_back(t);
      }
    o.own.clear();
    for (uint32_t t : o.triangles)
      for (uint32_t f = atlas_.triangle_begin[t]; f < atlas_.triangle_begin[t + 1]; ++f)
        o.own.push_back(atlas_.fragments[atlas_.triangle_fragments[f]].texel);
    std::sort(o.own.begin(), o.own.end());
    o.own.erase(std::unique(o.own.begin(), o.own.end()), o.own.end());
    o.pose_at_build = scene_.nodes[o.node].world;
    triangle_lists.push_back(o.triangles);
  }
  // The spatial index over static patches; cells about d_max wide, the
  // reach of a candidate query around the moved object.
  std::vector<uint8_t> is_static(atlas_.texel_count(), 1);
  dynamic_patches_.clear();
  for (const Object& o : objects_)
    for (uint32_t texel : o.own) {
      if (is_static[texel]) dynamic_patches_.push_back(texel);
      is_static[texel] = 0;
    }
  std::sort(dynamic_patches_.begin(), dynamic_patches_.end());
  static_patches_.Build(patch_center_, patch_radius_, is_static, params_.d_max);
  VISQ_ASSIGN_OR_RETURN(rays_, InstancedRayScene::Create(scene_, triangle_lists));

  // Influenced lists: patches near each object whose rays meet it first.
  for (size_t k = 0; k < objects_.size(); ++k) {
    Object& o = objects_[k];
    const std::vector<uint32_t> candidates = Candidates(o);
    std::vector<glm::vec3> value;
    std::vector<std::vector<int32_t>> met;
    TracePatches(candidates, value, met);
    o.influenced.clear();
    for (size_t i = 0; i < candidates.size(); ++i)
      if (std::find(met[i].begin(), met[i].end(), static_cast<int32_t>(k)) != met[i].end())
        o.influenced.push_back(candidates[i]);
  }
  return absl::OkStatus();
}

std::vector<Ball> ObscuranceUpdater::ClusterBalls(const Object& object) const {
  // One bounding sphere is useless for an object spread over the scene (a
  // set of columns, say); the triangles grouped by a coarse grid over its box
  // give balls that reject most patches and rays.
  Bounds box;
  for (uint32_t t : object.triangles)
    for (int c = 0; c < 3; ++c) box.Extend(scene_.Vertex(t, c));
  if (box.Empty()) return {};
  constexpr int kCellsAlongLongestAxis = 8;
  const glm::dvec3 extent = box.Extent();
  const double cell = std::max({extent.x, extent.y, extent.z}) / kCellsAlongLongestAxis;
  glm::ivec3 cells(1);
  if (cell > 0)
    for (int a = 0; a < 3; ++a) cells[a] = std::clamp(static_cast<int>(std::ceil(extent[a] / cell)), 1, kCellsAlongLongestAxis);
  std::vector<Bounds> grouped(static_cast<size_t>(cells.x) * cells.y * cells.z);
  for (uint32_t t : object.triangles) {
    const glm::dvec3 centroid = (scene_.Vertex(t, 0) + scene_.Vertex(t, 1) + scene_.Vertex(t, 2)) / 3.0;
    glm::ivec3 at(0);
    for (int a = 0; a < 3; ++a)
      if (cell > 0) at[a] = std::clamp(static_cast<int>((centroid[a] - box.min[a]) / cell), 0, cells[a] - 1);
    Bounds& group = grouped[(static_cast<size_t>(at.z) * cells.y + at.y) * cells.x + at.x];
    for (int c = 0; c < 3; ++c) group.Extend(scene_.Vertex(t, c));
  }
  // The rays meet the object through Embree's float instance transform, so
  // each ball is a little wider than its triangles: a grazing ray that the
  // float geometry catches is never ruled out by the double-precision ball.
  const double slack = 1e-5 * glm::length(extent);
  std::vector<Ball> balls;
  for (const Bounds& group : grouped)
    if (!group.Empty()) balls.push_back(Ball{group.Center(), 0.5 * glm::length(group.Extent()) + slack});
  return balls;
}

std::vector<uint32_t> ObscuranceUpdater::Candidates(const Object& object, ObscuranceUpdate* figures) const {
  const std::vector<Ball> balls = ClusterBalls(object);
  std::vector<uint32_t> out;
  if (balls.empty()) return out;
  Ball all{glm::dvec3(0.0), 0.0};
  {
    Bounds b;
    for (const Ball& ball : balls) {
      b.Extend(ball.center - glm::dvec3(ball.radius));
      b.Extend(ball.center + glm::dvec3(ball.radius));
    }
    all = Ball{b.Center(), 0.5 * glm::length(b.Extent())};
  }
  const size_t k = static_cast<size_t>(&object - objects_.data());
  // Patches within d_max of the object's balls, minus its own.
  // The pool: every texel (the plain path) or the static patches whose
  // cells meet the reach of the object's balls, and the dynamic patches.
  std::vector<uint32_t> pool;
  if (options_.exhaustive) {
    pool.resize(atlas_.texel_count());
    for (uint32_t texel = 0; texel < pool.size(); ++texel) pool[texel] = texel;
  } else {
    const glm::dvec3 reach(all.radius + params_.d_max);
    static_patches_.Query(all.center - reach, all.center + reach, pool);
    pool = SortedUnion(pool, dynamic_patches_);
  }
  std::vector<uint32_t> near;
  for (uint32_t texel : pool) {
    if (patch_radius_[texel] < 0) continue;
    if (glm::length(patch_center_[texel] - all.center) > all.radius + params_.d_max + patch_radius_[texel]) continue;
    if (std::binary_search(object.own.begin(), object.own.end(), texel)) continue;
    near.push_back(texel);
  }
  if (figures != nullptr) {
    figures->pooled = static_cast<uint32_t>(pool.size());
    figures->within_reach = static_cast<uint32_t>(near.size());
  }
  // Keep those with a ray that meets the object alone within d_max. Tests,
  // cheapest first: balls in reach of the patch and in front of some of its
  // triangles; ray directions towards one of them (origins are computed only
  // for those); the ray against the balls; the ray against the object.
  std::vector<uint8_t> keep(near.size(), 0);
  ForEachIndex(near.size(), options_.threads, [&](size_t i) {
    const uint32_t texel = near[i];
    thread_local std::vector<Ball> in_reach;
    thread_local std::vector<glm::dvec4> planes;
    planes.clear();
    for (uint32_t f = atlas_.texel_begin[texel]; f < atlas_.texel_begin[texel + 1]; ++f) {
      const uint32_t t = atlas_.fragments[f].triangle;
      const glm::dvec3 pa = scene_.Vertex(t, 0);
      const glm::dvec3 n = glm::cross(scene_.Vertex(t, 1) - pa, scene_.Vertex(t, 2) - pa);
      const double length = glm::length(n);
      // A degenerate triangle sends rays anywhere: a plane no ball is behind.
      planes.push_back(length > 0 ? glm::dvec4(n / length, -glm::dot(n / length, pa)) : glm::dvec4(0, 0, 0, 1e300));
    }
    in_reach.clear();
    for (const Ball& ball : balls) {
      if (glm::length(patch_center_[texel] - ball.center) > ball.radius + params_.d_max + patch_radius_[texel]) continue;
      // Rays leave each triangle into its front half-space.
      bool in_front_of_one = false;
      for (const glm::dvec4& plane : planes)
        in_front_of_one |= glm::dot(glm::dvec3(plane), ball.center) + plane.w >= -ball.radius;
      if (in_front_of_one) in_reach.push_back(ball);
    }
    if (in_reach.empty()) return;
    thread_local std::vector<PatchRay> patch_rays;
    const DirectionFilter towards_object{patch_center_[texel], patch_radius_[texel], in_reach};
    GeneratePatchRays(scene_, atlas_, texel, options_.seed, options_.rays_per_patch, patch_rays, &towards_object);
    for (const PatchRay& r : patch_rays) {
      bool may_meet = false;
      for (const Ball& ball : in_reach) {
        const glm::dvec3 oc = ball.center - r.origin;
        const double along = glm::dot(oc, r.direction);
        if (glm::dot(oc, oc) - along * along > ball.radius * ball.radius) continue;
        if (along + ball.radius < 0 || along - ball.radius > params_.d_max) continue;
        may_meet = true;
        break;
      }
      // One ray at a time on both paths: the first hit ends the patch's
      // search, and a stream's packet traversal rounds grazing rays
      // through the instance transform differently from a single ray's,
      // which would make the fast path's lists differ from the plain one's.
      if (may_meet && rays_->HitsObject(k, r.origin, r.direction, params_.d_max)) {
        keep[i] = 1;
        break;
      }
    }
  });
  for (size_t i = 0; i < near.size(); ++i)
    if (keep[i]) out.push_back(near[i]);
  return out;
}

void ObscuranceUpdater::TracePatches(const std::vector<uint32_t>& texels, std::vector<glm::vec3>& value,
                                     std::vector<std::vector<int32_t>>& met) const {
  value.assign(texels.size(), glm::vec3(0.0f));
  met.assign(texels.size(), {});
  ForEachIndex(texels.size(), options_.threads, [&](size_t i) {
    thread_local std::vector<PatchRay> patch_rays;
    GeneratePatchRays(scene_, atlas_, texels[i], options_.seed, options_.rays_per_patch, patch_rays);
    thread_local std::vector<InstancedRayScene::Hit> hits;
    hits.resize(patch_rays.size());
    if (!options_.ray_streams) {
      for (size_t j = 0; j < patch_rays.size(); ++j)
        hits[j] = rays_->Closest(patch_rays[j].origin, patch_rays[j].direction, params_.d_max);
    } else {
      rays_->ClosestStream(patch_rays, params_.d_max, hits);
    }
    glm::dvec3 sum(0.0);
    for (size_t j = 0; j < patch_rays.size(); ++j) {
      const InstancedRayScene::Hit& hit = hits[j];
      sum += RayValue(scene_, ambient_, params_.color_bleeding, params_.d_max, hit.hit, hit.t, hit.triangle);
      if (hit.hit && hit.object >= 0 && std::find(met[i].begin(), met[i].end(), hit.object) == met[i].end())
        met[i].push_back(hit.object);
    }
    if (!patch_rays.empty()) value[i] = glm::vec3(sum / static_cast<double>(patch_rays.size()));
  });
}

StatusOr<ObscuranceUpdate> ObscuranceUpdater::MoveNode(uint32_t node, const glm::dmat4& new_world) {
  const auto start = std::chrono::steady_clock::now();
  if (node >= scene_.nodes.size())
    return absl::InvalidArgumentError(absl::StrCat("node: ", node, " is not a node of the scene (", scene_.nodes.size(),
                                                   " nodes)"));
  for (int c = 0; c < 4; ++c)
    for (int r = 0; r < 4; ++r)
      if (!std::isfinite(new_world[c][r]))
        return absl::InvalidArgumentError(absl::StrCat("matrix: element [", c, "][", r, "] is not finite"));
  size_t k = objects_.size();
  for (size_t i = 0; i < objects_.size(); ++i)
    if (objects_[i].node == node) k = i;
  if (k == objects_.size()) {
    VISQ_RETURN_IF_ERROR(AddDynamicNode(node));
    k = objects_.size() - 1;
  }
  Object& object = objects_[k];
  ObscuranceUpdate update;
  update.influenced_before = static_cast<uint32_t>(object.influenced.size());

  // Move the geometry: scene positions (for ray origins on the object) and
  // the instance transform (for the rays).
  VISQ_RETURN_IF_ERROR(MoveNodeSubtree(scene_, node, new_world));
  rays_->SetTransform(k, new_world * glm::inverse(object.pose_at_build));
  rays_->Commit();
  ComputePatchBounds(object.own);
  const auto moved = std::chrono::steady_clock::now();
  update.move_ms = MillisecondsBetween(start, moved);

  // Recompute: old list, own patches, and patches whose rays meet the object now.
  const std::vector<uint32_t> fresh = Candidates(object, &update);
  update.candidates = static_cast<uint32_t>(fresh.size());
  update.own_patches = static_cast<uint32_t>(object.own.size());
  const std::vector<uint32_t> must = SortedUnion(object.influenced, object.own);
  const std::vector<uint32_t> recompute = SortedUnion(must, fresh);
  const auto found = std::chrono::steady_clock::now();
  update.candidates_ms = MillisecondsBetween(moved, found);
  std::vector<glm::vec3> value;
  std::vector<std::vector<int32_t>> met;
  TracePatches(recompute, value, met);
  update.trace_ms = MillisecondsSince(found);
  update.recomputed = static_cast<uint32_t>(recompute.size());
  update.rays = static_cast<uint64_t>(recompute.size()) * options_.rays_per_patch;

  // A fresh candidate whose full-scene rays all met something else first did
  // not change: it keeps its bits. The lists of every dynamic object follow
  // what the recomputed patches now meet.
  std::vector<uint32_t> changed;
  std::vector<std::vector<uint32_t>> add(objects_.size()), drop(objects_.size());
  for (size_t i = 0; i < recompute.size(); ++i) {
    const uint32_t texel = recompute[i];
    const bool meets = std::find(met[i].begin(), met[i].end(), static_cast<int32_t>(k)) != met[i].end();
    if (!meets && !std::binary_search(must.begin(), must.end(), texel)) continue;
    changed.push_back(texel);
    // A patch the bake's samples never reached (a sliver of a triangle in a
    // texel; depth peeling leaves such texels filled from their neighbours)
    // stays filled, as a rebake leaves it; its gutter neighbours then agree
    // with the rebake's too. After a ray-cast bake every patch is estimated.
    if (result_.estimated[texel]) {
      result_.w[texel] = value[i];
      if (texel < result_.texel_effective_samples.size())
        result_.texel_effective_samples[texel] = static_cast<float>(options_.rays_per_patch);
    }
    for (size_t j = 0; j < objects_.size(); ++j) {
      if (std::binary_search(objects_[j].own.begin(), objects_[j].own.end(), texel)) continue;
      const bool now = std::find(met[i].begin(), met[i].end(), static_cast<int32_t>(j)) != met[i].end();
      (now ? add[j] : drop[j]).push_back(texel);
    }
  }
  for (size_t j = 0; j < objects_.size(); ++j) {
    std::vector<uint32_t> kept;
    std::set_difference(objects_[j].influenced.begin(), objects_[j].influenced.end(), drop[j].begin(), drop[j].end(),
                        std::back_inserter(kept));
    objects_[j].influenced = SortedUnion(kept, add[j]);
  }
  update.influenced_after = static_cast<uint32_t>(object.influenced.size());

  // Filled texels next to changed patches take the new neighbour values;
  // a gutter texel reads filled texels with surface too (FilledValue), so
  // the neighbours of those are refilled after them.
  std::vector<uint32_t> texels = changed;
  const glm::dvec3 unoccluded = UnoccludedValue(ambient_, params_.color_bleeding);
  auto add_filled_neighbours = [&](uint32_t texel) {
    const int x = static_cast<int>(texel % atlas_.width), y = static_cast<int>(texel / atlas_.width);
    for (int dy = -1; dy <= 1; ++dy)
      for (int dx = -1; dx <= 1; ++dx) {
        const int nx = x + dx, ny = y + dy;
        if (nx < 0 || ny < 0 || nx >= static_cast<int>(atlas_.width) || ny >= static_cast<int>(atlas_.height)) continue;
        const uint32_t j = static_cast<uint32_t>(ny) * atlas_.width + static_cast<uint32_t>(nx);
        if (!result_.estimated[j]) texels.push_back(j);
      }
  };
  for (uint32_t texel : changed) add_filled_neighbours(texel);
  const size_t first_ring = texels.size();
  for (size_t i = 0; i < first_ring; ++i)
    if (!result_.estimated[texels[i]] && atlas_.Covered(texels[i])) add_filled_neighbours(texels[i]);
  std::sort(texels.begin(), texels.end());
  texels.erase(std::unique(texels.begin(), texels.end()), texels.end());
  RefillTexels(atlas_, result_, texels, unoccluded);
  for (uint32_t texel : texels) {
    result_.intensity[texel] =
        atlas_.Covered(texel) ? glm::vec3(TexelReflectivity(scene_, atlas_, texel) * result_.ambient.ambient_intensity *
                                          glm::dvec3(result_.w[texel]))
                              : glm::vec3(0.0f);
    update.texels.push_back(texel);
    update.w.push_back(result_.w[texel]);
    update.intensity.push_back(result_.intensity[texel]);
  }
  // Triangle and vertex averages over the changed texels.
  for (uint32_t texel : texels)
    for (uint32_t f = atlas_.texel_begin[texel]; f < atlas_.texel_begin[texel + 1]; ++f)
      update.triangles.push_back(atlas_.fragments[f].triangle);
  std::sort(update.triangles.begin(), update.triangles.end());
  update.triangles.erase(std::unique(update.triangles.begin(), update.triangles.end()), update.triangles.end());
  // Each such triangle by rays of its own (its texels' mean would mix in
  // the neighbours that share them): as many as its texels got, for its
  // area in texels, from one patch's worth up to kMostTexelsPerTriangle.
  constexpr double kMostTexelsPerTriangle = 16;
  if (result_.triangle_effective_samples.size() != scene_.TriangleCount())
    result_.triangle_effective_samples.resize(scene_.TriangleCount(), 0.0f);
  std::vector<glm::vec3> own(update.triangles.size());
  std::vector<uint32_t> own_rays(update.triangles.size(), 0);
  ForEachIndex(update.triangles.size(), options_.threads, [&](size_t i) {
    thread_local std::vector<PatchRay> triangle_rays;
    const uint32_t t = update.triangles[i];
    const glm::dvec2 a = atlas_.corner_uv[3 * t], b = atlas_.corner_uv[3 * t + 1], c = atlas_.corner_uv[3 * t + 2];
    const double texels = 0.5 * std::abs((b.x - a.x) * (c.y - a.y) - (b.y - a.y) * (c.x - a.x));
    const uint32_t n = static_cast<uint32_t>(
        std::lround(options_.rays_per_patch * std::clamp(std::round(texels), 1.0, kMostTexelsPerTriangle)));
    GenerateTriangleRays(scene_, t, options_.seed, n, triangle_rays);
    glm::dvec3 sum(0.0);
    for (const PatchRay& r : triangle_rays) {
      const InstancedRayScene::Hit hit = rays_->Closest(r.origin, r.direction, params_.d_max);
      sum += RayValue(scene_, ambient_, params_.color_bleeding, params_.d_max, hit.hit, hit.t, hit.triangle);
    }
    own_rays[i] = static_cast<uint32_t>(triangle_rays.size());
    if (!triangle_rays.empty()) own[i] = glm::vec3(sum / static_cast<double>(triangle_rays.size()));
  });
  for (size_t i = 0; i < update.triangles.size(); ++i) {
    const uint32_t t = update.triangles[i];
    result_.triangle_w[t] = own_rays[i] > 0 ? own[i] : TriangleAverage(atlas_, result_, t);
    result_.triangle_effective_samples[t] = static_cast<float>(own_rays[i]);
    update.triangle_w.push_back(result_.triangle_w[t]);
    update.rays += own_rays[i];
    for (int c = 0; c < 3; ++c) update.vertices.push_back(scene_.triangles[t][c]);
  }
  std::sort(update.vertices.begin(), update.vertices.end());
  update.vertices.erase(std::unique(update.vertices.begin(), update.vertices.end()), update.vertices.end());
  for (uint32_t v : update.vertices) {
    glm::dvec3 sum(0.0);
    double area = 0;
    for (uint32_t i = vertex_begin_[v]; i < vertex_begin_[v + 1]; ++i) {
      const uint32_t t = vertex_triangles_[i];
      const double a = 0.5 * glm::length(glm::cross(scene_.Vertex(t, 1) - scene_.Vertex(t, 0),
                                                    scene_.Vertex(t, 2) - scene_.Vertex(t, 0)));
      sum += a * glm::dvec3(result_.triangle_w[t]);
      area += a;
    }
    result_.vertex_w[v] = area > 0 ? glm::vec3(sum / area) : glm::vec3(0.0f);
    update.vertex_w.push_back(result_.vertex_w[v]);
  }
  update.milliseconds = MillisecondsSince(start);
  return update;
}

std::vector<uint32_t> ObscuranceUpdater::InfluencedPatches(uint32_t node) const {
  for (const Object& o : objects_)
    if (o.node == node) return o.influenced;
  return {};
}

std::vector<uint32_t> ObscuranceUpdater::OwnPatches(uint32_t node) const {
  for (const Object& o : objects_)
    if (o.node == node) return o.own;
  return {};
}

}  // namespace visq::obscurance
