// What a resident scene will hold once every structure its queries build
// exists: the geometry (known at load), the Embree BVH, the exact method's
// triangle index and the GPU buffers. --max-scene-bytes admits a scene by
// this estimate, so a scene that fits as geometry but not once queried is
// refused at load instead of failing a query later. A placed scene's
// flattened copy (Scene::Flattened), which a bake or an export builds and
// the scene then keeps and counts, is not in it: no visibility query needs it.
#pragma once

#include <cstdint>

#include "scene/scene.h"

namespace visq::core {

// Bytes of each structure, measured with `visq_bench_structures --copies 16`
// (tests/bench/structure_bench.cpp) on Sponza (66K triangles, 0.94 vertices
// a triangle), Veach's "ajar" room (383K, 0.50) and the bunny (69K, 0.52),
// each alone and as 16 copies (1.06M to 6.1M triangles), and on the tests'
// generated grid (2M, 0.50):
//   Embree BVH at MEDIUM (the Engine's resident BVH): 82.4-93.6 a triangle,
//     of which Embree's float32 copy of the vertices is 12 a vertex and its
//     copy of the triangles' indices 12 a triangle; the rest 78.9-82.3 a
//     triangle (HIGH: 82.4-102.5 in all). A scene traced without instances
//     lends Embree its own indices (EmbreeSceneOptions::shared_scene):
//     72.9-73.1 a triangle on the ajar room and the bunny.
//   triangle index (exact::SceneTriangleIndex, which reads triangle boxes
//     off the scene it shares, over full leaves): 20.0 a triangle at every
//     size (66K to 20M).
//   GPU buffers: exactly what gpu::GpuScene::EstimateBytes says: 52 a
//     triangle it holds (3 float32 corners, a material index, 3 element
//     indices in the order of the triangle cluster hierarchy), and 80 for
//     each run of the scene's triangle order it draws with one placement
//     record.
// Each constant is the largest measured, rounded up.
//
// A mesh that the scene places more than once (Scene::placements) costs the
// CPU structures its triangles once and an instance per placement where
// they keep it as an instance (the BVH: EmbreeScene::TracedAsInstances; the
// index: every placement; the GPU buffers: every placement of at least
// kFewestTrianglesToInstance triangles).
// Per instance, measured over 1,000 and 10,000 placements of an
// 800-triangle grid: Embree 117-138 bytes, the index 194-220 (measured
// before it kept each placement's box: 48 bytes more now).
inline constexpr uint64_t kEmbreeBvhBytesPerTriangle = 84;
inline constexpr uint64_t kEmbreeSharedIndexBytesPerTriangle = 12;  // not copied when shared
inline constexpr uint64_t kEmbreeBvhBytesPerVertex = 12;
inline constexpr uint64_t kEmbreeBvhBytesPerInstance = 160;
inline constexpr uint64_t kTriangleIndexBytesPerTriangle = 21;
inline constexpr uint64_t kTriangleIndexBytesPerInstance = 280;
// GPU_RAYCAST's flat BVH (raycast::FlatBvh, on the GPU): 48 bytes of
// corners a flattened triangle and a 32-byte node per 1.1-1.4 triangles;
// measured with visq_bench_rays at 82.6 (Sponza), 83.6 (the ajar room) and
// 92.4 (the bunny) bytes a triangle. Built only when asked for, so it is not
// in the admission estimate; Engine::AdmitRayScene checks it then.
inline constexpr uint64_t kGpuRayBytesPerTriangle = 96;

struct StructureEstimate {
  uint64_t scene_bytes = 0;           // the geometry as loaded (Scene::CpuBytes)
  uint64_t embree_bvh_bytes = 0;
  uint64_t triangle_index_bytes = 0;
  uint64_t gpu_bytes = 0;
  // What the CPU structures hold: triangles held once, and instances.
  uint64_t unique_triangles = 0;
  uint64_t instances = 0;

  uint64_t cpu_bytes() const { return scene_bytes + embree_bvh_bytes + triangle_index_bytes; }
  uint64_t total_bytes() const { return cpu_bytes() + gpu_bytes; }
};

StructureEstimate EstimateStructures(const Scene& scene);

}  // namespace visq::core
