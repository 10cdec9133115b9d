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

// Whether a ray can pass through one of the balls within d_max.
bool MayMeetABall(const PatchRay& r, const std::vector<Ball>& balls, double d_max) {
  for (const Ball& ball : balls) {
    const glm::dvec3 oc = ball.center - r.origin;
    const double along = glm::dot(oc, r.direction);
    if (glm::dot(oc, oc) - along * along > ball.radius * ball.radius) continue;
    if (along + ball.radius < 0 || along - ball.radius > d_max) continue;
    return true;
  }
  return false;
}

// The planes of a texel's triangles: its rays leave each into its front
// half-space.
void TexelPlanes(const std::vector<glm::dvec4>& triangle_plane, const ObscuranceAtlas& atlas, uint32_t texel,
                 std::vector<glm::dvec4>& planes);

// One ball around a few.
Ball Enclosing(const std::vector<Ball>& balls) {
  Bounds b;
  for (const Ball& ball : balls) {
    b.Extend(ball.center - glm::dvec3(ball.radius));
    b.Extend(ball.center + glm::dvec3(ball.radius));
  }
  return Ball{b.Center(), 0.5 * glm::length(b.Extent())};
}

// The plane of a triangle (unit normal, offset); a degenerate triangle
// sends rays anywhere: a plane no ball is behind.
glm::dvec4 TrianglePlane(const Scene& scene, uint32_t t) {
  const glm::dvec3 pa = scene.Vertex(t, 0);
  const glm::dvec3 n = glm::cross(scene.Vertex(t, 1) - pa, scene.Vertex(t, 2) - pa);
  const double length = glm::length(n);
  return length > 0 ? glm::dvec4(n / length, -glm::dot(n / length, pa)) : glm::dvec4(0, 0, 0, 1e300);
}

void TexelPlanes(const std::vector<glm::dvec4>& triangle_plane, const ObscuranceAtlas& atlas, uint32_t texel,
                 std::vector<glm::dvec4>& planes) {
  planes.clear();
  for (uint32_t f = atlas.texel_begin[texel]; f < atlas.texel_begin[texel + 1]; ++f)
    planes.push_back(triangle_plane[atlas.fragments[f].triangle]);
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
  // The updater moves nodes and reads vertices by index: it keeps the
  // scene flattened.
  u->scene_ = scene.placements.empty() ? std::move(scene) : Scene(scene.Flattened());
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
  u->patch_center_.assign(u->atlas_.texel_count(), glm::dvec3(0.0));
  u->patch_radius_.assign(u->atlas_.texel_count(), -1.0);
  for (uint32_t texel = 0; texel < u->atlas_.texel_count(); ++texel) u->ComputePatchBound(texel);
  u->triangle_plane_.resize(s.triangles.size());
  for (uint32_t t = 0; t < s.triangles.size(); ++t) u->triangle_plane_[t] = TrianglePlane(s, t);
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
  for (uint32_t texel : texels) ComputePatchBound(texel);
}

void ObscuranceUpdater::ComputePatchBound(uint32_t texel) {
  // A patch's world footprint: its fragments' clipped polygons mapped back
  // through each triangle's atlas-to-world map.
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
  if (lo.x > hi.x) return;
  patch_center_[texel] = 0.5 * (lo + hi);
  patch_radius_[texel] = 0.5 * glm::length(hi - lo);
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
  // Their tallies are kept: every patch with a ray that meets a dynamic
  // object alone then has one, which the fast path's moves rely on.
  patch_tally_.Reset(atlas_.texel_count());
  triangle_tally_.Reset(scene_.TriangleCount());
  for (size_t k = 0; k < objects_.size(); ++k) {
    Object& o = objects_[k];
    const std::vector<uint32_t> candidates = Candidates(o);
    std::vector<uint32_t> untraced;
    for (uint32_t texel : candidates)
      if (!patch_tally_.Contains(texel)) untraced.push_back(texel);
    std::vector<RayTally> tallies = TracePatches(untraced);
    for (size_t i = 0; i < untraced.size(); ++i) patch_tally_.Set(untraced[i], std::move(tallies[i]));
    o.influenced.clear();
    for (uint32_t texel : candidates)
      if (patch_tally_.At(texel).FirstHits(static_cast<int32_t>(k)) > 0) o.influenced.push_back(texel);
  }
  return absl::OkStatus();
}

