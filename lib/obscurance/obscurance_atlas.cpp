#include "obscurance/obscurance_atlas.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <numeric>
#include <unordered_map>

namespace visq::obscurance {
namespace {

double Cross2(const glm::dvec2& a, const glm::dvec2& b) { return a.x * b.y - a.y * b.x; }

// Sutherland-Hodgman against one half plane keep(p) >= 0, keep linear.
template <typename Keep>
void ClipAgainst(ClippedPolygon& poly, Keep keep) {
  ClippedPolygon out;
  for (int i = 0; i < poly.n; ++i) {
    const glm::dvec2& a = poly.p[i];
    const glm::dvec2& b = poly.p[(i + 1) % poly.n];
    const double ka = keep(a), kb = keep(b);
    if (ka >= 0) out.p[out.n++] = a;
    if ((ka >= 0) != (kb >= 0)) out.p[out.n++] = a + (b - a) * (ka / (ka - kb));
  }
  poly = out;
}

// The texels a triangle's fragments can lie in: its atlas box, clamped to
// the atlas. A triangle of no atlas area, or with a corner that is not
// finite, is degenerate: one fragment, in the texel of its centroid
// (clamped; texel 0 when it is not finite), given as x0, y0.
struct TriangleTexels {
  bool degenerate = false;
  uint32_t x0 = 0, y0 = 0, x1 = 0, y1 = 0;  // inclusive
};

uint32_t ClampTexel(double v, uint32_t resolution) {
  const double f = std::floor(v);
  if (!(f >= 0.0)) return 0;  // NaN too
  return f >= resolution - 1.0 ? resolution - 1 : static_cast<uint32_t>(f);
}

TriangleTexels TexelsOf(const glm::dvec2& a, const glm::dvec2& b, const glm::dvec2& c, uint32_t resolution) {
  TriangleTexels box;
  const double uv_area = 0.5 * std::abs(Cross2(b - a, c - a));
  if (!(uv_area > 1e-12) || !std::isfinite(uv_area)) {
    const glm::dvec2 m = (a + b + c) / 3.0;
    box.degenerate = true;
    box.x0 = box.x1 = ClampTexel(m.x, resolution);
    box.y0 = box.y1 = ClampTexel(m.y, resolution);
    return box;
  }
  const glm::dvec2 lo = glm::min(a, glm::min(b, c)), hi = glm::max(a, glm::max(b, c));
  box.x0 = ClampTexel(lo.x, resolution);
  box.y0 = ClampTexel(lo.y, resolution);
  box.x1 = ClampTexel(hi.x, resolution);
  box.y1 = ClampTexel(hi.y, resolution);
  return box;
}

struct Chart {
  std::vector<uint32_t> triangles;
  glm::dvec3 axis_u{0.0}, axis_v{0.0};
  glm::dvec2 lo{0.0}, hi{0.0};  // projected bounds, world units
  glm::dvec2 offset{0.0};       // placed corner, texels
};

// Welded vertex ids, so that charts grow across vertices the file split.
std::vector<uint32_t> WeldPositions(const Scene& placed_scene) {
  const Scene& scene = placed_scene.Flattened();
  const double extent = std::max(1e-30, glm::length(scene.bounds.Extent()));
  const double cell = extent * 1e-7;
  std::unordered_map<uint64_t, uint32_t> ids;
  std::vector<uint32_t> weld(scene.positions.size());
  for (size_t i = 0; i < scene.positions.size(); ++i) {
    const glm::dvec3 q = glm::floor((scene.positions[i] - scene.bounds.min) / cell + 0.5);
    const uint64_t key = (static_cast<uint64_t>(q.x) * 73856093ull) ^ (static_cast<uint64_t>(q.y) * 19349663ull * 1000003ull) ^
                         (static_cast<uint64_t>(q.z) * 83492791ull * 998244353ull);
    // Hash collisions only merge charts' adjacency, never geometry: harmless.
    weld[i] = ids.emplace(key, static_cast<uint32_t>(i)).first->second;
  }
  return weld;
}

// Shelf packing, tallest first. False if the charts do not fit.
bool Pack(std::vector<Chart>& charts, const std::vector<uint32_t>& order, double scale, uint32_t gutter,
          uint32_t width, uint32_t height) {
  double x = 0, y = 0, shelf = 0;
  for (uint32_t c : order) {
    Chart& chart = charts[c];
    const double w = std::ceil((chart.hi.x - chart.lo.x) * scale + 1e-3) + 2.0 * gutter;
    const double h = std::ceil((chart.hi.y - chart.lo.y) * scale + 1e-3) + 2.0 * gutter;
    if (w > width) return false;
    if (x + w > width) { x = 0; y += shelf; shelf = 0; }
    if (y + h > height) return false;
    chart.offset = glm::dvec2(x + gutter, y + gutter);
    x += w;
    shelf = std::max(shelf, h);
  }
  return true;
}

StatusOr<std::vector<glm::vec2>> BuildCharts(const Scene& placed_scene, uint32_t resolution, const AtlasOptions& options,
                                             uint32_t* chart_count, double* texels_per_unit) {
  const Scene& scene = placed_scene.Flattened();
  const size_t nt = scene.TriangleCount();
  std::vector<glm::dvec3> normal(nt);
  std::vector<double> area(nt);
  for (size_t t = 0; t < nt; ++t) {
    const glm::dvec3 n = glm::cross(scene.Vertex(t, 1) - scene.Vertex(t, 0), scene.Vertex(t, 2) - scene.Vertex(t, 0));
    area[t] = 0.5 * glm::length(n);
    normal[t] = area[t] > 0 ? n / (2.0 * area[t]) : glm::dvec3(0.0, 0.0, 1.0);
  }
  // Edge adjacency over welded vertices.
  const std::vector<uint32_t> weld = WeldPositions(scene);
  std::unordered_map<uint64_t, std::vector<uint32_t>> edges;
  edges.reserve(nt * 3);
  auto edge_key = [&](uint32_t a, uint32_t b) {
    a = weld[a]; b = weld[b];
    if (a > b) std::swap(a, b);
    return (static_cast<uint64_t>(a) << 32) | b;
  };
  for (size_t t = 0; t < nt; ++t)
    for (int c = 0; c < 3; ++c)
      edges[edge_key(scene.triangles[t][c], scene.triangles[t][(c + 1) % 3])].push_back(static_cast<uint32_t>(t));

  // Grow charts breadth-first from the largest unassigned triangle, within
  // one node and a normal cone around the seed.
  std::vector<uint32_t> by_area(nt);
  std::iota(by_area.begin(), by_area.end(), 0u);
  // Areas are compared rounded to 2^-24 of the largest: triangles of equal
  // area (the rings of a turned pot) then keep their index order wherever
  // the object stands, so moving a node rigidly and building the atlas
  // again gives the same charts (exact areas differ in the last bits after
  // a move, and would pick other seeds).
  double largest = 0;
  for (double a : area) largest = std::max(largest, a);
  std::vector<double> area_key(nt);
  const double quantum = largest > 0 ? largest * 0x1p-24 : 1.0;
  for (size_t t = 0; t < nt; ++t) area_key[t] = std::round(area[t] / quantum);
  std::stable_sort(by_area.begin(), by_area.end(), [&](uint32_t a, uint32_t b) { return area_key[a] > area_key[b]; });
  std::vector<int32_t> chart_of(nt, -1);
  std::vector<Chart> charts;
  std::vector<uint32_t> queue;
  for (uint32_t seed : by_area) {
    if (chart_of[seed] >= 0) continue;
    const int32_t id = static_cast<int32_t>(charts.size());
    Chart chart;
    const glm::dvec3 n0 = normal[seed];
    queue.assign(1, seed);
    chart_of[seed] = id;
    for (size_t q = 0; q < queue.size(); ++q) {
      const uint32_t t = queue[q];
      chart.triangles.push_back(t);
      if (area[t] <= 0) continue;  // a degenerate triangle never joins others
      for (int c = 0; c < 3; ++c) {
        for (uint32_t other : edges[edge_key(scene.triangles[t][c], scene.triangles[t][(c + 1) % 3])]) {
          if (chart_of[other] >= 0 || area[other] <= 0) continue;
          if (scene.triangle_node[other] != scene.triangle_node[seed]) continue;
          if (glm::dot(normal[other], n0) < options.chart_normal_cos) continue;
          chart_of[other] = id;
          queue.push_back(other);
        }
      }
    }
    // Project onto the plane of the seed normal.
    const glm::dvec3 helper = std::abs(n0.x) < 0.9 ? glm::dvec3(1, 0, 0) : glm::dvec3(0, 1, 0);
    chart.axis_u = glm::normalize(glm::cross(helper, n0));
    chart.axis_v = glm::cross(n0, chart.axis_u);
    chart.lo = glm::dvec2(std::numeric_limits<double>::infinity());
    chart.hi = -chart.lo;
    for (uint32_t t : chart.triangles)
      for (int c = 0; c < 3; ++c) {
        const glm::dvec3 p = scene.Vertex(t, c);
        const glm::dvec2 q(glm::dot(p, chart.axis_u), glm::dot(p, chart.axis_v));
        chart.lo = glm::min(chart.lo, q);
        chart.hi = glm::max(chart.hi, q);
      }
    charts.push_back(std::move(chart));
  }

  // Pack at the largest uniform scale that fits: start from the scale at
  // which the charts' areas alone would fill the atlas and shrink.
  std::vector<uint32_t> order(charts.size());
  std::iota(order.begin(), order.end(), 0u);
  // Heights rounded like the areas above: charts of equal height (the sides
  // of a turned pot) keep their order when the node moves.
  double tallest = 0;
  for (const Chart& c : charts) tallest = std::max(tallest, c.hi.y - c.lo.y);
  const double height_quantum = tallest > 0 ? tallest * 0x1p-24 : 1.0;
  std::vector<double> height_key(charts.size());
  for (size_t c = 0; c < charts.size(); ++c)
    height_key[c] = std::round((charts[c].hi.y - charts[c].lo.y) / height_quantum);
  std::stable_sort(order.begin(), order.end(), [&](uint32_t a, uint32_t b) { return height_key[a] > height_key[b]; });
  double box_area = 0;
  for (const Chart& c : charts) box_area += std::max(1e-30, (c.hi.x - c.lo.x) * (c.hi.y - c.lo.y));
  double scale = std::sqrt(static_cast<double>(resolution) * resolution / box_area);
  bool packed = false;
  for (int attempt = 0; attempt < 200 && !packed; ++attempt) {
    packed = Pack(charts, order, scale, options.gutter, resolution, resolution);
    if (!packed) scale *= 0.95;
  }
  if (!packed)
    return absl::InvalidArgumentError(absl::StrCat("resolution: ", resolution, " is too small for the scene's ",
                                                   charts.size(), " atlas charts"));
  // Grow back in small steps while it still fits (the shrink overshoots).
  for (int attempt = 0; attempt < 20; ++attempt) {
    if (!Pack(charts, order, scale * 1.01, options.gutter, resolution, resolution)) break;
    scale *= 1.01;
  }
  Pack(charts, order, scale, options.gutter, resolution, resolution);

  std::vector<glm::vec2> corner_uv(nt * 3);
  for (const Chart& chart : charts)
    for (uint32_t t : chart.triangles)
      for (int c = 0; c < 3; ++c) {
        const glm::dvec3 p = scene.Vertex(t, c);
        const glm::dvec2 q(glm::dot(p, chart.axis_u), glm::dot(p, chart.axis_v));
        corner_uv[3 * t + c] = glm::vec2(chart.offset + (q - chart.lo) * scale);
      }
  *chart_count = static_cast<uint32_t>(charts.size());
  *texels_per_unit = scale;
  return corner_uv;
}

}  // namespace

double ClippedPolygon::Area() const {
  double a = 0;
  for (int i = 0; i < n; ++i) a += Cross2(p[i], p[(i + 1) % n]);
  return 0.5 * std::abs(a);
}

ClippedPolygon ClipTriangleToTexel(const glm::dvec2& a, const glm::dvec2& b, const glm::dvec2& c, uint32_t x,
                                   uint32_t y) {
  ClippedPolygon poly;
  poly.p[0] = a; poly.p[1] = b; poly.p[2] = c;
  poly.n = 3;
  const double x0 = x, x1 = x + 1.0, y0 = y, y1 = y + 1.0;
  ClipAgainst(poly, [&](const glm::dvec2& p) { return p.x - x0; });
  if (poly.n) ClipAgainst(poly, [&](const glm::dvec2& p) { return x1 - p.x; });
  if (poly.n) ClipAgainst(poly, [&](const glm::dvec2& p) { return p.y - y0; });
  if (poly.n) ClipAgainst(poly, [&](const glm::dvec2& p) { return y1 - p.y; });
  return poly;
}

StatusOr<ObscuranceAtlas> BuildObscuranceAtlas(const Scene& placed_scene, uint32_t resolution, const AtlasOptions& options) {
  const Scene& scene = placed_scene.Flattened();
  if (resolution == 0 || resolution > kMaxAtlasResolution)
    return absl::InvalidArgumentError(
        absl::StrCat("resolution: ", resolution, " must be in [1, ", kMaxAtlasResolution, "]"));
  if (scene.TriangleCount() == 0) return absl::InvalidArgumentError("scene: no triangles to bake");
  auto stopped = [&](const char* where) { return options.stop.Check(absl::StrCat("obscurance atlas, ", where)); };
  ObscuranceAtlas atlas;
  atlas.width = atlas.height = resolution;
  const size_t nt = scene.TriangleCount();

  // Atlas coordinates per corner: the file's lightmap UVs or our charts.
  if (!scene.lightmap_uvs.empty() && !options.force_build) {
    atlas.from_lightmap_uvs = true;
    atlas.corner_uv.resize(nt * 3);
    for (size_t t = 0; t < nt; ++t)
      for (int c = 0; c < 3; ++c)
        atlas.corner_uv[3 * t + c] = scene.lightmap_uvs[scene.triangles[t][c]] * static_cast<float>(resolution);
  } else {
    VISQ_ASSIGN_OR_RETURN(atlas.corner_uv,
                          BuildCharts(scene, resolution, options, &atlas.chart_count, &atlas.texels_per_unit));
  }
  VISQ_RETURN_IF_ERROR(stopped("after its charts"));

  // What the fragments can cost, before any of them exists: four full-UV
  // quads at 4096^2 are 67M fragments (2.4 GB), which a budget refuses here.
  const AtlasWorkEstimate estimate = AtlasWorkBytes(atlas.corner_uv, resolution);
  if (estimate.fragments > std::numeric_limits<uint32_t>::max())
    return absl::ResourceExhaustedError(absl::StrCat("resolution: ", resolution, " makes up to ", estimate.fragments,
                                                     " triangle-texel fragments, above the atlas's 2^32"));
  if (options.reserve) VISQ_RETURN_IF_ERROR(options.reserve(estimate.bytes));

  // Fragments: each triangle clipped against the texels its box touches;
  // the world area of a piece is its atlas area times the triangle's
  // world-to-atlas area ratio (the map is affine on a triangle).
  std::vector<PatchFragment> fragments;
  fragments.reserve(estimate.fragments);
  uint64_t clipped_since_check = 0;
  constexpr uint64_t kTexelsBetweenStopChecks = 16384;
  for (size_t t = 0; t < nt; ++t) {
    const glm::dvec2 a = atlas.corner_uv[3 * t], b = atlas.corner_uv[3 * t + 1], c = atlas.corner_uv[3 * t + 2];
    const double world = 0.5 * glm::length(glm::cross(scene.Vertex(t, 1) - scene.Vertex(t, 0),
                                                      scene.Vertex(t, 2) - scene.Vertex(t, 0)));
    if (world <= 0) continue;
    const TriangleTexels box = TexelsOf(a, b, c, resolution);
    if (box.degenerate) {
      // Degenerate in the atlas (lightmap UVs can be): the whole triangle
      // belongs to the texel of its centroid.
      fragments.push_back({box.y0 * resolution + box.x0, static_cast<uint32_t>(t), world});
      continue;
    }
    const double uv_area = 0.5 * std::abs(Cross2(b - a, c - a));
    for (uint32_t y = box.y0; y <= box.y1; ++y) {
      for (uint32_t x = box.x0; x <= box.x1; ++x) {
        const double piece = ClipTriangleToTexel(a, b, c, x, y).Area();
        if (piece > uv_area * 1e-9) fragments.push_back({y * resolution + x, static_cast<uint32_t>(t), piece / uv_area * world});
      }
      // One full-atlas triangle is 16M clips at 4096^2: ask between rows.
      clipped_since_check += box.x1 - box.x0 + 1;
      if (clipped_since_check >= kTexelsBetweenStopChecks) {
        clipped_since_check = 0;
        VISQ_RETURN_IF_ERROR(stopped("while clipping triangles to texels"));
      }
    }
  }
  VISQ_RETURN_IF_ERROR(stopped("before sorting its fragments"));

  // Fragments by texel, stable (triangle order within a texel): a counting
  // sort, linear in the fragments.
  atlas.texel_begin.assign(static_cast<size_t>(resolution) * resolution + 1, 0);
  for (const PatchFragment& f : fragments) ++atlas.texel_begin[f.texel + 1];
  std::partial_sum(atlas.texel_begin.begin(), atlas.texel_begin.end(), atlas.texel_begin.begin());
  {
    std::vector<PatchFragment> sorted(fragments.size());
    // texel_begin[i] walks to the end of texel i, then is put back.
    for (const PatchFragment& f : fragments) sorted[atlas.texel_begin[f.texel]++] = f;
    for (size_t i = atlas.texel_begin.size() - 1; i > 0; --i) atlas.texel_begin[i] = atlas.texel_begin[i - 1];
    atlas.texel_begin[0] = 0;
    fragments = std::move(sorted);
  }
  atlas.triangle_begin.assign(nt + 1, 0);
  for (const PatchFragment& f : fragments) ++atlas.triangle_begin[f.triangle + 1];
  std::partial_sum(atlas.triangle_begin.begin(), atlas.triangle_begin.end(), atlas.triangle_begin.begin());
  atlas.triangle_fragments.resize(fragments.size());
  std::vector<uint32_t> cursor(atlas.triangle_begin.begin(), atlas.triangle_begin.end() - 1);
  for (uint32_t i = 0; i < fragments.size(); ++i) atlas.triangle_fragments[cursor[fragments[i].triangle]++] = i;
  atlas.fragments = std::move(fragments);
  return atlas;
}

AtlasWorkEstimate AtlasWorkBytes(const std::vector<glm::vec2>& corner_uv, uint32_t resolution) {
  AtlasWorkEstimate out;
  const uint64_t nt = corner_uv.size() / 3;
  for (uint64_t t = 0; t < nt; ++t) {
    const glm::dvec2 a = corner_uv[3 * t], b = corner_uv[3 * t + 1], c = corner_uv[3 * t + 2];
    const TriangleTexels box = TexelsOf(a, b, c, resolution);
    if (box.degenerate) {
      out.fragments += 1;
      continue;
    }
    const uint64_t box_texels = uint64_t{box.x1 - box.x0 + 1} * (box.y1 - box.y0 + 1);
    const glm::dvec2 extent = glm::max(a, glm::max(b, c)) - glm::min(a, glm::min(b, c));
    const double met = 0.5 * std::abs(Cross2(b - a, c - a)) + 2.0 * (extent.x + extent.y) + 4.0;
    out.fragments += met < double(box_texels) ? static_cast<uint64_t>(met) : box_texels;
  }
  // Per fragment: itself, its copy in the sort, its index per triangle;
  // per texel and per triangle an offset (and the triangles' cursors); the
  // corner coordinates.
  out.bytes = out.fragments * (2 * sizeof(PatchFragment) + sizeof(uint32_t)) +
              (uint64_t{resolution} * resolution + 1) * sizeof(uint32_t) + (nt + 1) * 2 * sizeof(uint32_t) +
              corner_uv.size() * sizeof(glm::vec2);
  return out;
}

}  // namespace visq::obscurance
