// Volumetric shadows (Chen et al. 2011) as a core query: the budget, the
// render, and what the shadow map's resolution costs in accuracy.
#pragma once

#include <optional>
#include <string>
#include <vector>

#include "common/status.h"
#include "core/accuracy_planner.h"
#include "core/accuracy_statement.h"
#include "core/call_options.h"
#include "visq/gpu/volumetric_shadows.h"
#include "core/work_timing.h"

namespace visq::core {

class Engine;

struct VolumetricQuery {
  std::string scene;
  uint64_t scene_version = 0;
  volumetric_shadows::VolumetricParams params;
  // Also render with a shadow map of half the size and state the
  // difference as an estimate of the image's error.
  bool estimate_error = false;
  // Instead of params.shadow_map_size: the smallest map, from 256 up by
  // doubling, whose error estimate is within target.max_error (or, without
  // one, the largest the time budget allows; 4096 at most).
  std::optional<AccuracyTarget> target;
  CallOptions call;  // the core sets params.job from it
};

// The image error the shadow map's resolution leaves, estimated from the
// same image at half and a quarter of the map's size: the min-max traversal
// integrates the rectified map exactly, so what is left is where the map
// puts shadow edges. If that error falls as a power of the map's texel,
// e(N) ~ C N^-p, then with d1 = |I(N) - I(N/2)| and d2 = |I(N/2) - I(N/4)|
// the ratio r = d1 / d2 ~ 2^-p, and the error left in I(N) is the tail of a
// geometric series, d1 r / (1 - r) (Richardson's estimate). r is taken from
// the images' L1 differences (a steadier measure of the order than one
// pixel) and kept in [1/2, 3/4]: at first order or faster the estimate is
// d1 itself (what a two-image estimate states), and a slow convergence
// (shadow edges at grazing light) at most triples it. An estimate, not a
// bound. Without a quarter-size map (N / 4 below the smallest map) r is
// taken as 1/2.
struct VolumetricErrorEstimate {
  uint32_t coarse_map_size = 0;   // N / 2
  uint32_t coarser_map_size = 0;  // N / 4; 0 without one
  double max_difference = 0;      // d1: the largest |I(N) - I(N / 2)| of any pixel and channel
  double convergence_ratio = 0.5; // r, as used (clamped)
  double measured_ratio = 0;      // the L1 differences' ratio before the clamp; 0 without N / 4
  double max_pixel_error = 0;     // the estimate: d1 r / (1 - r)
  double relative_l1_error = 0;   // the same for sum |I(N) - I(N / 2)| / sum I(N)
};

// Richardson's factor r / (1 - r) for a ratio of successive differences,
// clamped as VolumetricErrorEstimate says.
double VolumetricTailFactor(double ratio);

struct VolumetricAnswer {
  volumetric_shadows::VolumetricResult result;
  std::optional<VolumetricErrorEstimate> estimate;
  std::vector<uint32_t> maps_rendered;  // in order; the answer's is the last
  double other_renders_ms = 0;          // the renders before the answer's
  double delivery_ms = 0;               // in the sink during the answer's render: the stream's writes
};
// The rendered maps' time too (a target's tries), but not its bands'
// delivery.
inline WorkTiming WorkTimingOf(const VolumetricAnswer& a) {
  const volumetric_shadows::VolumetricTimings& t = a.result.timings;
  return {t.queue_ms, a.other_renders_ms + t.total_ms - t.queue_ms - a.delivery_ms};
}

// With `sink`, each band of image rows goes to it as it is made (or, with a
// target, once the map is chosen) and the result holds the figures only
// (gpu::RenderVolumetricShadows).
[[nodiscard]] StatusOr<VolumetricAnswer> RunVolumetricShadow(Engine& engine, const VolumetricQuery& query,
                                                            const volumetric_shadows::VolumetricBandSink& sink = {});

// "min-max-mipmap" or "ray-marching".
const char* VolumetricMethodName(volumetric_shadows::VolumetricMethod method);

// The image's promise from its figures (it goes with the first band): no
// numeric bound against the continuous integral, what is exact and at what
// resolution the shadow boundary is resolved.
AccuracyStatement VolumetricStatement(const volumetric_shadows::VolumetricResult& figures);

// With an error estimate, the statement the last message carries; without
// one, nothing to add.
std::optional<AccuracyStatement> VolumetricEstimateStatement(const VolumetricAnswer& answer);

}  // namespace visq::core
