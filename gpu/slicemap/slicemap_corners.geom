// Orthographic views: the triangle's corners in image texels (x, y) and
// view depth fraction (z), computed from the band-independent clip
// positions and sent flat to the fragment stage, which evaluates the
// triangle itself there instead of trusting the rasterizer's interpolation
// (which differs in its last bits with each band's viewport offset).
//
// CONSERVATIVE: the triangle is replaced by its texel-space bounding box
// grown by half a texel (and a little), so every texel whose square the
// triangle touches gets a fragment, even for triangles seen edge-on; the
// fragment stage clips the triangle to the texel's column.
// Otherwise the triangle is drawn as it is; the fragment stage takes its
// plane at the texel's centre (PLANE_DEPTH).
layout(triangles) in;
layout(triangle_strip, max_vertices = 4) out;

in float v_depth[];
in vec3 v_light_to_point[];

uniform vec2 u_image_size;

flat out vec3 g_corner0;
flat out vec3 g_corner1;
flat out vec3 g_corner2;

void main() {
  vec3 c[3];
  for (int i = 0; i < 3; ++i) {
    vec2 ndc = gl_in[i].gl_Position.xy / gl_in[i].gl_Position.w;
    c[i] = vec3((ndc * 0.5 + 0.5) * u_image_size, v_depth[i]);
  }
#ifdef CONSERVATIVE
  // Half a texel, plus more than the rasterizer's subpixel snapping (GL
  // guarantees at least 4 subpixel bits: 1/16 texel), so a texel center on
  // the box's edge is never lost; the fragment stage's exact clip discards
  // the texels the triangle does not touch.
  const float kGrow = 0.5 + 0.0625 + 0.01;
  vec2 lo = min(min(c[0].xy, c[1].xy), c[2].xy) - vec2(kGrow);
  vec2 hi = max(max(c[0].xy, c[1].xy), c[2].xy) + vec2(kGrow);
  vec2 quad[4] = vec2[](vec2(lo.x, lo.y), vec2(hi.x, lo.y), vec2(lo.x, hi.y), vec2(hi.x, hi.y));
  for (int i = 0; i < 4; ++i) {
    g_corner0 = c[0];
    g_corner1 = c[1];
    g_corner2 = c[2];
    gl_Position = vec4(quad[i] / u_image_size * 2.0 - 1.0, 0.0, 1.0);
    EmitVertex();
  }
#else
  // The same triangle, in the same order (its facing decides a solid's
  // front and back maps).
  for (int i = 0; i < 3; ++i) {
    g_corner0 = c[0];
    g_corner1 = c[1];
    g_corner2 = c[2];
    gl_Position = gl_in[i].gl_Position;
    EmitVertex();
  }
#endif
  EndPrimitive();
}
