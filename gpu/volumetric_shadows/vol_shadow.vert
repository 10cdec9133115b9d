// Shadow map and camera passes, vertex stage: anchor-relative positions to
// the view's clip space (the matrix is built in double relative to the same
// anchor on the CPU). The camera pass (CAMERA) also hands its fragments the
// triangle's face normal, from the triangle's own placed corners, and its
// material.
#include "scene_vertex.glsl"
uniform mat4 u_clip_from_anchor;
out vec3 v_position;
#ifdef CAMERA
layout(std430, binding = 0) readonly buffer Positions { float positions[]; };
layout(std430, binding = 1) readonly buffer TriangleMaterials { uint triangle_material[]; };
flat out vec3 v_face_normal;  // unnormalized; every corner of a triangle computes the same
flat out uint v_material;

vec3 Corner(int i) {
  int base = ((gl_VertexID / 3) * 3 + i) * 3;
  return PlaceCorner(vec3(positions[base], positions[base + 1], positions[base + 2]));
}
#endif
void main() {
  v_position = ScenePosition();
  gl_Position = u_clip_from_anchor * vec4(v_position, 1.0);
#ifdef CAMERA
  vec3 a = Corner(0), b = Corner(1), c = Corner(2);
  v_face_normal = cross(b - a, c - a);
  v_material = triangle_material[gl_VertexID / 3];
#endif
}
