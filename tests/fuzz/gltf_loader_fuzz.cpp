// libFuzzer target: arbitrary bytes as a .gltf (JSON) or .glb file. The
// loader must return a Status for every input: never crash, hang or read
// out of bounds (run under AddressSanitizer and UBSan). Small limits, as in
// gltf_structure_fuzz.cpp: an input within the defaults (2^27 triangles) can
// take minutes under the sanitizers, and any expansion that escapes the
// limits meets -rss_limit_mb.
#include <unistd.h>

#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <string>

#include "scene/gltf_loader.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  // The first byte picks the container, the rest is the file.
  if (size < 1) return 0;
  static const std::filesystem::path dir = [] {
    auto d = std::filesystem::temp_directory_path() / ("visq-fuzz-" + std::to_string(::getpid()));
    std::filesystem::create_directories(d);
    return d;
  }();
  const auto path = dir / ((data[0] & 1) ? "input.glb" : "input.gltf");
  if (std::FILE* f = std::fopen(path.c_str(), "wb")) {
    std::fwrite(data + 1, 1, size - 1, f);
    std::fclose(f);
  }
  visq::GltfLoadReport report;
  visq::GltfLoadLimits limits;
  limits.max_triangles = uint64_t{1} << 20;
  limits.max_scene_bytes = uint64_t{256} << 20;
  visq::StatusOr<visq::Scene> scene = visq::LoadGltfFile(path, &report, limits);
  if (scene.ok() && scene->TriangleCount() == 0) __builtin_trap();  // the loader promises triangles
  if (scene.ok() && scene->TriangleCount() > limits.max_triangles) __builtin_trap();
  return 0;
}