void ObscuranceUpdater::RayTally::Add(const glm::dvec3& value, int32_t object, int sign) {
  // Values are at most 1 per channel (rho times a reflectivity); the clamp
  // only keeps a hostile material from overflowing the integer.
  for (int c = 0; c < 3; ++c) {
    sum[c] += sign * static_cast<int64_t>(std::llround(std::clamp(value[c], -1048576.0, 1048576.0) * kFixedOne));
    sum_of_squares[c] += sign * static_cast<int64_t>(std::llround(std::min(value[c] * value[c], 1.0) * kFixedOne));
  }
  if (object < 0) return;
  for (auto& [o, count] : first_hits)
    if (o == object) {
      count += sign;
      return;
    }
  first_hits.emplace_back(object, sign);
}

int32_t ObscuranceUpdater::RayTally::FirstHits(int32_t object) const {
  for (const auto& [o, count] : first_hits)
    if (o == object) return count;
  return 0;
}

float ObscuranceUpdater::RayTally::Variance() const {
  if (rays < 2) return -1.0f;
  glm::dvec3 sums, squares;
  for (int c = 0; c < 3; ++c) {
    sums[c] = static_cast<double>(sum[c]) / kFixedOne;
    // Each fixed-point term is within 2^-33 of its value, so the variance
    // from the sums is within 2^-31 n / (n - 1) of the values' own: raising
    // the squares by 2^-31 a ray covers it.
    squares[c] = static_cast<double>(sum_of_squares[c]) / kFixedOne + 0x1p-31 * rays;
  }
  return LargestChannelVariance(sums, squares, rays);
}

glm::vec3 ObscuranceUpdater::RayTally::Mean() const {
  if (rays == 0) return glm::vec3(0.0f);
  glm::dvec3 mean;
  for (int c = 0; c < 3; ++c) mean[c] = static_cast<double>(sum[c]) / kFixedOne / rays;
  return glm::vec3(mean);
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
  const Ball all = Enclosing(balls);
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
    TexelPlanes(triangle_plane_, atlas_, texel, planes);
    BallsInReach(patch_center_[texel], patch_radius_[texel], planes, balls, in_reach);
    if (in_reach.empty()) return;
    thread_local std::vector<PatchRay> patch_rays;
    const DirectionFilter towards_object{patch_center_[texel], patch_radius_[texel], in_reach};
    GeneratePatchRays(scene_, atlas_, texel, options_.seed, options_.rays_per_patch, patch_rays, &towards_object);
    for (const PatchRay& r : patch_rays) {
      // One ray at a time: the first hit ends the patch's search, and a
      // stream's packet traversal rounds grazing rays through the instance
      // transform differently from a single ray's.
      if (MayMeetABall(r, in_reach, params_.d_max) && rays_->HitsObject(k, r.origin, r.direction, params_.d_max)) {
        keep[i] = 1;
        break;
      }
    }
  });
  for (size_t i = 0; i < near.size(); ++i)
    if (keep[i]) out.push_back(near[i]);
  return out;
}

