#include "core/structure_estimate.h"

namespace visq::core {

StructureEstimate EstimateStructures(const Scene& scene) {
  const uint64_t triangles = scene.TriangleCount();
  StructureEstimate e;
  e.scene_bytes = scene.CpuBytes();
  e.embree_bvh_bytes = triangles * kEmbreeBvhBytesPerTriangle + scene.positions.size() * kEmbreeBvhBytesPerVertex;
  e.triangle_index_bytes = triangles * kTriangleIndexBytesPerTriangle;
  e.gpu_bytes = triangles * kGpuBytesPerTriangle;
  return e;
}

}  // namespace visq::core
