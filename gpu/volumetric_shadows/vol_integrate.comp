// Per pixel: the in-scattered light along the view ray, over the lit parts
// of the ray inside the medium (see visq/gpu/volumetric_shadows.h), and
// optionally the direct light on the surface the ray hits.
//
// The ray's clipped segment [s_lo, s_hi] projects to one epipolar row; in
// column coordinates c (distance from the epipole, in rectified texels) the
// ray's shadow-map depth is affine, Z(c), and the distance along the ray is
// projective, S(c) (perspective-correct interpolation; affine for a
// directional light). Texel j of the row covers c in [j, j + 1]; it is lit
// where Z(c) <= depth(j) + bias.
//
// Defines: SPOT (else directional), INTEGRAND_ANALYTIC | INTEGRAND_PREFIX |
// INTEGRAND_PER_TEXEL | INTEGRAND_SVD (with SVD_RANK, SVD_GRID),
// WEIGHTED (per-texel light weights exist), RAY_MARCH (test every texel
// instead of descending the min-max tree).
#include "vol_light.glsl"
layout(local_size_x = 8, local_size_y = 8) in;
layout(binding = 0) uniform sampler2D u_shadow_map;
layout(binding = 1) uniform sampler2D u_geometry;  // normal.xyz, distance; distance < 0: no surface
layout(binding = 2) uniform sampler2D u_albedo;
layout(std430, binding = 0) readonly buffer RectDepth { float rect_depth[]; };
layout(std430, binding = 1) readonly buffer TreeMin { float tree_min[]; };
layout(std430, binding = 2) readonly buffer TreeMax { float tree_max[]; };
layout(std430, binding = 3) readonly buffer RectWeight { float rect_weight[]; };
layout(std430, binding = 4) readonly buffer RectUnit { float rect_unit[]; };
#ifdef INTEGRAND_SVD
layout(std430, binding = 5) readonly buffer Prefix { double prefix[]; };  // [(row (cols + 1) + j) K + k]
layout(std430, binding = 9) readonly buffer SvdTable { float svd_table[]; };
layout(std430, binding = 10) readonly buffer SvdTerms { float svd_terms[]; };  // [(row cols + j) K + k]
#include "vol_svd.glsl"
uniform float u_svd_alpha0, u_svd_alpha_step;  // the table's alpha nodes
uniform float u_eye_light_distance;            // spot: d, computed in double
#else
layout(std430, binding = 5) readonly buffer Prefix { float prefix[]; };
#endif
layout(std430, binding = 7) writeonly buffer Output { vec4 out_pixels[]; };  // inscatter, direct rgb

uniform ivec2 u_image_size;
uniform int u_first_row;  // the band's first image row (one dispatch per band)
uniform vec3 u_eye;                          // anchor-relative
uniform vec3 u_cam_forward, u_cam_right, u_cam_up;  // right/up scaled by the half-FOV tangents
uniform mat4 u_light_clip;                   // light clip space from anchor-relative
uniform vec4 u_c0;                           // light clip of the eye (computed in double)
uniform float u_map_size;
uniform vec2 u_epipole;                      // shadow-map texels
uniform float u_theta_ref, u_theta_min_rel, u_dtheta, u_r0, u_dr;
uniform int u_rows, u_cols, u_levels;
uniform float u_bias;                        // window-depth bias of the medium's shadow test
uniform float u_sigma_s, u_sigma_t, u_g;
uniform float u_intensity;
uniform vec3 u_light_dir;                    // directional: travel direction
uniform vec3 u_light_pos;                    // spot: anchor-relative
uniform float u_half_depth;                  // directional: the box's half depth (l = (z_ndc + 1) * half)
uniform float u_medium_start;                // directional: l of the medium's entry plane
uniform vec3 u_medium_min, u_medium_max;     // the medium's box, anchor-relative
uniform int u_direct;
uniform float u_normal_offset;               // direct light: world offset per unit distance (spot) or absolute

const float kPi = 3.14159265358979;

