// Camera pass: per pixel, the distance from the eye to the first surface
// along the view ray, the surface's face normal (turned towards the eye) and
// its material color. The face normal comes from the triangle's own corners
// (gl_PrimitiveID is the triangle id: one non-indexed draw).
in vec3 v_position;
uniform vec3 u_eye;
layout(std430, binding = 0) readonly buffer Positions { float positions[]; };
layout(std430, binding = 1) readonly buffer TriangleMaterials { uint triangle_material[]; };
layout(std430, binding = 2) readonly buffer MaterialAlbedo { vec4 material_albedo[]; };
layout(location = 0) out vec4 out_geometry;  // normal.xyz, distance
layout(location = 1) out vec4 out_albedo;

vec3 Corner(int i) {
  int base = (gl_PrimitiveID * 3 + i) * 3;
  return vec3(positions[base], positions[base + 1], positions[base + 2]);
}

void main() {
  vec3 a = Corner(0), b = Corner(1), c = Corner(2);
  vec3 n = cross(b - a, c - a);
  float len = length(n);
  n = len > 0.0 ? n / len : vec3(0.0, 1.0, 0.0);
  vec3 to_surface = v_position - u_eye;
  if (dot(n, to_surface) > 0.0) n = -n;
  out_geometry = vec4(n, length(to_surface));
  out_albedo = material_albedo[triangle_material[gl_PrimitiveID]];
}
