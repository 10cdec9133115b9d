// One thread per segment: does any triangle block p + t d for t in
// [t_near, t_far]? With CLOSEST_HIT defined: which triangle is met first,
// and where. A stack traversal of the flat BVH (raycast/flat_bvh.h)
// and the watertight ray-triangle test of Woop, Benthin and Wald (JCGT
// 2013), whose edge functions fall back to double precision when one is
// exactly zero, so that a segment through a shared edge hits one of its
// triangles, never neither.
layout(local_size_x = 64) in;

// The C++ layouts of raycast::FlatBvhNode and FlatBvhCorner (std430: a
// uint packs after a vec3). Indices are uints, never float bits: a GPU may
// flush a float that is a small integer's bits (a denormal) to 0.
struct Node {
  vec3 lower;
  uint link;  // an inner node: its second child (the first follows it); a leaf: its first triangle
  vec3 upper;
  uint count;  // a leaf's triangles; 0 for an inner node
};
struct Corner {
  vec3 position;
  uint triangle;  // the first corner's: the scene triangle's index
};
layout(std430, binding = 0) readonly buffer Nodes { Node nodes[]; };
layout(std430, binding = 1) readonly buffer Corners { Corner corners[]; };
layout(std430, binding = 2) readonly buffer Segments { vec4 segments[]; };  // two per segment
layout(std430, binding = 3) readonly buffer Ignore { uint ignore_triangle[]; };
#ifdef CLOSEST_HIT
// A miss has triangle 0xFFFFFFFF.
struct Hit {
  float t;
  uint triangle;
  float u;
  float v;
};
layout(std430, binding = 4) writeonly buffer Hits { Hit hits[]; };
#else
layout(std430, binding = 4) buffer Blocked { uint blocked_bits[]; };
#endif

uniform uint segment_count;
uniform uint node_count;

#define STACK_SIZE (MAX_DEPTH + 2)

// The box's entry before the segment's far end and exit after its near end;
// the exit widened by 2 gamma(3) (Ize 2013) so that rounding never culls a
// box the segment touches.
bool HitsBox(vec3 lower, vec3 upper, vec3 origin, vec3 inverse_direction, float t_near, float t_far) {
  vec3 t0 = (lower - origin) * inverse_direction;
  vec3 t1 = (upper - origin) * inverse_direction;
  vec3 t_min = min(t0, t1), t_max = max(t0, t1);
  float enter = max(max(t_min.x, t_min.y), max(t_min.z, t_near));
  float leave = min(min(t_max.x, t_max.y), min(t_max.z, t_far)) * 1.0000004;
  return enter <= leave;
}

// The ray's shear, computed once (Woop et al., section 3).
struct Shear {
  int kx, ky, kz;
  float sx, sy, sz;
};

Shear MakeShear(vec3 d) {
  Shear s;
  vec3 a = abs(d);
  s.kz = a.x > a.y ? (a.x > a.z ? 0 : 2) : (a.y > a.z ? 1 : 2);
  s.kx = (s.kz + 1) % 3;
  s.ky = (s.kx + 1) % 3;
  if (d[s.kz] < 0.0) {
    int swap = s.kx;
    s.kx = s.ky;
    s.ky = swap;
  }
  s.sx = d[s.kx] / d[s.kz];
  s.sy = d[s.ky] / d[s.kz];
  s.sz = 1.0 / d[s.kz];
  return s;
}

