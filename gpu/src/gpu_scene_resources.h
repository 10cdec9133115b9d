// The GL side of a GpuScene. Layout, for every algorithm's shaders:
// - positions: one vec3 (float, relative to the anchor) per triangle corner,
//   non-indexed (3 per triangle), bound to attribute 0 of `vertex_array`;
//   gl_VertexID / 3 is the triangle id, which algorithms use to look up
//   per-triangle data.
// - cluster_order: the element buffer of `vertex_array`, every triangle's
//   three corners (3t, 3t + 1, 3t + 2) in the order of GpuScene::clusters(),
//   so that an algorithm draws the clusters a cull keeps as index ranges
//   (glMultiDrawElements) and still reads triangle t at gl_VertexID / 3.
// - triangle_materials: std430 uint per triangle (material index), for
//   algorithms that need colors (bind as a shader storage buffer).
// Non-indexed costs 3x the index-buffer layout's vertex memory but gives
// every algorithm the triangle id for free without a geometry shader.
#pragma once

#include "gl_object.h"
#include "visq/gpu/gpu_scene.h"

namespace visq::gpu {

struct GpuScene::Resources {
  GlBuffer positions;
  GlBuffer triangle_materials;
  GlBuffer cluster_order;
  GlVertexArray vertex_array;
  GLsizei vertex_count = 0;
};

}  // namespace visq::gpu
