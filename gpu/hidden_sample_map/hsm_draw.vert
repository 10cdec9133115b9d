// Hidden-sample map: scene corners, placed and anchor-relative, go straight
// to the geometry shader, which does all the per-triangle work.
#include "scene_vertex.glsl"
out vec3 v_position;
void main() { v_position = ScenePosition(); }
