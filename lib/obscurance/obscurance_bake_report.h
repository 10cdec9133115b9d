// What the GPU obscurance bake reports (its progress after each direction,
// its stats at the end) and what its preview returns (the image), so that
// the core and the transport name them without naming gpu/
// (visq/gpu/obscurance.h is the bake and the preview themselves). Header
// only: no GL, no gRPC.
#pragma once

#include <cstdint>
#include <vector>

namespace visq::obscurance {

struct ObscuranceProgress {
  uint32_t directions_done = 0;
  uint32_t directions_total = 0;
  double elapsed_seconds = 0;
  double estimated_seconds_left = 0;
  uint32_t layers_last_direction = 0;
};

struct ObscuranceBakeStats {
  uint64_t layers = 0;       // over all directions
  uint32_t max_layers = 0;   // of one direction
  uint32_t truncated_directions = 0;  // that hit max_layers
  uint32_t bundle_resolution = 0;
  double seconds = 0;
};

struct ObscurancePreviewImage {
  uint32_t width = 0, height = 0;
  // Linear RGB per pixel, index (y * width + x) * 3, y = 0 the TOP row;
  // background pixels are 0.
  std::vector<float> rgb;
  std::vector<uint8_t> covered;  // per pixel: 1 where a surface was drawn
  double queue_ms = 0;   // waiting for the GL thread
  double render_ms = 0;  // on the GL thread (upload, draw, readback)
  double total_ms = 0;
};

}  // namespace visq::obscurance
