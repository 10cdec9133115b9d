// Hidden-sample map: scene corners (relative to the scene anchor) go straight
// to the geometry shader, which does all the per-triangle work.
layout(location = 0) in vec3 a_position;
out vec3 v_position;
void main() { v_position = a_position; }