// Whether the segment meets the triangle at some t in [t_near, t_far], and
// where: t, and the weights of v1 and v2 (Embree's u and v).
bool HitsTriangle(Shear s, vec3 origin, vec3 v0, vec3 v1, vec3 v2, float t_near, float t_far, out float t,
                  out float weight1, out float weight2) {
  t = 0.0;
  weight1 = 0.0;
  weight2 = 0.0;
  vec3 a = v0 - origin, b = v1 - origin, c = v2 - origin;
  float ax = a[s.kx] - s.sx * a[s.kz], ay = a[s.ky] - s.sy * a[s.kz];
  float bx = b[s.kx] - s.sx * b[s.kz], by = b[s.ky] - s.sy * b[s.kz];
  float cx = c[s.kx] - s.sx * c[s.kz], cy = c[s.ky] - s.sy * c[s.kz];
  // The edge functions: u weighs v0, v weighs v1, w weighs v2.
  float u = cx * by - cy * bx;
  float v = ax * cy - ay * cx;
  float w = bx * ay - by * ax;
  if (u == 0.0 || v == 0.0 || w == 0.0) {
    u = float(double(cx) * double(by) - double(cy) * double(bx));
    v = float(double(ax) * double(cy) - double(ay) * double(cx));
    w = float(double(bx) * double(ay) - double(by) * double(ax));
  }
  if ((u < 0.0 || v < 0.0 || w < 0.0) && (u > 0.0 || v > 0.0 || w > 0.0)) return false;
  float det = u + v + w;
  if (det == 0.0) return false;
  float az = s.sz * a[s.kz], bz = s.sz * b[s.kz], cz = s.sz * c[s.kz];
  float t_scaled = u * az + v * bz + w * cz;
  // t = t_scaled / det within [t_near, t_far], without the division.
  float magnitude = abs(det);
  if (det < 0.0) t_scaled = -t_scaled;
  if (!(t_scaled >= t_near * magnitude && t_scaled <= t_far * magnitude)) return false;
#ifdef CLOSEST_HIT
  t = t_scaled / magnitude;
  weight1 = v / det;
  weight2 = w / det;
#endif
  return true;
}

void main() {
  uint k = gl_GlobalInvocationID.x + gl_GlobalInvocationID.y * gl_NumWorkGroups.x * gl_WorkGroupSize.x;
  if (k >= segment_count || node_count == 0u) return;
  vec4 first = segments[2u * k], second = segments[2u * k + 1u];
  vec3 origin = first.xyz, direction = second.xyz;
  float t_near = first.w, t_far = second.w;
  if (!(t_far >= t_near)) {
#ifdef CLOSEST_HIT
    hits[k] = Hit(0.0, 0xFFFFFFFFu, 0.0, 0.0);
#endif
    return;
  }
  uint ignored = ignore_triangle[k];
  // An axis the segment does not move along gets a huge finite inverse:
  // infinity times a box side through the origin would be NaN.
  vec3 moving = vec3(abs(direction.x) > 1e-30 ? direction.x : 1e-30, abs(direction.y) > 1e-30 ? direction.y : 1e-30,
                     abs(direction.z) > 1e-30 ? direction.z : 1e-30);
  vec3 inverse_direction = 1.0 / moving;
  Shear shear = MakeShear(direction);

#ifdef CLOSEST_HIT
  Hit best = Hit(0.0, 0xFFFFFFFFu, 0.0, 0.0);
#endif
  uint stack[STACK_SIZE];
  int top = 0;
  stack[top++] = 0u;
  while (top > 0) {
    uint index = stack[--top];
    Node node = nodes[index];
    if (!HitsBox(node.lower, node.upper, origin, inverse_direction, t_near, t_far)) continue;
    uint count = node.count;
    uint link = node.link;
    if (count == 0u) {
      // The second child, then the first (it follows its parent), which is
      // visited next. A tree no deeper than MAX_DEPTH never holds more than
      // MAX_DEPTH + 1 entries.
      stack[top++] = link;
      stack[top++] = index + 1u;
      continue;
    }
    for (uint i = 0u; i < count; ++i) {
      uint t = link + i;
      Corner c0 = corners[3u * t];
      uint triangle = c0.triangle;
      if (triangle == ignored) continue;
      float hit_t, weight1, weight2;
      if (!HitsTriangle(shear, origin, c0.position, corners[3u * t + 1u].position, corners[3u * t + 2u].position,
                        t_near, t_far, hit_t, weight1, weight2))
        continue;
#ifdef CLOSEST_HIT
      // Nearer hits only from now on: the segment ends here.
      t_far = hit_t;
      best = Hit(hit_t, triangle, weight1, weight2);
#else
      atomicOr(blocked_bits[k >> 5u], 1u << (k & 31u));
      return;
#endif
    }
  }
#ifdef CLOSEST_HIT
  hits[k] = best;
#endif
}
