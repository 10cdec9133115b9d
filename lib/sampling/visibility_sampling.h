// The sampled-visibility model shared by every method that answers a
// hidden-sample map or patch-to-patch visibility (Eisemann & Décoret 2007):
// patches, requests, results and their error bounds, the source and
// receiver sample positions, and the checks on a request. The GPU path
// (gpu/hidden_sample_map), the Embree reference and the exact method all
// speak these types, so none of them reaches into another for a type.
//
// A source patch S carries N explicit samples S_i; a receiver patch R is
// sampled implicitly at the texel centres R_j of a W x H grid. For every R_j
// the answer is the set B_j of source samples whose open segment (R_j, S_i) is
// blocked by a scene triangle: the hidden-sample map.
//
// Segment semantics: only the part of a triangle strictly between the two
// endpoints counts; triangles behind the receiver or beyond the source block
// nothing, triangles crossing either plane block with their part between
// them, and (as in visq::raycast::EmbreeScene::Occluded) geometry closer than
// delta = 2^-17 * max(extent / 8, |patch corner|) to the source plane or to
// the receiver point is ignored, so the light's own quad and the floor under
// the receiver never block.
#pragma once

#include <cstddef>
#include <cstdint>
#include <functional>
#include <vector>

#include <glm/glm.hpp>

#include "common/band.h"
#include "common/job_timing.h"
#include "common/normal_estimate.h"
#include "common/status.h"
#include "scene/scene.h"