ObscuranceUpdater::RayTally ObscuranceUpdater::TraceRays(const std::vector<PatchRay>& rays) const {
  thread_local std::vector<InstancedRayScene::Hit> hits;
  hits.resize(rays.size());
  if (!options_.ray_streams) {
    for (size_t j = 0; j < rays.size(); ++j) hits[j] = rays_->Closest(rays[j].origin, rays[j].direction, params_.d_max);
  } else {
    rays_->ClosestStream(rays, params_.d_max, hits);
  }
  RayTally tally;
  tally.rays = static_cast<uint32_t>(rays.size());
  for (const InstancedRayScene::Hit& hit : hits)
    tally.Add(RayValue(scene_, ambient_, params_.color_bleeding, params_.d_max, hit.hit, hit.t, hit.triangle),
              hit.hit ? hit.object : -1, +1);
  return tally;
}

std::vector<ObscuranceUpdater::RayTally> ObscuranceUpdater::TracePatches(const std::vector<uint32_t>& texels) const {
  std::vector<RayTally> out(texels.size());
  ForEachIndex(texels.size(), options_.threads, [&](size_t i) {
    thread_local std::vector<PatchRay> patch_rays;
    GeneratePatchRays(scene_, atlas_, texels[i], options_.seed, options_.rays_per_patch, patch_rays);
    out[i] = TraceRays(patch_rays);
  });
  return out;
}

uint32_t ObscuranceUpdater::TriangleRayCount(uint32_t t) const {
  // As many rays as its texels got, for its area in texels: a triangle's
  // W then has a patch's noise or less, and a large triangle costs at most
  // kMostTexelsPerTriangle patches' worth.
  constexpr double kMostTexelsPerTriangle = 16;
  const glm::dvec2 a = atlas_.corner_uv[3 * t], b = atlas_.corner_uv[3 * t + 1], c = atlas_.corner_uv[3 * t + 2];
  const double texels = 0.5 * std::abs((b.x - a.x) * (c.y - a.y) - (b.y - a.y) * (c.x - a.x));
  return static_cast<uint32_t>(
      std::lround(options_.rays_per_patch * std::clamp(std::round(texels), 1.0, kMostTexelsPerTriangle)));
}

void ObscuranceUpdater::BallsInReach(const glm::dvec3& center, double radius, const std::vector<glm::dvec4>& planes,
                                     const std::vector<Ball>& balls, std::vector<Ball>& out) const {
  out.clear();
  for (const Ball& ball : balls) {
    const glm::dvec3 offset = center - ball.center;
    const double reach = ball.radius + params_.d_max + radius;
    if (glm::dot(offset, offset) > reach * reach) continue;
    bool in_front_of_one = false;
    for (const glm::dvec4& plane : planes)
      in_front_of_one |= glm::dot(glm::dvec3(plane), ball.center) + plane.w >= -ball.radius;
    if (in_front_of_one) out.push_back(ball);
  }
}

void ObscuranceUpdater::FindAffectedRays(size_t k, const std::vector<PatchRay>& rays, const std::vector<Ball>& old_balls,
                                         const std::vector<Ball>& new_balls, Retrace& out, uint64_t& traced) const {
  // A ray that meets the object alone at neither pose keeps its first hit.
  for (const PatchRay& r : rays) {
    const bool was = MayMeetABall(r, old_balls, params_.d_max) && rays_->HitsObject(k, r.origin, r.direction, params_.d_max);
    const bool now = MayMeetABall(r, new_balls, params_.d_max) && rays_->HitsProbe(k, r.origin, r.direction, params_.d_max);
    if (!was && !now) continue;
    out.meets_now |= now;
    out.rays.push_back(r);
    if (out.tally == nullptr) continue;
    // The Embree scene still holds the object where it was: the ray's old value leaves the tally.
    const InstancedRayScene::Hit hit = rays_->Closest(r.origin, r.direction, params_.d_max);
    out.tally->Add(RayValue(scene_, ambient_, params_.color_bleeding, params_.d_max, hit.hit, hit.t, hit.triangle),
                   hit.hit ? hit.object : -1, -1);
    ++traced;
  }
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
  VISQ_ASSIGN_OR_RETURN(ObscuranceUpdate update, options_.exhaustive ? MoveNodePlain(k, new_world)
                                                                     : MoveNodeFast(k, new_world));
  update.milliseconds = MillisecondsSince(start);
  return update;
}

