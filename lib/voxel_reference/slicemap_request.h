// The slicemap's requests and answers (Eisemann & Décoret 2006, "Fast Scene
// Voxelization and its Applications"): what a voxelization or a
// transmittance query asks for and what it returns, band by band. The GPU
// algorithm (gpu/slicemap, visq/gpu/slicemap.h) answers in these types, the
// core and the transport name them without naming gpu/, and the CPU
// reference beside them (voxel_reference.h) checks the same grid. Header
// only: no GL, no gRPC, nothing to link.
//
// A grid is an orthographic view box seen along its w axis: one 2D image of
// width x height texels (u, v), each texel a column of `slices` bits along w.
//
// Packed layout of SlicemapGrid::bits (the same in the CPU reference):
//   column(x, y) = y * width + x        x along u, y along v, (0, 0) at the
//                                        box corner center - u*hu - v*hv
//   word(x, y, k) = column * words_per_column + k / 32
//   bit(k) = 1u << (k % 32)             k = 0 is the slice nearest the box's
//                                        front face (center - w*hw)
#pragma once

#include <bit>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include <glm/glm.hpp>

#include "common/band.h"
#include "common/job_options.h"
#include "common/status.h"
#include "voxel_reference/voxel_box.h"

namespace visq::voxel_reference {

enum class VoxelizeMode { kSurface, kSolid };
// kUniform: slices split the box depth evenly. kLocal: each column's slices
// split [near, far] of the geometry in that column (one min/max depth pass).
enum class SlicePrecision { kUniform, kLocal };
// kStandard: one sample per texel center, depth at that sample (the paper;
// misses triangles seen edge-on or thinner than a texel). kConservative: a
// geometry shader widens each triangle to its texel bounding box and the
// fragment shader clips the triangle to the texel's column, setting every
// slice the clipped polygon's depth range touches: the grid contains every
// voxel whose closed box the triangle touches (plus voxels within ~1e-3
// voxel of touching, from float rounding).
enum class Rasterization { kStandard, kConservative };

// Half-open range of triangle indices [first, first + count).
struct TriangleRange {
  uint32_t first = 0;
  uint32_t count = 0;
};

// Caps (RESOURCE_EXHAUSTED beyond them). 4096 columns, rows and slices
// covers every grid the tools ask for; the byte cap keeps one request from
// taking the GPU's memory.
inline constexpr uint32_t kMaxSlicemapImageSize = 4096;
inline constexpr uint32_t kMaxSlicemapSlices = 4096;
inline constexpr uint32_t kSlicesPerPass = 1024;       // 8 targets x 4 channels x 32 bits
inline constexpr uint32_t kSolidSlicesPerPass = 512;   // front and back maps share the 8 targets
inline constexpr uint64_t kDefaultMaxSlicemapBytes = uint64_t{1} << 30;
inline constexpr size_t kDefaultSlicemapColumnsPerJob = size_t{1} << 18;

// What a slicemap draws, in whichever view: the grid, what it records, the
// triangles and the caps. Voxelization draws it in a box (VoxelizeParams),
// transmittance in each light's view.
struct SlicemapSettings {
  uint32_t width = 128;   // texels along u
  uint32_t height = 128;  // texels along v
  uint32_t slices = 128;  // bits along w
  VoxelizeMode mode = VoxelizeMode::kSurface;
  SlicePrecision precision = SlicePrecision::kUniform;
  Rasterization rasterization = Rasterization::kStandard;
  // Empty: every triangle of the scene.
  std::vector<TriangleRange> triangles;
  // Largest packed result (and per-pass GPU targets) accepted.
  uint64_t max_bytes = kDefaultMaxSlicemapBytes;
  // Each pass is drawn and read back a band of image rows of at most this
  // many columns at a time, on targets of that size (the server halves its
  // bands while other calls wait). The bits are those of one draw: every
  // fragment's depth is computed from the triangle's corners at the image
  // texel's centre, the same arithmetic in every band, where the
  // rasterizer's interpolated depth moved with the band's viewport offset
  // (on llvmpipe, 21 of 262,144 columns of a sphere at 512 x 512 x 1,024
  // fell in the neighbouring slice with bands of 64 rows against one of
  // 512).
  size_t max_columns_per_job = kDefaultSlicemapColumnsPerJob;
  // A band's draw is cut into pieces of about piece_target_ms (0: one
  // draw), the call asked between them, and a GL job draws pieces for
  // about draw_ms_per_job before the next job of the band goes on: other
  // queries get the GL thread between jobs.
  double piece_target_ms = 25.0;
  double draw_ms_per_job = 50.0;
  JobOptions job;
};

struct VoxelizeParams : SlicemapSettings {
  OrientedBox box;
};

struct SlicemapGrid {
  uint32_t width = 0, height = 0, slices = 0;
  uint32_t words_per_column = 0;  // ceil(slices / 32)
  std::vector<uint32_t> bits;     // layout at the top of this file

