#include "obscurance/obscurance_rays.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <numbers>
#include <optional>
#include <span>
#include <type_traits>

#include "common/random.h"
#include "raycast/embree_scene.h"

namespace visq::obscurance {
namespace {

// Where, in the square of CosineDirection's (u_radius, azimuth in turns),
// lie the directions a DirectionFilter may pass, for one frame: a few
// windows, each a range of u_radius (the squared sine of the polar angle)
// and an arc of azimuths, found from the cone each ball subtends. A sample
// outside every window fails the filter, so it is skipped before its
// direction is computed; one inside is still tested. The windows are wider
// than the cones by kWindowMargin radians, far above the rounding of the
// angle-sum azimuth.
struct DirectionWindows {
  static constexpr int kMost = 8;
  static constexpr double kWindowMargin = 1e-7;
  bool all = true;
  int count = 0;
  struct Window {
    double u_lo = 0, u_hi = 1, turn_lo = 0, turn_width = 1;
  } w[kMost];

  bool Contains(double u_radius, double turn) const {
    if (all) return true;
    for (int i = 0; i < count; ++i) {
      const Window& x = w[i];
      if (u_radius < x.u_lo || u_radius > x.u_hi) continue;
      double d = turn - x.turn_lo;
      if (d < 0) d += 1.0;
      if (d <= x.turn_width) return true;
    }
    return false;
  }

  static DirectionWindows Of(const DirectionFilter* filter, const glm::dvec3& tu, const glm::dvec3& tv,
                             const glm::dvec3& normal) {
    if (filter == nullptr) return DirectionWindows{};
    // The bounds' cones when they are far enough, else the targets'.
    DirectionWindows out = Of(filter->bounds, *filter, tu, tv, normal);
    if (out.all || filter->bounds.empty()) out = Of(filter->targets, *filter, tu, tv, normal);
    return out;
  }