Status ObscuranceUpdater::MoveObjectPositions(size_t k, const glm::dmat4& new_world, ObscuranceUpdate& update) {
  Object& object = objects_[k];
  update.influenced_before = static_cast<uint32_t>(object.influenced.size());
  update.own_patches = static_cast<uint32_t>(object.own.size());
  VISQ_RETURN_IF_ERROR(MoveNodeSubtree(scene_, object.node, new_world));
  ComputePatchBounds(object.own);
  for (uint32_t t : object.triangles) triangle_plane_[t] = TrianglePlane(scene_, t);
  return absl::OkStatus();
}

StatusOr<ObscuranceUpdate> ObscuranceUpdater::MoveNodePlain(size_t k, const glm::dmat4& new_world) {
  const auto start = std::chrono::steady_clock::now();
  Object& object = objects_[k];
  ObscuranceUpdate update;

  // Move the geometry: scene positions (for ray origins on the object) and
  // the instance transform (for the rays).
  VISQ_RETURN_IF_ERROR(MoveObjectPositions(k, new_world, update));
  rays_->SetTransform(k, new_world * glm::inverse(object.pose_at_build));
  rays_->Commit();
  const auto moved = std::chrono::steady_clock::now();
  update.move_ms = MillisecondsBetween(start, moved);

  // Recompute in full: old list, own patches, and patches whose rays meet the object now.
  const std::vector<uint32_t> fresh = Candidates(object, &update);
  update.candidates = static_cast<uint32_t>(fresh.size());
  const std::vector<uint32_t> must = SortedUnion(object.influenced, object.own);
  const std::vector<uint32_t> recompute = SortedUnion(must, fresh);
  const auto found = std::chrono::steady_clock::now();
  update.candidates_ms = MillisecondsBetween(moved, found);
  std::vector<RayTally> tallies = TracePatches(recompute);
  update.trace_ms = MillisecondsSince(found);
  update.recomputed = static_cast<uint32_t>(recompute.size());

  // A fresh candidate whose rays all met something else first did not
  // change: it keeps its bits.
  std::vector<uint32_t> changed;
  for (size_t i = 0; i < recompute.size(); ++i) {
    const uint32_t texel = recompute[i];
    update.rays += tallies[i].rays;
    const bool meets = tallies[i].FirstHits(static_cast<int32_t>(k)) > 0;
    patch_tally_.Set(texel, std::move(tallies[i]));
    if (meets || std::binary_search(must.begin(), must.end(), texel)) changed.push_back(texel);
  }
  Finish(k, changed, update);
  return update;
}

namespace {

// The ball around a triangle's corners, from its centroid.
Ball TriangleBall(const Scene& scene, uint32_t t) {
  const glm::dvec3 pa = scene.Vertex(t, 0), pb = scene.Vertex(t, 1), pc = scene.Vertex(t, 2);
  const glm::dvec3 center = (pa + pb + pc) / 3.0;
  return {center, std::max({glm::length(pa - center), glm::length(pb - center), glm::length(pc - center)})};
}

// Whether a ball (an element) lies within d_max of one of `reach`.
bool WithinReach(const Ball& element, const std::vector<Ball>& reach, double d_max) {
  for (const Ball& all : reach)
    if (glm::length(element.center - all.center) <= all.radius + d_max + element.radius) return true;
  return false;
}

}  // namespace

ObscuranceUpdater::MoveBalls::MoveBalls(std::vector<Ball> before, std::vector<Ball> after)
    : old_balls(std::move(before)), new_balls(std::move(after)) {
  if (!old_balls.empty()) old_bound.push_back(Enclosing(old_balls));
  if (!new_balls.empty()) new_bound.push_back(Enclosing(new_balls));
  reach = old_bound;
  reach.insert(reach.end(), new_bound.begin(), new_bound.end());
}

