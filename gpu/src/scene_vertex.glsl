// A scene corner as every algorithm's vertex stage reads it (layout in
// gpu_scene_resources.h): the corner from the shared buffer, placed by its
// draw's placement record (one per instance, divisor 1).
layout(location = 0) in vec3 a_position;   // anchor-relative, or the mesh's own space
layout(location = 1) in vec4 a_place_x;    // rows of the affine placement to anchor-relative
layout(location = 2) in vec4 a_place_y;
layout(location = 3) in vec4 a_place_z;
layout(location = 4) in int a_triangle_offset;  // scene triangle = corner / 3 + this

// Unplaced corners (the identity record) are returned as they are, so that
// a scene without instances draws the very floats it uploaded.
vec3 PlaceCorner(vec3 corner) {
  if (a_place_x == vec4(1.0, 0.0, 0.0, 0.0) && a_place_y == vec4(0.0, 1.0, 0.0, 0.0) &&
      a_place_z == vec4(0.0, 0.0, 1.0, 0.0))
    return corner;
  vec4 p = vec4(corner, 1.0);
  return vec3(dot(a_place_x, p), dot(a_place_y, p), dot(a_place_z, p));
}

vec3 ScenePosition() { return PlaceCorner(a_position); }

// The scene's (flattened) triangle and corner this vertex stands for.
uint SceneTriangle() { return uint(gl_VertexID / 3 + a_triangle_offset); }
uint SceneCorner() { return 3u * SceneTriangle() + uint(gl_VertexID % 3); }
