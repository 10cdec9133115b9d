// Shadow map and camera passes, vertex stage: anchor-relative positions to
// the view's clip space (the matrix is built in double relative to the same
// anchor on the CPU).
layout(location = 0) in vec3 a_position;
uniform mat4 u_clip_from_anchor;
out vec3 v_position;
void main() {
  v_position = a_position;
  gl_Position = u_clip_from_anchor * vec4(a_position, 1.0);
}