// Per-ray state (initialized: the compiler warns about globals otherwise).
vec3 g_d = vec3(0.0);
vec4 g_c0 = vec4(0.0), g_c1 = vec4(0.0);  // light clip = g_c0 + s g_c1
float g_sin = 0.0, g_sout = 0.0;          // the segment inside the medium
// s and clip w at the column-ordered ends, their columns, depth and slope.
float g_s_clo = 0.0, g_s_chi = 0.0, g_w_clo = 1.0, g_w_chi = 1.0;
float g_clo = 0.0, g_chi = 1.0, g_zlo = 0.0, g_dzdc = 0.0;
int g_rbase = 0, g_pbase = 0;
float g_K = 0.0, g_a = 0.0, g_l0 = 0.0, g_l1 = 0.0;  // directional
float g_s0 = 0.0, g_h = 1.0;                        // spot: closest approach to the light
float g_prefix_factor = 0.0;
#ifdef INTEGRAND_SVD
// This ray's SVD factor and U_k(alpha) S_k; g_svd false: exact per texel.
bool g_svd = false;
float g_svd_factor = 0.0;
float g_svd_u[SVD_RANK];
#endif

float Phase(float cos_theta) {
  float g = u_g;
  float denom = 1.0 + g * g - 2.0 * g * cos_theta;
  return (1.0 - g * g) / (4.0 * kPi * denom * sqrt(denom));
}

float Z(float c) { return g_zlo + (c - g_clo) * g_dzdc; }
float S(float c) {
  float lambda = (c - g_clo) / (g_chi - g_clo);
  return mix(g_s_clo / g_w_clo, g_s_chi / g_w_chi, lambda) / mix(1.0 / g_w_clo, 1.0 / g_w_chi, lambda);
}

// The in-scattered light over [sa, sb] of texel j, all of it lit.
float Piece(int j, float sa, float sb) {
  if (!(sb > sa)) return 0.0;
#ifdef SPOT
  float sm = 0.5 * (sa + sb);
  vec3 x = u_eye + sm * g_d - u_light_pos;
  float l = length(x);
  float cos_theta = dot(x, -g_d) / max(l, 1e-30);
  // Exact integral of ds / l^2 over [sa, sb]: (atan(B) - atan(A)) / h.
  float angle = atan((sb - sa) * g_h, g_h * g_h + (sa - g_s0) * (sb - g_s0)) / g_h;
  float v = u_sigma_s * u_intensity * Phase(cos_theta) * exp(-u_sigma_t * (l + sm - g_sin)) * angle;
#else
  float x = g_a * (sb - sa);
  float e1 = x < 1e-4 ? 1.0 - 0.5 * x : (1.0 - exp(-x)) / x;  // (1 - e^-x) / x
  float v = g_K * exp(-u_sigma_t * (g_l0 + g_l1 * sa + sa - g_sin)) * (sb - sa) * e1;
#endif
#ifdef WEIGHTED
  v *= rect_weight[g_rbase + j];
#endif
  return v;
}

// Piece over the columns [ca, cb] (s may run either way along c).
float PieceC(int j, float ca, float cb) {
  float sa = S(ca), sb = S(cb);
  return Piece(j, min(sa, sb), max(sa, sb));
}

// Texel j with all of [j, j + 1] on the segment and lit.
float FullTexel(int j) {
#if defined(INTEGRAND_PREFIX)
  return g_prefix_factor * rect_unit[g_rbase + j];
#elif defined(INTEGRAND_SVD)
  // The rank-K integrand at the texel's phi, times its weight x angle: the
  // terms the prefix sums add up.
  if (!g_svd) return PieceC(j, float(j), float(j + 1));
  int base = (g_rbase + j) * SVD_RANK;
  float f = 0.0;
  for (int k = 0; k < SVD_RANK; ++k) f += g_svd_u[k] * svd_terms[base + k];
  return g_svd_factor * f;
#else
  return PieceC(j, float(j), float(j + 1));
#endif
}

// Columns [ja, jb), all on the segment and lit.
float Span(int ja, int jb) {
#if defined(INTEGRAND_ANALYTIC)
  return PieceC(ja, float(ja), float(jb));
#elif defined(INTEGRAND_PREFIX)
  return g_prefix_factor * (prefix[g_pbase + jb] - prefix[g_pbase + ja]);
#elif defined(INTEGRAND_SVD)
  if (g_svd) {
    float f = 0.0;
    int a = (g_pbase + ja) * SVD_RANK, b = (g_pbase + jb) * SVD_RANK;
    for (int k = 0; k < SVD_RANK; ++k) f += g_svd_u[k] * float(prefix[b + k] - prefix[a + k]);
    return g_svd_factor * f;
  }
  float sum = 0.0;
  for (int j = ja; j < jb; ++j) sum += FullTexel(j);
  return sum;
#else
  float sum = 0.0;
  for (int j = ja; j < jb; ++j) sum += FullTexel(j);
  return sum;
#endif
}

