// Slicemap voxelization, fragment stage (Eisemann & Décoret 2006). Variants:
//   DEPTH_RANGE_PASS  local precision: write (near, -far) of this fragment's
//                     depth range; MIN blending keeps each column's range.
//   CONSERVATIVE      the geometry stage sent the whole triangle; clip it to
//                     this texel's column and set every slice it touches.
//   PLANE_DEPTH       (orthographic, not conservative) the geometry stage sent
//                     the whole triangle; depth is its plane at the texel's
//                     centre in the image, the same in every band.
//   PERSPECTIVE       depth is the distance from the light (point lights).
//   LOCAL             slices split the column's [near, far] (u_near_far).
//   SOLID             front faces OR into targets [0, TARGETS), back faces
//                     into [TARGETS, 2 TARGETS) (two slicemaps, one pass).
//   TARGETS           RGBA32UI targets per slicemap in this pass.
#if defined(CONSERVATIVE) || defined(PLANE_DEPTH)
flat in vec3 g_corner0;
flat in vec3 g_corner1;
flat in vec3 g_corner2;
#else
in vec3 v_light_to_point;
in float v_depth;
#endif

uniform float u_slices;         // slices of the whole grid
uniform int u_pass_first_slice;  // first slice this pass writes
uniform int u_pass_slices;       // slices this pass writes
uniform vec2 u_radial;           // perspective: fraction = (|p - L| - x) * y
uniform sampler2D u_near_far;    // local: (near, -far) per column
uniform vec2 u_band_origin;      // the image texel of the target's (0, 0): a band's first row

// A column whose geometry spans (almost) no depth still gets slices of this
// thickness (as a fraction of the view depth); slicemap.cpp applies the
// same rule to the near/far it reports.
const float kMinLocalRange = 1.0 / 1048576.0;
// Conservative mode grows the texel square and the slice range by this much
// (texels, slices), so that float rounding never drops a touching voxel.
const float kConservativeSlack = 1e-3;

#ifdef DEPTH_RANGE_PASS
layout(location = 0) out vec2 o_near_far;
#else
#ifdef SOLID
layout(location = 0) out uvec4 o_bits[2 * TARGETS];
#else
layout(location = 0) out uvec4 o_bits[TARGETS];
#endif
#endif

#ifdef CONSERVATIVE
// The depth range of the triangle inside this texel's column (the square
// [lo, hi] in texels): Sutherland-Hodgman against the four sides. The
// clipped polygon is convex and connected, so every depth between its
// minimum and maximum is reached inside the column: the range is exact.
bool ColumnDepthRange(vec2 lo, vec2 hi, out float zmin, out float zmax) {
  vec3 poly[8];
  vec3 next[8];
  poly[0] = g_corner0;
  poly[1] = g_corner1;
  poly[2] = g_corner2;
  int n = 3;
  for (int side = 0; side < 4; ++side) {
    int axis = side / 2;
    float sgn = (side % 2 == 0) ? 1.0 : -1.0;
    float bound = (side % 2 == 0) ? lo[axis] : hi[axis];
    int m = 0;
    for (int i = 0; i < n; ++i) {
      vec3 a = poly[i];
      vec3 b = poly[(i + 1) % n];
      float da = sgn * (a[axis] - bound);
      float db = sgn * (b[axis] - bound);
      if (da >= 0.0) next[m++] = a;
      if ((da >= 0.0) != (db >= 0.0)) next[m++] = mix(a, b, da / (da - db));
    }
    n = m;
    if (n == 0) return false;
    for (int i = 0; i < n; ++i) poly[i] = next[i];
  }
  zmin = poly[0].z;
  zmax = poly[0].z;
  for (int i = 1; i < n; ++i) {
    zmin = min(zmin, poly[i].z);
    zmax = max(zmax, poly[i].z);
  }
  return true;
}
#elif defined(PLANE_DEPTH)
// The triangle's plane at this texel's centre in the whole image. The
// rasterizer's interpolated depth is the same plane, but computed from the
// band's window coordinates, so its last bits (and, at a slice boundary,
// the slice) depended on how the grid was cut into bands. Held within the
// corners' depths, which a sliver's division by a tiny area could leave.
float FragmentDepth() {
  vec2 q = floor(gl_FragCoord.xy) + u_band_origin + vec2(0.5);
  vec2 e0 = g_corner1.xy - g_corner0.xy, e1 = g_corner2.xy - g_corner1.xy, e2 = g_corner0.xy - g_corner2.xy;
  float area = e0.x * (g_corner2.y - g_corner0.y) - e0.y * (g_corner2.x - g_corner0.x);
  float w0 = e1.x * (q.y - g_corner1.y) - e1.y * (q.x - g_corner1.x);
  float w1 = e2.x * (q.y - g_corner2.y) - e2.y * (q.x - g_corner2.x);
  float w2 = e0.x * (q.y - g_corner0.y) - e0.y * (q.x - g_corner0.x);
  float lo = min(min(g_corner0.z, g_corner1.z), g_corner2.z);
  float hi = max(max(g_corner0.z, g_corner1.z), g_corner2.z);
  if (area == 0.0) return lo;
  return clamp((w0 * g_corner0.z + w1 * g_corner1.z + w2 * g_corner2.z) / area, lo, hi);
}
#else
float FragmentDepth() {
#ifdef PERSPECTIVE
  return (length(v_light_to_point) - u_radial.x) * u_radial.y;
#else
  return v_depth;
#endif
}
#endif