  bool Get(uint32_t x, uint32_t y, uint32_t k) const {
    return (bits[(size_t{y} * width + x) * words_per_column + k / 32] >> (k % 32)) & 1u;
  }
  uint64_t CountOccupied() const {
    uint64_t n = 0;
    for (uint32_t word : bits) n += static_cast<uint64_t>(std::popcount(word));
    return n;
  }
};

// Wall-clock per stage on the GL thread, each stage closed by glFinish (on a
// real GPU this adds a sync per stage; on llvmpipe it costs nothing).
struct SlicemapTimings {
  double queue_ms = 0;      // waiting for the GL thread
  double setup_ms = 0;      // programs (cached after the first call), targets
  double depth_ms = 0;      // local precision: the near/far pass
  double voxelize_ms = 0;   // the slicemap passes
  double readback_ms = 0;   // targets to the packed layout
  double resolve_ms = 0;    // solid: in/out along each column (CPU)
  double total_ms = 0;      // everything, queue included
};

struct VoxelizeResult {
  SlicemapGrid grid;
  uint64_t occupied_voxels = 0;
  VoxelizeMode mode = VoxelizeMode::kSurface;
  SlicePrecision precision = SlicePrecision::kUniform;
  Rasterization rasterization = Rasterization::kStandard;
  uint32_t passes = 0;  // rasterizations of the scene, depth pass included
  // GL jobs: the set-up (with the depth pass), then one per pass and band of
  // image rows (up to 2^18 columns each). Other queries get the GL thread
  // between them.
  uint32_t gl_jobs = 0;
  // Local precision: per column (index y * width + x), the depth range the
  // column's slices split, as a fraction of the box depth (0 = front face,
  // 1 = back face); slice k of the column covers
  // [near + k (far - near) / slices, near + (k + 1) (far - near) / slices].
  // A column with no geometry has near = 1, far = 0 and no bits. Empty for
  // uniform precision.
  std::vector<float> column_near, column_far;
  // Solid: columns whose front/back sequence the resolution could not make
  // consistent (open meshes, overlapping or nested shells). Those columns keep
  // only their surface voxels. `resolved_columns` counts columns whose
  // inconsistency was fixed by the slides' rule (see slicemap.cpp).
  uint64_t ambiguous_columns = 0;
  uint64_t resolved_columns = 0;
  std::vector<uint32_t> ambiguous_column_list;  // column indices, ascending
  OrientedBox box;  // the grid's, as voxelized (the scene's own where none was asked)
  SlicemapTimings timings;
};

// One band of image rows of a voxelization, whole in depth, as soon as its
// passes are done: columns [first, first + columns) in the packed layout,
// and their local ranges (local precision only).
struct VoxelizeBand : BandPlace {
  std::vector<uint32_t> bits;
  std::vector<float> column_near, column_far;
};
// With the figures so far (sizes, modes, box; the counts up to this band).
using VoxelizeBandSink = BandSink<VoxelizeResult, VoxelizeBand>;

// ---------------------------------------------------------------------------
// Transmittance shadow maps: the absorbing nodes are voxelized solid in the
// light's view (local precision), and each query point's optical depth is
// sigma * (the length of occupied voxels between the light and the point)
// counted with popcount over its texel's column.

enum class TransmittanceLightKind { kPoint, kDirectional };

struct TransmittanceLight {
  TransmittanceLightKind kind = TransmittanceLightKind::kDirectional;
  glm::dvec3 position{0.0};                // point light
  glm::dvec3 direction{0.0, -1.0, 0.0};    // directional: the way light travels
};

struct AbsorbingNode {
  uint32_t node = 0;        // index into Scene::nodes (its own triangles)
  double absorption = 1.0;  // sigma, per world unit of path length inside the node
};

// Texel centers of a rectangle: origin + (i + 0.5) / nu * u + (j + 0.5) / nv * v,
// appended to the query points in row order (j major).
struct ReceiverPatch {
  glm::dvec3 origin{0.0};
  glm::dvec3 u{1.0, 0.0, 0.0};
  glm::dvec3 v{0.0, 0.0, 1.0};
  uint32_t nu = 0, nv = 0;
};

inline constexpr size_t kMaxTransmittanceGroups = 8;  // distinct absorption values
inline constexpr size_t kMaxTransmittancePoints = 1 << 24;

struct TransmittanceParams {
  TransmittanceLight light;
  std::vector<AbsorbingNode> nodes;
  std::vector<glm::dvec3> points;
  ReceiverPatch patch;            // optional (nu = nv = 0: none)
  uint32_t resolution = 256;      // light-view image is resolution x resolution
  uint32_t slices = 256;          // solid passes: up to 512 per pass
  JobOptions job;

