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
//    four source corners (eq. 3), reaching the receiver's edge only along
//    the axes where a segment can leave the polygon nearly level (and then
//    within the wedge those segments make), and clipped to the receiver
//    rectangle - this is the shaft culling;
// 4. emit it as a quad (or the wedge's polygon) carrying the clipped
//    polygon in the source frame
//    (x, y centred patch coordinates, d distance from the source plane) for
//    the fragment shader's per-receiver-point back-projection.
layout(triangles) in;
layout(triangle_strip, max_vertices = 7) out;

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

// Marks the ways along the receiver's axes (+a, -a, +b, -b) that a
// direction points, a component within `slack` of 0 counting as both.
void OpenTowards(inout bvec4 open, vec2 direction, float slack) {
  open.x = open.x || direction.x >= -slack;
  open.y = open.y || direction.x <= slack;
  open.z = open.z || direction.y >= -slack;
  open.w = open.w || direction.y <= slack;
}

// Widens the cone of directions (angles from `reference`, the first
// direction given: x the least, y the greatest) to hold `direction`. A zero
// direction leaves no cone: every way.
void Widen(inout vec2 cone, inout vec2 reference, inout bool any_direction, vec2 direction) {
  if (dot(direction, direction) < 1e-30) { any_direction = true; cone = vec2(-4.0, 4.0); return; }
  if (!any_direction) { any_direction = true; reference = direction; cone = vec2(0.0); return; }
  float angle = atan(reference.x * direction.y - reference.y * direction.x, dot(reference, direction));
  cone = vec2(min(cone.x, angle), max(cone.y, angle));
}

