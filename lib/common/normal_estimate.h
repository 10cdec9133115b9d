// The normal approximation that visq states beside its rigorous bounds: a
// half-width z(confidence) * standard deviation, labelled an estimate
// wherever it is reported, because it holds only as far as the central
// limit theorem does for the samples at hand (its coverage is measured in
// docs/accuracy.md, not promised).
#pragma once

#include <array>
#include <cmath>
#include <cstdint>
#include <limits>

namespace visq {

// z with P(|N(0, 1)| > z) = 1 - confidence, for confidence in (0, 1), by
// bisection on erfc to double precision; +inf outside (0, 1).
inline double TwoSidedNormalQuantile(double confidence) {
  if (!(confidence > 0.0) || !(confidence < 1.0)) return std::numeric_limits<double>::infinity();
  double low = 0.0, high = 40.0;
  for (int i = 0; i < 100; ++i) {
    const double mid = 0.5 * (low + high);
    (std::erfc(mid / std::sqrt(2.0)) > 1.0 - confidence ? low : high) = mid;
  }
  return high;
}

// P(|T| <= t) for Student's t with `dof` >= 1 degrees of freedom, in closed
// form (Abramowitz & Stegun 26.7.3 for odd dof, 26.7.4 for even), O(dof).
inline double StudentTwoSidedMass(double t, int dof) {
  const double theta = std::atan(t / std::sqrt(static_cast<double>(dof)));
  const double c = std::cos(theta), s = std::sin(theta), c2 = c * c;
  if (dof % 2 == 0) {
    double term = 1.0, sum = 1.0;
    for (int k = 2; k <= dof - 2; k += 2) sum += (term *= c2 * (k - 1) / k);
    return s * sum;
  }
  double sum = 0.0;
  if (dof > 1) {
    double term = c;
    sum = c;
    for (int k = 3; k <= dof - 2; k += 2) sum += (term *= c2 * (k - 1) / k);
  }
  return 2.0 / 3.14159265358979323846 * (theta + s * sum);
}

// t with P(|T_dof| > t) = 1 - confidence: Student's t, the normal quantile's
// counterpart where the variance itself is estimated from dof degrees of
// freedom. By bisection on the closed form up to 64 degrees of freedom;
// beyond, the Cornish-Fisher expansion in 1 / dof to its third term (Abramowitz
// & Stegun 26.7.5), within 2e-5 of the quantile there at 95 %. +inf for a
// confidence outside (0, 1) or dof < 1.
inline double TwoSidedStudentQuantile(double confidence, int dof) {
  if (!(confidence > 0.0) || !(confidence < 1.0) || dof < 1) return std::numeric_limits<double>::infinity();
  if (dof > 64) {
    const double z = TwoSidedNormalQuantile(confidence), n = static_cast<double>(dof);
    const double z3 = z * z * z, z5 = z3 * z * z, z7 = z5 * z * z;
    return z + (z3 + z) / (4 * n) + (5 * z5 + 16 * z3 + 3 * z) / (96 * n * n) +
           (3 * z7 + 19 * z5 + 17 * z3 - 15 * z) / (384 * n * n * n);
  }
  double low = 0.0, high = 1.0;
  while (StudentTwoSidedMass(high, dof) < confidence && high < 1e300) high *= 2.0;
  for (int i = 0; i < 200 && high - low > 1e-12 * high; ++i) {
    const double mid = 0.5 * (low + high);
    (StudentTwoSidedMass(mid, dof) < confidence ? low : high) = mid;
  }
  return high;
}

// The spread of many non-negative values (a map's per-texel estimates,
// which are streamed a band at a time and never held whole) in logarithmic
// bins of 1/64 of a decade from 1e-7 to 1: a quantile is answered as its
// bin's upper edge, at most 3.7 % above the value it stands for and never
// below it.
class LogSpread {
 public:
  void Add(double value) {
    ++count_;
    if (!(value > 0.0)) {
      ++bins_[0];
      return;
    }
    const double position = (std::log10(value) - kLowestDecade) * kBinsPerDecade;
    const int bin = position < 0 ? 1 : std::min(kBins - 1, 1 + static_cast<int>(std::ceil(position)));
    ++bins_[bin];
  }
  uint64_t count() const { return count_; }
  // The q-quantile (q in [0, 1]), rounded up to its bin's upper edge; 0
  // without values.
  double Quantile(double q) const {
    if (count_ == 0) return 0.0;
    const uint64_t rank = std::min<uint64_t>(count_ - 1, static_cast<uint64_t>(q * static_cast<double>(count_)));
    uint64_t seen = 0;
    for (int bin = 0; bin < kBins; ++bin) {
      seen += bins_[bin];
      if (seen > rank) return UpperEdge(bin);
    }
    return UpperEdge(kBins - 1);
  }

 private:
  static constexpr double kLowestDecade = -7.0;
  static constexpr int kBinsPerDecade = 64;
  // Bin 0 holds zeros, bin 1 everything up to 1e-7, bin b > 1 the values in
  // (1e-7 * 10^((b - 2) / 64), 1e-7 * 10^((b - 1) / 64)] up to 1, and the
  // last everything above 1 (its edge infinite).
  static constexpr int kBins = 3 + 7 * kBinsPerDecade;
  static double UpperEdge(int bin) {
    if (bin == 0) return 0.0;
    if (bin == kBins - 1) return std::numeric_limits<double>::infinity();
    return std::pow(10.0, kLowestDecade + static_cast<double>(bin - 1) / kBinsPerDecade);
  }
  std::array<uint64_t, kBins> bins_{};
  uint64_t count_ = 0;
};

}  // namespace visq
