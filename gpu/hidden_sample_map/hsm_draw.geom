// Hidden-sample map, per triangle (paper sections 3, 4 and 7):
// 1. shaft culling: drop triangles wholly outside one plane of the convex
//    hull of source and receiver (every segment lies inside it); optional
//    watertight culling: drop triangles front-facing from all four source
//    corners;
// 2. segment semantics: clip the triangle to the slab in front of the source
//    plane (d >= delta) and in front of the receiver (e >= u_clip_e), since
//    only the part strictly between the two endpoints can block a segment;
// 3. influence region: the bounding box, on the receiver (or, for a
//    heightfield, on a plane behind it), of the polygon's projections from the
//    four source corners (eq. 3), clipped to the receiver rectangle - this is
//    the shaft culling;
// 4. emit it as a quad carrying the clipped polygon in the source frame
//    (x, y centred patch coordinates, d distance from the source plane) for
//    the fragment shader's per-receiver-point back-projection.
layout(triangles) in;
layout(triangle_strip, max_vertices = 4) out;

in vec3 v_position[];

uniform mat4 u_world_to_source;    // anchor-relative world -> (x, y, d, 1)
uniform mat4 u_world_to_receiver;  // anchor-relative world -> (a, b, e, 1)
uniform vec3 u_source_corners[4];  // anchor-relative world
uniform float u_delta;             // ignore-distance near the endpoints
uniform float u_clip_e;            // keep e >= this (receiver side clip)
uniform float u_far_e;             // plane the influence region is projected on
uniform bool u_heightfield;
uniform bool u_watertight;
uniform vec4 u_shaft_planes[16];  // inside: dot(xyz, p) + w >= 0 (loosened)
uniform int u_shaft_plane_count;

flat out vec3 g_poly[5];
flat out vec3 g_poly_receiver[5];  // the same vertices in (a, b, e)
flat out int g_count;
flat out vec4 g_plane;  // the triangle's plane in the source frame

// Sutherland-Hodgman against one plane, keeping value >= level. Each vertex
// carries its source-frame and receiver-frame coordinates.
void ClipPolygon(inout vec3 src[5], inout vec3 rcv[5], inout int n, bool use_d, float level) {
  vec3 out_src[5];
  vec3 out_rcv[5];
  int m = 0;
  for (int i = 0; i < n; ++i) {
    int j = (i + 1 == n) ? 0 : i + 1;
    float vi = use_d ? src[i].z : rcv[i].z;
    float vj = use_d ? src[j].z : rcv[j].z;
    bool in_i = vi >= level, in_j = vj >= level;
    if (in_i && m < 5) { out_src[m] = src[i]; out_rcv[m] = rcv[i]; ++m; }
    if (in_i != in_j && m < 5) {
      float t = (level - vi) / (vj - vi);
      out_src[m] = mix(src[i], src[j], t);
      out_rcv[m] = mix(rcv[i], rcv[j], t);
      if (use_d) out_src[m].z = level; else out_rcv[m].z = level;
      ++m;
    }
  }
  for (int i = 0; i < m; ++i) { src[i] = out_src[i]; rcv[i] = out_rcv[i]; }
  n = m;
}

void main() {
  vec3 w0 = v_position[0], w1 = v_position[1], w2 = v_position[2];
  for (int k = 0; k < u_shaft_plane_count; ++k) {
    vec4 plane = u_shaft_planes[k];
    if (dot(plane.xyz, w0) + plane.w < 0.0 && dot(plane.xyz, w1) + plane.w < 0.0 &&
        dot(plane.xyz, w2) + plane.w < 0.0)
      return;
  }
  vec3 normal = cross(w1 - w0, w2 - w0);
  if (u_watertight) {
    bool all_front = true;
    for (int c = 0; c < 4; ++c) all_front = all_front && dot(normal, u_source_corners[c] - w0) > 0.0;
    if (all_front) return;
  }

  // Both frames for the three corners, then the slab clip.
  vec3 src[5];
  vec3 rcv[5];
  for (int i = 0; i < 3; ++i) {
    src[i] = (u_world_to_source * vec4(v_position[i], 1.0)).xyz;
    rcv[i] = (u_world_to_receiver * vec4(v_position[i], 1.0)).xyz;
  }
  int n = 3;
  ClipPolygon(src, rcv, n, true, u_delta);
  if (n < 3) return;
  ClipPolygon(src, rcv, n, false, u_clip_e);
  if (n < 3) return;

  // Influence region in receiver coordinates (a, b).
  vec2 lo = vec2(1e30), hi = vec2(-1e30);
  bool unbounded = false;
  for (int c = 0; c < 4 && !unbounded; ++c) {
    vec3 corner = (u_world_to_receiver * vec4(u_source_corners[c], 1.0)).xyz;
    for (int i = 0; i < n; ++i) {
      float denom = corner.z - rcv[i].z;
      if (denom <= 1e-6 * max(corner.z - u_far_e, 1e-30)) { unbounded = true; break; }
      float t = (corner.z - u_far_e) / denom;
      vec2 p = corner.xy + t * (rcv[i].xy - corner.xy);
      lo = min(lo, p);
      hi = max(hi, p);
    }
  }
  if (u_heightfield) {
    for (int i = 0; i < n; ++i) { lo = min(lo, rcv[i].xy); hi = max(hi, rcv[i].xy); }
  }
  if (unbounded) { lo = vec2(0.0); hi = vec2(1.0); }
  // Float slack, then the receiver rectangle.
  vec2 slack = 1e-4 * (hi - lo) + vec2(1e-5);
  lo = max(lo - slack, vec2(0.0));
  hi = min(hi + slack, vec2(1.0));
  if (lo.x >= hi.x || lo.y >= hi.y) return;

  vec3 s0 = (u_world_to_source * vec4(w0, 1.0)).xyz;
  vec3 s1 = (u_world_to_source * vec4(w1, 1.0)).xyz;
  vec3 s2 = (u_world_to_source * vec4(w2, 1.0)).xyz;
  vec3 plane_normal = cross(s1 - s0, s2 - s0);
  vec4 plane = vec4(plane_normal, -dot(plane_normal, s0));

  vec2 quad[4] = vec2[](vec2(lo.x, lo.y), vec2(hi.x, lo.y), vec2(lo.x, hi.y), vec2(hi.x, hi.y));
  for (int k = 0; k < 4; ++k) {
    for (int i = 0; i < 5; ++i) { g_poly[i] = src[min(i, n - 1)]; g_poly_receiver[i] = rcv[min(i, n - 1)]; }
    g_count = n;
    g_plane = plane;
    gl_Position = vec4(quad[k] * 2.0 - 1.0, 0.0, 1.0);
    EmitVertex();
  }
  EndPrimitive();
}
