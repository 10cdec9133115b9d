// The SVD table of the spot light's integrand factor (svd_integrand.h):
// svd_table = U_k(alpha_i) S_k for i < SVD_GRID, then V_k(phi_i), each
// [i * SVD_RANK + k]; factors are linear between nodes. The includer
// declares svd_table.
uniform float u_svd_x_step;  // light-ray nodes at i u_svd_x_step (spot: phi; directional: p)

// V_k(x), clamped to the table.
void SvdLightFactors(float x_value, out float v[SVD_RANK]) {
  float x = clamp(x_value / u_svd_x_step, 0.0, float(SVD_GRID - 1));
  int i = min(int(x), SVD_GRID - 2);
  float t = x - float(i);
  int base = SVD_GRID * SVD_RANK + i * SVD_RANK;
  for (int k = 0; k < SVD_RANK; ++k) v[k] = mix(svd_table[base + k], svd_table[base + SVD_RANK + k], t);
}

// U_k(alpha) S_k, alpha at nodes alpha0 + i step (clamped to the table).
void SvdViewFactors(float alpha, float alpha0, float step, out float u[SVD_RANK]) {
  float x = clamp((alpha - alpha0) / step, 0.0, float(SVD_GRID - 1));
  int i = min(int(x), SVD_GRID - 2);
  float t = x - float(i);
  int base = i * SVD_RANK;
  for (int k = 0; k < SVD_RANK; ++k) u[k] = mix(svd_table[base + k], svd_table[base + SVD_RANK + k], t);
}