std::vector<uint32_t> ObscuranceUpdater::PatchesNearMove(const Object& object, const MoveBalls& balls,
                                                         ObscuranceUpdate& update) const {
  std::vector<uint32_t> near;
  if (balls.reach.empty()) return near;
  std::vector<uint32_t> pool;
  for (const Ball& all : balls.reach) {
    std::vector<uint32_t> found;
    const glm::dvec3 reach(all.radius + params_.d_max);
    static_patches_.Query(all.center - reach, all.center + reach, found);
    pool = SortedUnion(pool, found);
  }
  pool = SortedUnion(pool, dynamic_patches_);
  update.pooled = static_cast<uint32_t>(pool.size());
  for (uint32_t texel : pool) {
    if (patch_radius_[texel] < 0) continue;
    if (!WithinReach({patch_center_[texel], patch_radius_[texel]}, balls.reach, params_.d_max)) continue;
    if (std::binary_search(object.own.begin(), object.own.end(), texel)) continue;
    near.push_back(texel);
  }
  update.within_reach = static_cast<uint32_t>(near.size());
  return near;
}

std::vector<uint32_t> ObscuranceUpdater::TrianglesNearMove(size_t k, const std::vector<uint32_t>& near,
                                                           const MoveBalls& balls) const {
  const int32_t kk = static_cast<int32_t>(k);
  std::vector<uint32_t> triangles;
  for (const std::vector<uint32_t>* texels : {&near, &objects_[k].own})
    for (uint32_t texel : *texels)
      for (uint32_t f = atlas_.texel_begin[texel]; f < atlas_.texel_begin[texel + 1]; ++f) {
        const uint32_t t = atlas_.fragments[f].triangle;
        if (object_of_triangle_[t] != kk && triangle_tally_.Contains(t)) triangles.push_back(t);
      }
  std::sort(triangles.begin(), triangles.end());
  triangles.erase(std::unique(triangles.begin(), triangles.end()), triangles.end());
  std::erase_if(triangles,
                [&](uint32_t t) { return !WithinReach(TriangleBall(scene_, t), balls.reach, params_.d_max); });
  return triangles;
}

void ObscuranceUpdater::SearchAffectedRays(size_t k, const MoveBalls& balls, std::vector<Retrace>& patches,
                                           std::vector<Retrace>& triangles, ObscuranceUpdate& update) {
  std::vector<uint64_t> probed(patches.size() + triangles.size(), 0), traced_before(probed.size(), 0);
  auto search = [&](Retrace& rec, const Ball& element, const std::vector<glm::dvec4>& planes, bool triangle,
                    size_t slot) {
    // The ball around all of a pose's balls first: most patches are out of
    // its reach, and then of every one of them.
    thread_local std::vector<Ball> in_old, in_new, in_either;
    in_old.clear();
    in_new.clear();
    BallsInReach(element.center, element.radius, planes, balls.old_bound, in_old);
    if (!in_old.empty()) BallsInReach(element.center, element.radius, planes, balls.old_balls, in_old);
    BallsInReach(element.center, element.radius, planes, balls.new_bound, in_new);
    if (!in_new.empty()) BallsInReach(element.center, element.radius, planes, balls.new_balls, in_new);
    if (in_old.empty() && in_new.empty()) return;
    in_either = in_old;
    in_either.insert(in_either.end(), in_new.begin(), in_new.end());
    thread_local std::vector<Ball> bounds;
    bounds.clear();
    if (in_either.size() > 2) {
      if (!in_old.empty()) bounds.push_back(Enclosing(in_old));
      if (!in_new.empty()) bounds.push_back(Enclosing(in_new));
    }
    const DirectionFilter towards_object{element.center, element.radius, in_either, bounds};
    thread_local std::vector<PatchRay> rays;
    if (triangle)
      GenerateTriangleRays(scene_, rec.element, options_.seed, TriangleRayCount(rec.element), rays, &towards_object);
    else
      GeneratePatchRays(scene_, atlas_, rec.element, options_.seed, options_.rays_per_patch, rays, &towards_object);
    probed[slot] = rays.size();
    FindAffectedRays(k, rays, in_old, in_new, rec, traced_before[slot]);
  };
  ForEachIndex(patches.size(), options_.threads, [&](size_t i) {
    Retrace& rec = patches[i];
    rec.tally = patch_tally_.Find(rec.element);
    thread_local std::vector<glm::dvec4> planes;
    TexelPlanes(triangle_plane_, atlas_, rec.element, planes);
    search(rec, {patch_center_[rec.element], patch_radius_[rec.element]}, planes, false, i);
  });
  ForEachIndex(triangles.size(), options_.threads, [&](size_t i) {
    Retrace& rec = triangles[i];
    rec.tally = triangle_tally_.Find(rec.element);
    const std::vector<glm::dvec4> planes = {triangle_plane_[rec.element]};
    search(rec, TriangleBall(scene_, rec.element), planes, true, patches.size() + i);
  });
  for (size_t i = 0; i < probed.size(); ++i) {
    update.probed_rays += probed[i];
    update.rays += traced_before[i];
    if (i >= patches.size()) update.triangle_rays += traced_before[i];
  }
}

