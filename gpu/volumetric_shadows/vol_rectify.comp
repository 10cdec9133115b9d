// Epipolar rectification: texel (column, row) of the rectified map is the
// shadow-map texel (nearest) at distance r0 + (column + 0.5) dr from the
// epipole in direction theta(row) = ref + min_rel + (row + 0.5) dtheta.
// Outside the shadow map: depth 1 (nothing blocks; the medium ends there).
// WEIGHTS: also the light's weight per rectified texel (texture, cone) and
// the quantity the prefix sums add up ("unit"): the weight itself for a
// directional light, the weight times the angle the texel subtends at a spot
// light (ds / l^2 = dphi / h along any ray of the slice).
// INTEGRAND_SVD: also the texel's x for the SVD table (rect_phi): spot, the
// angle at the light between the texel's center direction and the direction
// to the eye; directional, the world distance p from the epipole (the eye's
// light ray), with the unit weight times the texel's world length dp.
#include "vol_light.glsl"
layout(local_size_x = 8, local_size_y = 8) in;
layout(binding = 0) uniform sampler2D u_shadow_map;
layout(std430, binding = 0) writeonly buffer RectDepth { float rect_depth[]; };
#ifdef WEIGHTS
layout(std430, binding = 3) writeonly buffer RectWeight { float rect_weight[]; };
layout(std430, binding = 4) writeonly buffer RectUnit { float rect_unit[]; };
#endif
#ifdef INTEGRAND_SVD
layout(std430, binding = 8) writeonly buffer RectPhi { float rect_phi[]; };
uniform vec3 u_eye_in_light;  // spot: unit, in the light's (right, up, axis) frame
uniform vec2 u_texel_world;   // directional: a shadow-map texel's world size
#endif
uniform vec2 u_epipole;
uniform float u_theta_ref, u_theta_min_rel, u_dtheta, u_r0, u_dr;
uniform int u_rows, u_cols, u_map_size;

vec2 TexelToNdc(vec2 p) { return p / float(u_map_size) * 2.0 - 1.0; }

void main() {
  ivec2 id = ivec2(gl_GlobalInvocationID.xy);
  if (id.x >= u_cols || id.y >= u_rows) return;
  float theta = u_theta_ref + u_theta_min_rel + (float(id.y) + 0.5) * u_dtheta;
  vec2 dir = vec2(cos(theta), sin(theta));
  float r = u_r0 + (float(id.x) + 0.5) * u_dr;
  vec2 p = u_epipole + r * dir;
  ivec2 t = ivec2(floor(p));
  float depth = 1.0;
  if (all(greaterThanEqual(t, ivec2(0))) && all(lessThan(t, ivec2(u_map_size))))
    depth = texelFetch(u_shadow_map, t, 0).r;
  int index = id.y * u_cols + id.x;
  rect_depth[index] = depth;
#ifdef WEIGHTS
  float w = LightWeight(TexelToNdc(p));
  rect_weight[index] = w;
#ifdef SPOT
  // Angle at the light between the directions of the texel's two edges.
  vec3 a = vec3(TexelToNdc(u_epipole + (r - 0.5 * u_dr) * dir) * u_tan_half, 1.0);
  vec3 b = vec3(TexelToNdc(u_epipole + (r + 0.5 * u_dr) * dir) * u_tan_half, 1.0);
  float angle = atan(length(cross(a, b)), dot(a, b));
  rect_unit[index] = w * angle;
#ifdef INTEGRAND_SVD
  vec3 c = vec3(TexelToNdc(p) * u_tan_half, 1.0);
  rect_phi[index] = atan(length(cross(c, u_eye_in_light)), dot(c, u_eye_in_light));
#endif
#else
#ifdef INTEGRAND_SVD
  rect_unit[index] = w * u_dr * length(dir * u_texel_world);
  rect_phi[index] = length((p - u_epipole) * u_texel_world);
#else
  rect_unit[index] = w;
#endif
#endif
#endif
}
