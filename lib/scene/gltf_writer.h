// Writes a scene model as glTF 2.0 (.gltf + .bin, or .glb): for the sample
// scenes the project generates and for tests that build scenes in code.
#pragma once

#include <filesystem>

#include "common/status.h"
#include "scene/scene.h"

namespace visq {

// One glTF node per SceneNode (world-space positions, identity transforms,
// parents kept), one primitive per material of the node.
[[nodiscard]] Status WriteGltfFile(const Scene& scene, const std::filesystem::path& path);

}  // namespace visq
