// Slicemap voxelization and transmittance (Eisemann & Décoret 2006, "Fast
// Scene Voxelization and its Applications"; slides in
// ../shared/papers/fast-scene-voxelization.txt). GL-free and protobuf-free:
// the algorithm and its shaders live in gpu/slicemap/.
//
// A grid is an orthographic view box seen along its w axis: one 2D image of
// width x height texels (u, v), each texel a column of `slices` bits along w.
// The scene is rasterized once per pass of up to 1024 slices (8 RGBA32UI
// render targets x 128 bits); each fragment turns its depth into a bit mask
// and the OR logic op combines all fragments.
//
// The requests and answers, and the packed layout of SlicemapGrid::bits, are
// in lib/voxel_reference/slicemap_request.h.
#pragma once

#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include <glm/glm.hpp>

#include "common/status.h"
#include "scene/scene.h"
#include "voxel_reference/slicemap_request.h"
#include "visq/gpu/gpu_scene.h"
#include "visq/gpu/gpu_worker.h"

namespace visq::gpu {

// The requests and answers are lib/voxel_reference's (slicemap_request.h),
// beside the CPU reference; this header is the GPU's entry points.
using voxel_reference::OrientedBox;
using voxel_reference::VoxelizeMode;
using voxel_reference::SlicePrecision;
using voxel_reference::Rasterization;
using voxel_reference::TriangleRange;
using voxel_reference::kMaxSlicemapImageSize;
using voxel_reference::kMaxSlicemapSlices;
using voxel_reference::kSlicesPerPass;
using voxel_reference::kSolidSlicesPerPass;
using voxel_reference::kDefaultMaxSlicemapBytes;
using voxel_reference::kDefaultSlicemapColumnsPerJob;
using voxel_reference::SlicemapSettings;
using voxel_reference::VoxelizeParams;
using voxel_reference::SlicemapGrid;
using voxel_reference::SlicemapTimings;
using voxel_reference::VoxelizeResult;
using voxel_reference::VoxelizeBand;
using voxel_reference::VoxelizeBandSink;
using voxel_reference::TransmittanceLight;
using voxel_reference::AbsorbingNode;
using voxel_reference::ReceiverPatch;
using voxel_reference::kMaxTransmittanceGroups;
using voxel_reference::kMaxTransmittancePoints;
using voxel_reference::TransmittanceParams;
using voxel_reference::TransmittanceResult;
using LightKind = voxel_reference::TransmittanceLightKind;

// The axis-aligned box `bounds` (grown by `margin` on every side) seen along
// world axis `depth_axis` (0 = x, 1 = y, 2 = z); u, v follow cyclically
// (depth z: u = x, v = y; depth x: u = y, v = z; depth y: u = z, v = x).
OrientedBox AxisAlignedSlicemapBox(const Bounds& bounds, int depth_axis, double margin = 0.0);

// Voxelizes `gpu_scene` (the GPU copy of `scene`) into `params.box`. Without
// a sink the result holds the whole grid; with one, each band goes to the
// sink and the result holds the figures only (the grid's sizes, no bits).
[[nodiscard]] StatusOr<VoxelizeResult> Voxelize(GpuWorker& worker, const GpuScene& gpu_scene,
                                                const VoxelizeParams& params, const VoxelizeBandSink& sink = {});

// Checks params without touching the GPU: INVALID_ARGUMENT or
// RESOURCE_EXHAUSTED naming the field and value.
[[nodiscard]] Status ValidateVoxelizeParams(const VoxelizeParams& params, uint32_t triangle_count);

// ---------------------------------------------------------------------------
// Transmittance shadow maps: the absorbing nodes are voxelized solid in the
// light's view (local precision), and each query point's optical depth is
// sigma * (the length of occupied voxels between the light and the point)
// counted with popcount over its texel's column.

// Checks params against the scene without touching the GPU.
[[nodiscard]] Status ValidateTransmittanceParams(const TransmittanceParams& params, const Scene& scene);

[[nodiscard]] StatusOr<TransmittanceResult> Transmittance(GpuWorker& worker, const Scene& scene,
                                                          const GpuScene& gpu_scene,
                                                          const TransmittanceParams& params);

}  // namespace visq::gpu
