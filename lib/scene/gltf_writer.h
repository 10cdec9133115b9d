// Writes a scene model as glTF 2.0 (.gltf + .bin, or .glb): for the sample
// scenes the project generates and for tests that build scenes in code.
#pragma once

#include <filesystem>
#include <string>
#include <vector>

#include <glm/glm.hpp>

#include "common/status.h"
#include "scene/scene.h"

namespace visq {

// One glTF node per SceneNode (parents kept), one primitive per run of the
// node's triangles with one material (the loader's primitives again, the
// triangles in their order), indexed, its vertices the scene's positions that its triangles
// use (split only where corners of one position read the occlusion texture
// through different UVs), with the scene's normals and texture coordinate
// sets (TEXCOORD_1 = lightmap_uvs; where a scene has lightmap UVs and no
// TEXCOORD_0, they stand in as set 0 too, which glTF requires). Positions are world space under identity transforms, except in
// a node centred 1024 or more from the origin: there they are relative to
// the node's centre, rounded to a whole unit, which its translation adds
// back, so that far geometry keeps its detail through float32 accessors.
[[nodiscard]] Status WriteGltfFile(const Scene& scene, const std::filesystem::path& path);

// What a written scene may carry beyond its geometry and materials.
struct GltfExtras {
  // A PNG that every material takes as its occlusionTexture: a baked
  // obscurance atlas.
  std::string occlusion_png;
  // The UV through which each triangle corner reads occlusion_png (3 per
  // triangle, in the scene's triangle order), written as one more TEXCOORD
  // set after the scene's own. Empty: the texture is read through
  // TEXCOORD_1, the scene's lightmap_uvs.
  std::vector<glm::vec2> occlusion_uv;
  // COLOR_0 per scene position (linear RGB in [0, 1]); empty: none.
  std::vector<glm::vec3> vertex_colors;
};

// The same document as one binary glTF (.glb) in memory, with the extras.
[[nodiscard]] StatusOr<std::string> WriteGlb(const Scene& scene, const GltfExtras& extras = {});

}  // namespace visq
