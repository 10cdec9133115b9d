// Depth peeling, one layer (paper 4.1): the scene under the orthographic view
// of one bundle direction. Each fragment carries its patch (atlas texel) and
// its triangle; gl_VertexID indexes the non-indexed corner layout.
layout(location = 0) in vec3 a_position;  // relative to the GpuScene anchor
layout(std430, binding = 0) readonly buffer CornerUv { vec2 corner_uv[]; };  // texels, per corner
uniform mat4 u_clip_from_scene;
out vec2 v_uv;
flat out uint v_triangle;
void main() {
  gl_Position = u_clip_from_scene * vec4(a_position, 1.0);
  v_uv = corner_uv[gl_VertexID];
  v_triangle = uint(gl_VertexID) / 3u;
}
