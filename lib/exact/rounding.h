// The error constants of the exact predicates' floating-point filters,
// derived from the unit roundoff instead of typed: Higham's gamma_n
// (Accuracy and Stability of Numerical Algorithms, Lemma 3.1) for n
// roundings, and Shewchuk's static error bounds (Adaptive Precision
// Floating-Point Arithmetic and Fast Robust Geometric Predicates, 1997).
// tests/exact/exact_predicates_test.cpp holds each to the value it replaced.
#pragma once

#include <limits>

namespace visq::exact {

// u = 2^-53: a rounding to nearest is within u of the exact result, relatively.
inline constexpr double kUnitRoundoff = std::numeric_limits<double>::epsilon() / 2;

// gamma_n = n u / (1 - n u) bounds the relative error of n roundings
// (1 + d_1) ... (1 + d_n) - 1, |d_i| <= u; rounded up past the few ulps of
// its own evaluation, so that it is never below the real gamma_n.
constexpr double Gamma(int n) {
  const double nu = n * kUnitRoundoff;
  return nu / (1.0 - nu) * (1.0 + 4.0 * kUnitRoundoff);
}

// Shewchuk's first-stage bounds (o3derrboundA, ccwerrboundA), as his code
// computes them with epsilon = u: orient3d's determinant is within
// (7 + 56 u) u of its permanent, orient2d's within (3 + 16 u) u.
inline constexpr double kOrient3dFilter = (7.0 + 56.0 * kUnitRoundoff) * kUnitRoundoff;
inline constexpr double kOrient2dFilter = (3.0 + 16.0 * kUnitRoundoff) * kUnitRoundoff;

// A fan plane's normal n = (a - p) x (b - p): each component is within four
// roundings of its magnitude |u_y v_z| + |u_z v_y| (two differences, a
// product, the difference of products), and the magnitude as computed is
// itself two roundings low at most, so gamma_5 of the computed magnitude
// covers it: 4u (1 + 2u) + O(u^2) < 5u.
inline constexpr double kFanNormalError = Gamma(5);

// A filter's bound, a sum of positive terms, is itself rounded: about a
// dozen ulps (24 u) for the dot-product filters' terms, sums and
// precomputed parts; the factor 1 + gamma_36 covers that with half again
// to spare. The fan plane's offset radius has fewer terms: 1 + gamma_18.
inline constexpr double kDotFilterRounding = 1.0 + Gamma(36);
inline constexpr double kOffsetRadiusRounding = 1.0 + Gamma(18);

}  // namespace visq::exact