// Texel j restricted to [ca, cb] (full: the whole texel): the height-field
// test at both ends, and the crossing where they differ.
float Leaf(int j, float ca, float cb, bool full) {
  float zm = rect_depth[g_rbase + j] + u_bias;
  float za = Z(ca), zb = Z(cb);
  bool la = za <= zm, lb = zb <= zm;
  if (la && lb) return full ? FullTexel(j) : PieceC(j, ca, cb);
  if (!la && !lb) return 0.0;
  float cx = clamp(ca + (zm - za) / (zb - za) * (cb - ca), ca, cb);
  return la ? PieceC(j, ca, cx) : PieceC(j, cx, cb);
}

// The interior columns [ja, jb), every one fully on the segment.
float Interior(int ja, int jb) {
  float sum = 0.0;
#ifdef RAY_MARCH
  // Brute force: every texel in turn.
  for (int j = ja; j < jb; ++j) sum += Leaf(j, float(j), float(j + 1), true);
#else
  // Min-max traversal: the largest aligned node at j inside [j, jb); lit
  // nodes are integrated whole, shadowed ones skipped, mixed ones refined.
  int j = ja;
  while (j < jb) {
    int level = 0;
    while (level < u_levels && (j & ((2 << level) - 1)) == 0 && j + (2 << level) <= jb) ++level;
    while (true) {
      if (level == 0) {
        sum += Leaf(j, float(j), float(j + 1), true);
        j += 1;
        break;
      }
      int size = 1 << level;
      int node = g_rbase + u_cols - (u_cols >> (level - 1)) + (j >> level);
      float za = Z(float(j)), zb = Z(float(j + size));
      if (max(za, zb) <= tree_min[node] + u_bias) {  // fully lit
        sum += Span(j, j + size);
        j += size;
        break;
      }
      if (min(za, zb) > tree_max[node] + u_bias) {  // fully shadowed
        j += size;
        break;
      }
      --level;  // mixed: refine
    }
  }
#endif
  return sum;
}

// The part of [lo, hi] where every clip-space half-space w +- x, w +- y,
// w +- z >= 0 holds (the light's frustum, which is the medium).
bool ClipToLight(inout float lo, inout float hi) {
  for (int axis = 0; axis < 3; ++axis) {
    for (int sign = -1; sign <= 1; sign += 2) {
      float f0 = g_c0.w + float(sign) * g_c0[axis];
      float f1 = g_c1.w + float(sign) * g_c1[axis];
      if (abs(f1) < 1e-30) {
        if (f0 < 0.0) return false;
      } else if (f1 > 0.0) {
        lo = max(lo, -f0 / f1);
      } else {
        hi = min(hi, -f0 / f1);
      }
    }
  }
  return hi > lo;
}

// Shadow-map texel coordinates, clip w and window depth of the ray at s.
vec2 ProjectTexel(float s, out float w, out float z) {
  vec4 clip = g_c0 + s * g_c1;
  w = clip.w;
  z = 0.5 * clip.z / clip.w + 0.5;
  return (clip.xy / clip.w * 0.5 + 0.5) * u_map_size;
}

// The part of [lo, hi] inside the medium's box.
bool ClipToMedium(inout float lo, inout float hi) {
  for (int axis = 0; axis < 3; ++axis) {
    if (abs(g_d[axis]) < 1e-30) {
      if (u_eye[axis] < u_medium_min[axis] || u_eye[axis] > u_medium_max[axis]) return false;
      continue;
    }
    float t0 = (u_medium_min[axis] - u_eye[axis]) / g_d[axis];
    float t1 = (u_medium_max[axis] - u_eye[axis]) / g_d[axis];
    lo = max(lo, min(t0, t1));
    hi = min(hi, max(t0, t1));
  }
  return hi > lo;
}

