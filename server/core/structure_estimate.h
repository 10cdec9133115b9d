// What a resident scene will hold once every structure its queries build
// exists: the geometry (known at load), the Embree BVH, the exact method's
// triangle index and the GPU buffers. --max-scene-bytes admits a scene by
// this estimate, so a scene that fits as geometry but not once queried is
// refused at load instead of failing a query later.
#pragma once

#include <cstdint>

#include "scene/scene.h"

namespace visq {

// Bytes per triangle of each structure, measured with
// `visq_bench_structures --copies 16 --repeat 5` (tests/bench/structure_bench.cpp)
// on Sponza (66K triangles), Veach's "ajar" room (383K) and the bunny (69K),
// each alone and as 16 copies (1.06M to 6.1M triangles):
//   Embree BVH, MEDIUM (Engine's resident BVH): 82.4-93.6; HIGH 82.8-102.5.
//     Embree's own float32 copy of the vertices and indices included.
//   triangle index (exact::SceneTriangleIndex): 73.9-83.6.
//   GPU buffers: 40 exactly (3 float32 corners and a material index).
// Each constant is the largest measured, rounded up.
inline constexpr uint64_t kEmbreeBvhBytesPerTriangle = 96;
inline constexpr uint64_t kTriangleIndexBytesPerTriangle = 86;
inline constexpr uint64_t kGpuBytesPerTriangle = 40;

struct StructureEstimate {
  uint64_t scene_bytes = 0;           // the geometry as loaded (Scene::CpuBytes)
  uint64_t embree_bvh_bytes = 0;
  uint64_t triangle_index_bytes = 0;
  uint64_t gpu_bytes = 0;

  uint64_t cpu_bytes() const { return scene_bytes + embree_bvh_bytes + triangle_index_bytes; }
  uint64_t total_bytes() const { return cpu_bytes() + gpu_bytes; }
};

StructureEstimate EstimateStructures(const Scene& scene);

}  // namespace visq
