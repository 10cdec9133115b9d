// A quad over the left half of the target (x in [-1, 0]): the self-test
// knows exactly which texels it must write.
const vec2 kCorners[4] = vec2[](vec2(-1.0, -1.0), vec2(0.0, -1.0), vec2(-1.0, 1.0), vec2(0.0, 1.0));
void main() { gl_Position = vec4(kCorners[gl_VertexID], 0.0, 1.0); }
