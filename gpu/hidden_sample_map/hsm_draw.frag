// Hidden-sample map, per receiver point and triangle (paper sections 4-5):
// back-project the clipped triangle from the receiver point R onto the source
// plane (homogeneous, so that parts projecting to infinity stay exact), orient
// it counter-clockwise, turn each edge into Hough (theta, r) and AND the
// bitmasks of samples left of the edges. The OR logic op combines triangles.
//
// Defines: GROUPS (uvec4 groups of 128 samples written by this pass) and
// EXACT_LOOKUP (1: resolve the table cell's ambiguous samples with the exact
// edge test; 0: pure Hough, writing the conservative "maybe blocked" masks to
// targets [0, GROUPS) and the "surely blocked" ones to [GROUPS, 2 GROUPS)).
#include "hsm_decorrelation.glsl"

flat in vec3 g_poly[5];
flat in vec3 g_poly_receiver[5];
flat in int g_count;
flat in vec4 g_plane;

#if EXACT_LOOKUP
layout(location = 0) out uvec4 o_bits[GROUPS];
#else
layout(location = 0) out uvec4 o_bits[2 * GROUPS];
#endif

layout(std430, binding = 0) readonly buffer Samples { vec2 samples[]; };

uniform usampler2DArray u_table;  // [L planes | A planes] x theta x r
uniform int u_theta_res;
uniform int u_r_res;
uniform float u_r_max;
uniform int u_layer_base;    // first group (uvec4 of words) of this pass
uniform int u_ambiguous_layer_offset;
uniform int u_sample_count;
uniform mat4 u_receiver_to_source;  // (a, b, h, 1) -> (x, y, d, 1)
uniform vec3 u_d_gradient;  // d(source distance) / d(a, b, e)
uniform float u_e_per_height;  // e of a heightfield point per unit height (+-1)
uniform vec2 u_receiver_size;
uniform int u_first_row;  // of the band of receiver rows this job draws
uniform float u_delta;
uniform bool u_heightfield;
uniform sampler2D u_heights;
uniform bool u_decorrelate;
uniform uint u_decorrelation_seed;
uniform float u_decorrelation_amplitude;
uniform vec4 u_sample_box;  // the samples' bounding box: (lo.x, lo.y, hi.x, hi.y)

const float kPi = 3.14159265358979;