  static DirectionWindows Of(std::span<const Ball> balls, const DirectionFilter& filter_ref, const glm::dvec3& tu,
                             const glm::dvec3& tv, const glm::dvec3& normal) {
    DirectionWindows out;
    const DirectionFilter* filter = &filter_ref;
    if (balls.empty() || balls.size() > kMost) return out;
    constexpr double kPi = std::numbers::pi, m = kWindowMargin;
    auto sin2 = [](double a) { return std::sin(a) * std::sin(a); };
    for (const Ball& ball : balls) {
      const glm::dvec3 v = ball.center - filter->patch_center;
      const double distance = glm::length(v), reach = ball.radius + filter->patch_radius;
      // Close by, MayMeet also passes some directions away from the ball.
      if (!(distance > 2.0 * reach)) return out;
      const double theta = std::asin(reach / distance);
      const double alpha = std::acos(std::clamp(glm::dot(v, normal) / distance, -1.0, 1.0));
      Window x;
      if (alpha - theta - m > 0.5 * kPi) continue;  // wholly below the horizon
      x.u_hi = alpha + theta + m >= 0.5 * kPi ? 1.0 : sin2(alpha + theta + m);
      if (alpha - theta - m > 0) {
        x.u_lo = sin2(alpha - theta - m);
        const double ratio = std::sin(theta) / std::sin(alpha);
        if (ratio < 1) {
          const double half = (std::asin(ratio) + m) / (2.0 * kPi);
          const double center = std::atan2(glm::dot(v, tv), glm::dot(v, tu)) / (2.0 * kPi);
          x.turn_lo = center - half - std::floor(center - half);
          x.turn_width = 2.0 * half;
        }
      }
      out.w[out.count++] = x;
    }
    out.all = false;
    return out;
  }
};

// What every ray leaving one fragment shares: its triangle's corners, the
// fragment's clipped atlas polygon split into a fan, and the tangent frame.
// Computed once per fragment, not once per ray.
struct FragmentSampler {
  uint32_t triangle = 0;
  glm::dvec2 a{0.0}, b{0.0}, c{0.0};
  glm::dvec3 pa{0.0}, pb{0.0}, pc{0.0};
  double det = 0;
  ClippedPolygon poly;
  double fan[8] = {};
  double fan_total = 0;
  glm::dvec3 normal{0.0}, tu{0.0}, tv{0.0};
  DirectionWindows windows;
};

// The frame is all a direction needs; the clipped polygon is prepared only
// when a ray from the fragment is kept.
void PrepareFrame(const Scene& placed_scene, const ObscuranceAtlas& atlas, const PatchFragment& f, FragmentSampler& out) {
  const Scene& scene = placed_scene.Flattened();
  const uint32_t t = f.triangle;
  out.triangle = t;
  out.a = atlas.corner_uv[3 * t];
  out.b = atlas.corner_uv[3 * t + 1];
  out.c = atlas.corner_uv[3 * t + 2];
  out.pa = scene.Vertex(t, 0);
  out.pb = scene.Vertex(t, 1);
  out.pc = scene.Vertex(t, 2);
  out.normal = glm::normalize(glm::cross(out.pb - out.pa, out.pc - out.pa));
  const glm::dvec3 helper = std::abs(out.normal.x) < 0.9 ? glm::dvec3(1, 0, 0) : glm::dvec3(0, 1, 0);
  out.tu = glm::normalize(glm::cross(helper, out.normal));
  out.tv = glm::cross(out.normal, out.tu);
}

void PreparePolygon(uint32_t x, uint32_t y, FragmentSampler& out) {
  const glm::dvec2 a = out.a, b = out.b, c = out.c;
  out.det = (b.x - a.x) * (c.y - a.y) - (b.y - a.y) * (c.x - a.x);
  out.fan_total = 0;
  if (std::abs(out.det) > 1e-12) {
    out.poly = ClipTriangleToTexel(a, b, c, x, y);
    for (int k = 1; k + 1 < out.poly.n; ++k) {
      const glm::dvec2 e1 = out.poly.p[k] - out.poly.p[0], e2 = out.poly.p[k + 1] - out.poly.p[0];
      out.fan[k] = 0.5 * std::abs(e1.x * e2.y - e1.y * e2.x);
      out.fan_total += out.fan[k];
    }
  }
}

// What a thread keeps of its scratch between patches: a texel of many
// fragments, or many rays, would otherwise hold the thread's largest
// patch's buffers for the life of the process (they are thread_local), out
// of the work budget's sight.
inline constexpr size_t kKeptScratchBytes = size_t{1} << 20;
template <typename... Vectors>
void ReleaseLargeScratch(Vectors&... vectors) {
  auto release = [](auto& v) {
    if (v.capacity() * sizeof(v[0]) > kKeptScratchBytes) std::remove_reference_t<decltype(v)>().swap(v);
  };
  (release(vectors), ...);
}

// Ray j of n takes its direction from cell j of n equal cells of the square
// of (u_radius, turn) (EqualAreaCellOf), computed once per n and thread.
const std::vector<EqualAreaCell>& DirectionCells(uint32_t n) {
  thread_local std::vector<std::pair<uint32_t, std::vector<EqualAreaCell>>> kept;
  for (const auto& [count, cells] : kept)
    if (count == n) return cells;
  if (kept.size() >= 32) kept.erase(kept.begin());
  std::vector<EqualAreaCell> cells(n);
  for (uint32_t j = 0; j < n; ++j) cells[j] = EqualAreaCellOf(n, j);
  kept.emplace_back(n, std::move(cells));
  return kept.back().second;
}

// The uniforms of one ray: its own stream, independent of every other ray's.
SplitMix RayStream(uint64_t element_hash, uint32_t j) { return SplitMix{SplitMix64(element_hash + j)}; }

// A unit direction in the frame (tu, tv, normal), cosine-distributed for
// (u_radius, turn) uniform in the unit square: sin^2 of the polar angle and
// the azimuth in turns.
glm::dvec3 CosineDirection(const glm::dvec3& tu, const glm::dvec3& tv, const glm::dvec3& normal, double u_radius,
                           double turn) {
  const double r = std::sqrt(u_radius), phi = 2.0 * std::numbers::pi * turn;
  return tu * (r * std::cos(phi)) + tv * (r * std::sin(phi)) + normal * std::sqrt(std::max(0.0, 1.0 - u_radius));
}

}  // namespace

void GeneratePatchRays(const Scene& placed_scene, const ObscuranceAtlas& atlas, uint32_t texel, uint64_t seed, uint32_t n,
                       std::vector<PatchRay>& out, const DirectionFilter* only_towards) {
  const Scene& scene = placed_scene.Flattened();
  out.clear();
  const uint32_t begin = atlas.texel_begin[texel], end = atlas.texel_begin[texel + 1];
  if (begin == end) return;
  // Running sums of the fragments' areas: a sample picks its fragment by a
  // binary search (a texel can hold many small triangles' fragments).
  thread_local std::vector<double> area_below;
  area_below.resize(end - begin + 1);
  area_below[0] = 0;
  for (uint32_t i = begin; i < end; ++i) area_below[i - begin + 1] = area_below[i - begin] + atlas.fragments[i].world_area;
  const double total = area_below[end - begin];
  const uint64_t h = SplitMix64(SplitMix64(seed) ^ (static_cast<uint64_t>(texel) * 0xD1B54A32D192ED03ull));
  const std::vector<EqualAreaCell>& cells = DirectionCells(n);
  const uint32_t x = texel % atlas.width, y = texel / atlas.width;
  // A sampler for each fragment a ray picks: at most n of them, however
  // many fragments the texel holds (a texel under a million tiny triangles
  // grew a sampler per fragment, some 700 bytes each, kept by the thread).
  // Reused, not re-constructed, from patch to patch: constructing them cost
  // more than the patch's filtered rays.
  thread_local std::vector<FragmentSampler> samplers;
  thread_local std::vector<uint32_t> slot_of;  // per fragment: its sampler's index + 1; 0: none yet
  thread_local std::vector<uint8_t> prepared;  // per sampler; bit 0: frame, bit 1: polygon
  slot_of.assign(end - begin, 0);
  uint32_t slots_used = 0;
  out.reserve(n);
  for (uint32_t j = 0; j < n; ++j) {
    SplitMix uniforms = RayStream(h, j);
    // A fragment in proportion to its world area, then a fan triangle of
    // its clipped polygon in proportion to atlas area (affine per triangle).
    const double pick = uniforms.Uniform() * total;
    // The last fragment whose running sum is at most `pick`, the last one at most.
    const size_t above = static_cast<size_t>(std::upper_bound(area_below.begin() + 1, area_below.end() - 1, pick) -
                                             area_below.begin());
    const uint32_t fi = begin + static_cast<uint32_t>(above - 1);
    uint32_t& slot = slot_of[fi - begin];
    if (slot == 0) {
      if (slots_used == samplers.size()) samplers.emplace_back();
      if (slots_used == prepared.size()) prepared.push_back(0);
      prepared[slots_used] = 0;
      slot = ++slots_used;
    }
    FragmentSampler& f = samplers[slot - 1];
    uint8_t& ready = prepared[slot - 1];
    if (!(ready & 1)) {
      PrepareFrame(scene, atlas, atlas.fragments[fi], f);
      f.windows = DirectionWindows::Of(only_towards, f.tu, f.tv, f.normal);
      ready |= 1;
    }
    // Cosine-distributed direction around the geometric normal, from the
    // ray's own cell of the direction square.
    const EqualAreaCell& cell = cells[j];
    const double u_radius = cell.x0 + cell.width * uniforms.Uniform();
    const double turn = cell.y0 + cell.height * uniforms.Uniform();
    if (!f.windows.Contains(u_radius, turn)) continue;
    const double u_fan = uniforms.Uniform(), u1 = uniforms.Uniform(), u2 = uniforms.Uniform();
    const glm::dvec3 dir = CosineDirection(f.tu, f.tv, f.normal, u_radius, turn);
    if (only_towards != nullptr && !only_towards->MayMeet(dir)) continue;
    if (!(ready & 2)) {
      PreparePolygon(x, y, f);
      ready |= 2;
    }
    glm::dvec3 point;
    if (std::abs(f.det) <= 1e-12) {
      // Degenerate in the atlas: the whole triangle is this patch.
      const double s = std::sqrt(u1);
      point = f.pa * (1 - s) + f.pb * (s * (1 - u2)) + f.pc * (s * u2);
    } else {
      const ClippedPolygon& poly = f.poly;
      double fp = u_fan * f.fan_total;
      int k = 1;
      for (; k + 2 < poly.n && fp >= f.fan[k]; ++k) fp -= f.fan[k];
      const double s = std::sqrt(u1);
      const glm::dvec2 q = poly.n >= 3 ? poly.p[0] * (1 - s) + poly.p[k] * (s * (1 - u2)) + poly.p[k + 1] * (s * u2)
                                       : (f.a + f.b + f.c) / 3.0;
      // Barycentrics of q in the atlas triangle map it to the world.
      const glm::dvec2 a = f.a, b = f.b, c = f.c;
      const double l1 = ((q.x - a.x) * (c.y - a.y) - (q.y - a.y) * (c.x - a.x)) / f.det;
      const double l2 = ((b.x - a.x) * (q.y - a.y) - (b.y - a.y) * (q.x - a.x)) / f.det;
      point = f.pa + (f.pb - f.pa) * l1 + (f.pc - f.pa) * l2;
    }
    out.push_back(PatchRay{point, dir, f.triangle});
  }
  ReleaseLargeScratch(area_below, slot_of, samplers, prepared);
}

void GenerateTriangleRays(const Scene& placed_scene, uint32_t triangle, uint64_t seed, uint32_t n, std::vector<PatchRay>& out,
                          const DirectionFilter* only_towards) {
  const Scene& scene = placed_scene.Flattened();
  out.clear();
  const glm::dvec3 pa = scene.Vertex(triangle, 0), pb = scene.Vertex(triangle, 1), pc = scene.Vertex(triangle, 2);
  const glm::dvec3 cross = glm::cross(pb - pa, pc - pa);
  const double length = glm::length(cross);
  if (!(length > 0)) return;
  const glm::dvec3 normal = cross / length;
  const glm::dvec3 helper = std::abs(normal.x) < 0.9 ? glm::dvec3(1, 0, 0) : glm::dvec3(0, 1, 0);
  const glm::dvec3 tu = glm::normalize(glm::cross(helper, normal)), tv = glm::cross(normal, tu);
  // Its rays' streams, hashed apart from the texels'.
  const uint64_t h = SplitMix64(SplitMix64(seed ^ 0x7472692E72617973ull) ^ (uint64_t{triangle} * 0x9E3779B97F4A7C15ull));
  const std::vector<EqualAreaCell>& cells = DirectionCells(n);
  out.reserve(n);
  const DirectionWindows windows = DirectionWindows::Of(only_towards, tu, tv, normal);
  for (uint32_t j = 0; j < n; ++j) {
    SplitMix uniforms = RayStream(h, j);
    const EqualAreaCell& cell = cells[j];
    const double u_radius = cell.x0 + cell.width * uniforms.Uniform();
    const double turn = cell.y0 + cell.height * uniforms.Uniform();
    if (!windows.Contains(u_radius, turn)) continue;
    const double u1 = uniforms.Uniform(), u2 = uniforms.Uniform();
    const glm::dvec3 dir = CosineDirection(tu, tv, normal, u_radius, turn);
    if (only_towards != nullptr && !only_towards->MayMeet(dir)) continue;
    const double s = std::sqrt(u1);
    const glm::dvec3 point = pa * (1 - s) + pb * (s * (1 - u2)) + pc * (s * u2);
    out.push_back(PatchRay{point, dir, triangle});
  }
}

StatusOr<std::vector<glm::vec3>> EstimateTriangleObscuranceByRays(const Scene& placed_scene, const ObscuranceParams& params,
                                                                   const RayEstimateOptions& options) {
  const Scene& scene = placed_scene.Flattened();
  VISQ_RETURN_IF_ERROR(ValidateParams(params));
  if (options.rays_per_patch == 0) return absl::InvalidArgumentError("rays_per_patch: 0 must be at least 1");
  VISQ_ASSIGN_OR_RETURN(raycast::EmbreeScene embree, raycast::EmbreeScene::Create(scene));
  const AmbientModel ambient = ComputeAmbient(scene, params.color_bleeding);
  const uint32_t nt = static_cast<uint32_t>(scene.TriangleCount());
  std::vector<glm::vec3> w(nt, glm::vec3(0.0f));
  constexpr uint32_t kBatchTriangles = 2048;
  std::vector<PatchRay> triangle_rays;
  std::vector<raycast::Ray> rays;
  for (uint32_t first = 0; first < nt; first += kBatchTriangles) {
    rays.clear();
    const uint32_t end = std::min(nt, first + kBatchTriangles);
    std::vector<uint32_t> begin(end - first + 1, 0);
    for (uint32_t t = first; t < end; ++t) {
      GenerateTriangleRays(scene, t, options.seed, options.rays_per_patch, triangle_rays);
      for (const PatchRay& r : triangle_rays) rays.push_back(raycast::Ray{r.origin, r.direction, params.d_max, t});
      begin[t - first + 1] = static_cast<uint32_t>(rays.size());
    }
    if (rays.empty()) continue;
    raycast::TraceOptions trace;
    trace.threads = options.threads;
    VISQ_ASSIGN_OR_RETURN(std::vector<raycast::Hit> hits, embree.Intersect(rays, trace));
    for (uint32_t t = first; t < end; ++t) {
      const uint32_t b = begin[t - first], e = begin[t - first + 1];
      if (b == e) continue;
      glm::dvec3 sum(0.0);
      for (uint32_t i = b; i < e; ++i)
        sum += RayValue(scene, ambient, params.color_bleeding, params.d_max, hits[i].hit, hits[i].t, hits[i].triangle);
      w[t] = glm::vec3(sum / static_cast<double>(e - b));
    }
  }
  return w;
}

namespace {

// Shifted to start at patch_center, a ray that passes within r of a ball's
// center passes within r + patch_radius of it.
bool MayMeetOne(std::span<const Ball> balls, const glm::dvec3& patch_center, double patch_radius,
                const glm::dvec3& direction) {
  for (const Ball& ball : balls) {
    const double reach = ball.radius + patch_radius;
    const glm::dvec3 to_target = ball.center - patch_center;
    const double along = glm::dot(to_target, direction);
    if (along < -reach) continue;
    if (glm::dot(to_target, to_target) - along * along <= reach * reach) return true;
  }
  return false;
}

// ObscuranceResult::texel_stratum_variance of a texel's `rays` values, one
// in each stratum in order: half the mean squared difference over the pairs
// of neighbouring strata, the largest channel's, rounded up to a float; -1
// without a pair.
float StratumVariance(const glm::dvec3* values, uint32_t rays) {
  glm::dvec3 squares(0.0);
  uint32_t pairs = 0;
  ForEachStratumPair(rays, [&](uint32_t j) {
    const glm::dvec3 d = values[j] - values[j + 1];
    squares += d * d;
    ++pairs;
  });
  if (pairs == 0) return -1.0f;
  const double largest = std::max({squares.x, squares.y, squares.z}) / (2.0 * pairs);
  const float f = static_cast<float>(largest);
  return static_cast<double>(f) < largest ? std::nextafter(f, 2.0f) : f;
}

}  // namespace

bool DirectionFilter::MayMeet(const glm::dvec3& direction) const {
  if (!bounds.empty() && !MayMeetOne(bounds, patch_center, patch_radius, direction)) return false;
  return MayMeetOne(targets, patch_center, patch_radius, direction);
}

glm::dvec3 RayValue(const Scene& placed_scene, const AmbientModel& ambient, bool color_bleeding, double d_max, bool hit,
                    double distance, uint32_t hit_triangle) {
  const Scene& scene = placed_scene.Flattened();
  if (!hit || distance >= d_max) return UnoccludedValue(ambient, color_bleeding);
  const double rho = Rho(distance, d_max);
  if (!color_bleeding) return glm::dvec3(rho);
  return rho * scene.materials[scene.triangle_material[hit_triangle]].reflectivity;
}

uint32_t RayEstimateBatchTexels(uint32_t rays_per_patch) {
  return static_cast<uint32_t>(std::clamp<uint64_t>(kRayEstimateBatchRays / std::max(rays_per_patch, 1u), 1, 4096));
}

uint64_t RayEstimateBatchBytes(uint32_t rays_per_patch) {
  const uint64_t texels = RayEstimateBatchTexels(rays_per_patch);
  const uint64_t rays = texels * rays_per_patch;
  return rays * (sizeof(raycast::Ray) + sizeof(uint32_t) + sizeof(raycast::Hit) + sizeof(glm::dvec3)) +
         texels * (2 * sizeof(glm::dvec3) + sizeof(uint32_t) + sizeof(double) + sizeof(size_t));
}

uint64_t PatchRayScratchBytes(uint32_t n, uint64_t fragments) {
  return uint64_t{n} * (sizeof(PatchRay) + sizeof(FragmentSampler) + 1) +
         (fragments + 1) * (sizeof(double) + sizeof(uint32_t)) + uint64_t{n} * sizeof(EqualAreaCell);
}

StatusOr<ObscuranceResult> EstimateObscurancesByRays(const Scene& placed_scene, const ObscuranceAtlas& atlas,
                                                     const ObscuranceParams& params,
                                                     const RayEstimateOptions& options) {
  const Scene& scene = placed_scene.Flattened();
  VISQ_RETURN_IF_ERROR(ValidateParams(params));
  if (options.rays_per_patch == 0)
    return absl::InvalidArgumentError("rays_per_patch: 0 must be at least 1");
  std::optional<raycast::EmbreeScene> embree;
  if (!options.closest_hits) {
    VISQ_ASSIGN_OR_RETURN(raycast::EmbreeScene own, raycast::EmbreeScene::Create(scene));
    embree.emplace(std::move(own));
  }
  const AmbientModel ambient = ComputeAmbient(scene, params.color_bleeding);
  const uint32_t n = atlas.texel_count();
  std::vector<glm::vec3> w(n, glm::vec3(0.0f));
  std::vector<uint8_t> estimated(n, 0);
  // Texels in batches of about kRayEstimateBatchRays rays: generate them,
  // trace them in one Intersect call. Sized by rays, not texels: 4,096
  // texels a batch were 35 GB of rays at 65,536 rays a patch.
  const uint32_t kBatchTexels = RayEstimateBatchTexels(options.rays_per_patch);
  const size_t batch_rays = size_t{kBatchTexels} * options.rays_per_patch;
  std::vector<PatchRay> patch_rays;
  std::vector<raycast::Ray> rays;
  std::vector<uint32_t> ray_texel;
  std::vector<float> texel_variance(n, 0.0f), texel_stratum_variance(n, -1.0f);
  // A triangle's estimate from the rays that leave it, each weighed by the
  // surface its patch's rays share (the patch's area over its rays): a texel
  // that the triangle shares with the gutter or a neighbour sends all its
  // rays from less surface, and unweighted, those rays near the triangle's
  // edges (often its most occluded part) would count for more than its
  // interior.
  struct TriangleRays {
    glm::dvec3 weighted_sum{0.0}, sum{0.0}, squares{0.0};
    double weight = 0, weight_squared = 0, first_weight = -1;
    uint32_t count = 0;
    bool equal_weights = true;
  };
  std::vector<TriangleRays> triangle_rays(scene.TriangleCount());
  // Exactly one batch's worth: grown by doubling, they would hold up to
  // twice that.
  rays.reserve(batch_rays);
  ray_texel.reserve(batch_rays);
  std::vector<glm::dvec3> values;
  values.reserve(batch_rays);
  std::vector<size_t> first_ray(kBatchTexels, 0);  // each texel's rays are contiguous, in stratum order
  for (uint32_t first = 0; first < n; first += kBatchTexels) {
    rays.clear();
    ray_texel.clear();
    for (uint32_t t = first; t < std::min(n, first + kBatchTexels); ++t) {
      first_ray[t - first] = rays.size();
      GeneratePatchRays(scene, atlas, t, options.seed, options.rays_per_patch, patch_rays);
      for (const PatchRay& r : patch_rays) {
        rays.push_back(raycast::Ray{r.origin, r.direction, params.d_max, r.triangle});
        ray_texel.push_back(t);
      }
    }
    if (rays.empty()) continue;
    VISQ_RETURN_IF_ERROR(options.stop.Check("obscurance rays"));
    raycast::TraceOptions trace;
    trace.threads = options.threads;
    trace.stop = options.stop;
    VISQ_ASSIGN_OR_RETURN(std::vector<raycast::Hit> hits,
                          options.closest_hits ? options.closest_hits(rays) : embree->Intersect(rays, trace));
    std::vector<glm::dvec3> sum(kBatchTexels, glm::dvec3(0.0)), squares(kBatchTexels, glm::dvec3(0.0));
    std::vector<uint32_t> count(kBatchTexels, 0);
    values.resize(rays.size());
    for (size_t i = 0; i < rays.size(); ++i) {
      const uint32_t slot = ray_texel[i] - first;
      values[i] = RayValue(scene, ambient, params.color_bleeding, params.d_max, hits[i].hit, hits[i].t,
                           hits[i].triangle);
      sum[slot] += values[i];
      squares[slot] += values[i] * values[i];
      ++count[slot];
    }
    // Each ray also counts for the triangle it leaves (see BuildResult),
    // weighed by its patch's area over the patch's rays.
    std::vector<double> ray_weight(kBatchTexels, 0.0);
    for (uint32_t s = 0; s < kBatchTexels && first + s < n; ++s) {
      if (count[s] == 0) continue;
      double patch_area = 0;
      for (uint32_t f = atlas.texel_begin[first + s]; f < atlas.texel_begin[first + s + 1]; ++f)
        patch_area += atlas.fragments[f].world_area;
      ray_weight[s] = patch_area / count[s];
    }
    for (size_t i = 0; i < rays.size(); ++i) {
      const double weight = ray_weight[ray_texel[i] - first];
      TriangleRays& tr = triangle_rays[rays[i].ignore_triangle];
      tr.weighted_sum += weight * values[i];
      tr.sum += values[i];
      tr.squares += values[i] * values[i];
      tr.weight += weight;
      tr.weight_squared += weight * weight;
      if (tr.first_weight < 0) tr.first_weight = weight;
      tr.equal_weights = tr.equal_weights && weight == tr.first_weight;
      ++tr.count;
    }
    for (uint32_t s = 0; s < kBatchTexels && first + s < n; ++s)
      if (count[s]) {
        w[first + s] = glm::vec3(sum[s] / static_cast<double>(count[s]));
        texel_variance[first + s] = LargestChannelVariance(sum[s], squares[s], count[s]);
        if (count[s] == options.rays_per_patch)  // one ray in each stratum: pairs of neighbouring strata
          texel_stratum_variance[first + s] = StratumVariance(&values[first_ray[s]], count[s]);
        estimated[first + s] = 1;
      }
  }
  // Every ray is an independent sample: a texel's estimate is worth its
  // rays, a triangle's the rays that left it.
  OwnSampleEstimates own;
  own.texel_effective_samples.assign(n, 0.0f);
  for (uint32_t t = 0; t < n; ++t)
    if (estimated[t]) own.texel_effective_samples[t] = static_cast<float>(options.rays_per_patch);
  own.texel_sample_variance = std::move(texel_variance);
  own.texel_stratum_variance = std::move(texel_stratum_variance);
  own.triangle_w.assign(scene.TriangleCount(), glm::vec3(0.0f));
  own.triangle_effective_samples.assign(scene.TriangleCount(), 0.0f);
  own.triangle_sample_variance.assign(scene.TriangleCount(), 0.0f);
  for (size_t t = 0; t < scene.TriangleCount(); ++t) {
    const TriangleRays& tr = triangle_rays[t];
    if (tr.count == 0 || !(tr.weight > 0)) continue;
    if (tr.equal_weights) {
      // One weight: the plain mean, whose rays' variance bounds it.
      own.triangle_w[t] = glm::vec3(tr.sum / static_cast<double>(tr.count));
      own.triangle_effective_samples[t] = static_cast<float>(tr.count);
      own.triangle_sample_variance[t] = LargestChannelVariance(tr.sum, tr.squares, tr.count);
    } else {
      // Weighted: Hoeffding's inequality holds for it at Kish's effective
      // count (the weighted mean's sum of squared normalized weights); the
      // variance-aware bounds are for equal weights.
      own.triangle_w[t] = glm::vec3(tr.weighted_sum / tr.weight);
      own.triangle_effective_samples[t] = static_cast<float>(tr.weight * tr.weight / tr.weight_squared);
      own.triangle_sample_variance[t] = -1.0f;
    }
  }
  ObscuranceResult out =
      BuildResult(scene, atlas, params.color_bleeding, std::move(w), std::move(estimated), std::move(own));
  out.mean_samples_per_patch = options.rays_per_patch;
  return out;
}

}  // namespace visq::obscurance
