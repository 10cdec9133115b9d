// The obscurance illumination model of Méndez-Feliu, Sbert et al. ("Real-time
// Obscurances with Color Bleeding"), the part that needs neither a GPU nor a
// ray tracer: parameters and their validation, rho(d), the unoccluded value,
// the ambient intensity I_A (eq. 3 and 5), the bake's direction sequence, and
// turning summed transfers into W(P) and I(P) = R(P) I_A W(P) (eq. 1) per
// patch, per triangle and per vertex.
#pragma once

#include <cstdint>
#include <span>
#include <vector>

#include <glm/glm.hpp>

#include "common/random.h"
#include "common/status.h"
#include "obscurance/obscurance_atlas.h"
#include "visq/obscurance_partial.h"
#include "scene/scene.h"

namespace visq::obscurance {

inline constexpr uint32_t kMaxDirections = 1u << 20;
inline constexpr uint32_t kMaxBundleResolution = 8192;

struct ObscuranceParams {
  // Occlusions farther than d_max (scene units) do not count: rho(d) = 1.
  double d_max = 1.0;
  // Eq. 4 (RGB: multiply by the reflectivity seen, R_ave when nothing is seen
  // within d_max) instead of eq. 2.
  bool color_bleeding = false;
  // The bake: directions of the sequence [first_direction, first + count).
  uint32_t first_direction = 0;
  uint32_t direction_count = 256;
  uint64_t seed = 1;
  // Pixels across the bundle of parallel rays (the scene's bounding sphere
  // diameter); 0 picks 2 x the atlas width, at most kMaxBundleResolution.
  uint32_t bundle_resolution = 0;
};

// INVALID_ARGUMENT naming the field and its value ("d_max: nan must be > 0").
[[nodiscard]] Status ValidateParams(const ObscuranceParams& params);
uint32_t EffectiveBundleResolution(const ObscuranceParams& params, const ObscuranceAtlas& atlas);

// rho(d) = sqrt(d / d_max) below d_max, 1 beyond (eq. 2).
inline double Rho(double d, double d_max) { return d >= d_max ? 1.0 : std::sqrt(std::max(d, 0.0) / d_max); }

// Area-weighted scene averages behind eq. 3 and 5.
struct AmbientModel {
  glm::dvec3 r_ave{0.0};             // sum A_i R_i / A_total
  glm::dvec3 mean_emission{0.0};     // sum A_i E_i / A_total
  glm::dvec3 ambient_intensity{0.0}; // I_A, eq. 3 (no bleeding) or eq. 5
  // R_ave >= 1 in some channel makes I_A infinite (a closed scene that never
  // loses light); such channels use R_ave = kMaxAmbientReflectivity instead.
  bool clamped = false;
};
inline constexpr double kMaxAmbientReflectivity = 0.99;
AmbientModel ComputeAmbient(const Scene& scene, bool color_bleeding);

// The value a direction contributes: rho(d) (times R(Q) with color bleeding)
// for a surface seen at distance d < d_max, else the unoccluded value (1, or
// R_ave with color bleeding).
glm::dvec3 UnoccludedValue(const AmbientModel& ambient, bool color_bleeding);

// One direction of the bake's sequence: a direction over the hemisphere z >
// 0 (a line set covers both senses), from a Halton (2, 3) sequence under a
// Cranley-Patterson rotation drawn from the seed; and, per direction, a roll
// of the image plane and a sub-pixel offset (hashed from seed and index) so
// that the pixel grids of successive bundles do not align with the atlas.
struct BundleDirection {
  glm::dvec3 view{0.0, 0.0, 1.0};  // unit; rays travel along +view
  glm::dvec3 right{1.0, 0.0, 0.0}; // image x; right x up = -view
  glm::dvec3 up{0.0, 1.0, 0.0};
  glm::dvec2 pixel_offset{0.0};    // in pixels, [0, 1)
};
BundleDirection DirectionOfSequence(uint64_t seed, uint32_t index);

// W, I and the averages the clients use.
struct ObscuranceResult {
  uint32_t width = 0, height = 0;
  bool color_bleeding = false;
  // Per texel (y * width + x): W (gray in all three channels without color
  // bleeding) and I = R(P) I_A W(P). Texels that no sample reached (gutter,
  // slivers) hold their neighbours' average so that filtering does not bleed.
  std::vector<glm::vec3> w;
  std::vector<glm::vec3> intensity;
  // Per texel: 1 when the value is an estimate of that patch, 0 when it was
  // filled from neighbours (gutter or never sampled).
  std::vector<uint8_t> estimated;
  // Per triangle: the mean of the samples that fell on the triangle itself
  // (not the mean of its texels, which on a mesh finer than the atlas mixes
  // in the neighbours sharing them); a triangle that no sample reached takes
  // its texels' area-weighted mean, with no bound (effective count 0).
  std::vector<glm::vec3> triangle_w;
  std::vector<glm::vec3> vertex_w;    // per Scene::positions, area-weighted over triangles
  // How many independent samples each estimate is worth: per texel and per
  // triangle, the effective number of directions (Kish: (sum of counts)^2 /
  // (sum of squared counts), the counts being each direction's samples of
  // the element) or of rays; 0 where there is no estimate of its own. The
  // bounds (ObscuranceBoundsOf) follow from these.
  std::vector<float> texel_effective_samples;
  std::vector<float> triangle_effective_samples;
  // Where an element's estimate is the mean of independent rays (the
  // ray-cast bake, the update): the unbiased sample variance of its rays'
  // values, the largest over the channels; empty, or negative for an
  // element, where the estimate is not (depth peeling weighs directions of
  // one Halton sequence; an update over such a bake). With it, the
  // element's bound follows how little its values vary
  // (ObscuranceHalfWidthOfRays).
  std::vector<float> texel_sample_variance;
  std::vector<float> triangle_sample_variance;
  // Where a texel's rays are one in each of its direction strata (the
  // ray-cast bake): the variance of one ray's value that W's own variance
  // follows, from rays in neighbouring strata (half the mean squared
  // difference of pairs of neighbouring cells of a row: the collapsed-strata
  // estimator), the largest over the channels; -1 where unknown (a texel an
  // update recomputed), empty where no texel has it. The sample variance
  // also counts how much the strata's own means differ, which stratification
  // takes out of W's error; this does not (it still counts how much two
  // neighbouring cells' means differ). Only the estimate uses it: no
  // inequality here holds from it.
  std::vector<float> texel_stratum_variance;
  AmbientModel ambient;
  uint64_t directions = 0;
  double mean_samples_per_patch = 0;  // over estimated texels
};

// What each W of a result can promise at `confidence`, 1 (nothing) without
// an estimate of its own. A texel or triangle whose rays' variance is known
// gets ObscuranceHalfWidthOfRays; the others Hoeffding's half-width for
// their effective number of samples, each a mean of values in [0, 1]
// (ObscuranceHalfWidth). A vertex's W is the area-weighted mean of its
// triangles', so its Hoeffding half-width is at most the area-weighted mean
// of theirs (Minkowski on the ranges of the per-direction terms), which is
// what it gets: the variance-aware bounds of several triangles would only
// hold together at a lower confidence.
struct ObscuranceBounds {
  std::vector<float> texel;     // per texel; 1 for texels filled from neighbours
  std::vector<float> triangle;  // per triangle
  std::vector<float> vertex;    // per Scene::positions
};
double ObscuranceHalfWidth(double effective_samples, double confidence);
// The half-width, per channel the widest, of the mean `mean` of `rays`
// independent values in [0, 1] whose unbiased sample variance is at most
// `variance` in every channel, at `confidence`: per channel the smaller of
// Chernoff's (Hoeffding 1963, Theorem 1: the Kullback-Leibler form, tight
// where the mean is near 0 or 1) and the empirical Bernstein half-width
// (Maurer & Pontil 2009, Theorem 4, two-sided), each at half the risk, so
// the smaller holds at `confidence`. Both hold for independent values that
// are not identically distributed, as stratified rays are
// (docs/obscurance-bounds.md).
// Never more than Hoeffding's at half the risk.
double ObscuranceHalfWidthOfRays(double rays, const glm::dvec3& mean, double variance, double confidence);
// The pairs of neighbouring strata among `rays` rays, one in each cell of
// EqualAreaCellOf(rays, j) in the order j: neighbouring cells of one row,
// (first, first + 1), (first + 2, first + 3), ...; a row of odd length
// leaves its last cell unpaired. Calls `pair(j)` for each pair (j, j + 1).
template <typename Pair>
void ForEachStratumPair(uint32_t rays, Pair&& pair);
// How many pairs ForEachStratumPair gives for `rays` rays.
uint32_t StratumPairCount(uint32_t rays);
// The estimate each texel states beside its bound, where its rays' variance
// is known (empty otherwise; -1 for a texel without an estimate of its own):
// a Student-t half-width t(confidence, dof) sqrt(v / rays) at a moderated
// variance v. A texel's own v is its stratum variance (dof: its pairs) where
// known, else its sample variance (dof: rays - 1); v pools it with its 3 x 3
// atlas neighbours', the neighbours weighing at most as much as the texel's
// own (dof: its own plus that weight). A texel whose few rays all agreed
// (variance 0) while its neighbours' did not gets their spread, not 0: near
// a contact shadow a handful of rays miss the near wall at random.
// Not a bound: its coverage is measured (docs/obscurance-bounds.md).
std::vector<float> ObscuranceTexelEstimates(const ObscuranceResult& result, double confidence);
// The largest half-width ObscuranceTexelEstimates states for a texel of at
// least `rays` rays whose neighbours have at least as many (every texel of a
// ray-cast bake has its rays per patch): a plan's estimate before its bake.
// The variance it uses is at most the sample variance, at most
// rays / (4 (rays - 1)) for values in [0, 1], and its degrees of freedom are
// at least the pairs of strata, at least (rays - sqrt(rays) - 1) / 2.
double LargestObscuranceEstimate(double rays, double confidence);
// The unbiased sample variance of `n` values (per channel, from their sums
// and sums of squares), the largest over the channels, never below 0 and
// rounded up to a float.
float LargestChannelVariance(const glm::dvec3& sum, const glm::dvec3& sum_of_squares, double n);
ObscuranceBounds ObscuranceBoundsOf(const Scene& scene, const ObscuranceResult& result, double confidence);

// ObscuranceBoundsOf's half-widths for the listed elements only, each
// vector in the order of its list (an update's changed texels, triangles
// and vertices): a vertex's from all of its triangles, listed or not. One
// pass over the triangles, none over the atlas.
ObscuranceBounds ObscuranceBoundsOfListed(const Scene& scene, const ObscuranceResult& result, double confidence,
                                          std::span<const uint32_t> texels, std::span<const uint32_t> triangles,
                                          std::span<const uint32_t> vertices);

// One bound for a whole answer that holds for what it claims. An element
// whose estimate rests on at least kCoveredShare of the nominal count (the
// directions, or the rays per patch) is covered: at the confidence, its W is
// within `error_bound`, the largest own half-width among the covered
// elements, which is at most CoveredHalfWidth(nominal). The others (slivers
// along a chart's edge, triangles a few samples reached) are counted outside,
// and only their own, wider bounds hold for them. A fixed share, rather than
// the widest bound of all, keeps one sliver from making the figure 1 and
// lets a plan know its bound before the bake.
inline constexpr double kCoveredShare = 0.25;
double CoveredHalfWidth(double nominal_samples, double confidence);
struct ObscuranceAnswerBound {
  double error_bound = 1.0;
  struct Kind {
    uint64_t elements = 0;  // with an estimate of their own
    uint64_t outside = 0;   // of those, the ones whose own bound exceeds error_bound
  };
  Kind texels, triangles, vertices;
};
ObscuranceAnswerBound ObscuranceAnswerBoundOf(const ObscuranceResult& result, const ObscuranceBounds& bounds,
                                              double nominal_samples, double confidence);

// What a triangle-level estimate rests on besides the texels: W per
// triangle from its own samples and how many samples each estimate is worth.
struct OwnSampleEstimates {
  std::vector<float> texel_effective_samples;  // per texel (empty: none known)
  std::vector<glm::vec3> triangle_w;           // per triangle (empty: from the texels)
  std::vector<float> triangle_effective_samples;
  std::vector<float> texel_sample_variance;     // ObscuranceResult's; empty: unknown
  std::vector<float> triangle_sample_variance;
  std::vector<float> texel_stratum_variance;    // ObscuranceResult's; empty: unknown
};

// W per texel from fixed-point sums (count 0: not estimated); with `own`,
// W per triangle from the partial's triangle sums and the effective counts.
void FinalizeFromPartial(const ObscurancePartial& partial, std::vector<glm::vec3>& w, std::vector<uint8_t>& estimated,
                         double* mean_samples, OwnSampleEstimates* own = nullptr);
// Fills texels that are not estimated, then I, per-triangle and per-vertex
// values. `w` and `estimated` come from FinalizeFromPartial or a ray estimate.
ObscuranceResult BuildResult(const Scene& scene, const ObscuranceAtlas& atlas, bool color_bleeding,
                             std::vector<glm::vec3> w, std::vector<uint8_t> estimated, OwnSampleEstimates own = {});
// FinalizeFromPartial + BuildResult.
[[nodiscard]] StatusOr<ObscuranceResult> FinalizeObscurances(const Scene& scene, const ObscuranceAtlas& atlas,
                                                             const ObscuranceParams& params,
                                                             const ObscurancePartial& partial);

// Helpers shared with the update: reflectivity of a texel (area-weighted over
// its fragments), gutter filling around given texels, triangle and vertex
// averages of given triangles.
glm::dvec3 TexelReflectivity(const Scene& scene, const ObscuranceAtlas& atlas, uint32_t texel);
glm::vec3 FilledValue(const ObscuranceAtlas& atlas, const ObscuranceResult& result, uint32_t texel,
                      const glm::dvec3& fallback);
// FilledValue for the texels of `texels` that are not estimated: those with
// surface first, then the gutter (which may read them).
void RefillTexels(const ObscuranceAtlas& atlas, ObscuranceResult& result, const std::vector<uint32_t>& texels,
                  const glm::dvec3& fallback);
glm::vec3 TriangleAverage(const ObscuranceAtlas& atlas, const ObscuranceResult& result, uint32_t triangle);

// A stable 64-bit hash of what a bake depends on, for ObscurancePartial.
uint64_t BakeFingerprint(const Scene& scene, const ObscuranceAtlas& atlas, const ObscuranceParams& params);

template <typename Pair>
void ForEachStratumPair(uint32_t rays, Pair&& pair) {
  const auto rows = static_cast<uint64_t>(EqualAreaRowCount(rays));
  for (uint64_t r = 0; r < rows && rays > 0; ++r) {
    const uint64_t first = r * rays / rows, end = (r + 1) * rays / rows;
    for (uint64_t j = first; j + 1 < end; j += 2) pair(static_cast<uint32_t>(j));
  }
}

}  // namespace visq::obscurance
