#include "obscurance/obscurance_model.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <numbers>
#include <unordered_map>

#include "common/normal_estimate.h"
#include "common/random.h"

namespace visq::obscurance {
namespace {

struct Fnv {
  uint64_t h = 1469598103934665603ull;
  void Bytes(const void* data, size_t n) {
    const auto* p = static_cast<const unsigned char*>(data);
    for (size_t i = 0; i < n; ++i) h = (h ^ p[i]) * 1099511628211ull;
  }
  template <typename T>
  void Value(const T& v) { Bytes(&v, sizeof(v)); }
};

}  // namespace

Status ValidateParams(const ObscuranceParams& params) {
  if (!(params.d_max > 0) || !std::isfinite(params.d_max))
    return absl::InvalidArgumentError(absl::StrCat("d_max: ", params.d_max, " must be a finite number > 0"));
  if (params.direction_count == 0 || params.direction_count > kMaxDirections)
    return absl::InvalidArgumentError(
        absl::StrCat("direction_count: ", params.direction_count, " must be in [1, ", kMaxDirections, "]"));
  if (static_cast<uint64_t>(params.first_direction) + params.direction_count > kMaxDirections)
    return absl::InvalidArgumentError(absl::StrCat("first_direction: ", params.first_direction, " + direction_count ",
                                                   params.direction_count, " exceeds ", kMaxDirections));
  if (params.bundle_resolution > kMaxBundleResolution)
    return absl::InvalidArgumentError(absl::StrCat("bundle_resolution: ", params.bundle_resolution,
                                                   " must be at most ", kMaxBundleResolution));
  return absl::OkStatus();
}

uint32_t EffectiveBundleResolution(const ObscuranceParams& params, const ObscuranceAtlas& atlas) {
  if (params.bundle_resolution != 0) return params.bundle_resolution;
  return std::min(kMaxBundleResolution, 2 * std::max(atlas.width, atlas.height));
}

AmbientModel ComputeAmbient(const Scene& scene, bool color_bleeding) {
  AmbientModel out;
  double total = 0;
  glm::dvec3 ar(0.0), ae(0.0);
  for (size_t t = 0; t < scene.TriangleCount(); ++t) {
    const double a = 0.5 * glm::length(glm::cross(scene.Vertex(t, 1) - scene.Vertex(t, 0),
                                                  scene.Vertex(t, 2) - scene.Vertex(t, 0)));
    const Material& m = scene.materials[scene.triangle_material[t]];
    total += a;
    ar += a * m.reflectivity;
    ae += a * m.emission;
  }
  if (total <= 0) return out;
  out.r_ave = ar / total;
  out.mean_emission = ae / total;
  glm::dvec3 r = out.r_ave;
  for (int c = 0; c < 3; ++c)
    if (r[c] > kMaxAmbientReflectivity) { r[c] = kMaxAmbientReflectivity; out.clamped = true; }
  // Eq. 3: I_A = R_ave / (1 - R_ave) * sum(A E) / A_total; eq. 5 drops the
  // leading R_ave because the bleeding W already carries one reflection.
  out.ambient_intensity = (color_bleeding ? glm::dvec3(1.0) : r) / (1.0 - r) * out.mean_emission;
  return out;
}

glm::dvec3 UnoccludedValue(const AmbientModel& ambient, bool color_bleeding) {
  return color_bleeding ? ambient.r_ave : glm::dvec3(1.0);
}

BundleDirection DirectionOfSequence(uint64_t seed, uint32_t index) {
  // Halton (2, 3) under a per-seed Cranley-Patterson rotation.
  const double s1 = UnitFromBits(SplitMix64(seed * 2 + 1)), s2 = UnitFromBits(SplitMix64(seed * 2 + 2));
  double u1 = RadicalInverse(2, index + 1ull) + s1, u2 = RadicalInverse(3, index + 1ull) + s2;
  u1 -= std::floor(u1);
  u2 -= std::floor(u2);
  // Uniform over the hemisphere z > 0: z uniform in (0, 1] (Archimedes).
  const double z = 1.0 - u1, r = std::sqrt(std::max(0.0, 1.0 - z * z)), phi = 2.0 * std::numbers::pi * u2;
  BundleDirection d;
  d.view = glm::dvec3(r * std::cos(phi), r * std::sin(phi), z);
  // A roll of the image plane and a sub-pixel offset, hashed per direction.
  const uint64_t h = SplitMix64(SplitMix64(seed ^ 0x6F6273637572ull) + index);
  const double roll = 2.0 * std::numbers::pi * UnitFromBits(SplitMix64(h + 1));
  d.pixel_offset = glm::dvec2(UnitFromBits(SplitMix64(h + 2)), UnitFromBits(SplitMix64(h + 3)));
  const glm::dvec3 helper = std::abs(d.view.z) < 0.9 ? glm::dvec3(0, 0, 1) : glm::dvec3(1, 0, 0);
  const glm::dvec3 a = glm::normalize(glm::cross(helper, d.view));
  const glm::dvec3 b = glm::cross(d.view, a);
  // right x up = -view, like a camera looking down -z.
  d.right = std::cos(roll) * a + std::sin(roll) * b;
  d.up = glm::cross(d.right, d.view);
  return d;
}

namespace {

// sum / (count * scale) per channel, gray in all three without bleeding.
glm::vec3 MeanOf(const uint64_t* sums, uint32_t channels, uint64_t count) {
  const double denom = static_cast<double>(count) * kObscuranceFixedPointScale;
  if (channels == 1) return glm::vec3(static_cast<float>(static_cast<double>(sums[0]) / denom));
  glm::vec3 out(0.0f);
  for (uint32_t c = 0; c < 3; ++c) out[c] = static_cast<float>(static_cast<double>(sums[c]) / denom);
  return out;
}

// Kish's effective count (sum c)^2 / (sum c^2) of a mean weighted by the
// per-direction counts c; `fallback` where the squares are unknown.
float EffectiveDirections(uint64_t count, const std::vector<double>& squares, size_t at, double fallback) {
  if (count == 0) return 0.0f;
  if (at >= squares.size() || !(squares[at] > 0)) return static_cast<float>(fallback);
  const double c = static_cast<double>(count);
  return static_cast<float>(c * c / squares[at]);
}

}  // namespace

void FinalizeFromPartial(const ObscurancePartial& partial, std::vector<glm::vec3>& w, std::vector<uint8_t>& estimated,
                         double* mean_samples, OwnSampleEstimates* own) {
  const size_t n = partial.counts.size();
  w.assign(n, glm::vec3(0.0f));
  estimated.assign(n, 0);
  double samples = 0;
  size_t with = 0;
  for (size_t i = 0; i < n; ++i) {
    const uint64_t count = partial.counts[i];
    if (count == 0) continue;
    estimated[i] = 1;
    samples += static_cast<double>(count);
    ++with;
    w[i] = MeanOf(&partial.sums[i * partial.channels], partial.channels, count);
  }
  if (mean_samples != nullptr) *mean_samples = with ? samples / with : 0.0;
  if (own == nullptr) return;
  // Without the squares (a partial merged from a transport that drops them)
  // every direction counts as one: the figure of the bake as a whole.
  const double directions = static_cast<double>(partial.DirectionCount());
  own->texel_effective_samples.assign(n, 0.0f);
  for (size_t i = 0; i < n; ++i)
    own->texel_effective_samples[i] = EffectiveDirections(partial.counts[i], partial.count_squares, i, directions);
  own->triangle_w.clear();
  own->triangle_effective_samples.clear();
  const size_t triangles = partial.triangle_counts.size();
  if (triangles == 0 || partial.triangle_sums.size() != triangles * partial.channels) return;
  own->triangle_w.assign(triangles, glm::vec3(0.0f));
  own->triangle_effective_samples.assign(triangles, 0.0f);
  for (size_t t = 0; t < triangles; ++t) {
    const uint64_t count = partial.triangle_counts[t];
    if (count == 0) continue;
    own->triangle_w[t] = MeanOf(&partial.triangle_sums[t * partial.channels], partial.channels, count);
    own->triangle_effective_samples[t] = EffectiveDirections(count, partial.count_squares, n + t, directions);
  }
}

double ObscuranceHalfWidth(double effective_samples, double confidence) {
  if (!(effective_samples > 0) || confidence >= 1.0) return 1.0;
  return std::min(1.0, std::sqrt(std::log(2.0 / (1.0 - confidence)) / (2.0 * effective_samples)));
}

namespace {

// Bernoulli Kullback-Leibler divergence KL(p || q).
double BernoulliDivergence(double p, double q) {
  auto term = [](double a, double b) { return a > 0.0 ? a * std::log(a / b) : 0.0; };
  return term(p, q) + term(1.0 - p, 1.0 - q);
}

// The Chernoff half-width around `mean`: the farthest q on either side with
// rays * KL(mean || q) <= log(2 / risk) (each tail at risk / 2), by
// bisection, rounded outwards.
double ChernoffHalfWidth(double rays, double mean, double risk) {
  const double limit = std::log(2.0 / risk) / rays;
  // The float the mean was stored in may sit a rounding off the sum's mean.
  const double slack = 1e-6;
  double widest = 0.0;
  for (const double side : {-1.0, 1.0}) {
    const double from = std::clamp(mean + side * slack, 0.0, 1.0);
    const double end = side > 0 ? 1.0 : 0.0;
    if (BernoulliDivergence(from, end) <= limit) {
      widest = std::max(widest, std::abs(end - mean));
      continue;
    }
    double inside = from, outside = end;
    for (int i = 0; i < 60; ++i) {
      const double mid = 0.5 * (inside + outside);
      (BernoulliDivergence(from, mid) <= limit ? inside : outside) = mid;
    }
    widest = std::max(widest, std::abs(outside - mean));
  }
  return widest;
}

}  // namespace

double ObscuranceHalfWidthOfRays(double rays, const glm::dvec3& mean, double variance, double confidence) {
  if (!(rays >= 2) || !(variance >= 0) || confidence >= 1.0) return ObscuranceHalfWidth(rays, confidence);
  const double risk = 1.0 - confidence;
  // Maurer & Pontil's bound at risk / 2, shared three ways: the variance's
  // upper confidence bound and the two tails of Bernstein's inequality, so
  // log(3 / (risk / 2)) in each.
  const double log_term = std::log(6.0 / risk);
  const double bernstein = std::sqrt(2.0 * variance * log_term / rays) + 7.0 * log_term / (3.0 * (rays - 1.0));
  // Chernoff's at the other risk / 2, channel by channel.
  double widest = 0.0;
  for (int c = 0; c < 3; ++c) {
    if (!(mean[c] >= 0.0 && mean[c] <= 1.0)) return ObscuranceHalfWidth(rays, confidence);
    widest = std::max(widest, std::min(bernstein, ChernoffHalfWidth(rays, mean[c], risk / 2)));
  }
  return std::min(1.0, widest);
}

float LargestChannelVariance(const glm::dvec3& sum, const glm::dvec3& sum_of_squares, double n) {
  if (!(n >= 2)) return 0.0f;
  double largest = 0.0;
  for (int c = 0; c < 3; ++c)
    largest = std::max(largest, (sum_of_squares[c] - sum[c] * sum[c] / n) / (n - 1.0));
  const float f = static_cast<float>(largest);
  return static_cast<double>(f) < largest ? std::nextafter(f, 2.0f) : f;
}

namespace {

// One element's own half-width: 1 (W's whole range) without an estimate of
// its own.
// Rounded up to a float, so that the stored bound never says less than the
// computed one.
float UpFloat(double half_width) {
  const float f = static_cast<float>(half_width);
  return static_cast<double>(f) < half_width ? std::nextafter(f, 2.0f) : f;
}
float ElementHalfWidth(const std::vector<float>& samples, const std::vector<float>& variance,
                       const std::vector<glm::vec3>& mean, size_t i, double confidence) {
  if (i >= samples.size()) return 1.0f;
  if (i < variance.size() && i < mean.size())
    return UpFloat(ObscuranceHalfWidthOfRays(samples[i], glm::dvec3(mean[i]), variance[i], confidence));
  return UpFloat(ObscuranceHalfWidth(samples[i], confidence));
}
float TexelHalfWidth(const ObscuranceResult& result, size_t texel, double confidence) {
  const bool own = texel < result.estimated.size() && result.estimated[texel];
  return own ? ElementHalfWidth(result.texel_effective_samples, result.texel_sample_variance, result.w, texel,
                                confidence)
             : 1.0f;
}
float TriangleHalfWidth(const ObscuranceResult& result, size_t triangle, double confidence) {
  return ElementHalfWidth(result.triangle_effective_samples, result.triangle_sample_variance, result.triangle_w,
                          triangle, confidence);
}
// What a vertex's bound averages: Hoeffding's, whatever the triangle's own.
float TriangleHoeffdingHalfWidth(const ObscuranceResult& result, size_t triangle, double confidence) {
  return ElementHalfWidth(result.triangle_effective_samples, {}, {}, triangle, confidence);
}
double TriangleArea(const Scene& scene, uint32_t t) {
  return 0.5 * glm::length(glm::cross(scene.Vertex(t, 1) - scene.Vertex(t, 0), scene.Vertex(t, 2) - scene.Vertex(t, 0)));
}

}  // namespace

uint32_t StratumPairCount(uint32_t rays) {
  uint32_t pairs = 0;
  ForEachStratumPair(rays, [&](uint32_t) { ++pairs; });
  return pairs;
}

std::vector<float> ObscuranceTexelEstimates(const ObscuranceResult& result, double confidence) {
  const size_t n = result.w.size();
  if (result.texel_sample_variance.size() != n || result.texel_effective_samples.size() != n ||
      result.estimated.size() != n || static_cast<size_t>(result.width) * result.height != n)
    return {};
  const bool strata = result.texel_stratum_variance.size() == n;
  // A texel's own variance per ray and its degrees of freedom: its pairs of
  // strata, or its rays - 1.
  struct Own {
    bool known = false;
    double variance = 0, dof = 0;
  };
  uint32_t last_rays = 0, last_pairs = 0;  // StratumPairCount's last answer: texels mostly share one count
  auto own = [&](size_t i) -> Own {
    const double rays = result.texel_effective_samples[i], sample = result.texel_sample_variance[i];
    if (!result.estimated[i] || !(rays >= 2) || !(sample >= 0)) return {};
    if (strata && result.texel_stratum_variance[i] >= 0 && rays == std::floor(rays) && rays < 4e9) {
      const auto count = static_cast<uint32_t>(rays);
      if (count != last_rays) last_pairs = StratumPairCount(last_rays = count);
      // Stratification makes W's variance at most what independent rays'
      // would be, which the sample variance estimates: the smaller of the two.
      if (last_pairs > 0)
        return {true, std::min<double>(result.texel_stratum_variance[i], sample), static_cast<double>(last_pairs)};
    }
    return {true, sample, rays - 1.0};
  };
  std::vector<float> out(n, -1.0f);
  std::unordered_map<int, double> quantiles;  // per degrees of freedom
  const int width = static_cast<int>(result.width), height = static_cast<int>(result.height);
  for (int y = 0; y < height; ++y)
    for (int x = 0; x < width; ++x) {
      const size_t i = static_cast<size_t>(y) * result.width + static_cast<size_t>(x);
      const Own self = own(i);
      if (!self.known) continue;
      double pooled_dof = 0.0, pooled_squares = 0.0;
      for (int dy = -1; dy <= 1; ++dy)
        for (int dx = -1; dx <= 1; ++dx) {
          const int nx = x + dx, ny = y + dy;
          if ((dx == 0 && dy == 0) || nx < 0 || ny < 0 || nx >= width || ny >= height) continue;
          const Own other = own(static_cast<size_t>(ny) * result.width + static_cast<size_t>(nx));
          pooled_dof += other.dof;
          pooled_squares += other.dof * other.variance;
        }
      const double prior_dof = std::min(pooled_dof, self.dof);
      const double prior_variance = pooled_dof > 0 ? pooled_squares / pooled_dof : 0.0;
      const double total_dof = self.dof + prior_dof;
      const double variance = (self.dof * self.variance + prior_dof * prior_variance) / total_dof;
      const int dof = static_cast<int>(std::clamp(total_dof, 1.0, 1e9));
      auto [it, fresh] = quantiles.try_emplace(dof, 0.0);
      if (fresh) it->second = TwoSidedStudentQuantile(confidence, dof);
      out[i] = UpFloat(std::min(1.0, it->second * std::sqrt(variance / result.texel_effective_samples[i])));
    }
  return out;
}

double LargestObscuranceEstimate(double rays, double confidence) {
  if (!(rays >= 2)) return 1.0;
  const double fewest_dof = std::max(1.0, std::floor((rays - std::sqrt(rays) - 1.0) / 2.0));
  return std::min(1.0, TwoSidedStudentQuantile(confidence, static_cast<int>(std::min(1e9, fewest_dof))) *
                           std::sqrt(1.0 / (4.0 * (rays - 1.0))));
}

ObscuranceBounds ObscuranceBoundsOf(const Scene& scene, const ObscuranceResult& result, double confidence) {
  ObscuranceBounds out;
  out.texel.resize(result.w.size());
  for (size_t i = 0; i < out.texel.size(); ++i) out.texel[i] = TexelHalfWidth(result, i, confidence);
  out.triangle.resize(scene.TriangleCount());
  for (size_t t = 0; t < out.triangle.size(); ++t) out.triangle[t] = TriangleHalfWidth(result, t, confidence);
  // A vertex: the area-weighted mean of its triangles' half-widths.
  std::vector<double> sum(scene.positions.size(), 0.0), area(scene.positions.size(), 0.0);
  for (uint32_t t = 0; t < scene.TriangleCount(); ++t) {
    const double a = TriangleArea(scene, t);
    const double half_width = TriangleHoeffdingHalfWidth(result, t, confidence);
    for (int c = 0; c < 3; ++c) {
      sum[scene.triangles[t][c]] += a * half_width;
      area[scene.triangles[t][c]] += a;
    }
  }
  out.vertex.assign(scene.positions.size(), 1.0f);
  for (size_t v = 0; v < sum.size(); ++v)
    if (area[v] > 0) out.vertex[v] = static_cast<float>(std::min(1.0, sum[v] / area[v]));
  return out;
}

ObscuranceBounds ObscuranceBoundsOfListed(const Scene& scene, const ObscuranceResult& result, double confidence,
                                          std::span<const uint32_t> texels, std::span<const uint32_t> triangles,
                                          std::span<const uint32_t> vertices) {
  ObscuranceBounds out;
  out.texel.reserve(texels.size());
  for (uint32_t i : texels) out.texel.push_back(TexelHalfWidth(result, i, confidence));
  out.triangle.reserve(triangles.size());
  for (uint32_t t : triangles) out.triangle.push_back(TriangleHalfWidth(result, t, confidence));
  // A vertex, as in ObscuranceBoundsOf, from the triangles that touch it.
  std::unordered_map<uint32_t, size_t> slot;
  slot.reserve(vertices.size());
  for (size_t k = 0; k < vertices.size(); ++k) slot.emplace(vertices[k], k);
  std::vector<double> sum(vertices.size(), 0.0), area(vertices.size(), 0.0);
  for (uint32_t t = 0; t < scene.TriangleCount() && !slot.empty(); ++t) {
    for (int c = 0; c < 3; ++c) {
      const auto it = slot.find(scene.triangles[t][c]);
      if (it == slot.end()) continue;
      const double a = TriangleArea(scene, t);
      sum[it->second] += a * TriangleHoeffdingHalfWidth(result, t, confidence);
      area[it->second] += a;
    }
  }
  out.vertex.assign(vertices.size(), 1.0f);
  for (size_t k = 0; k < vertices.size(); ++k)
    if (area[k] > 0) out.vertex[k] = static_cast<float>(std::min(1.0, sum[k] / area[k]));
  return out;
}

double CoveredHalfWidth(double nominal_samples, double confidence) {
  return ObscuranceHalfWidth(kCoveredShare * nominal_samples, confidence);
}

ObscuranceAnswerBound ObscuranceAnswerBoundOf(const ObscuranceResult& result, const ObscuranceBounds& bounds,
                                              double nominal_samples, double confidence) {
  // The per-element bounds are floats: compare them with the cap as floats.
  const float cap = UpFloat(CoveredHalfWidth(nominal_samples, confidence));
  ObscuranceAnswerBound out;
  float widest = 0.0f;
  auto count = [&](ObscuranceAnswerBound::Kind& kind, float own) {
    ++kind.elements;
    if (own > cap) ++kind.outside;
    else widest = std::max(widest, own);
  };
  for (size_t i = 0; i < bounds.texel.size(); ++i)
    if (i < result.estimated.size() && result.estimated[i]) count(out.texels, bounds.texel[i]);
  for (size_t t = 0; t < bounds.triangle.size(); ++t)
    if (t < result.triangle_effective_samples.size() && result.triangle_effective_samples[t] > 0)
      count(out.triangles, bounds.triangle[t]);
  for (float own : bounds.vertex)
    if (own < 1.0f) count(out.vertices, own);
  out.error_bound = widest > 0.0f ? widest : cap;
  return out;
}

glm::dvec3 TexelReflectivity(const Scene& scene, const ObscuranceAtlas& atlas, uint32_t texel) {
  glm::dvec3 r(0.0);
  double area = 0;
  for (uint32_t i = atlas.texel_begin[texel]; i < atlas.texel_begin[texel + 1]; ++i) {
    const PatchFragment& f = atlas.fragments[i];
    r += f.world_area * scene.materials[scene.triangle_material[f.triangle]].reflectivity;
    area += f.world_area;
  }
  return area > 0 ? r / area : glm::dvec3(0.0);
}

glm::vec3 FilledValue(const ObscuranceAtlas& atlas, const ObscuranceResult& result, uint32_t texel,
                      const glm::dvec3& fallback) {
  const int x = static_cast<int>(texel % result.width), y = static_cast<int>(texel / result.width);
  // The estimated neighbours' mean; for a gutter texel with none, the mean
  // of its neighbours that hold surface (filled themselves: slivers the bake
  // could not sample), so that it follows its chart, not the unoccluded value.
  glm::dvec3 sum(0.0), covered_sum(0.0);
  int n = 0, covered_n = 0;
  const bool gutter = !atlas.Covered(texel);
  for (int dy = -1; dy <= 1; ++dy)
    for (int dx = -1; dx <= 1; ++dx) {
      const int nx = x + dx, ny = y + dy;
      if (nx < 0 || ny < 0 || nx >= static_cast<int>(result.width) || ny >= static_cast<int>(result.height)) continue;
      const uint32_t j = static_cast<uint32_t>(ny) * result.width + static_cast<uint32_t>(nx);
      if (result.estimated[j]) {
        sum += glm::dvec3(result.w[j]);
        ++n;
      } else if (gutter && atlas.Covered(j)) {
        covered_sum += glm::dvec3(result.w[j]);
        ++covered_n;
      }
    }
  if (n) return glm::vec3(sum / static_cast<double>(n));
  return glm::vec3(covered_n ? covered_sum / static_cast<double>(covered_n) : fallback);
}

void RefillTexels(const ObscuranceAtlas& atlas, ObscuranceResult& result, const std::vector<uint32_t>& texels,
                  const glm::dvec3& fallback) {
  // Texels with surface first: the gutter may read them.
  for (uint32_t t : texels)
    if (!result.estimated[t] && atlas.Covered(t)) result.w[t] = FilledValue(atlas, result, t, fallback);
  for (uint32_t t : texels)
    if (!result.estimated[t] && !atlas.Covered(t)) result.w[t] = FilledValue(atlas, result, t, fallback);
}

glm::vec3 TriangleAverage(const ObscuranceAtlas& atlas, const ObscuranceResult& result, uint32_t triangle) {
  glm::dvec3 sum(0.0);
  double area = 0;
  for (uint32_t k = atlas.triangle_begin[triangle]; k < atlas.triangle_begin[triangle + 1]; ++k) {
    const PatchFragment& f = atlas.fragments[atlas.triangle_fragments[k]];
    sum += f.world_area * glm::dvec3(result.w[f.texel]);
    area += f.world_area;
  }
  return area > 0 ? glm::vec3(sum / area) : glm::vec3(0.0f);
}

ObscuranceResult BuildResult(const Scene& scene, const ObscuranceAtlas& atlas, bool color_bleeding,
                             std::vector<glm::vec3> w, std::vector<uint8_t> estimated, OwnSampleEstimates own) {
  ObscuranceResult out;
  out.width = atlas.width;
  out.height = atlas.height;
  out.color_bleeding = color_bleeding;
  out.ambient = ComputeAmbient(scene, color_bleeding);
  out.w = std::move(w);
  out.estimated = std::move(estimated);
  // A bake sample can land in a texel that holds no surface: the fragment
  // shader takes floor(uv) of an interpolated uv, which rounds across a
  // chart's edge now and then (one sample in a gutter texel). Such a texel is
  // filled like the rest of the gutter: its one-sample value is noise, and
  // the update, which never recomputes texels without surface, would keep
  // it stale while a rebake moves it.
  for (uint32_t i = 0; i < atlas.texel_count(); ++i)
    if (out.estimated[i] && !atlas.Covered(i)) out.estimated[i] = 0;
  const glm::dvec3 unoccluded = UnoccludedValue(out.ambient, color_bleeding);
  // Texels without an estimate take their estimated neighbours' mean (the
  // gutter), a gutter texel with none its filled neighbours' with surface,
  // or the unoccluded value when none is near.
  const uint32_t n = atlas.texel_count();
  std::vector<uint32_t> all(n);
  for (uint32_t i = 0; i < n; ++i) all[i] = i;
  RefillTexels(atlas, out, all, unoccluded);
  // I(P) = R(P) I_A W(P), eq. 1.
  out.intensity.assign(n, glm::vec3(0.0f));
  for (uint32_t i = 0; i < n; ++i)
    if (atlas.Covered(i))
      out.intensity[i] = glm::vec3(TexelReflectivity(scene, atlas, i) * out.ambient.ambient_intensity *
                                   glm::dvec3(out.w[i]));
  // What each texel's estimate is worth; a filled texel nothing of its own.
  out.texel_effective_samples = std::move(own.texel_effective_samples);
  out.texel_effective_samples.resize(n, 0.0f);
  for (uint32_t i = 0; i < n; ++i)
    if (!out.estimated[i]) out.texel_effective_samples[i] = 0.0f;
  out.texel_sample_variance = std::move(own.texel_sample_variance);
  if (!out.texel_sample_variance.empty()) out.texel_sample_variance.resize(n, -1.0f);
  out.texel_stratum_variance = std::move(own.texel_stratum_variance);
  if (!out.texel_stratum_variance.empty()) out.texel_stratum_variance.resize(n, -1.0f);
  // Per triangle its own samples' mean; where it has none, its texels'.
  const size_t nt = scene.TriangleCount();
  const bool has_own = own.triangle_w.size() == nt && own.triangle_effective_samples.size() == nt;
  const bool has_variance = has_own && own.triangle_sample_variance.size() == nt;
  out.triangle_w.resize(nt);
  out.triangle_effective_samples.assign(nt, 0.0f);
  if (has_variance) out.triangle_sample_variance.assign(nt, 0.0f);
  for (uint32_t t = 0; t < nt; ++t) {
    if (has_own && own.triangle_effective_samples[t] > 0) {
      out.triangle_w[t] = own.triangle_w[t];
      out.triangle_effective_samples[t] = own.triangle_effective_samples[t];
      if (has_variance) out.triangle_sample_variance[t] = own.triangle_sample_variance[t];
    } else {
      out.triangle_w[t] = TriangleAverage(atlas, out, t);
    }
  }
  std::vector<glm::dvec3> vsum(scene.positions.size(), glm::dvec3(0.0));
  std::vector<double> varea(scene.positions.size(), 0.0);
  for (uint32_t t = 0; t < scene.TriangleCount(); ++t) {
    const double a = 0.5 * glm::length(glm::cross(scene.Vertex(t, 1) - scene.Vertex(t, 0),
                                                  scene.Vertex(t, 2) - scene.Vertex(t, 0)));
    for (int c = 0; c < 3; ++c) {
      vsum[scene.triangles[t][c]] += a * glm::dvec3(out.triangle_w[t]);
      varea[scene.triangles[t][c]] += a;
    }
  }
  out.vertex_w.resize(scene.positions.size());
  for (size_t v = 0; v < vsum.size(); ++v) out.vertex_w[v] = varea[v] > 0 ? glm::vec3(vsum[v] / varea[v]) : glm::vec3(0.0f);
  return out;
}

StatusOr<ObscuranceResult> FinalizeObscurances(const Scene& scene, const ObscuranceAtlas& atlas,
                                               const ObscuranceParams& params, const ObscurancePartial& partial) {
  if (partial.width != atlas.width || partial.height != atlas.height)
    return absl::InvalidArgumentError(absl::StrCat("partial: atlas ", partial.width, "x", partial.height,
                                                   " does not match ", atlas.width, "x", atlas.height));
  if (partial.channels != (params.color_bleeding ? 3u : 1u))
    return absl::InvalidArgumentError(absl::StrCat("partial: ", partial.channels, " channels, color_bleeding ",
                                                   params.color_bleeding ? "on" : "off"));
  if (!partial.triangle_counts.empty() && partial.triangle_counts.size() != scene.TriangleCount())
    return absl::InvalidArgumentError(absl::StrCat("partial: ", partial.triangle_counts.size(),
                                                   " triangle counts, the scene has ", scene.TriangleCount()));
  std::vector<glm::vec3> w;
  std::vector<uint8_t> estimated;
  double mean = 0;
  OwnSampleEstimates own;
  FinalizeFromPartial(partial, w, estimated, &mean, &own);
  ObscuranceResult out =
      BuildResult(scene, atlas, params.color_bleeding, std::move(w), std::move(estimated), std::move(own));
  out.directions = partial.DirectionCount();
  out.mean_samples_per_patch = mean;
  return out;
}

uint64_t BakeFingerprint(const Scene& scene, const ObscuranceAtlas& atlas, const ObscuranceParams& params) {
  Fnv f;
  f.Bytes(scene.positions.data(), scene.positions.size() * sizeof(glm::dvec3));
  f.Bytes(scene.triangles.data(), scene.triangles.size() * sizeof(glm::uvec3));
  f.Bytes(scene.triangle_material.data(), scene.triangle_material.size() * sizeof(uint32_t));
  for (const Material& m : scene.materials) { f.Value(m.reflectivity); f.Value(m.emission); }
  f.Value(atlas.width);
  f.Value(atlas.height);
  f.Bytes(atlas.corner_uv.data(), atlas.corner_uv.size() * sizeof(glm::vec2));
  f.Value(params.d_max);
  f.Value(params.color_bleeding);
  f.Value(params.seed);
  f.Value(EffectiveBundleResolution(params, atlas));
  return f.h;
}

}  // namespace visq::obscurance
