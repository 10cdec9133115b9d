// A baked obscurance solution in the form a game mesh takes: the atlas UV
// of every triangle corner, and the scene as binary glTF with those UVs as
// TEXCOORD_1 and W as the occlusion texture.
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

// The scene with one vertex per triangle corner (a built atlas cuts charts
// apart, so corners of one position may have different UVs), those UVs as
// TEXCOORD_1, and `w` (RGB per texel, in [0, 1]) as an 8-bit PNG that every
// material reads as its occlusion texture. Nodes, names and materials are
// kept; positions are world space, as the scene holds them.
[[nodiscard]] StatusOr<std::string> BakedSceneGlb(const Scene& scene, const std::vector<glm::vec2>& corner_uv,
                                                  uint32_t width, uint32_t height, const std::vector<glm::vec3>& w);

}  // namespace visq::obscurance
