// Per-row prefix sums of the light's unit weights (the slides' "light CDF"):
// prefix[row * (cols + 1) + j] = sum of rect_unit over columns [0, j). One
// invocation per row, in order, so the sums are deterministic.
layout(local_size_x = 64) in;
layout(std430, binding = 4) readonly buffer RectUnit { float rect_unit[]; };
layout(std430, binding = 5) writeonly buffer Prefix { float prefix[]; };
uniform int u_cols, u_rows;

void main() {
  int row = int(gl_GlobalInvocationID.x);
  if (row >= u_rows) return;
  float sum = 0.0;
  int src = row * u_cols, dst = row * (u_cols + 1);
  prefix[dst] = 0.0;
  for (int j = 0; j < u_cols; ++j) {
    sum += rect_unit[src + j];
    prefix[dst + j + 1] = sum;
  }
}