vec2 Turned(vec2 v, float angle) { return vec2(cos(angle) * v.x - sin(angle) * v.y, sin(angle) * v.x + cos(angle) * v.y); }

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

  // Influence region in receiver coordinates (a, b): the receiver points R
  // for which a segment from some source point S passes through the
  // polygon, projected on the plane e = u_far_e. A segment descends from S
  // to R, so it meets a point X only where e_S > e_X; there R lies on the
  // line from S through X, at (e_S - far) / (e_S - e_X) of the way. That
  // ratio is linear-fractional in S and in X, so over the source rectangle
  // and the polygon its extremes are at corner-vertex pairs, except where
  // e_S - e_X reaches 0: there R leaves towards infinity along (X - S).(a, b).
  // Those directions are the pairs X - S with e = 0, the section at e = 0 of
  // the convex hull of the 4 n differences, whose extremes lie on the
  // segments between a difference below 0 and one above. The region is the
  // hull of the pairs' projections plus the cone of those directions: along
  // an axis it reaches the receiver's edge where some direction points that
  // way (within float slack), and is bounded by the projections elsewhere.
  // A polygon wholly above the source (every vertex at or over every
  // corner) meets no segment and has no region. A bumpy receiver can rise
  // above part of the source, where segments climb, so there any pair
  // without a descent keeps the whole receiver.
  vec3 corners[4];
  for (int c = 0; c < 4; ++c) corners[c] = (u_world_to_receiver * vec4(u_source_corners[c], 1.0)).xyz;
  vec2 lo = vec2(1e30), hi = vec2(-1e30);
  bool unbounded = false;
  bvec4 open = bvec4(false);  // reaches the receiver's edge towards +a, -a, +b, -b
  vec2 cone = vec2(0.0), reference = vec2(1.0, 0.0);  // the directions, as Widen keeps them
  bool any_direction = false;
  int below_count = 0, above_count = 0;  // differences X - S with e_X < e_S, and with e_X >= e_S
  for (int c = 0; c < 4; ++c) {
    float height = corners[c].z - u_far_e;
    for (int i = 0; i < n; ++i) {
      vec3 difference = rcv[i] - corners[c];
      float descent = -difference.z;  // e_S - e_X
      if (descent > 1e-6 * max(height, 1e-30)) {
        vec2 p = corners[c].xy + (height / descent) * difference.xy;
        lo = min(lo, p);
        hi = max(hi, p);
      } else {
        unbounded = unbounded || u_heightfield;
      }
      if (abs(descent) <= 1e-6 * max(height, 1e-30)) {
        // Nearly level: R is far along the difference itself, starting from
        // beside the corner, whose own foot bounds where it starts.
        lo = min(lo, corners[c].xy);
        hi = max(hi, corners[c].xy);
        OpenTowards(open, difference.xy, 1e-4 * length(difference.xy));
        Widen(cone, reference, any_direction, difference.xy);
      }
      if (descent > 0.0) ++below_count; else ++above_count;
    }
  }
  if (below_count == 0 && !u_heightfield) return;
  // Only a polygon that straddles a source corner's level has both kinds
  // (never where source and receiver are parallel).
  if (below_count > 0 && above_count > 0) {
    for (int c = 0; c < 4; ++c) {
      for (int i = 0; i < n; ++i) {
        vec3 a = rcv[i] - corners[c];
        if (a.z >= 0.0) continue;
        for (int d = 0; d < 4; ++d) {
          for (int j = 0; j < n; ++j) {
            vec3 b = rcv[j] - corners[d];
            if (b.z < 0.0) continue;
            vec2 direction = mix(a.xy, b.xy, -a.z / (b.z - a.z));
            OpenTowards(open, direction, 1e-4 * (length(a.xy) + length(b.xy)));
            Widen(cone, reference, any_direction, direction);
          }
        }
      }
    }
  }
  // Where the directions make a cone narrower than 170 degrees, the region
  // within the receiver lies in the hull of the projections' box B and of
  // B moved by L along the cone's two edges (turned out by a milliradian
  // for rounding), when L is the receiver's reach from B over cos(half the
  // cone's angle): a point of B plus a and b along the edges lies in the
  // receiver only while a + b <= L. That hull is the Minkowski sum of B
  // and the triangle (0, L u1, L u2): seven vertices at most, made by
  // walking their edges in angle order from the lowest corner. Elsewhere
  // the region is the box, open along the axes the directions point along.
  vec2 polygon[7];
  int polygon_size = 0;
  if (any(open) && any_direction && cone.y - cone.x < radians(170.0) && !u_heightfield && !unbounded) {
    vec2 box_slack = 1e-4 * (hi - lo) + vec2(1e-5);
    vec2 b_lo = lo - box_slack, b_hi = hi + box_slack;
    vec2 u1 = Turned(normalize(reference), cone.x - 1e-3), u2 = Turned(normalize(reference), cone.y + 1e-3);
    float reach = length(max(b_hi, vec2(1.0)) - min(b_lo, vec2(0.0)));
    float L = 1.01 * reach / cos(0.5 * (cone.y - cone.x + 2e-3));
    vec2 edges[7] = vec2[](vec2(b_hi.x - b_lo.x, 0.0), vec2(0.0, b_hi.y - b_lo.y), vec2(b_lo.x - b_hi.x, 0.0),
                           vec2(0.0, b_lo.y - b_hi.y), L * u1, L * (u2 - u1), -L * u2);
    float angles[7];
    for (int k = 0; k < 7; ++k) {
      float angle = atan(edges[k].y, edges[k].x);
      angles[k] = angle < 0.0 ? angle + 2.0 * radians(180.0) : angle;
    }
    for (int k = 1; k < 7; ++k) {  // insertion sort by angle
      for (int j = k; j > 0 && angles[j - 1] > angles[j]; --j) {
        float angle = angles[j]; angles[j] = angles[j - 1]; angles[j - 1] = angle;
        vec2 edge = edges[j]; edges[j] = edges[j - 1]; edges[j - 1] = edge;
      }
    }
    vec2 triangle[3] = vec2[](vec2(0.0), L * u1, L * u2);
    vec2 lowest = triangle[0];
    for (int k = 1; k < 3; ++k)
      if (triangle[k].y < lowest.y || (triangle[k].y == lowest.y && triangle[k].x < lowest.x)) lowest = triangle[k];
    vec2 walk = b_lo + lowest;
    vec2 hull[7];
    for (int k = 0; k < 7; ++k) {
      hull[k] = walk;
      walk += edges[k];
    }
    // As a strip: v0, v1, v6, v2, v5, v3, v4.
    int order[7] = int[](0, 1, 6, 2, 5, 3, 4);
    for (int k = 0; k < 7; ++k) polygon[k] = hull[order[k]];
    polygon_size = 7;
  }

  if (open.x) hi.x = 1.0;
  if (open.y) lo.x = 0.0;
  if (open.z) hi.y = 1.0;
  if (open.w) lo.y = 0.0;
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

  if (polygon_size == 0) {
    polygon[0] = vec2(lo.x, lo.y);
    polygon[1] = vec2(hi.x, lo.y);
    polygon[2] = vec2(lo.x, hi.y);
    polygon[3] = vec2(hi.x, hi.y);
    polygon_size = 4;
  }
  for (int k = 0; k < polygon_size; ++k) {
    for (int i = 0; i < 5; ++i) { g_poly[i] = src[min(i, n - 1)]; g_poly_receiver[i] = rcv[min(i, n - 1)]; }
    g_count = n;
    g_plane = plane;
    gl_Position = vec4(polygon[k] * 2.0 - 1.0, 0.0, 1.0);
    EmitVertex();
  }
  EndPrimitive();
}
