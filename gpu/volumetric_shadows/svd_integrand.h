// The slides' "SVD approximation" (Chen et al. 2011, slide 30, after Baran
// et al. 2010) of the ray-dependent factor of the in-scattering integrand,
// for a spot light and for a (textured) directional light. CPU only (Eigen,
// double); no GL here.
//
// Spot light. In the epipolar plane through the eye E and the light L (d = |E - L|), a
// view ray at angle alpha from E->L and a light ray at angle phi from L->E
// meet at P with (law of sines) s = |EP| = d sin(phi) / sin(alpha + phi) and
// l = |LP| = d sin(alpha) / sin(alpha + phi); the scattering angle has
// cos = cos(alpha + phi), ds / l^2 = dphi / h with h = d sin(alpha), and
//   l + s - d = 2 d sin(alpha / 2) sin(phi / 2) / cos((alpha + phi) / 2).
// So a lit light ray phi contributes
//   sigma_s I w(phi) exp(-sigma_t (d - s_in)) / h * f(alpha, phi) dphi,
//   f(alpha, phi) = phase(cos(alpha + phi)) exp(-sigma_t (l + s - d)),
// where f depends on the medium only through sigma_t d and the phase. f is
// tabulated on a kSvdGrid x kSvdGrid grid, alpha over [margin, pi - margin]
// (rays closer to pointing at or away from the light are integrated
// exactly: there the domain alpha + phi < pi pinches to a corner and f is
// not smooth), phi over [0, pi], and truncated to rank K:
// f ~ sum_k U_k(alpha) S_k V_k(phi), each factor interpolated linearly
// between grid nodes.
//
// Directional light (travelling along w). In the epipolar plane a light ray
// is the line parallel to w at offset p from the eye's; a view ray at angle
// alpha from w reaches it at s = p / sin(alpha), where the light's depth in
// the medium is l = l_E + s cos(alpha), so l + s = l_E + p cot(alpha / 2)
// and ds = dp / sin(alpha): a lit light ray contributes
//   sigma_s I phase w(p) exp(-sigma_t (l_E - s_in)) / sin(alpha) * f dp,
//   f(alpha, p) = exp(-sigma_t p cot(alpha / 2)),
// tabulated over alpha in [margin, pi - margin] (near 0, f pinches to p = 0)
// and p in [0, p_max].
#pragma once

#include <vector>

namespace visq::gpu {

inline constexpr int kSvdGrid = 256;  // nodes per axis
inline constexpr int kSvdMaxRank = 8;

struct SvdIntegrandTable {
  int rank = 0;
  // Largest |f_K - f| over the domain that occurs (spot: alpha + phi < pi), at the
  // grid's nodes and at its cells' centers (where the linear interpolation
  // of U and V is worst), relative to the largest f.
  double relative_error = 0;
  double max_f = 0;
  double alpha0 = 0, alpha_step = 0;  // alpha_i = alpha0 + i alpha_step
  double x_step = 0;                  // x_i = i x_step (phi for a spot, p for a directional light)
  // [i * rank + k]: U_k(alpha_i) S_k and V_k(x_i).
  std::vector<float> u, v;
};

// f as above, in double. `max_depth` bounds sigma_t (l + s - d) over the
// medium (2 sigma_t times the farthest light distance): beyond it there are
// no points, and clamping there keeps f continuous (no values past
// alpha + phi = pi are used either; they continue the clamp, or the phase
// when sigma_t d = 0).
double SpotIntegrandFactor(double alpha, double phi, double sigma_t_d, double g, double max_depth);

// The smallest rank K <= max_rank whose relative error is at most
// `tolerance` (max_rank when none is); alpha over [alpha_lo, alpha_hi].
SvdIntegrandTable BuildSpotSvdTable(double sigma_t_d, double g, double max_depth, double alpha_lo, double alpha_hi,
                                    double tolerance, int max_rank = kSvdMaxRank);

// f of the directional light, p in world units.
double DirectionalIntegrandFactor(double alpha, double p, double sigma_t);

// The same for the directional light, p over [0, p_max].
SvdIntegrandTable BuildDirectionalSvdTable(double sigma_t, double p_max, double alpha_lo, double alpha_hi,
                                           double tolerance, int max_rank = kSvdMaxRank);

}  // namespace visq::gpu