void main() {
  // The band's framebuffer holds rows [u_first_row, ...) of the receiver,
  // and u_heights holds the same rows.
  ivec2 band_texel = ivec2(gl_FragCoord.xy);
  ivec2 texel = band_texel + ivec2(0, u_first_row);
  vec2 receiver_point = (gl_FragCoord.xy + vec2(0.0, float(u_first_row))) / u_receiver_size;
  float h = u_heightfield ? texelFetch(u_heights, band_texel, 0).r : 0.0;
  vec3 R = (u_receiver_to_source * vec4(receiver_point, h, 1.0)).xyz;

  // Back-projection from R: X -> (d_R x_X - d_X x_R, d_R y_X - d_X y_R, d_R - d_X).
  // w = d_R - d_X > 0 exactly for the points strictly between the source
  // plane and R; clip to w >= delta (only needed when the planes are not
  // parallel or the receiver is bumpy).
  vec3 poly[6];
  int n = g_count;
  bool clip = false;
  // w = d_R - d_X from the receiver-frame difference: near the receiver
  // plane X and R are close and d_R - d_X would cancel catastrophically.
  vec3 R_receiver = vec3(receiver_point, u_e_per_height * h);
  for (int i = 0; i < 5; ++i) {
    if (i < n) {
      vec3 X = g_poly[i];
      float w = dot(u_d_gradient, R_receiver - g_poly_receiver[i]);
      poly[i] = vec3(R.z * (X.x - R.x) + R.x * w, R.z * (X.y - R.y) + R.y * w, w);
      clip = clip || w < u_delta;
    }
  }
  if (clip) {
    vec3 kept[6];
    int m = 0;
    for (int i = 0; i < n; ++i) {
      vec3 a = poly[i], b = poly[(i + 1 == n) ? 0 : i + 1];
      bool in_a = a.z >= u_delta, in_b = b.z >= u_delta;
      if (in_a && m < 6) kept[m++] = a;
      if (in_a != in_b && m < 6) kept[m++] = mix(a, b, (u_delta - a.z) / (b.z - a.z));
    }
    if (m < 3) discard;
    for (int i = 0; i < m; ++i) poly[i] = kept[i];
    n = m;
  }

  // Orientation of the back-projection = side of R w.r.t. the triangle plane.
  float side = dot(g_plane.xyz, R) + g_plane.w;
  if (side == 0.0) discard;

  vec2 offset = u_decorrelate
      ? HsmDecorrelationOffset(u_decorrelation_seed, uint(texel.x), uint(texel.y), u_decorrelation_amplitude)
      : vec2(0.0);

  // Edges as lines l: sample s is inside iff l.x s.x + l.y s.y + l.z > 0 for all.
  vec3 lines[6];
  ivec2 cells[6];
  int edges = 0;
  for (int i = 0; i < n; ++i) {
    vec3 l = cross(poly[i], poly[(i + 1 == n) ? 0 : i + 1]);
    if (side < 0.0) l = -l;
    l.z += l.x * offset.x + l.y * offset.y;  // the pattern seen from here is s + offset
    float len = length(l.xy);
    if (len == 0.0) {
      if (l.z > 0.0) continue;  // the line at infinity, all samples on the left
      if (l.z < 0.0) discard;   // no sample on the left: nothing hidden
      continue;                 // a degenerate edge: the others bound the polygon
    }
    float theta = atan(l.y, l.x);
    float r = -l.z / len;
    int ti = int(floor((theta + kPi) * (float(u_theta_res) / (2.0 * kPi))));
    ti = ti >= u_theta_res ? ti - u_theta_res : max(ti, 0);
    int ri = clamp(int(floor((r + u_r_max) * (float(u_r_res) / (2.0 * u_r_max)))), 0, u_r_res - 1);
    lines[edges] = l;
    cells[edges] = ivec2(ri, ti);
    ++edges;
  }

#if EXACT_LOOKUP
  // Most fragments of a large influence region see the triangle miss the
  // source: where one edge has every sample's box wholly outside it (its
  // largest value over the box's corners below 0, with a margin for the
  // rounding of the per-sample test), no sample is hidden and the lookups
  // are skipped.
  for (int e = 0; e < edges; ++e) {
    vec3 l = lines[e];
    vec2 far_corner = vec2(l.x > 0.0 ? u_sample_box.z : u_sample_box.x, l.y > 0.0 ? u_sample_box.w : u_sample_box.y);
    vec2 reach = max(abs(u_sample_box.xy), abs(u_sample_box.zw));
    float margin = 1e-5 * (abs(l.x) * reach.x + abs(l.y) * reach.y + abs(l.z));
    if (dot(l, vec3(far_corner, 1.0)) < -margin) discard;
  }
#endif

  bool any_bit = false;
  for (int g = 0; g < GROUPS; ++g) {
    int layer = u_layer_base + g;
    uvec4 sure = uvec4(0xFFFFFFFFu), maybe = uvec4(0xFFFFFFFFu);
    for (int e = 0; e < edges; ++e) {
      uvec4 left = texelFetch(u_table, ivec3(cells[e], layer), 0);
      uvec4 ambiguous = texelFetch(u_table, ivec3(cells[e], layer + u_ambiguous_layer_offset), 0);
      sure &= left;
      maybe &= left | ambiguous;
    }
#if EXACT_LOOKUP
    // Only the samples some cell could not decide get the exact edge test.
    uvec4 candidates = maybe & ~sure;
    for (int c = 0; c < 4; ++c) {
      uint bits = candidates[c];
      while (bits != 0u) {
        int bit = findLSB(bits);
        bits &= bits - 1u;
        int index = ((layer * 4 + c) << 5) + bit;
        vec3 s = vec3(samples[index], 1.0);
        bool inside = true;
        for (int e = 0; e < edges; ++e) inside = inside && dot(lines[e], s) >= 0.0;
        if (inside) sure[c] |= 1u << uint(bit);
      }
    }
    o_bits[g] = sure;
    any_bit = any_bit || any(notEqual(sure, uvec4(0u)));
#else
    o_bits[g] = maybe;
    o_bits[GROUPS + g] = sure;
    any_bit = any_bit || any(notEqual(maybe, uvec4(0u)));
#endif
  }
  if (!any_bit) discard;
}
