// Writes a scene model as glTF 2.0 (.gltf + .bin, or .glb): for the sample
// scenes the project generates and for tests that build scenes in code.
#pragma once

#include <filesystem>
#include <string>

#include "common/status.h"
#include "scene/scene.h"

namespace visq {

// One glTF node per SceneNode (parents kept), one primitive per material of
// the node. Positions are world space under identity transforms, except in
// a node centred 1024 or more from the origin: there they are relative to
// the node's centre, rounded to a whole unit, which its translation adds
// back, so that far geometry keeps its detail through float32 accessors.
[[nodiscard]] Status WriteGltfFile(const Scene& scene, const std::filesystem::path& path);

// What a written scene may carry beyond its geometry and materials.
struct GltfExtras {
  // A PNG that every material takes as its occlusionTexture, read through
  // TEXCOORD_1 (the scene's lightmap_uvs): a baked obscurance atlas.
  std::string occlusion_png;
};

// The same document as one binary glTF (.glb) in memory, with the extras.
[[nodiscard]] StatusOr<std::string> WriteGlb(const Scene& scene, const GltfExtras& extras = {});

}  // namespace visq
