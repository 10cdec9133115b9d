// Per-row prefix sums of the light's unit weights (the slides' "light CDF"):
// prefix[row * (cols + 1) + j] = sum of rect_unit over columns [0, j). One
// invocation per row, in order, so the sums are deterministic.
// INTEGRAND_SVD: SVD_RANK sums per column, in double, of the terms
// rect_unit times V_k(phi) (the SVD's light-ray factors, linear between the
// table's nodes): prefix[(row * (cols + 1) + j) * SVD_RANK + k]; the terms
// themselves (float) go to svd_terms[(row * cols + j) * SVD_RANK + k] for
// single texels.
layout(local_size_x = 64) in;
layout(std430, binding = 4) readonly buffer RectUnit { float rect_unit[]; };
uniform int u_cols, u_rows;
#ifdef INTEGRAND_SVD
layout(std430, binding = 5) writeonly buffer Prefix { double prefix[]; };
layout(std430, binding = 8) readonly buffer RectPhi { float rect_phi[]; };
layout(std430, binding = 9) readonly buffer SvdTable { float svd_table[]; };  // U (alpha) then V (phi)
layout(std430, binding = 10) writeonly buffer SvdTerms { float svd_terms[]; };
#include "vol_svd.glsl"
#else
layout(std430, binding = 5) writeonly buffer Prefix { float prefix[]; };
#endif

void main() {
  int row = int(gl_GlobalInvocationID.x);
  if (row >= u_rows) return;
  int src = row * u_cols, dst = row * (u_cols + 1);
#ifdef INTEGRAND_SVD
  double sum[SVD_RANK];
  for (int k = 0; k < SVD_RANK; ++k) {
    sum[k] = 0.0;
    prefix[dst * SVD_RANK + k] = 0.0;
  }
  for (int j = 0; j < u_cols; ++j) {
    float v[SVD_RANK];
    SvdLightFactors(rect_phi[src + j], v);
    float unit = rect_unit[src + j];
    for (int k = 0; k < SVD_RANK; ++k) {
      float term = unit * v[k];
      svd_terms[(src + j) * SVD_RANK + k] = term;
      sum[k] += double(term);
      prefix[(dst + j + 1) * SVD_RANK + k] = sum[k];
    }
  }
#else
  float sum = 0.0;
  prefix[dst] = 0.0;
  for (int j = 0; j < u_cols; ++j) {
    sum += rect_unit[src + j];
    prefix[dst + j + 1] = sum;
  }
#endif
}