float Inscatter(float s_end) {
  g_sin = 0.0;
  g_sout = s_end;
  if (!ClipToLight(g_sin, g_sout) || !ClipToMedium(g_sin, g_sout)) {
    g_sout = g_sin;
    return 0.0;
  }
#ifdef SPOT
  vec3 to_light = u_light_pos - u_eye;
  g_s0 = dot(to_light, g_d);
  g_h = max(length(to_light - g_s0 * g_d), 1e-6);
#ifdef INTEGRAND_SVD
  // alpha: the angle between the ray and the direction to the light. Rays
  // outside the table's alpha range (pointing nearly at or away from the
  // light) or entering the medium far beyond the light (the factor would
  // amplify the table's error by more than e^2) stay exact.
  float d_el = u_eye_light_distance;
  float alpha = acos(clamp(g_s0 / d_el, -1.0, 1.0));
  float alpha_end = u_svd_alpha0 + float(SVD_GRID - 1) * u_svd_alpha_step;
  g_svd = alpha >= u_svd_alpha0 && alpha <= alpha_end && u_sigma_t * (g_sin - d_el) <= 2.0;
  if (g_svd) {
    g_svd_factor = u_sigma_s * u_intensity * exp(u_sigma_t * (g_sin - d_el)) / g_h;
    SvdViewFactors(alpha, u_svd_alpha0, u_svd_alpha_step, g_svd_u);
  }
#endif
#else
  g_l0 = u_half_depth * (g_c0.z + 1.0) - u_medium_start;
  g_l1 = u_half_depth * g_c1.z;
  g_a = u_sigma_t * (1.0 + g_l1);
  g_K = u_sigma_s * u_intensity * Phase(dot(u_light_dir, -g_d));
#ifdef INTEGRAND_SVD
  // alpha: the angle between the ray and the light's travel direction. Rays
  // within the margin of it or of its opposite, or whose medium entry has
  // f below e^-2 (the table's absolute error amplified), stay exact.
  float cos_a = clamp(dot(g_d, u_light_dir), -1.0, 1.0);
  float alpha = acos(cos_a);
  float alpha_end = u_svd_alpha0 + float(SVD_GRID - 1) * u_svd_alpha_step;
  g_svd = alpha >= u_svd_alpha0 && alpha <= alpha_end && u_sigma_t * g_sin * (1.0 + cos_a) <= 2.0;
  if (g_svd) {
    g_svd_factor = g_K * exp(-u_sigma_t * (g_l0 - g_sin)) / sqrt(max(1.0 - cos_a * cos_a, 1e-12));
    SvdViewFactors(alpha, u_svd_alpha0, u_svd_alpha_step, g_svd_u);
  }
#endif
#endif
  // The row: the direction from the epipole to the segment's middle.
  float wm, zmid;
  vec2 pm = ProjectTexel(0.5 * (g_sin + g_sout), wm, zmid) - u_epipole;
  float rel = atan(pm.y, pm.x) - u_theta_ref;
  rel -= 2.0 * kPi * floor((rel + kPi) / (2.0 * kPi));  // into [-pi, pi)
  int row = clamp(int(floor((rel - u_theta_min_rel) / u_dtheta)), 0, u_rows - 1);
  g_rbase = row * u_cols;
  g_pbase = row * (u_cols + 1);

  // Column coordinates, clip w and depths of the ends, ordered by column.
  float w_in, w_out, z_in, z_out;
  vec2 p_in = ProjectTexel(g_sin, w_in, z_in), p_out = ProjectTexel(g_sout, w_out, z_out);
  float c_in = clamp((length(p_in - u_epipole) - u_r0) / u_dr, 0.0, float(u_cols));
  float c_out = clamp((length(p_out - u_epipole) - u_r0) / u_dr, 0.0, float(u_cols));
  bool forward = c_in <= c_out;
  g_clo = forward ? c_in : c_out;
  g_chi = forward ? c_out : c_in;
  g_s_clo = forward ? g_sin : g_sout;
  g_s_chi = forward ? g_sout : g_sin;
  g_w_clo = forward ? w_in : w_out;
  g_w_chi = forward ? w_out : w_in;
  g_zlo = forward ? z_in : z_out;
  float zhi = forward ? z_out : z_in;
  int j0 = min(int(floor(g_clo)), u_cols - 1), j1 = min(int(floor(g_chi)), u_cols - 1);

  if (g_chi - g_clo < 1e-3) {
    // The ray runs (nearly) along the light: its whole segment falls in one
    // texel, and the test is along s: lit where clip.z - zm_ndc clip.w <= 0.
    float zm_ndc = 2.0 * (rect_depth[g_rbase + j0] + u_bias) - 1.0;
    float f0 = g_c0.z - zm_ndc * g_c0.w, f1 = g_c1.z - zm_ndc * g_c1.w;
    float fa = f0 + f1 * g_sin, fb = f0 + f1 * g_sout;
    if (fa <= 0.0 && fb <= 0.0) return Piece(j0, g_sin, g_sout);
    if (fa > 0.0 && fb > 0.0) return 0.0;
    float sx = clamp(-f0 / f1, g_sin, g_sout);
    return fa <= 0.0 ? Piece(j0, g_sin, sx) : Piece(j0, sx, g_sout);
  }
  g_dzdc = (zhi - g_zlo) / (g_chi - g_clo);
#ifdef INTEGRAND_PREFIX
#ifdef SPOT
  g_prefix_factor = u_sigma_s * u_intensity * Phase(0.0) / g_h;  // isotropic phase only
#else
  g_prefix_factor = g_K * (g_s_chi - g_s_clo) / (g_chi - g_clo);
#endif
#endif
  if (j0 == j1) return Leaf(j0, g_clo, g_chi, false);
  return Leaf(j0, g_clo, float(j0 + 1), false) + Interior(j0 + 1, j1) + Leaf(j1, float(j1), g_chi, false);
}