std::vector<uint32_t> ObscuranceUpdater::RetraceAfterMove(size_t k, std::vector<Retrace>& patches,
                                                          std::vector<Retrace>& triangles, ObscuranceUpdate& update) {
  const Object& object = objects_[k];
  std::vector<uint32_t> full;
  std::vector<uint32_t> retraced;
  for (const Retrace& rec : patches) {
    if (rec.rays.empty()) continue;
    update.candidates += rec.meets_now;
    if (rec.tally != nullptr) retraced.push_back(rec.element);
    else if (rec.meets_now) full.push_back(rec.element);
  }
  for (uint32_t texel : object.influenced)
    if (!std::binary_search(retraced.begin(), retraced.end(), texel)) full.push_back(texel);
  std::sort(full.begin(), full.end());
  full = SortedUnion(full, object.own);
  std::vector<uint64_t> traced_after(patches.size() + triangles.size(), 0);
  auto add_new_values = [&](Retrace& rec, size_t slot) {
    if (rec.tally == nullptr) return;
    for (const PatchRay& r : rec.rays) {
      const InstancedRayScene::Hit hit = rays_->Closest(r.origin, r.direction, params_.d_max);
      rec.tally->Add(RayValue(scene_, ambient_, params_.color_bleeding, params_.d_max, hit.hit, hit.t, hit.triangle),
                     hit.hit ? hit.object : -1, +1);
    }
    traced_after[slot] = rec.rays.size();
  };
  ForEachIndex(patches.size(), options_.threads, [&](size_t i) { add_new_values(patches[i], i); });
  ForEachIndex(triangles.size(), options_.threads, [&](size_t i) { add_new_values(triangles[i], patches.size() + i); });
  std::vector<RayTally> tallies = TracePatches(full);
  for (size_t i = 0; i < traced_after.size(); ++i) {
    update.rays += traced_after[i];
    if (i >= patches.size()) update.triangle_rays += traced_after[i];
  }
  for (size_t i = 0; i < full.size(); ++i) {
    update.rays += tallies[i].rays;
    patch_tally_.Set(full[i], std::move(tallies[i]));
  }
  update.recomputed = static_cast<uint32_t>(retraced.size() + full.size());
  return SortedUnion(retraced, full);
}