// Bits k0..k1 (pass-local slice indices, inclusive) that fall in word `word`.
uint RangeMask(int word, int k0, int k1) {
  int lo = max(k0 - 32 * word, 0);
  int hi = min(k1 - 32 * word, 31);
  if (lo > hi) return 0u;
  return (0xFFFFFFFFu >> uint(31 - hi)) & (0xFFFFFFFFu << uint(lo));
}

void main() {
  // This fragment's depth range, as fractions of the view depth.
#ifdef CONSERVATIVE
  vec2 texel = floor(gl_FragCoord.xy) + u_band_origin;
  vec2 texel_lo = texel - vec2(kConservativeSlack);
  vec2 texel_hi = texel + vec2(1.0 + kConservativeSlack);
  float zmin, zmax;
  // Fast path for the many texels deep inside a triangle: when the whole
  // (grown) square lies inside the projection, the range is the triangle's
  // plane at the square's corners. Edge texels take the exact clip.
  vec2 e0 = g_corner1.xy - g_corner0.xy, e1 = g_corner2.xy - g_corner1.xy, e2 = g_corner0.xy - g_corner2.xy;
  float area = e0.x * (g_corner2.y - g_corner0.y) - e0.y * (g_corner2.x - g_corner0.x);
  bool inside = abs(area) > 1e-3;
  vec4 zc;
  if (inside) {
    vec2 corners[4] = vec2[](texel_lo, vec2(texel_hi.x, texel_lo.y), vec2(texel_lo.x, texel_hi.y), texel_hi);
    float s = sign(area);
    for (int i = 0; i < 4; ++i) {
      vec2 q = corners[i];
      float w0 = s * (e1.x * (q.y - g_corner1.y) - e1.y * (q.x - g_corner1.x));
      float w1 = s * (e2.x * (q.y - g_corner2.y) - e2.y * (q.x - g_corner2.x));
      float w2 = s * (e0.x * (q.y - g_corner0.y) - e0.y * (q.x - g_corner0.x));
      // A small margin keeps rounding on the clip's side of the decision.
      if (min(min(w0, w1), w2) < 1e-3 * abs(area)) inside = false;
      zc[i] = (w0 * g_corner0.z + w1 * g_corner1.z + w2 * g_corner2.z) / abs(area);
    }
  }
  if (inside) {
    zmin = min(min(zc.x, zc.y), min(zc.z, zc.w));
    zmax = max(max(zc.x, zc.y), max(zc.z, zc.w));
  } else if (!ColumnDepthRange(texel_lo, texel_hi, zmin, zmax)) {
    discard;
  }
#else
  float zmin = FragmentDepth();
  float zmax = zmin;
#endif
  if (zmax < 0.0 || zmin > 1.0) discard;
  zmin = clamp(zmin, 0.0, 1.0);
  zmax = clamp(zmax, 0.0, 1.0);

#ifdef DEPTH_RANGE_PASS
  o_near_far = vec2(zmin, -zmax);
#else
  // Map depth to slices: uniformly over the view, or over the column's range.
#ifdef LOCAL
  vec2 near_far = texelFetch(u_near_far, ivec2(gl_FragCoord.xy + u_band_origin), 0).xy;
  float near = near_far.x;
  float far = max(-near_far.y, near + kMinLocalRange);
  float s0 = (zmin - near) / (far - near) * u_slices;
  float s1 = (zmax - near) / (far - near) * u_slices;
#else
  float s0 = zmin * u_slices;
  float s1 = zmax * u_slices;
#endif
#ifdef CONSERVATIVE
  s0 -= kConservativeSlack;
  s1 += kConservativeSlack;
#endif
  int last = int(u_slices) - 1;
  int k0 = clamp(int(floor(s0)), 0, last) - u_pass_first_slice;
  int k1 = clamp(int(floor(s1)), 0, last) - u_pass_first_slice;
  if (k1 < 0 || k0 >= u_pass_slices) discard;
  k1 = min(k1, u_pass_slices - 1);

  // One mask word per channel of every target; OR does the rest.
#ifdef SOLID
  // glFrontFace(GL_CW): "front" is a face whose normal points back at the
  // viewer, where the column enters the surface.
  bool entering = gl_FrontFacing;
  for (int t = 0; t < 2 * TARGETS; ++t) o_bits[t] = uvec4(0u);
  for (int t = 0; t < TARGETS; ++t) {
    uvec4 bits = uvec4(RangeMask(4 * t, k0, k1), RangeMask(4 * t + 1, k0, k1), RangeMask(4 * t + 2, k0, k1),
                       RangeMask(4 * t + 3, k0, k1));
    if (entering) o_bits[t] = bits; else o_bits[TARGETS + t] = bits;
  }
#else
  for (int t = 0; t < TARGETS; ++t)
    o_bits[t] = uvec4(RangeMask(4 * t, k0, k1), RangeMask(4 * t + 1, k0, k1), RangeMask(4 * t + 2, k0, k1),
                      RangeMask(4 * t + 3, k0, k1));
#endif
#endif
}
