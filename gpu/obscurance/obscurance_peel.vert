// Depth peeling, one layer (paper 4.1): the scene under the orthographic view
// of one bundle direction. Each fragment carries its patch (atlas texel) and
// its scene triangle; the atlas's corners are 3 * triangle + corner.
#include "scene_vertex.glsl"
layout(std430, binding = 0) readonly buffer CornerUv { vec2 corner_uv[]; };  // texels, per corner
uniform mat4 u_clip_from_scene;
out vec2 v_uv;
flat out uint v_triangle;
void main() {
  gl_Position = u_clip_from_scene * vec4(ScenePosition(), 1.0);
  v_uv = corner_uv[SceneCorner()];
  v_triangle = SceneTriangle();
}