StatusOr<ObscuranceUpdate> ObscuranceUpdater::MoveNodeFast(size_t k, const glm::dmat4& new_world) {
  const auto start = std::chrono::steady_clock::now();
  Object& object = objects_[k];
  ObscuranceUpdate update;

  // Move the scene positions (rays leaving the object start there) and the
  // probe; the Embree scene keeps the object where it was until the old
  // values of the affected rays are traced.
  std::vector<Ball> old_balls = ClusterBalls(object);
  VISQ_RETURN_IF_ERROR(MoveObjectPositions(k, new_world, update));
  const MoveBalls balls(std::move(old_balls), ClusterBalls(object));
  const glm::dmat4 delta = new_world * glm::inverse(object.pose_at_build);
  rays_->SetProbeTransform(k, delta);
  const auto moved = std::chrono::steady_clock::now();
  update.move_ms = MillisecondsBetween(start, moved);

  // The pool: static patches whose cells meet the reach of the old or new
  // balls, and the patches on dynamic objects; kept: those within d_max of
  // either, minus the object's own. Triangles with tallies near the object
  // (its own are traced in full): every point within reach lies in a near
  // patch or one of the object's own, so their fragments name them all.
  const std::vector<uint32_t> near = PatchesNearMove(object, balls, update);
  const std::vector<uint32_t> near_triangles = TrianglesNearMove(k, near, balls);

  // Each near element's rays towards the old or new balls, tested against
  // the object alone at both poses; the affected rays' old values leave the
  // tallies now, while the scene still holds the object where it was.
  std::vector<Retrace> patch_retrace(near.size()), triangle_retrace(near_triangles.size());
  for (size_t i = 0; i < near.size(); ++i) patch_retrace[i].element = near[i];
  for (size_t i = 0; i < near_triangles.size(); ++i) triangle_retrace[i].element = near_triangles[i];
  SearchAffectedRays(k, balls, patch_retrace, triangle_retrace, update);

  // Move the object in the Embree scene; the affected rays' new values join
  // the tallies. A patch without a tally whose rays meet the object now,
  // the object's own patches, and (should the search have missed one) a
  // patch of the old list not re-traced, are traced in full.
  rays_->SetTransform(k, delta);
  rays_->Commit();
  const auto found = std::chrono::steady_clock::now();
  update.candidates_ms = MillisecondsBetween(moved, found);
  const std::vector<uint32_t> recomputed = RetraceAfterMove(k, patch_retrace, triangle_retrace, update);
  update.trace_ms = MillisecondsSince(found);

  // Changed: the old list, the own patches, and those whose rays meet the
  // object first now.
  const int32_t kk = static_cast<int32_t>(k);
  std::vector<uint32_t> meets;
  for (uint32_t texel : recomputed)
    if (patch_tally_.At(texel).FirstHits(kk) > 0) meets.push_back(texel);
  Finish(k, SortedUnion(SortedUnion(object.influenced, object.own), meets), update);
  return update;
}

