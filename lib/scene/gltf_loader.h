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
  // The external files the geometry was read from (buffers; images are
  // never read), resolved: an upload stores these and its main file only.
  std::vector<std::filesystem::path> files_read;
};

// What one glTF file may reach and produce. Every file is hostile: its URIs
// may point anywhere, and a kilobyte of nodes that share children can
// flatten to billions of triangles.
struct GltfLoadLimits {
  // External buffers and images resolve, after percent-decoding, to files
  // inside this folder only (an upload's staging folder, a repository
  // scene's own folder). Empty: the main file's folder. Absolute URIs, paths
  // that leave the folder, hidden names and the working directory are
  // refused.
  std::filesystem::path file_root;
  // Counted from the document before anything is flattened.
  uint64_t max_triangles = uint64_t{1} << 27;
  uint64_t max_scene_bytes = uint64_t{8} << 30;  // Scene::CpuBytes, estimated
  // Meshes placed by nodes and EXT_mesh_gpu_instancing instances, whatever
  // their triangles: a mesh without any, instanced 2^40 times by a sparse
  // accessor of one value, is a kilobyte of JSON. Each placement also counts
  // its matrices in max_scene_bytes.
  uint64_t max_placements = uint64_t{1} << 24;
  int max_node_depth = 1024;                       // root = depth 1
};

// Loads the default scene (or the first) of a glTF file, flattening the node
// hierarchy to world space. Malformed or unsupported content, and URIs that
// leave `limits.file_root`, are INVALID_ARGUMENT with a message naming the
// offending element; a document that would flatten beyond the limits is
// RESOURCE_EXHAUSTED, refused before it is flattened.
[[nodiscard]] StatusOr<Scene> LoadGltfFile(const std::filesystem::path& path, GltfLoadReport* report = nullptr,
                                           const GltfLoadLimits& limits = {});

}  // namespace visq
