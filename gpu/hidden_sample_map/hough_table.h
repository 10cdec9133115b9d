// The Hough bitmask table of the hidden-sample map (paper section 5), built
// on the CPU for one sample pattern and cached on the GPU.
//
// For every (theta, r) cell and sample, the table stores whether the sample
// is left of EVERY oriented line of the cell (plane L) or could be on either
// side (plane A, the ambiguity mask); samples in neither are right of every
// line. A line is {p : cos(theta) p.x + sin(theta) p.y = r}, its left the side
// where cos(theta) p.x + sin(theta) p.y > r, in centred patch coordinates
// (s - 0.5, t - 0.5). Cells are widened by kHoughMargin on every side and
// classification needs |distance| > kHoughMargin, so a lookup whose float
// (theta, r) lands in a neighbouring cell, or a sample within float error of
// a line, is always in A: the exact fragment test decides those.
#pragma once

#include <cstdint>
#include <vector>

#include <glm/glm.hpp>

#include "common/stop_token.h"

namespace visq::gpu::hsm {

inline constexpr double kHoughMargin = 1e-5;

struct HoughTableLayout {
  int theta_res = 256;
  int r_res = 256;
  int sample_count = 0;
  float r_max = 0.0f;  // r in [-r_max, r_max] maps onto the r texels (clamped)
  int groups() const { return (sample_count + 127) / 128; }  // uvec4 layers per plane
};

// centred: the float sample positions the shader tests, (s - 0.5, t - 0.5).
// Returns texels laid out as a GL_TEXTURE_2D_ARRAY of RGBA32UI: layer
// (plane * groups + group), row theta index, column r index, 4 words.
// `stop` is asked between rows of theta: the table of 4096 samples is a
// quarter of a billion cell tests, seconds on a slow core, and a call that
// no longer wants it should not pay them. Returns an empty table once
// `stop` said stop.
std::vector<uint32_t> BuildHoughTable(const std::vector<glm::vec2>& centred, HoughTableLayout& layout,
                                      const StopToken& stop = {});

}  // namespace visq::gpu::hsm
