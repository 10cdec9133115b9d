// The GL side of a GpuScene. Layout, for every algorithm's shaders (which
// read a corner through scene_vertex.glsl):
// - positions: vec3 float corners, non-indexed (3 per triangle), bound to
//   attribute 0 of `vertex_array`: first the unplaced triangles, in the
//   scene's order and relative to the anchor; then each held mesh once, in
//   its own space.
// - placements: one record per segment of the scene's triangle order (a run
//   of unplaced triangles, or one placement of a held mesh), and record 0,
//   the identity: three float rows of the affine map to anchor-relative
//   space and the triangle offset (scene triangle = buffer corner / 3 +
//   offset), attributes 1-4 with divisor 1, so that a draw's base instance
//   picks its record.
// - cluster_order: the element buffer of `vertex_array`, each part's corners
//   in the order of its TriangleClusters (the unplaced part's from element
//   0), so that a cull's clusters are index ranges of one buffer.
// - whole_draw: the indirect commands of GpuScene::Whole(), one a segment.
// - triangle_materials: std430 uint per triangle of the buffer (material
//   index, at gl_VertexID / 3: a held mesh's placements share their
//   materials), for algorithms that need colors (bind as a shader storage
//   buffer).
// Non-indexed costs 3x the index-buffer layout's vertex memory but gives
// every algorithm the triangle id for free without a geometry shader.
#pragma once

#include <cstdint>

#include "gl_object.h"
#include "visq/gpu/gpu_scene.h"

namespace visq::gpu {

// One placement record, as attributes 1-4 read it.
struct PlacementRecord {
  float rows[3][4];
  int32_t triangle_offset;
  int32_t unused[3];
};
static_assert(sizeof(PlacementRecord) == 64);

struct GpuScene::Resources {
  GlBuffer positions;
  GlBuffer placements;
  GlBuffer triangle_materials;
  GlBuffer cluster_order;
  GlBuffer whole_draw;
  GlVertexArray vertex_array;
  GLsizei whole_draws = 0;
};

}  // namespace visq::gpu
