// A baked obscurance solution in the form a game mesh takes: the atlas UV
// of every triangle corner, and the scene as binary glTF with those UVs as a
// TEXCOORD set of its own and W as the occlusion texture (and COLOR_0).
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include <glm/glm.hpp>

#include "common/status.h"
#include "scene/scene.h"

namespace visq::obscurance {

// The atlas coordinates of ObscuranceAtlas::corner_uv (texels) as glTF UVs:
// u = x / width, v = y / height, two floats per corner, three corners per
// triangle in the scene's triangle order. Texel (x, y) of the W atlas (index
// y * width + x) covers [x, x + 1] / width × [y, y + 1] / height; row 0 is
// the image's top row, as glTF has it.
std::vector<float> AtlasUvs(const std::vector<glm::vec2>& corner_uv, uint32_t width, uint32_t height);

// What a baked scene's glTF carries beyond the scene and its W atlas.
struct BakedSceneOptions {
  // The atlas is the scene's TEXCOORD_1 (ObscuranceAtlas::from_lightmap_uvs):
  // W is read through that set, and no set is added.
  bool atlas_is_lightmap_uvs = false;
  // W per scene position (ObscuranceResult::vertex_w, the area-weighted mean
  // of its triangles') as COLOR_0, which DCC viewports and renderers show
  // where they ignore glTF's occlusion texture. Empty: no COLOR_0.
  std::vector<glm::vec3> vertex_w;
};

// The scene as the studio's tools read it back: its nodes, names,
// materials, positions, normals and texture coordinate sets kept, indexed
// (a position is split only where a built atlas cuts its corners apart),
// with the atlas UVs as the TEXCOORD set after the scene's own (so
// TEXCOORD_0 when the scene has none) unless the atlas is TEXCOORD_1, and
// `w` (RGB per texel, in [0, 1]) as an 8-bit PNG that every material reads
// as its occlusion texture through that set. Positions are world space, as
// the scene holds them (gltf_writer.h).
[[nodiscard]] StatusOr<std::string> BakedSceneGlb(const Scene& scene, const std::vector<glm::vec2>& corner_uv,
                                                  uint32_t width, uint32_t height, const std::vector<glm::vec3>& w,
                                                  BakedSceneOptions options = {});

}  // namespace visq::obscurance
