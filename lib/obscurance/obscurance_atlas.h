// The patches of the obscurance model: texels of one atlas over the whole
// scene (paper, section 4.1). The glTF's lightmap UVs (TEXCOORD_1) when the
// scene has them; otherwise an atlas built here: nearly planar charts grown
// over shared edges within one node, projected onto their mean plane,
// scaled uniformly (one texel size for the whole scene) and shelf-packed with
// a gutter around every chart.
#pragma once

#include <array>
#include <cstdint>
#include <functional>
#include <vector>

#include <glm/glm.hpp>

#include "common/status.h"
#include "common/stop_token.h"
#include "scene/scene.h"

namespace visq::obscurance {

inline constexpr uint32_t kMaxAtlasResolution = 8192;

struct AtlasOptions {
  // Empty texels around each chart (so 2 * gutter between two charts):
  // bilinear filtering at a chart's edge reads only its own texels or its
  // gutter, which the bake fills from the chart.
  uint32_t gutter = 1;
  // Triangles join a chart while their normal stays within this angle of the
  // chart's first triangle (cosine).
  double chart_normal_cos = 0.8;
  // Ignore TEXCOORD_1 and build an atlas anyway.
  bool force_build = false;
  // Called once, after the corner coordinates are known and before any
  // fragment is allocated, with an upper bound of the bytes the rest of the
  // build holds (AtlasWorkBytes): an error from it is the build's. The
  // server reserves its work budget here.
  std::function<Status(uint64_t bytes)> reserve;
  // Asked every few thousand texels clipped and between the build's
  // phases: once it says stop, the build returns its status ("obscurance
  // atlas, ...").
  StopToken stop;
};

// The part of one triangle that lies in one texel.
struct PatchFragment {
  uint32_t texel = 0;
  uint32_t triangle = 0;
  double world_area = 0;
};

struct ObscuranceAtlas {
  uint32_t width = 0, height = 0;
  bool from_lightmap_uvs = false;
  uint32_t chart_count = 0;     // built atlases only
  double texels_per_unit = 0;   // built atlases only
  // Atlas coordinates in texels ([0, width] x [0, height]) per triangle
  // corner, index 3 * triangle + corner.
  std::vector<glm::vec2> corner_uv;
  // Fragments sorted by texel; texel i owns [texel_begin[i], texel_begin[i+1]).
  std::vector<PatchFragment> fragments;
  std::vector<uint32_t> texel_begin;
  // Fragment indices per triangle: [triangle_begin[t], triangle_begin[t+1]) of
  // triangle_fragments.
  std::vector<uint32_t> triangle_fragments;
  std::vector<uint32_t> triangle_begin;

  uint32_t texel_count() const { return width * height; }
  bool Covered(uint32_t texel) const { return texel_begin[texel + 1] > texel_begin[texel]; }
};

// What an atlas's fragments can cost at most, found from its corner
// coordinates alone (no allocation): per triangle at most the texels of its
// clamped box, and at most its area plus twice its width and height plus 4
// in texels (the texels a convex shape meets lie in it grown by one texel
// each way); the fragments, the sort's second copy and the per-triangle
// index (36 bytes each), and the per-texel and per-triangle offsets.
struct AtlasWorkEstimate {
  uint64_t fragments = 0;  // upper bound
  uint64_t bytes = 0;
};
AtlasWorkEstimate AtlasWorkBytes(const std::vector<glm::vec2>& corner_uv, uint32_t resolution);

// INVALID_ARGUMENT for resolution 0 or above kMaxAtlasResolution
// ("resolution: 0 ..."), or a resolution too small for the scene's charts.
[[nodiscard]] StatusOr<ObscuranceAtlas> BuildObscuranceAtlas(const Scene& scene, uint32_t resolution,
                                                             const AtlasOptions& options = {});

// The convex polygon where a triangle (atlas coordinates) meets texel
// (x, y); at most 7 corners.
struct ClippedPolygon {
  std::array<glm::dvec2, 9> p;
  int n = 0;
  double Area() const;
};
ClippedPolygon ClipTriangleToTexel(const glm::dvec2& a, const glm::dvec2& b, const glm::dvec2& c, uint32_t x,
                                   uint32_t y);

}  // namespace visq::obscurance
