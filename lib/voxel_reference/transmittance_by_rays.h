// Transmittance on each point's own ray (Transmittance's RAY_STABBING): the
// line from the light through the point is cast against the absorbing nodes
// with Embree, every crossing in order, and the optical depth is each
// coefficient's sigma times the length of the segment light..point inside
// that coefficient's absorbers (their union: a point inside two boxes of one
// coefficient counts the path once, as the slicemap's solid does).
//
// Where the slicemap answers for the ray through the centre of the point's
// light-view texel, this answers for the point's own ray, on the CPU, at a
// cost that grows with the points and the crossings rather than with a
// light-view image.
//
// Inside and outside come from the crossings' facing (a closed mesh's
// triangles face out): along the whole line, each coefficient's count of
// entries minus exits must never go below zero and must end at zero. Where
// it does not (an open mesh, a two-sided sheet, inverted faces), the point
// is flagged ambiguous and states the whole interval, as the slicemap's
// ambiguous columns do.
#pragma once

#include <cstdint>
#include <memory>
#include <vector>

#include "common/status.h"
#include "common/stop_token.h"
#include "raycast/embree_scene.h"
#include "scene/scene.h"
#include "voxel_reference/slicemap_request.h"

namespace visq::voxel_reference {

// The absorbing nodes' triangles with a BVH of their own: what
// TransmittanceByRays casts against. It depends on the scene and the set of
// nodes only, not on their coefficients or the light, and its build is
// most of a small request's time (58 of 75 ms for 9,216 points behind the
// 69K-triangle bunny), so a server keeps it for the queries that follow.
struct AbsorberRays {
  std::vector<uint32_t> nodes;             // the scene's node indices, sorted, distinct
  Scene triangles;                         // their triangles, in the nodes' order
  std::vector<uint32_t> node_of_triangle;  // per triangle of `triangles`
  std::unique_ptr<raycast::EmbreeScene> embree;  // null when there is no triangle
  size_t MemoryBytes() const;
};

// `nodes`: indices into scene.nodes (any order, repeats allowed).
// INVALID_ARGUMENT for an index past the scene's nodes; CANCELLED or
// DEADLINE_EXCEEDED when `stop` says so during the build.
[[nodiscard]] StatusOr<std::shared_ptr<const AbsorberRays>> BuildAbsorberRays(const Scene& scene,
                                                                           std::vector<uint32_t> nodes,
                                                                           const StopToken& stop);

// The exact optical depth lies in [optical_depth - optical_depth_error,
// optical_depth] for every point not flagged: each crossing is placed
// within Embree's offset of where it is (2^-17 of the coordinates'
// magnitude around the absorbers; more where the ray grazes a surface,
// the float ray's sideways rounding over the sine of the angle), which the
// error counts per crossing.
// Absorber parts thinner than that offset can be missed whole (the ray
// restarts past each hit), and two surfaces closer than it along the line
// count as one crossing: a shared edge is crossed once, and absorbers that
// touch (a face shared by two boxes) flag the points behind them.
// lateral_offset is 0: the ray is the point's own.
// `params` as ValidateTransmittanceParams accepts them (the caller checks);
// params.job.stop is asked between rounds of crossings.
// `absorbers`, where given, must hold exactly the nodes params.nodes lists
// (else INVALID_ARGUMENT); without it they are built for this call.
[[nodiscard]] StatusOr<TransmittanceResult> TransmittanceByRays(const Scene& scene, const TransmittanceParams& params,
                                                                const AbsorberRays* absorbers = nullptr);

}  // namespace visq::voxel_reference
