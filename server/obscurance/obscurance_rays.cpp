#include "obscurance/obscurance_rays.h"

#include <cmath>
#include <numbers>

#include "raycast/embree_scene.h"

namespace visq::obscurance {
namespace {

uint64_t Mix(uint64_t x) {
  x += 0x9E3779B97F4A7C15ull;
  x = (x ^ (x >> 30)) * 0xBF58476D1CE4E5B9ull;
  x = (x ^ (x >> 27)) * 0x94D049BB133111EBull;
  return x ^ (x >> 31);
}
double Unit(uint64_t bits) { return static_cast<double>(bits >> 11) * 0x1.0p-53; }
double RadicalInverse(uint32_t base, uint64_t i) {
  double inv = 1.0 / base, f = inv, r = 0;
  while (i > 0) { r += f * static_cast<double>(i % base); i /= base; f *= inv; }
  return r;
}
double Frac(double x) { return x - std::floor(x); }

}  // namespace

void GeneratePatchRays(const Scene& scene, const ObscuranceAtlas& atlas, uint32_t texel, uint64_t seed, uint32_t n,
                       std::vector<PatchRay>& out) {
  out.clear();
  const uint32_t begin = atlas.texel_begin[texel], end = atlas.texel_begin[texel + 1];
  if (begin == end) return;
  double total = 0;
  for (uint32_t i = begin; i < end; ++i) total += atlas.fragments[i].world_area;
  const uint64_t h = Mix(Mix(seed) ^ (static_cast<uint64_t>(texel) * 0xD1B54A32D192ED03ull));
  double shift[5];
  for (int k = 0; k < 5; ++k) shift[k] = Unit(Mix(h + k));
  const uint32_t x = texel % atlas.width, y = texel / atlas.width;
  out.reserve(n);
  for (uint32_t j = 0; j < n; ++j) {
    const double u0 = Frac(RadicalInverse(2, j + 1ull) + shift[0]);
    const double u1 = Frac(RadicalInverse(3, j + 1ull) + shift[1]);
    const double u2 = Frac(RadicalInverse(5, j + 1ull) + shift[2]);
    const double u3 = Frac(RadicalInverse(7, j + 1ull) + shift[3]);
    const double u4 = Frac(RadicalInverse(11, j + 1ull) + shift[4]);
    // A fragment in proportion to its world area, then a fan triangle of
    // its clipped polygon in proportion to atlas area (affine per triangle).
    double pick = u0 * total;
    uint32_t fi = begin;
    for (; fi + 1 < end && pick >= atlas.fragments[fi].world_area; ++fi) pick -= atlas.fragments[fi].world_area;
    const PatchFragment& f = atlas.fragments[fi];
    const uint32_t t = f.triangle;
    const glm::dvec2 a = atlas.corner_uv[3 * t], b = atlas.corner_uv[3 * t + 1], c = atlas.corner_uv[3 * t + 2];
    const glm::dvec3 pa = scene.Vertex(t, 0), pb = scene.Vertex(t, 1), pc = scene.Vertex(t, 2);
    glm::dvec3 point;
    const double det = (b.x - a.x) * (c.y - a.y) - (b.y - a.y) * (c.x - a.x);
    if (std::abs(det) <= 1e-12) {
      // Degenerate in the atlas: the whole triangle is this patch.
      const double s = std::sqrt(u1);
      point = pa * (1 - s) + pb * (s * (1 - u2)) + pc * (s * u2);
    } else {
      const ClippedPolygon poly = ClipTriangleToTexel(a, b, c, x, y);
      double fan_total = 0, fan[8];
      for (int k = 1; k + 1 < poly.n; ++k) {
        const glm::dvec2 e1 = poly.p[k] - poly.p[0], e2 = poly.p[k + 1] - poly.p[0];
        fan[k] = 0.5 * std::abs(e1.x * e2.y - e1.y * e2.x);
        fan_total += fan[k];
      }
      double fp = Frac(u0 * 7919.0) * fan_total;  // decorrelated from the fragment pick
      int k = 1;
      for (; k + 2 < poly.n && fp >= fan[k]; ++k) fp -= fan[k];
      const double s = std::sqrt(u1);
      const glm::dvec2 q = poly.n >= 3 ? poly.p[0] * (1 - s) + poly.p[k] * (s * (1 - u2)) + poly.p[k + 1] * (s * u2)
                                       : (a + b + c) / 3.0;
      // Barycentrics of q in the atlas triangle map it to the world.
      const double l1 = ((q.x - a.x) * (c.y - a.y) - (q.y - a.y) * (c.x - a.x)) / det;
      const double l2 = ((b.x - a.x) * (q.y - a.y) - (b.y - a.y) * (q.x - a.x)) / det;
      point = pa + (pb - pa) * l1 + (pc - pa) * l2;
    }
    // Cosine-distributed direction around the geometric normal.
    const glm::dvec3 nrm = glm::normalize(glm::cross(pb - pa, pc - pa));
    const glm::dvec3 helper = std::abs(nrm.x) < 0.9 ? glm::dvec3(1, 0, 0) : glm::dvec3(0, 1, 0);
    const glm::dvec3 tu = glm::normalize(glm::cross(helper, nrm)), tv = glm::cross(nrm, tu);
    const double r = std::sqrt(u3), phi = 2.0 * std::numbers::pi * u4;
    const glm::dvec3 dir = tu * (r * std::cos(phi)) + tv * (r * std::sin(phi)) + nrm * std::sqrt(std::max(0.0, 1.0 - u3));
    out.push_back(PatchRay{point, dir, t});
  }
}

glm::dvec3 RayValue(const Scene& scene, const AmbientModel& ambient, bool color_bleeding, double d_max, bool hit,
                    double distance, uint32_t hit_triangle) {
  if (!hit || distance >= d_max) return UnoccludedValue(ambient, color_bleeding);
  const double rho = Rho(distance, d_max);
  if (!color_bleeding) return glm::dvec3(rho);
  return rho * scene.materials[scene.triangle_material[hit_triangle]].reflectivity;
}

StatusOr<ObscuranceResult> EstimateObscurancesByRays(const Scene& scene, const ObscuranceAtlas& atlas,
                                                     const ObscuranceParams& params,
                                                     const RayEstimateOptions& options) {
  VISQ_RETURN_IF_ERROR(ValidateParams(params));
  if (options.rays_per_patch == 0)
    return absl::InvalidArgumentError("rays_per_patch: 0 must be at least 1");
  VISQ_ASSIGN_OR_RETURN(raycast::EmbreeScene embree, raycast::EmbreeScene::Create(scene));
  const AmbientModel ambient = ComputeAmbient(scene, params.color_bleeding);
  const uint32_t n = atlas.texel_count();
  std::vector<glm::vec3> w(n, glm::vec3(0.0f));
  std::vector<uint8_t> estimated(n, 0);
  // Texels in batches: generate rays, trace them in one Intersect call.
  constexpr uint32_t kBatchTexels = 4096;
  std::vector<PatchRay> patch_rays;
  std::vector<raycast::Ray> rays;
  std::vector<uint32_t> ray_texel;
  for (uint32_t first = 0; first < n; first += kBatchTexels) {
    rays.clear();
    ray_texel.clear();
    for (uint32_t t = first; t < std::min(n, first + kBatchTexels); ++t) {
      GeneratePatchRays(scene, atlas, t, options.seed, options.rays_per_patch, patch_rays);
      for (const PatchRay& r : patch_rays) {
        rays.push_back(raycast::Ray{r.origin, r.direction, params.d_max, r.triangle});
        ray_texel.push_back(t);
      }
    }
    if (rays.empty()) continue;
    raycast::TraceOptions trace;
    trace.threads = options.threads;
    VISQ_ASSIGN_OR_RETURN(std::vector<raycast::Hit> hits, embree.Intersect(rays, trace));
    std::vector<glm::dvec3> sum(kBatchTexels, glm::dvec3(0.0));
    std::vector<uint32_t> count(kBatchTexels, 0);
    for (size_t i = 0; i < rays.size(); ++i) {
      const uint32_t slot = ray_texel[i] - first;
      sum[slot] += RayValue(scene, ambient, params.color_bleeding, params.d_max, hits[i].hit, hits[i].t,
                            hits[i].triangle);
      ++count[slot];
    }
    for (uint32_t s = 0; s < kBatchTexels && first + s < n; ++s)
      if (count[s]) {
        w[first + s] = glm::vec3(sum[s] / static_cast<double>(count[s]));
        estimated[first + s] = 1;
      }
  }
  ObscuranceResult out = BuildResult(scene, atlas, params.color_bleeding, std::move(w), std::move(estimated));
  out.mean_samples_per_patch = options.rays_per_patch;
  return out;
}

}  // namespace visq::obscurance