  // The query points: the explicit ones, then the patch's texel centres.
  std::vector<glm::dvec3> QueryPoints() const {
    std::vector<glm::dvec3> out = points;
    for (uint32_t j = 0; j < patch.nv; ++j)
      for (uint32_t i = 0; i < patch.nu; ++i)
        out.push_back(patch.origin + (i + 0.5) / patch.nu * patch.u + (j + 0.5) / patch.nv * patch.v);
    return out;
  }
};

struct TransmittanceResult {
  // Per query point (explicit points first, then the patch's texels).
  std::vector<float> transmittance;        // exp(-optical_depth)
  std::vector<float> optical_depth;        // sum over groups of sigma * occupied length
  // Along the ray through the centre of the point's light-view texel, up to
  // the point's depth, the exact optical depth lies in [optical_depth -
  // optical_depth_error, optical_depth]: each surface crossing puts its
  // whole voxel in the solid, so each shell voxel counted contributes up to
  // sigma * its length. In an ambiguous column the interval is [0, sigma *
  // the column's length up to the point].
  std::vector<float> optical_depth_error;
  // Distance from the point's own light ray to that centre ray, at the point
  // (world units). Where the absorbers' thickness varies within it, the
  // point's own value can lie outside the interval.
  std::vector<float> lateral_offset;
  // 1 where the point's column was ambiguous in some group of absorbers.
  std::vector<uint8_t> ambiguous;
  // Largest slice length along the ray and texel size at the absorbers.
  double max_voxel_length = 0;
  double max_texel_size = 0;
  uint64_t ambiguous_columns = 0;  // over all groups; their counts are surface-only
  std::string error_statement;
  SlicemapTimings timings;  // summed over groups
  std::string method = "transmittance-slicemap";  // or "transmittance-ray-stabbing" (TransmittanceByRays)

  // `points` answers of light passing unabsorbed, none ambiguous.
  void AllTransmitting(size_t points) {
    transmittance.assign(points, 1.0f);
    optical_depth.assign(points, 0.0f);
    optical_depth_error.assign(points, 0.0f);
    lateral_offset.assign(points, 0.0f);
    ambiguous.assign(points, 0);
  }
};

}  // namespace visq::voxel_reference