// Lambert direct light on the surface at distance t, shadow-mapped with a
// normal offset, attenuated from the light and towards the eye.
vec3 Direct(float t, vec3 n, vec3 albedo) {
  vec3 x = u_eye + t * g_d;
#ifdef SPOT
  vec3 to_light = u_light_pos - x;
  float dist = length(to_light);
  vec3 l_dir = to_light / dist;
  float offset = u_normal_offset * dist;
#else
  vec3 l_dir = -u_light_dir;
  float offset = u_normal_offset;
#endif
  float cos_i = dot(n, l_dir);
  if (cos_i <= 0.0) return vec3(0.0);
  vec4 clip = u_light_clip * vec4(x + n * offset, 1.0);
  if (clip.w <= 0.0) return vec3(0.0);
  vec3 ndc = clip.xyz / clip.w;
  if (any(greaterThan(abs(ndc.xy), vec2(1.0)))) return vec3(0.0);
  ivec2 texel = clamp(ivec2(floor((ndc.xy * 0.5 + 0.5) * u_map_size)), ivec2(0), ivec2(int(u_map_size) - 1));
  if (ndc.z * 0.5 + 0.5 > texelFetch(u_shadow_map, texel, 0).r + 1e-5) return vec3(0.0);
  float w = LightWeight(ndc.xy);
#ifdef SPOT
  float e = u_intensity * w * exp(-u_sigma_t * dist) / (dist * dist);
#else
  float e = u_intensity * w * exp(-u_sigma_t * max(0.0, u_half_depth * (ndc.z + 1.0) - u_medium_start));
#endif
  float towards_eye = exp(-u_sigma_t * max(0.0, min(t, g_sout) - g_sin));
  return albedo / kPi * e * cos_i * towards_eye;
}

void main() {
  ivec2 id = ivec2(gl_GlobalInvocationID.xy) + ivec2(0, u_first_row);
  if (any(greaterThanEqual(id, u_image_size))) return;
  vec2 ndc = vec2((float(id.x) + 0.5) / float(u_image_size.x) * 2.0 - 1.0,
                  1.0 - (float(id.y) + 0.5) / float(u_image_size.y) * 2.0);
  g_d = normalize(u_cam_forward + ndc.x * u_cam_right + ndc.y * u_cam_up);
  g_c0 = u_c0;
  g_c1 = u_light_clip * vec4(g_d, 0.0);
  vec4 geometry = texelFetch(u_geometry, ivec2(id.x, u_image_size.y - 1 - id.y), 0);
  bool hit = geometry.w >= 0.0;
  float inscatter = Inscatter(hit ? geometry.w : 1e30);
  vec3 direct = vec3(0.0);
  if (u_direct != 0 && hit) direct = Direct(geometry.w, geometry.xyz, texelFetch(u_albedo, ivec2(id.x, u_image_size.y - 1 - id.y), 0).rgb);
  out_pixels[id.y * u_image_size.x + id.x] = vec4(inscatter, direct);
}
