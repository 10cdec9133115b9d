// Obscurance preview: the scene from a pinhole camera, each corner carrying
// its atlas coordinates (texels); gl_VertexID indexes the non-indexed corner
// layout, which is the atlas's 3 * triangle + corner.
layout(location = 0) in vec3 a_position;  // relative to the GpuScene anchor
layout(std430, binding = 0) readonly buffer CornerUv { vec2 corner_uv[]; };  // texels, per corner
uniform mat4 u_clip_from_anchor;
out vec2 v_uv;
void main() {
  gl_Position = u_clip_from_anchor * vec4(a_position, 1.0);
  v_uv = corner_uv[gl_VertexID];
}
