// What the obscurance calls hold in memory, found from the scene's and the
// atlas's sizes before anything is allocated, for --max-work-bytes
// (work_budget.h). Each figure is an upper bound of the bytes one part
// holds at once, read from the data structures it counts (their sizeof),
// so that a change of a structure changes its estimate with it.
//
// A ray-cast bake at 4096^2 peaked at about 14 GB against the 3.7 GB it
// reserved: the reservation counted the estimator's per-texel arrays but
// not its batches of rays (4,096 texels a batch, whatever rays_per_patch
// is), nor the result's copy the updater keeps, the updater itself, the
// answer's bounds or the copies made for the answer.
#pragma once

#include <cstdint>

#include "obscurance/obscurance_model.h"
#include "scene/scene.h"

namespace visq::core {

// The sizes the obscurance work's memory follows.
struct ObscuranceWorkShape {
  uint64_t texels = 0;
  uint64_t triangles = 0;
  uint64_t positions = 0;
  uint64_t scene_bytes = 0;  // Scene::CpuBytes(): the updater keeps a copy it moves
  uint64_t channels = 1;     // 3 with color bleeding
  uint64_t index_cell_bytes = 0;  // the updater's patch index's cells (PatchIndex::CellBytesAtMost)
};
ObscuranceWorkShape ObscuranceShapeOf(const Scene& scene, uint32_t resolution, const obscurance::ObscuranceParams& params);

// An obscurance::ObscuranceResult: W, I, the flags and per-element figures.
uint64_t ObscuranceResultBytes(const ObscuranceWorkShape& shape);

// The ray-cast estimator beyond the atlas and the result it returns: its
// Embree scene, per-triangle sums, a batch of rays and one thread's ray
// scratch.
uint64_t RayEstimateWorkBytes(const ObscuranceWorkShape& shape, uint32_t rays_per_patch);

// What a whole bake adds once it is done, until its answer is sent: the
// updater (ObscuranceUpdater::Create, with its own copy of the result and
// the scene, its Embree scene, patch bounds and index, and the tallies it
// keeps for every patch and triangle it may trace), the answer's bounds
// and the accuracy statement's sorted copies. The updater part stays
// reserved as long as the updater lives (ObscuranceUpdaterBytes).
uint64_t ObscuranceUpdaterBytes(const ObscuranceWorkShape& shape, uint32_t update_rays_per_patch);
uint64_t ObscuranceAnswerExtraBytes(const ObscuranceWorkShape& shape);

// One UpdateObscurances call beyond the updater: the moves' merged changes
// (at most every texel, triangle and vertex), the answer's lists, bounds
// and message, the candidate search's lists, and the rays each thread
// generates.
uint64_t ObscuranceUpdateCallBytes(const ObscuranceWorkShape& shape, uint32_t rays_per_patch);

}  // namespace visq::core