void ObscuranceUpdater::Finish(size_t k, const std::vector<uint32_t>& changed, ObscuranceUpdate& update) {
  // New W of the changed patches. The lists of every dynamic object follow
  // what their rays now meet first.
  std::vector<std::vector<uint32_t>> add(objects_.size()), drop(objects_.size());
  for (uint32_t texel : changed) {
    const RayTally& tally = patch_tally_.At(texel);
    // A patch the bake's samples never reached (a sliver of a triangle in a
    // texel; depth peeling leaves such texels filled from their neighbours)
    // stays filled, as a rebake leaves it; its gutter neighbours then agree
    // with the rebake's too. After a ray-cast bake every patch is estimated.
    if (result_.estimated[texel]) {
      result_.w[texel] = tally.Mean();
      if (texel < result_.texel_effective_samples.size())
        result_.texel_effective_samples[texel] = static_cast<float>(options_.rays_per_patch);
      // Over a depth-peeling bake, the recomputed patches' variance is known
      // and the others' is not.
      if (result_.texel_sample_variance.size() != result_.w.size())
        result_.texel_sample_variance.assign(result_.w.size(), -1.0f);
      result_.texel_sample_variance[texel] = tally.Variance();
      // Its rays are the update's, not one in each of the bake's strata.
      if (texel < result_.texel_stratum_variance.size()) result_.texel_stratum_variance[texel] = -1.0f;
    }
    for (size_t j = 0; j < objects_.size(); ++j) {
      if (std::binary_search(objects_[j].own.begin(), objects_[j].own.end(), texel)) continue;
      (tally.FirstHits(static_cast<int32_t>(j)) > 0 ? add[j] : drop[j]).push_back(texel);
    }
  }
  for (size_t j = 0; j < objects_.size(); ++j) {
    std::vector<uint32_t> kept;
    std::set_difference(objects_[j].influenced.begin(), objects_[j].influenced.end(), drop[j].begin(), drop[j].end(),
                        std::back_inserter(kept));
    objects_[j].influenced = SortedUnion(kept, add[j]);
  }
  update.influenced_after = static_cast<uint32_t>(objects_[k].influenced.size());

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

  // Each triangle touching a changed texel by rays of its own (its texels'
  // mean would mix in the neighbours that share them). The plain path, the
  // moved object's triangles, and triangles without a tally trace them in
  // full; the fast path's other tallies are current (their affected rays
  // were re-traced with the patches').
  const auto triangles_start = std::chrono::steady_clock::now();
  for (uint32_t texel : texels)
    for (uint32_t f = atlas_.texel_begin[texel]; f < atlas_.texel_begin[texel + 1]; ++f)
      update.triangles.push_back(atlas_.fragments[f].triangle);
  std::sort(update.triangles.begin(), update.triangles.end());
  update.triangles.erase(std::unique(update.triangles.begin(), update.triangles.end()), update.triangles.end());
  const int32_t kk = static_cast<int32_t>(k);
  // The moved object's tallies not recomputed below are out of date.
  for (uint32_t t : objects_[k].triangles)
    if (!std::binary_search(update.triangles.begin(), update.triangles.end(), t)) triangle_tally_.Erase(t);
  std::vector<uint32_t> full;
  for (uint32_t t : update.triangles)
    if (options_.exhaustive || object_of_triangle_[t] == kk || !triangle_tally_.Contains(t)) full.push_back(t);
  std::vector<RayTally> tallies(full.size());
  ForEachIndex(full.size(), options_.threads, [&](size_t i) {
    thread_local std::vector<PatchRay> triangle_rays;
    GenerateTriangleRays(scene_, full[i], options_.seed, TriangleRayCount(full[i]), triangle_rays);
    tallies[i] = TraceRays(triangle_rays);
  });
  for (size_t i = 0; i < full.size(); ++i) {
    update.rays += tallies[i].rays;
    update.triangle_rays += tallies[i].rays;
    triangle_tally_.Set(full[i], std::move(tallies[i]));
  }
  if (result_.triangle_effective_samples.size() != scene_.TriangleCount())
    result_.triangle_effective_samples.resize(scene_.TriangleCount(), 0.0f);
  if (result_.triangle_sample_variance.size() != scene_.TriangleCount())
    result_.triangle_sample_variance.assign(scene_.TriangleCount(), -1.0f);
  for (uint32_t t : update.triangles) {
    const RayTally& tally = triangle_tally_.At(t);
    result_.triangle_w[t] = tally.rays > 0 ? tally.Mean() : TriangleAverage(atlas_, result_, t);
    result_.triangle_effective_samples[t] = static_cast<float>(tally.rays);
    result_.triangle_sample_variance[t] = tally.Variance();
    update.triangle_w.push_back(result_.triangle_w[t]);
    for (int c = 0; c < 3; ++c) update.vertices.push_back(scene_.triangles[t][c]);
  }
  update.triangles_ms = MillisecondsSince(triangles_start);
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
