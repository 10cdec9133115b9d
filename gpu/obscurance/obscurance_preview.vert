// Obscurance preview: the scene from a pinhole camera, each corner carrying
// its atlas coordinates (texels); the atlas's corners are 3 * triangle +
// corner of the scene's triangles.
#include "scene_vertex.glsl"
layout(std430, binding = 0) readonly buffer CornerUv { vec2 corner_uv[]; };  // texels, per corner
uniform mat4 u_clip_from_anchor;
out vec2 v_uv;
void main() {
  gl_Position = u_clip_from_anchor * vec4(ScenePosition(), 1.0);
  v_uv = corner_uv[SceneCorner()];
}
