// Slicemap voxelization, vertex stage: anchor-relative positions to the
// view's clip space, plus what the fragment stage needs for the depth of each
// fragment as a fraction of the view's depth range.
#include "scene_vertex.glsl"

uniform mat4 u_clip_from_anchor;
// Orthographic: depth fraction = dot(u_depth_plane.xyz, p) + u_depth_plane.w.
uniform vec4 u_depth_plane;
// Perspective (point light): the light, anchor-relative.
uniform vec3 u_light;

out vec3 v_light_to_point;
out float v_depth;

void main() {
  vec3 position = ScenePosition();
  gl_Position = u_clip_from_anchor * vec4(position, 1.0);
  v_depth = dot(u_depth_plane.xyz, position) + u_depth_plane.w;
  v_light_to_point = position - u_light;
}
