// The sampled-visibility model's functions: validation, the source samples,
// the receiver samples, the decorrelation offsets, the mapping of patch
// visibility onto a hidden-sample map, and the bounds. Everything here is
// shared by the GPU path and the CPU references, so all test the same
// segments.
#include <algorithm>
#include <bit>
#include <cmath>
#include <limits>
#include <numbers>
#include <string>

#include "sampling/visibility_sampling.h"
#include "common/check.h"
#include "sampling/count_intervals.h"
#include "common/random.h"
#include "common/coordinates.h"

namespace visq::sampling {
namespace {

std::string Vec(const glm::dvec3& v) { return absl::StrCat("(", v.x, ", ", v.y, ", ", v.z, ")"); }
// Finite and within visq's coordinate range (common/coordinates.h).

Status ValidatePatch(const Patch& p, const std::string& field) {
  if (!InCoordinateRange(p.origin)) return absl::InvalidArgumentError(absl::StrCat(field, ".origin: non-finite or beyond ±1e15 ", Vec(p.origin)));
  if (!InCoordinateRange(p.edge_u)) return absl::InvalidArgumentError(absl::StrCat(field, ".edge_u: non-finite or beyond ±1e15 ", Vec(p.edge_u)));
  if (!InCoordinateRange(p.edge_v)) return absl::InvalidArgumentError(absl::StrCat(field, ".edge_v: non-finite or beyond ±1e15 ", Vec(p.edge_v)));
  const double area = glm::length(glm::cross(p.edge_u, p.edge_v));
  if (!(area > 1e-12 * glm::length(p.edge_u) * glm::length(p.edge_v)) || area == 0.0)
    return absl::InvalidArgumentError(absl::StrCat(field, ": degenerate patch, edge_u ", Vec(p.edge_u), " edge_v ",
                                                   Vec(p.edge_v)));
  return absl::OkStatus();
}

bool InsidePolygon(const std::vector<glm::dvec2>& poly, const glm::dvec2& p) {
  bool inside = false;
  for (size_t i = 0, j = poly.size() - 1; i < poly.size(); j = i++) {
    if ((poly[i].y > p.y) != (poly[j].y > p.y) &&
        p.x < (poly[j].x - poly[i].x) * (p.y - poly[i].y) / (poly[j].y - poly[i].y) + poly[i].x)
      inside = !inside;
  }
  return inside;
}

uint32_t Hash(uint32_t h) {
  h ^= h >> 16; h *= 0x7feb352du; h ^= h >> 15; h *= 0x846ca68bu; h ^= h >> 16;
  return h;
}

// A size the caller chose: below 1 is malformed (INVALID_ARGUMENT), above
// the server's cap RESOURCE_EXHAUSTED, as every cap of every RPC is.
Status ValidateCount(int64_t value, int64_t cap, std::string_view field) {
  if (value < 1) return absl::InvalidArgumentError(absl::StrCat(AbslView(field), ": ", value, " (must be at least 1)"));
  if (value > cap)
    return absl::ResourceExhaustedError(absl::StrCat(AbslView(field), ": ", value, " exceeds the cap of ", cap));
  return absl::OkStatus();
}

}  // namespace

Status ValidateHiddenSampleMapRequest(const HiddenSampleMapRequest& request) {
  const SourceSpec& s = request.source;
  const ReceiverSpec& r = request.receiver;
  const HiddenSampleMapOptions& o = request.options;
  VISQ_RETURN_IF_ERROR(ValidatePatch(s.patch, "source"));
  VISQ_RETURN_IF_ERROR(ValidatePatch(r.patch, "receiver"));
  VISQ_RETURN_IF_ERROR(ValidateCount(s.sample_count, kMaxHiddenSampleMapSamples, "samples.count"));
  if (s.pattern == SamplePattern::kCustom) {
    if (static_cast<int>(s.custom_uv.size()) != s.sample_count)
      return absl::InvalidArgumentError(absl::StrCat("samples.custom_uv: ", s.custom_uv.size(),
                                                     " positions for samples.count ", s.sample_count));
    for (size_t i = 0; i < s.custom_uv.size(); ++i) {
      const glm::dvec2 uv = s.custom_uv[i];
      if (!(uv.x >= 0.0 && uv.x <= 1.0 && uv.y >= 0.0 && uv.y <= 1.0))
        return absl::InvalidArgumentError(
            absl::StrCat("samples.custom_uv[", i, "]: (", uv.x, ", ", uv.y, ") not in [0, 1]^2"));
    }
  } else if (s.pattern != SamplePattern::kRegular && s.pattern != SamplePattern::kJittered) {
    return absl::InvalidArgumentError(absl::StrCat("samples.pattern: unknown value ", static_cast<int>(s.pattern)));
  }
  if (!s.polygon_uv.empty()) {
    if (s.polygon_uv.size() < 3)
      return absl::InvalidArgumentError(absl::StrCat("samples.polygon_uv: ", s.polygon_uv.size(), " vertices, need 3"));
    for (size_t i = 0; i < s.polygon_uv.size(); ++i)
      if (!std::isfinite(s.polygon_uv[i].x) || !std::isfinite(s.polygon_uv[i].y))
        return absl::InvalidArgumentError(absl::StrCat("samples.polygon_uv[", i, "]: non-finite or beyond ±1e15 (",
                                                       s.polygon_uv[i].x, ", ", s.polygon_uv[i].y, ")"));
  }
  if (!s.color_texture.empty() || s.color_texture_width != 0 || s.color_texture_height != 0) {
    if (s.color_texture_width < 1 || s.color_texture_height < 1 ||
        s.color_texture.size() != size_t(s.color_texture_width) * s.color_texture_height)
      return absl::InvalidArgumentError(absl::StrCat("samples.color_texture_rgb: ", s.color_texture.size(), " texels for ",
                                                     s.color_texture_width, " x ", s.color_texture_height));
    if (!s.sample_colors.empty())
      return absl::InvalidArgumentError("samples.sample_colors: give either sample_colors or color_texture");
  }
  // Colours are light: finite, non-negative, and small enough that a sum of
  // 2^24 of them stays finite in float.
  constexpr double kMaxColor = 1e30;
  auto valid_color = [](const glm::dvec3& c) {
    // NaN fails every comparison, infinity the cap.
    return c.x >= 0 && c.y >= 0 && c.z >= 0 && c.x <= kMaxColor && c.y <= kMaxColor && c.z <= kMaxColor;
  };
  for (size_t i = 0; i < s.sample_colors.size(); ++i)
    if (!valid_color(s.sample_colors[i]))
      return absl::InvalidArgumentError(absl::StrCat("samples.sample_colors[", i, "]: ", Vec(s.sample_colors[i]),
                                                     " is not finite, non-negative and at most 1e30"));
  for (size_t i = 0; i < s.color_texture.size(); ++i)
    if (!valid_color(s.color_texture[i]))
      return absl::InvalidArgumentError(absl::StrCat("samples.color_texture_rgb[", 3 * i, "..", 3 * i + 2, "]: ",
                                                     Vec(s.color_texture[i]),
                                                     " is not finite, non-negative and at most 1e30"));
  VISQ_RETURN_IF_ERROR(ValidateCount(r.width, 4096, "width"));
  VISQ_RETURN_IF_ERROR(ValidateCount(r.height, 4096, "height"));
  if (!r.heightfield.empty() && r.heightfield.size() != size_t(r.width) * r.height)
    return absl::InvalidArgumentError(absl::StrCat("heightfield: ", r.heightfield.size(),
                                                   " heights for ", r.width, " x ", r.height, " texels"));
  float h_min = 0.0f, h_max = 0.0f;
  for (size_t i = 0; i < r.heightfield.size(); ++i) {
    if (!std::isfinite(r.heightfield[i]))
      return absl::InvalidArgumentError(absl::StrCat("heightfield[", i, "]: ", r.heightfield[i]));
    h_min = std::min(h_min, r.heightfield[i]);
    h_max = std::max(h_max, r.heightfield[i]);
  }
  if (o.lookup != LookupMode::kExact && o.lookup != LookupMode::kHough)
    return absl::InvalidArgumentError(absl::StrCat("lookup: unknown value ", static_cast<int>(o.lookup)));
  if (o.hough_theta_resolution < 16 || o.hough_theta_resolution > 2048)
    return absl::InvalidArgumentError(
        absl::StrCat("hough_resolution: ", o.hough_theta_resolution, " not in [16, 2048]"));
  if (o.hough_r_resolution < 16 || o.hough_r_resolution > 2048)
    return absl::InvalidArgumentError(
        absl::StrCat("hough_resolution: ", o.hough_r_resolution, " not in [16, 2048]"));
  const double table_bytes =
      2.0 * o.hough_theta_resolution * o.hough_r_resolution * ((s.sample_count + 127) / 128) * 16.0;
  if (table_bytes > 1024.0 * 1024 * 1024)
    return absl::InvalidArgumentError(absl::StrCat("hough_resolution: table of ", table_bytes / 1048576,
                                                   " MiB for ", s.sample_count, " samples exceeds 1024 MiB"));
  if (!(o.confidence > 0.0 && o.confidence < 1.0))
    return absl::InvalidArgumentError(absl::StrCat("confidence: ", o.confidence, " not in (0, 1)"));

  // Geometry: every receiver point strictly on one side of the source plane,
  // every source corner strictly in front of the (bumpy) receiver.
  const glm::dvec3 ns = glm::normalize(glm::cross(s.patch.edge_u, s.patch.edge_v));
  const glm::dvec3 nr = glm::normalize(glm::cross(r.patch.edge_u, r.patch.edge_v));
  int side = 0;
  for (double a : {0.0, 1.0})
    for (double b : {0.0, 1.0})
      for (double h : {double(h_min), double(h_max)}) {
        const double d = glm::dot(ns, r.patch.At(a, b) + h * nr - s.patch.origin);
        const int sd = d > 0 ? 1 : (d < 0 ? -1 : 0);
        if (sd == 0 || (side != 0 && sd != side))
          return absl::InvalidArgumentError(absl::StrCat("receiver: corner ", Vec(r.patch.At(a, b)),
                                                         " is on or across the source plane"));
        side = sd;
      }
  int rside = 0;
  for (double a : {0.0, 1.0})
    for (double b : {0.0, 1.0}) {
      const double e = glm::dot(nr, s.patch.At(a, b) - r.patch.origin);
      const int se = e > 0 ? 1 : (e < 0 ? -1 : 0);
      const double bump = se > 0 ? h_max : -h_min;
      if (se == 0 || (rside != 0 && se != rside) || std::abs(e) <= bump)
        return absl::InvalidArgumentError(absl::StrCat("source.patch: corner ", Vec(s.patch.At(a, b)),
                                                       " is not strictly in front of the receiver"));
      rside = se;
    }
  return absl::OkStatus();
}

std::vector<glm::dvec2> StratifiedSamplePattern(int n, SamplePattern pattern, uint64_t seed) {
  std::vector<glm::dvec2> uv;
  if (n < 1) return uv;
  uv.reserve(size_t(n));
  const int rows = std::max(1, static_cast<int>(std::lround(std::sqrt(double(n)))));
  SplitMix rng{seed};
  for (int row = 0; row < rows; ++row) {
    // Rows of floor and ceil(n / rows) cells, spread evenly (row j ends at
    // sample floor((j + 1) n / rows)); a row's height is its share of n.
    const int64_t first = int64_t(row) * n / rows, end = int64_t(row + 1) * n / rows;
    const int cells = static_cast<int>(end - first);
    const double v0 = double(first) / n, height = double(cells) / n;
    for (int c = 0; c < cells; ++c) {
      double ju = 0.5, jv = 0.5;
      if (pattern == SamplePattern::kJittered) { ju = rng.Uniform(); jv = rng.Uniform(); }
      uv.emplace_back((c + ju) / cells, v0 + jv * height);
    }
  }
  return uv;
}

StatusOr<SourceSamples> ComputeSourceSamples(const SourceSpec& source) {
  SourceSamples out;
  const int n = source.sample_count;
  VISQ_RETURN_IF_ERROR(ValidateCount(n, kMaxHiddenSampleMapSamples, "samples.count"));
  out.requested = n;
  std::vector<glm::dvec2> uv;
  if (source.pattern == SamplePattern::kCustom) {
    uv = source.custom_uv;
  } else {
    uv = StratifiedSamplePattern(n, source.pattern, source.seed);
  }
  for (const glm::dvec2& p : uv)
    if (source.polygon_uv.empty() || InsidePolygon(source.polygon_uv, p)) out.uv.push_back(p);
  if (out.uv.empty())
    return absl::InvalidArgumentError(absl::StrCat("samples.polygon_uv: none of the ", n, " samples is inside"));
  for (const glm::dvec2& p : out.uv) out.world.push_back(source.patch.At(p.x, p.y));
  if (!source.sample_colors.empty()) {
    if (source.sample_colors.size() != out.uv.size())
      return absl::InvalidArgumentError(absl::StrCat("samples.sample_colors: ", source.sample_colors.size(),
                                                     " colours for ", out.uv.size(), " samples"));
    out.color = source.sample_colors;
  } else if (!source.color_texture.empty()) {
    for (const glm::dvec2& p : out.uv) {
      const int x = std::clamp(int(p.x * source.color_texture_width), 0, source.color_texture_width - 1);
      const int y = std::clamp(int(p.y * source.color_texture_height), 0, source.color_texture_height - 1);
      out.color.push_back(source.color_texture[size_t(y) * source.color_texture_width + x]);
    }
  }
  return out;
}

glm::dvec3 ReceiverSamplePosition(const ReceiverSpec& receiver, int x, int y) {
  glm::dvec3 p = receiver.patch.At((x + 0.5) / receiver.width, (y + 0.5) / receiver.height);
  if (!receiver.heightfield.empty())
    p += double(receiver.heightfield[size_t(y) * receiver.width + x]) *
         glm::normalize(glm::cross(receiver.patch.edge_u, receiver.patch.edge_v));
  return p;
}

glm::vec2 DecorrelationOffset(uint32_t seed, int x, int y, int sample_count) {
  const float amplitude = 1.0f / std::ceil(std::sqrt(float(sample_count)));
  const uint32_t h = Hash(uint32_t(x) * 0x9E3779B1u ^ Hash(uint32_t(y) * 0x85EBCA77u ^ seed));
  const uint32_t g = Hash(h ^ 0x68bc21ebu);
  constexpr float kScale = 1.0f / 16777216.0f;
  return {(float(h >> 8) * kScale - 0.5f) * amplitude, (float(g >> 8) * kScale - 0.5f) * amplitude};
}

glm::dvec3 SourceSampleSeenFrom(const HiddenSampleMapRequest& request, const SourceSamples& samples, int i, int x,
                                int y) {
  if (!request.options.decorrelate) return samples.world[i];
  const glm::vec2 o = DecorrelationOffset(request.options.decorrelation_seed, x, y, request.source.sample_count);
  return request.source.patch.At(samples.uv[i].x + double(o.x), samples.uv[i].y + double(o.y));
}


StatusOr<HiddenSampleMapRequest> PatchVisibilityAsHiddenSampleMap(const PatchVisibilityRequest& request) {
  VISQ_RETURN_IF_ERROR(ValidateCount(request.source_columns, kMaxHiddenSampleMapSamples, "source_columns"));
  VISQ_RETURN_IF_ERROR(ValidateCount(request.source_rows, kMaxHiddenSampleMapSamples, "source_rows"));
  VISQ_RETURN_IF_ERROR(ValidateCount(int64_t(request.source_columns) * request.source_rows, kMaxHiddenSampleMapSamples,
                                  "source_columns x source_rows"));
  VISQ_RETURN_IF_ERROR(ValidateCount(request.receiver_columns, 4096, "receiver_columns"));
  VISQ_RETURN_IF_ERROR(ValidateCount(request.receiver_rows, 4096, "receiver_rows"));
  HiddenSampleMapRequest map;
  map.source.patch = request.source;
  map.source.sample_count = request.source_columns * request.source_rows;
  map.source.pattern = SamplePattern::kCustom;
  for (int r = 0; r < request.source_rows; ++r)
    for (int c = 0; c < request.source_columns; ++c)
      map.source.custom_uv.emplace_back((c + 0.5) / request.source_columns, (r + 0.5) / request.source_rows);
  map.receiver.patch = request.receiver;
  map.receiver.width = request.receiver_columns;
  map.receiver.height = request.receiver_rows;
  map.options.lookup = request.lookup;
  map.options.watertight = request.watertight;
  map.options.want_bitmasks = true;
  return map;
}

PatchVisibilityResult SummarizePatchVisibility(const PatchVisibilityRequest& request,
                                               const HiddenSampleMapResult& hsm) {
  PatchVisibilityResult out;
  const int ns = hsm.sample_count, nr = hsm.width * hsm.height, wpt = hsm.words_per_texel;
  out.source_visible.assign(ns, 0.0f);
  out.receiver_visible.resize(nr);
  std::vector<uint32_t> source_seen(ns, 0);
  uint64_t unblocked = 0;
  for (int j = 0; j < nr; ++j) {
    out.receiver_visible[j] = hsm.visible_fraction[j];
    for (int i = 0; i < ns; ++i) {
      if ((hsm.blocked_bits[size_t(j) * wpt + i / 32] >> (i % 32)) & 1u) continue;
      ++source_seen[i];
      ++unblocked;
      if (out.unblocked.size() < request.unblocked_limit)
        out.unblocked.push_back({static_cast<uint32_t>(i), static_cast<uint32_t>(j)});
    }
  }
  for (int i = 0; i < ns; ++i) out.source_visible[i] = float(source_seen[i]) / float(nr);
  out.unblocked_total = unblocked;
  out.mutual_visible_fraction = double(unblocked) / (double(ns) * nr);
  out.error = hsm.error;
  // Both sides are sampled: the mean over ns * nr pairs.
  out.error.sampling = SamplingErrorBound(ns, hsm.error.confidence);
  out.error.rigorous = false;  // regular grids: an estimate
  out.timing = hsm.timing;
  return out;
}

Bounds QueryHull::Box() const {
  Bounds box;
  for (const glm::dvec3& p : source) box.Extend(p);
  for (const glm::dvec3& p : receiver) box.Extend(p);
  return box;
}

QueryHull HullOf(const HiddenSampleMapRequest& request) {
  QueryHull hull;
  const Patch& sp = request.source.patch;
  const Patch& rp = request.receiver.patch;
  const double spread =
      request.options.decorrelate ? 0.5 / std::ceil(std::sqrt(double(std::max(request.source.sample_count, 1)))) : 0.0;
  for (int k = 0; k < 4; ++k)
    hull.source.push_back(sp.At((k & 1) ? 1.0 + spread : -spread, (k & 2) ? 1.0 + spread : -spread));
  double lo = 0.0, hi = 0.0;
  for (float h : request.receiver.heightfield) {
    lo = std::min(lo, double(h));
    hi = std::max(hi, double(h));
  }
  const glm::dvec3 normal = glm::normalize(glm::cross(rp.edge_u, rp.edge_v));
  for (int k = 0; k < 4; ++k) {
    hull.receiver.push_back(rp.At(k & 1, k >> 1) + lo * normal);
    if (hi != lo) hull.receiver.push_back(rp.At(k & 1, k >> 1) + hi * normal);
  }
  return hull;
}

namespace {

double LargestCoordinate(const std::vector<glm::dvec3>& points, const glm::dvec3& origin) {
  double m = 0.0;
  for (const glm::dvec3& p : points) {
    const glm::dvec3 q = p - origin;
    m = std::max({m, std::abs(q.x), std::abs(q.y), std::abs(q.z)});
  }
  return m;
}

// Distance between two boxes (0 when they meet); infinite when one is empty.
double BoxDistance(const Bounds& a, const Bounds& b) {
  if (a.Empty() || b.Empty()) return std::numeric_limits<double>::infinity();
  const glm::dvec3 gap = glm::max(glm::dvec3(0.0), glm::max(a.min - b.max, b.min - a.max));
  return glm::length(gap);
}

// The sample spacing at each end: the source's sqrt(area / N), the
// receiver's texel (its shorter side).
struct Spacings {
  double source = 0.0;
  double receiver = 0.0;
};
Spacings SpacingsOf(const HiddenSampleMapRequest& request) {
  const Patch& sp = request.source.patch;
  const Patch& rp = request.receiver.patch;
  return {std::sqrt(glm::length(glm::cross(sp.edge_u, sp.edge_v)) / double(std::max(request.source.sample_count, 1))),
          std::min(glm::length(rp.edge_u) / std::max(request.receiver.width, 1),
                   glm::length(rp.edge_v) / std::max(request.receiver.height, 1))};
}

// Refuses an end whose tolerance hides detail that could matter.
Status ValidateEndPrecision(const char* field, double tolerance, double spacing, const std::vector<glm::dvec3>& corners,
                const FloatFrame& frame, double magnitude) {
  if (tolerance <= spacing / 4.0) return absl::OkStatus();
  Bounds end;
  for (const glm::dvec3& p : corners) end.Extend(p);
  if (BoxDistance(end, frame.bounds) > 2.0 * tolerance) return absl::OkStatus();
  return absl::FailedPreconditionError(absl::StrCat(
      field, ": its samples lie ", magnitude, " from the float32 anchor of the geometry they are traced against, "
      "where occluders within ", tolerance, " of them cannot be resolved (more than 1/4 of the sample spacing ",
      spacing, "); the exact method (PLUCKER_EXACT) works in double precision there"));
}

}  // namespace

StatusOr<EndpointTolerances> ResolvableEndpointTolerances(const HiddenSampleMapRequest& request,
                                                          const FloatFrame& frame, SegmentTracer tracer) {
  const QueryHull hull = HullOf(request);
  const double source_magnitude = LargestCoordinate(hull.source, frame.origin);
  const double receiver_magnitude = LargestCoordinate(hull.receiver, frame.origin);
  const glm::dvec3 frame_extent = frame.bounds.Empty() ? glm::dvec3(0.0) : frame.bounds.Extent();
  const double geometry = std::max({frame_extent.x, frame_extent.y, frame_extent.z}) / 8.0;
  const glm::dvec3 query_extent = hull.Box().Extent();
  const double query = glm::length(query_extent) / 8.0;
  EndpointTolerances out;
  if (tracer == SegmentTracer::kRaycast) {
    out.receiver = std::ldexp(std::max(receiver_magnitude, geometry), -17);
    out.source = std::ldexp(std::max({source_magnitude, receiver_magnitude, geometry}), -17);
  } else {
    out.source = out.receiver = std::ldexp(std::max({source_magnitude, receiver_magnitude, geometry, query}), -17);
  }
  const Spacings spacing = SpacingsOf(request);
  VISQ_RETURN_IF_ERROR(ValidateEndPrecision("receiver", out.receiver, spacing.receiver, hull.receiver, frame, receiver_magnitude));
  VISQ_RETURN_IF_ERROR(ValidateEndPrecision("source", out.source, spacing.source, hull.source, frame, source_magnitude));
  return out;
}

bool TolerancesAreNegligible(const HiddenSampleMapRequest& request, const EndpointTolerances& tolerances) {
  const Spacings spacing = SpacingsOf(request);
  return tolerances.source <= kNegligibleToleranceShare * spacing.source &&
         tolerances.receiver <= kNegligibleToleranceShare * spacing.receiver;
}

bool SamplesAreIndependentStrata(const HiddenSampleMapRequest& request) {
  return request.source.pattern == SamplePattern::kJittered && request.source.polygon_uv.empty() &&
         !request.options.decorrelate;
}

double SamplingErrorBound(int sample_count, double confidence) {
  // Hoeffding: P(|mean - p| > e) <= 2 exp(-2 N e^2).
  return std::sqrt(std::log(2.0 / (1.0 - confidence)) / (2.0 * double(sample_count)));
}

// How the confidence's failure probability is shared where split pairs are
// counted: the count's Clopper-Pearson interval, the pairs' variance limit,
// and Bennett's deviation. The texel takes the smaller of the two bounds,
// which then hold together. These shares keep an all-visible texel's bound
// within 15 % of the count's alone and make a penumbra texel's 1.7x
// tighter at N = 1024 (docs/texel-bounds.md).
constexpr double kCountShare = 0.5, kPairsShare = 0.2, kDeviationShare = 0.3;
// Below this many samples a penumbra splits too few pairs for their bound
// to win back the confidence it takes from the count's (on every shared
// scene at N = 32 and 128): the count's interval alone. A rule of N, fixed
// before the samples are seen, so the bound stays rigorous.
constexpr int kFewestSamplesToPair = 256;

void BoundTexels(const HiddenSampleMapRequest& request, HiddenSampleMapResult& map, HiddenSampleMapBand& band) {
  if (!SamplesAreIndependentStrata(request) || map.sample_count <= 0) {
    band.texel_error.clear();
    band.texel_estimate.clear();
    return;
  }
  const int n = map.sample_count;
  const double failure = 1.0 - request.options.confidence;
  VISQ_CHECK(band.split_pairs.empty() || band.split_pairs.size() == band.texels());
  const bool paired = !band.split_pairs.empty() && n >= kFewestSamplesToPair;
  const std::shared_ptr<CountIntervals> limits =
      StratifiedCountIntervals(n, paired ? 1.0 - kCountShare * failure : request.options.confidence);
  std::shared_ptr<SplitPairBounds> pair_bounds;
  if (paired) {
    const int maps = band.split_pair_maps;
    VISQ_CHECK(maps >= 1 && n % maps == 0);
    const int per_map = n / maps;
    pair_bounds = CachedSplitPairBounds(maps * (per_map / 2), maps * (per_map % 2), n, kPairsShare * failure,
                                        kDeviationShare * failure);
  }
  map.error.has_per_texel = true;
  map.error.per_texel_split_pairs = paired;
  // Each texel's count is exact: (n - blocked) / n in float, for n <= 65536.
  // The Hough lookup may have called up to lookup_error * n visible samples
  // hidden: the samples' own count then lies in [visible, visible + that].
  std::vector<int> visible(band.texels()), most(band.texels());
  for (size_t t = 0; t < band.texels(); ++t) {
    visible[t] = std::clamp(static_cast<int>(std::lround(double(band.visible_fraction[t]) * n)), 0, n);
    const int maybe = band.lookup_error.empty() ? 0 : static_cast<int>(std::lround(double(band.lookup_error[t]) * n));
    most[t] = std::clamp(visible[t] + maybe, 0, n);
  }
  std::vector<int> counts = visible;
  counts.insert(counts.end(), most.begin(), most.end());
  std::sort(counts.begin(), counts.end());
  counts.erase(std::unique(counts.begin(), counts.end()), counts.end());
  limits->Prepare(counts);
  if (pair_bounds) {
    std::vector<int> splits(band.split_pairs.begin(), band.split_pairs.end());
    std::sort(splits.begin(), splits.end());
    splits.erase(std::unique(splits.begin(), splits.end()), splits.end());
    pair_bounds->Prepare(splits);
  }
  band.texel_error.resize(band.texels());
  for (size_t t = 0; t < band.texels(); ++t) {
    const float answer = band.visible_fraction[t];
    float error = std::max(answer - limits->Low(visible[t]), limits->High(most[t]) - answer);
    if (pair_bounds) {
      // The samples' own fraction lies in [visible / n, most / n], the
      // truth within the deviation of it; the answer is visible / n in float.
      const double rounding = std::abs(double(answer) - double(visible[t]) / n);
      const double bound = rounding + double(most[t] - visible[t]) / n + pair_bounds->Deviation(band.split_pairs[t]);
      error = std::min(error, std::nextafter(static_cast<float>(bound), 2.0f));
    }
    band.texel_error[t] = error;
    map.error.per_texel_max = std::max(map.error.per_texel_max, double(error));
  }

  band.texel_estimate.clear();
  if (band.split_pairs.empty() || !(request.options.confidence < 1.0)) return;
  const int maps = band.split_pair_maps;
  const int unpaired = maps * ((n / maps) % 2);
  const double z = TwoSidedNormalQuantile(request.options.confidence);
  map.error.has_estimate = true;
  band.texel_estimate.resize(band.texels());
  for (size_t t = 0; t < band.texels(); ++t) {
    const float estimate = EstimateOfTexel(n, visible[t], most[t] - visible[t], band.split_pairs[t], unpaired,
                                           band.visible_fraction[t], z, band.texel_error[t]);
    band.texel_estimate[t] = estimate;
    map.error.estimate_max = std::max(map.error.estimate_max, double(estimate));
    map.error.estimate_spread.Add(estimate);
  }
}

float EstimateOfTexel(int n, int visible, int lookup_samples, int split_pairs, int unpaired, float answer, double z,
                      float bound) {
  VISQ_DCHECK_LT(0, n);
  const bool mixed = visible < n && visible + lookup_samples > 0;
  // Where every sample agrees, the pairs say nothing of the variance. Cells
  // hidden with probabilities h_i (visible, for an all-hidden texel) all
  // show visible with probability prod(1 - h_i) <= exp(-sum h_i), so at
  // most 1 - confidence where the truth lies ln(1 / (1 - confidence)) cells'
  // worth away (3 at 95 %); 1 - confidence is erfc(z / sqrt 2).
  const double all_agree = -std::log(std::erfc(z / std::numbers::sqrt2));
  double counts = all_agree;
  if (mixed) {
    double variance = double(split_pairs) + 0.25 * unpaired;
    if (split_pairs == 0) variance = std::max(variance, 1.0);
    // Never narrower than where every sample agrees: one or two samples
    // that disagree say no more of a texel's spread than none (the normal
    // approximation at one or two split pairs covered 79 % of texels three
    // cells' worth hidden, docs/texel-bounds.md).
    counts = std::max(z * std::sqrt(variance), all_agree);
  }
  const double rounding = std::abs(double(answer) - double(visible) / n);
  const double estimate = rounding + double(lookup_samples) / n + counts / n;
  return std::min(bound, std::nextafter(static_cast<float>(std::min(1.0, estimate)), 2.0f));
}

Status DeliverBand(HiddenSampleMapResult& map, const HiddenSampleMapBand& band, const HiddenSampleMapBandSink& sink) {
  if (sink) return sink(map, band);
  const size_t texels = size_t(map.width) * size_t(map.height);
  VISQ_CHECK_EQ(band.first, map.visible_fraction.size());
  VISQ_CHECK_LE(band.first + band.texels(), texels);
  if (band.first == 0) {
    map.visible_fraction.reserve(texels);
    if (!band.visible_rgb.empty()) map.visible_rgb.reserve(texels);
    if (!band.blocked_bits.empty()) map.blocked_bits.reserve(texels * size_t(map.words_per_texel));
    if (!band.lookup_error.empty()) map.error.lookup_per_texel.reserve(texels);
    if (!band.texel_error.empty()) map.error.per_texel.reserve(texels);
    if (!band.texel_estimate.empty()) map.error.per_texel_estimate.reserve(texels);
  }
  map.visible_fraction.insert(map.visible_fraction.end(), band.visible_fraction.begin(), band.visible_fraction.end());
  map.visible_rgb.insert(map.visible_rgb.end(), band.visible_rgb.begin(), band.visible_rgb.end());
  map.blocked_bits.insert(map.blocked_bits.end(), band.blocked_bits.begin(), band.blocked_bits.end());
  map.error.lookup_per_texel.insert(map.error.lookup_per_texel.end(), band.lookup_error.begin(),
                                    band.lookup_error.end());
  map.error.per_texel.insert(map.error.per_texel.end(), band.texel_error.begin(), band.texel_error.end());
  map.error.per_texel_estimate.insert(map.error.per_texel_estimate.end(), band.texel_estimate.begin(),
                                      band.texel_estimate.end());
  return absl::OkStatus();
}

}  // namespace visq::sampling