namespace visq::sampling {

// The parallelogram origin + s * edge_u + t * edge_v, (s, t) in [0, 1]^2, in
// world coordinates.
struct Patch {
  glm::dvec3 origin{0.0};
  glm::dvec3 edge_u{1.0, 0.0, 0.0};
  glm::dvec3 edge_v{0.0, 1.0, 0.0};
  glm::dvec3 At(double s, double t) const { return origin + s * edge_u + t * edge_v; }
};

enum class SamplePattern {
  kRegular,   // the centre of each of N equal-area cells (StratifiedSamplePattern)
  kJittered,  // one uniform sample in each of the same cells, seeded
  kCustom,    // SourceSpec::custom_uv as given
};

// The (s, t) positions of a kRegular or kJittered pattern of n samples. The
// patch is cut into n cells of equal area, so every sample stands for 1/n of
// the source for every n: round(sqrt n) rows along edge_v, row j holding
// floor((j + 1) n / rows) - floor(j n / rows) cells of equal width, each
// row's height its count / n. Cells are near square (their sides differ by
// less than one cell in a row). Row-major order, cells along edge_u. A grid
// of ceil(sqrt n) columns filled row by row would leave the last row partly
// empty, and its strip of the source under-weighted: a biased estimate.
[[nodiscard]] std::vector<glm::dvec2> StratifiedSamplePattern(int n, SamplePattern pattern, uint64_t seed);

// Bounds hidden-sample-map lookups (section 5).
enum class LookupMode {
  // The default: Hough-table lookups decide every sample that lies clearly on
  // one side of every edge; the few samples the table cell cannot decide
  // (its ambiguity mask) are tested exactly against the back-projected edge.
  // The bits are those of the exact segment test (= Embree on the same
  // segments, up to floating-point ties).
  kExact,
  // The paper's pure lookup, conservative towards "blocked"; each answer
  // carries a per-texel bound on its lookup error.
  kHough,
};

// Source samples per request: 1024 per pass (8 RGBA32UI targets), 4 passes.
inline constexpr int kMaxHiddenSampleMapSamples = 4096;

struct SourceSpec {
  Patch patch;
  int sample_count = 64;  // [1, 4096]: samples over the whole rectangle
  SamplePattern pattern = SamplePattern::kRegular;
  uint64_t seed = 1;                   // kJittered
  std::vector<glm::dvec2> custom_uv;   // kCustom: (s, t) in [0, 1]^2, one per sample
  // Optional light shape: a simple polygon in (s, t). Samples outside it are
  // dropped (sample_count counts samples over the rectangle; at least one
  // must remain).
  std::vector<glm::dvec2> polygon_uv;
  // Optional colours (section 8, colored / textured lights): either one
  // colour per sample that remains after the polygon, or a texture over the
  // patch (row-major, texel (0,0) at s = t = 0), looked up nearest per sample.
  std::vector<glm::vec3> sample_colors;
  int color_texture_width = 0, color_texture_height = 0;
  std::vector<glm::vec3> color_texture;
};

struct ReceiverSpec {
  Patch patch;
  int width = 64, height = 64;  // [1, 4096] each
  // Optional bumpy receiver (section 8): width * height heights, row-major,
  // offsetting each texel centre along the unit normal normalize(edge_u x
  // edge_v). Every displaced point must stay strictly on the receiver side of
  // the source plane.
  std::vector<float> heightfield;
};

struct HiddenSampleMapOptions {
  LookupMode lookup = LookupMode::kExact;
  // Hough bitmask table (theta x r texels); [16, 2048] each.
  int hough_theta_resolution = 256;
  int hough_r_resolution = 256;
  // Section 6.2: each receiver texel sees the pattern moved by its own offset
  // (DecorrelationOffset), trading aliasing for noise.
  bool decorrelate = false;
  uint32_t decorrelation_seed = 0;
  // Section 7: skip triangles front-facing from all 4 source corners. Only
  // valid for closed casters with both patches outside them.
  bool watertight = false;
  bool want_bitmasks = false;
  // Confidence of the sampling-error bound (Hoeffding), in (0, 1).
  double confidence = 0.95;
};

struct HiddenSampleMapRequest {
  SourceSpec source;
  ReceiverSpec receiver;
  HiddenSampleMapOptions options;
};

// The source samples actually used: CPU-computed once, shared by the GPU path
// and by any CPU reference (RAYCAST), so both test the same segments.
struct SourceSamples {
  std::vector<glm::dvec2> uv;       // (s, t) on the source patch
  std::vector<glm::dvec3> world;    // source.patch.At(s, t)
  std::vector<glm::vec3> color;     // empty unless colours were given
  int requested = 0;                // sample_count before the polygon
};

struct ErrorBound {
  // Hoeffding: with probability >= confidence, |visible fraction over N
  // samples - true visible fraction over the source| <= sqrt(ln(2 /
  // (1 - confidence)) / (2 N)) per texel. Rigorous when the samples are one
  // independent uniform sample in each of N equal-area cells (`rigorous`:
  // kJittered, no polygon, no decorrelation); for other sample sets (kRegular,
  // kCustom, PatchVisibility's grids) it is the half-width N such samples
  // would have: an estimate, not a guarantee.
  double sampling = 0.0;
  bool rigorous = false;
  double confidence = 0.95;
  // Lookup error, as a fraction of N: 0 for kExact (up to floating-point
  // ties); for kHough the largest per-texel bound (true blocked set B
  // satisfies sure <= B <= answer, see lookup_per_texel).
  double lookup_max = 0.0;
  std::vector<float> lookup_per_texel;  // kHough only: (|answer| - |sure|) / N
  // Rigorous sample sets only: each texel's own bound from its count of
  // visible samples and its split pairs (sampling/count_intervals.h), the
  // lookup's part included; with probability >= confidence, |answer_j -
  // true_j| <= per_texel[j]. `per_texel_max` is the largest, and the map's
  // bound.
  bool has_per_texel = false;
  bool per_texel_split_pairs = false;  // the split pairs' bound taken where smaller
  double per_texel_max = 0.0;
  std::vector<float> per_texel;
  // Beside the bounds, where the split pairs were counted (any N): each
  // texel's estimate, not a bound: the normal approximation's half-width at
  // the variance the split pairs estimate (EstimateOfTexel), at
  // `confidence`. `estimate_max` is the largest, `estimate_spread` their
  // spread over the map (bands are not held whole), `per_texel_estimate`
  // each, when the map is delivered whole.
  bool has_estimate = false;
  double estimate_max = 0.0;
  LogSpread estimate_spread;
  std::vector<float> per_texel_estimate;
  double total() const { return has_per_texel ? per_texel_max : sampling + lookup_max; }
};

struct HiddenSampleMapResult {
  int width = 0, height = 0;
  int sample_count = 0;    // N, after the polygon
  int words_per_texel = 0;  // ceil(N / 32)
  // Per texel, row-major (index y * width + x; x along edge_u, y along edge_v).
  std::vector<float> visible_fraction;
  std::vector<glm::vec3> visible_rgb;  // (1/N) sum of unblocked sample colours; if colours
  // Raw hidden-sample map (want_bitmasks): texel j's words are
  // [j * words_per_texel, (j + 1) * words_per_texel); source sample i is bit
  // (i % 32) of word (i / 32); a set bit means BLOCKED. Bits >= N are 0.
  std::vector<uint32_t> blocked_bits;
  ErrorBound error;
  JobTiming timing;       // the GL job (queue + run, readback included)
  double table_ms = 0.0;  // building the Hough table on the CPU (0 if cached)
  int passes = 0;
  SourceSamples samples;
};

// A map's texels [first, first + texels()) as they are made, a band of
// receiver rows at a time, so a large map is sent while it is drawn and
// never held whole. The arrays are laid out as HiddenSampleMapResult's, from
// the band's first texel.
struct HiddenSampleMapBand : BandPlace {
  std::vector<float> visible_fraction;
  std::vector<glm::vec3> visible_rgb;     // coloured lights only
  std::vector<uint32_t> blocked_bits;     // want_bitmasks only
  std::vector<float> lookup_error;        // kHough only: ErrorBound::lookup_per_texel's values
  std::vector<float> texel_error;         // rigorous sample sets only: ErrorBound::per_texel's values
  std::vector<float> texel_estimate;      // where split pairs were counted: ErrorBound::per_texel_estimate's
  // For BoundTexels, not sent: per texel, the pairs of pattern cells
  // (2i, 2i + 1) whose samples disagree, one blocked and one visible (with
  // the Hough lookup, the most that can); summed over `split_pair_maps`
  // maps of sample_count / split_pair_maps samples each. Empty where the
  // method does not count them: the count's bound alone then.
  std::vector<int32_t> split_pairs;
  int split_pair_maps = 1;
  size_t texels() const { return visible_fraction.size(); }
};

// With the map's figures (sizes, samples) known before any band.
using HiddenSampleMapBandSink = BandSink<HiddenSampleMapResult, HiddenSampleMapBand>;

// For a rigorous sample set (SamplesAreIndependentStrata): the bound of
// each of `band`'s texels from its count of visible samples, its split
// pairs where counted, and its lookup error, into band.texel_error, and the
// largest into map.error. Every sampled method calls it on each band before
// delivering it.
// Where the band's split pairs were counted, also each texel's estimate
// into band.texel_estimate (EstimateOfTexel) and their spread into
// map.error.
void BoundTexels(const HiddenSampleMapRequest& request, HiddenSampleMapResult& map, HiddenSampleMapBand& band);

// A texel's estimate beside its bound. For independent samples, one in each
// of n cells, the visible count's variance is the sum of the cells'
// p(1 - p); a pair of cells disagrees with probability p(1 - p) + q(1 - q)
// + (p - q)^2, so the `split_pairs` count is an estimate of the variance
// from above (by the squared difference of neighbouring cells, small where
// visibility changes smoothly), and each of the `unpaired` cells adds at
// most 1/4. A texel that saw both visible and hidden samples with no pair
// split is given one split pair's variance, not zero; its estimate is
// z(confidence) times that standard deviation over n. A texel whose samples
// all agree is given ln(1 / (1 - confidence)) / n, what agreeing samples
// can hide at that confidence (docs/texel-bounds.md). Both add the count's
// lookup uncertainty (`lookup_samples`, the Hough lookup's) and the float
// rounding of `answer`, and are never above `bound`, the texel's rigorous
// one.
float EstimateOfTexel(int n, int visible, int lookup_samples, int split_pairs, int unpaired, float answer, double z,
                      float bound);

// Hands `band` to `sink`, or, without a sink, appends it to `map`'s own
// arrays (a map answered whole). Every method that makes maps ends its
// bands here.
[[nodiscard]] Status DeliverBand(HiddenSampleMapResult& map, const HiddenSampleMapBand& band,
                                 const HiddenSampleMapBandSink& sink);

// Source sample positions for `source` (validated). Deterministic.
[[nodiscard]] StatusOr<SourceSamples> ComputeSourceSamples(const SourceSpec& source);

// Receiver sample j = (x, y): the texel centre, lifted by the heightfield.
glm::dvec3 ReceiverSamplePosition(const ReceiverSpec& receiver, int x, int y);

// Decorrelation offset of texel (x, y) in (s, t) units: the pattern seen from
// that texel is uv_i + offset. Integer hash, bit-identical on CPU and GPU;
// each component in [-0.5, 0.5) / ceil(sqrt(N)) (half a grid cell), so
// samples may sit up to that far outside the patch.
glm::vec2 DecorrelationOffset(uint32_t seed, int x, int y, int sample_count);

// World position of source sample i as seen from receiver texel (x, y)
// (with decorrelation applied when enabled).
glm::dvec3 SourceSampleSeenFrom(const HiddenSampleMapRequest& request, const SourceSamples& samples, int i,
                                int x, int y);

// INVALID_ARGUMENT naming the field and value for every bad parameter.
[[nodiscard]] Status ValidateHiddenSampleMapRequest(const HiddenSampleMapRequest& request);

struct PatchVisibilityRequest {
  Patch source;
  int source_columns = 32, source_rows = 32;  // regular grid, cell centres
  Patch receiver;
  int receiver_columns = 32, receiver_rows = 32;  // texel centres
  LookupMode lookup = LookupMode::kExact;
  bool watertight = false;
  size_t unblocked_limit = 0;  // how many unblocked pairs to list (0: none)
};

struct UnblockedPair {
  uint32_t source_sample;    // row * source_columns + column
  uint32_t receiver_sample;  // row * receiver_columns + column
};

struct PatchVisibilityResult {
  double mutual_visible_fraction = 0.0;     // unblocked pairs / all pairs
  std::vector<float> source_visible;        // per source sample: fraction of receiver samples it sees
  std::vector<float> receiver_visible;      // per receiver sample: fraction of source samples it sees
  std::vector<UnblockedPair> unblocked;     // in (receiver, source) order, at most unblocked_limit
  uint64_t unblocked_total = 0;
  ErrorBound error;
  JobTiming timing;
};

// Where every segment of a query lies: the source corners (moved out by the
// decorrelation offsets' reach) and the receiver corners (raised and lowered
// by the heightfield's extremes), world space.
struct QueryHull {
  std::vector<glm::dvec3> source;    // 4 corners
  std::vector<glm::dvec3> receiver;  // 4 or 8 corners
  Bounds Box() const;
};
QueryHull HullOf(const HiddenSampleMapRequest& request);

// The float32 copy of the geometry a sampled query is traced against:
// positions stored as float(p - origin), lying in `bounds` (world space).
struct FloatFrame {
  glm::dvec3 origin{0.0};
  Bounds bounds;
};

// How the tracer resolves a segment in float32.
enum class SegmentTracer {
  // The hidden-sample map: each triangle back-projected in the source's
  // frame, so both ends carry the rounding of the whole configuration.
  kRaster,
  // Embree, a ray from the receiver point towards the source sample: its
  // origin end keeps the precision of the receiver's own coordinates, its
  // far end that of the longer of the two (raycast::EmbreeScene::Occluded).
  kRaycast,
};

// Geometry closer than these to a segment's ends is ignored, so that the
// surfaces the ends lie on do not block their own segments. 2^-17 (128
// float ulps) of the magnitudes involved: the ends' coordinates relative to
// the frame origin, 1/8 of the stored geometry's extent (the rounding of
// the triangles through an end), and for RASTER 1/8 of the query's extent.
struct EndpointTolerances {
  double source = 0.0;    // around each source sample
  double receiver = 0.0;  // around each receiver point
};

// The tolerances of `request` in `frame`. FAILED_PRECONDITION, naming the
// end ("source" or "receiver") and the anchor, when geometry lies within an
// end's tolerance of its patch while the tolerance exceeds 1/4 of that end's
// sample spacing (source: sqrt(area / N); receiver: the texel), so that the
// ignored occluders would change the answer: a small query far from the
// frame's origin. An end with no geometry near it (a light far out in empty
// space) may have any tolerance.
[[nodiscard]] StatusOr<EndpointTolerances> ResolvableEndpointTolerances(const HiddenSampleMapRequest& request,
                                                                        const FloatFrame& frame,
                                                                        SegmentTracer tracer);

// Whether `tolerances` ignore at most 1/128 of a sample spacing at each end
// (ResolvableEndpointTolerances' spacings): an occluder must then lie within
// that share of a spacing of an end to be missed, as in a scene of a few
// hundred units traced at its own centre. Coarser tolerances may still
// resolve the query (at most 1/4), but they hide occluders that a frame
// nearer the query would see: the bits would change with geometry far from
// it (a copy of the scene 1e3 to 1e5 away).
bool TolerancesAreNegligible(const HiddenSampleMapRequest& request, const EndpointTolerances& tolerances);
inline constexpr double kNegligibleToleranceShare = 1.0 / 128.0;

// Whether the request's samples support Hoeffding's bound as a guarantee
// (ErrorBound::rigorous).
bool SamplesAreIndependentStrata(const HiddenSampleMapRequest& request);

// Hoeffding half-width of N samples' mean at `confidence`: the sampling
// part of every bound this module reports.
double SamplingErrorBound(int sample_count, double confidence);

// Patch visibility is a hidden-sample map whose source samples are the
// source grid's cell centers and whose receiver texels are the receiver
// grid's cells; these two functions are that mapping, shared by the GPU path
// and any other method producing the same map (ray casting).
[[nodiscard]] StatusOr<HiddenSampleMapRequest> PatchVisibilityAsHiddenSampleMap(const PatchVisibilityRequest& request);
PatchVisibilityResult SummarizePatchVisibility(const PatchVisibilityRequest& request,
                                               const HiddenSampleMapResult& map);

}  // namespace visq::sampling
