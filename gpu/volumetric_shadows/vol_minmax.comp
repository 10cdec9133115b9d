// One level of the per-row 1D min-max mipmaps: node i of level L covers
// columns [i 2^L, (i + 1) 2^L) and holds the min and max rectified depth
// over them. Level 0 is the rectified map itself; level L >= 1 sits in
// tree_min / tree_max at row * cols + (cols - cols >> (L - 1)) + i.
layout(local_size_x = 64) in;
layout(std430, binding = 0) readonly buffer RectDepth { float rect_depth[]; };
layout(std430, binding = 1) buffer TreeMin { float tree_min[]; };
layout(std430, binding = 2) buffer TreeMax { float tree_max[]; };
uniform int u_level, u_cols, u_rows;

void main() {
  int i = int(gl_GlobalInvocationID.x);
  int row = int(gl_GlobalInvocationID.y);
  int count = u_cols >> u_level;
  if (i >= count || row >= u_rows) return;
  int base = row * u_cols;
  float lo, hi;
  if (u_level == 1) {
    float a = rect_depth[base + 2 * i], b = rect_depth[base + 2 * i + 1];
    lo = min(a, b);
    hi = max(a, b);
  } else {
    int src = base + u_cols - (u_cols >> (u_level - 2)) + 2 * i;
    lo = min(tree_min[src], tree_min[src + 1]);
    hi = max(tree_max[src], tree_max[src + 1]);
  }
  int dst = base + u_cols - (u_cols >> (u_level - 1)) + i;
  tree_min[dst] = lo;
  tree_max[dst] = hi;
}
