// Camera pass: per pixel, the distance from the eye to the first surface
// along the view ray, the surface's face normal (turned towards the eye) and
// its material color, both handed on by the vertex stage (vol_shadow.vert
// with CAMERA).
in vec3 v_position;
flat in vec3 v_face_normal;
flat in uint v_material;
uniform vec3 u_eye;
layout(std430, binding = 2) readonly buffer MaterialAlbedo { vec4 material_albedo[]; };
layout(location = 0) out vec4 out_geometry;  // normal.xyz, distance
layout(location = 1) out vec4 out_albedo;

void main() {
  vec3 n = v_face_normal;
  float len = length(n);
  n = len > 0.0 ? n / len : vec3(0.0, 1.0, 0.0);
  vec3 to_surface = v_position - u_eye;
  if (dot(n, to_surface) > 0.0) n = -n;
  out_geometry = vec4(n, length(to_surface));
  out_albedo = material_albedo[v_material];
}
