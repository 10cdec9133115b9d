#include "core/structure_estimate.h"
#include "scene/placement_checks.h"

#include <algorithm>

#include "common/check.h"
#include "raycast/embree_scene.h"
#include "visq/gpu/gpu_scene.h"

namespace visq::core {
namespace {

// Triangles, vertices and instances a structure holds when it keeps the
// placements marked in `as_instance` as instances and flattens the rest.
struct Held {
  uint64_t triangles = 0;
  uint64_t vertices = 0;
  uint64_t instances = 0;
};

Held HeldBy(const Scene& scene, const std::vector<uint8_t>& as_instance) {
  Held held;
  // Placements are disjoint by construction (ValidatePlacements checks it):
  // the triangles flattened are the scene's less those of the placements
  // kept as instances.
  uint64_t flat = scene.TriangleCount();
  std::vector<uint8_t> mesh_held(scene.meshes.size(), 0);
  for (size_t k = 0; k < scene.placements.size(); ++k) {
    if (!as_instance[k]) continue;
    const MeshPlacement& placement = scene.placements[k];
    const SceneMesh& mesh = scene.meshes[placement.mesh];
    VISQ_DCHECK_LE(mesh.triangles.size(), flat);
    flat -= mesh.triangles.size();
    ++held.instances;
    if (!mesh_held[placement.mesh]) {
      mesh_held[placement.mesh] = 1;
      held.triangles += mesh.triangles.size();
      held.vertices += mesh.positions.size();
    }
  }
  held.triangles += flat;
  // The flattened triangles' share of the positions, at the scene's ratio.
  held.vertices += scene.TriangleCount() > 0 ? flat * scene.PositionCount() / scene.TriangleCount() : 0;
  return held;
}

}  // namespace

StructureEstimate EstimateStructures(const Scene& scene) {
  StructureEstimate e;
  e.scene_bytes = scene.CpuBytes();
  raycast::EmbreeSceneOptions resident_bvh;
  resident_bvh.quality = raycast::BuildQuality::kMedium;
  const Held bvh = HeldBy(scene, raycast::EmbreeScene::TracedAsInstances(scene, resident_bvh));
  e.embree_bvh_bytes = bvh.triangles * kEmbreeBvhBytesPerTriangle + bvh.vertices * kEmbreeBvhBytesPerVertex +
                       bvh.instances * kEmbreeBvhBytesPerInstance;
  // Without instances the BVH reads the scene's own triangle indices.
  if (bvh.instances == 0) e.embree_bvh_bytes -= bvh.triangles * kEmbreeSharedIndexBytesPerTriangle;
  const Held index = HeldBy(scene, PlacementsInRange(scene));
  e.triangle_index_bytes = index.triangles * kTriangleIndexBytesPerTriangle + index.instances * kTriangleIndexBytesPerInstance;
  e.unique_triangles = index.triangles;
  e.instances = index.instances;
  e.gpu_bytes = gpu::GpuScene::EstimateBytes(scene);
  return e;
}

}  // namespace visq::core
