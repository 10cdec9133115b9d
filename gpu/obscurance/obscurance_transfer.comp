// The transfer between two consecutive layers A (nearer) and B (next), both
// ways (paper 4.2), one invocation per bundle ray: a back-facing patch of A
// looks along the view and sees B; a front-facing patch of B looks back and
// sees A. What is seen at distance d < d_max gives rho(d) (times its
// reflectivity with color bleeding); nothing, or d >= d_max, the unoccluded
// value. Any surface occludes, whichever side of it is seen (eq. 2's "next
// surface"; the paper's shader skipped back sides, which leaves open
// geometry undefined). Sums are 64-bit fixed point built from two 32-bit
// atomics (carry on wrap), so the order of additions never matters.
//
// Every sample is summed twice: into its patch and into its own triangle.
// A triangle smaller than a texel shares the texel's sum with its
// neighbours, and the texel's W is not the triangle's (on a fine mesh the
// difference goes far beyond the noise); its own sum is. Each sample also
// counts in this direction's count of both (DirectionCounts, squared and
// cleared after the direction by obscurance_count_squares.comp).
layout(local_size_x = 8, local_size_y = 8) in;
layout(binding = 0) uniform usampler2D u_layer_a;
layout(binding = 1) uniform sampler2D u_depth_a;
layout(binding = 2) uniform usampler2D u_layer_b;
layout(binding = 3) uniform sampler2D u_depth_b;
uniform int u_has_a;
uniform int u_has_b;
uniform uint u_size;
uniform uint u_first_row;  // of this dispatch's band of pixel rows
uniform float u_depth_to_distance;
uniform float u_d_max;
uniform vec3 u_unoccluded;
layout(std430, binding = 1) readonly buffer TriangleMaterial { uint triangle_material[]; };
layout(std430, binding = 2) readonly buffer Reflectivity { vec4 reflectivity[]; };
layout(std430, binding = 3) buffer Sums { uint sums[]; };
layout(std430, binding = 4) buffer TriangleSums { uint triangle_sums[]; };
// Texels first, then triangles (offset u_texel_count).
layout(std430, binding = 5) buffer DirectionCounts { uint direction_counts[]; };
uniform uint u_texel_count;

const uint kStride = 2u * (CHANNELS + 1u);

void Add64(uint at, uint v) {
  const uint old = atomicAdd(sums[at], v);
  if (old > 0xFFFFFFFFu - v) atomicAdd(sums[at + 1u], 1u);
}

void AddTriangle64(uint at, uint v) {
  const uint old = atomicAdd(triangle_sums[at], v);
  if (old > 0xFFFFFFFFu - v) atomicAdd(triangle_sums[at + 1u], 1u);
}

void Contribute(uint patch_id, uint own_triangle, bool seen, float distance, uint seen_triangle) {
  vec3 value = u_unoccluded;
  if (seen && distance < u_d_max) {
    const float rho = sqrt(max(distance, 0.0) / u_d_max);
#if CHANNELS == 3
    value = rho * reflectivity[triangle_material[seen_triangle]].rgb;
#else
    value = vec3(rho);
#endif
  }
  const uint base = patch_id * kStride, own = own_triangle * kStride;
  for (uint c = 0u; c < CHANNELS; ++c) {
    const uint fixed_point = uint(value[c] * FIXED_POINT_SCALE + 0.5);
    Add64(base + 2u * c, fixed_point);
    AddTriangle64(own + 2u * c, fixed_point);
  }
  Add64(base + 2u * CHANNELS, 1u);
  AddTriangle64(own + 2u * CHANNELS, 1u);
  atomicAdd(direction_counts[patch_id], 1u);
  atomicAdd(direction_counts[u_texel_count + own_triangle], 1u);
}

void main() {
  const ivec2 pixel = ivec2(gl_GlobalInvocationID.x, gl_GlobalInvocationID.y + u_first_row);
  if (pixel.x >= int(u_size) || pixel.y >= int(u_size)) return;
  const uvec2 a = u_has_a != 0 ? texelFetch(u_layer_a, pixel, 0).rg : uvec2(0u);
  const uvec2 b = u_has_b != 0 ? texelFetch(u_layer_b, pixel, 0).rg : uvec2(0u);
  if (a.x == 0u && b.x == 0u) return;
  const float za = u_has_a != 0 ? texelFetch(u_depth_a, pixel, 0).r : 0.0;
  const float zb = u_has_b != 0 ? texelFetch(u_depth_b, pixel, 0).r : 1.0;
  const float distance = (zb - za) * u_depth_to_distance;
  if (a.x != 0u && (a.y & 1u) == 0u) Contribute(a.x - 1u, a.y >> 1, b.x != 0u, distance, b.y >> 1);
  if (b.x != 0u && (b.y & 1u) == 1u) Contribute(b.x - 1u, b.y >> 1, a.x != 0u, distance, a.y >> 1);
}
