// Slicemap voxelization, vertex stage: anchor-relative positions to the
// view's clip space, plus what the fragment stage needs for the depth of each
// fragment as a fraction of the view's depth range.
layout(location = 0) in vec3 a_position;

uniform mat4 u_clip_from_anchor;
// Orthographic: depth fraction = dot(u_depth_plane.xyz, p) + u_depth_plane.w.
uniform vec4 u_depth_plane;
// Perspective (point light): the light, anchor-relative.
uniform vec3 u_light;

out vec3 v_light_to_point;
out float v_depth;

void main() {
  gl_Position = u_clip_from_anchor * vec4(a_position, 1.0);
  v_depth = dot(u_depth_plane.xyz, a_position) + u_depth_plane.w;
  v_light_to_point = a_position - u_light;
}
