// glTF 2.0 (.gltf + buffers, .glb, data URIs) into the resident scene model.
#pragma once

#include <filesystem>
#include <string>
#include <vector>

#include "common/status.h"
#include "scene/scene.h"

namespace visq {

struct GltfLoadReport {
  // One line per kind of content the scene model does not keep ("3 textures",
  // "1 animation"), so the log can say in one line what was dropped.
  std::vector<std::string> dropped;
  size_t ignored_primitives = 0;  // points and lines
};

// Loads the default scene (or the first) of a glTF file, flattening the node
// hierarchy to world space. Malformed or unsupported content is
// INVALID_ARGUMENT with a message naming the offending element.
[[nodiscard]] StatusOr<Scene> LoadGltfFile(const std::filesystem::path& path,
                                           GltfLoadReport* report = nullptr);

}  // namespace visq
