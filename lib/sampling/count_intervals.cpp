#include "sampling/count_intervals.h"

#include <algorithm>
#include <cmath>
#include <deque>
#include <limits>
#include <mutex>

#include "common/check.h"
#include "common/parallel.h"

namespace visq::sampling {
namespace {

// The continued fraction of I_x(a, b) (modified Lentz), for x < (a + 1) /
// (a + b + 2), where it converges fast.
double BetaContinuedFraction(double a, double b, double x) {
  constexpr double kTiny = 1e-300, kEpsilon = 1e-15;
  double c = 1.0, d = 1.0 - (a + b) * x / (a + 1.0);
  if (std::abs(d) < kTiny) d = kTiny;
  d = 1.0 / d;
  double h = d;
  for (int m = 1; m <= 10000; ++m) {
    const double m2 = 2.0 * m;
    double aa = m * (b - m) * x / ((a + m2 - 1.0) * (a + m2));
    d = 1.0 + aa * d;
    if (std::abs(d) < kTiny) d = kTiny;
    c = 1.0 + aa / c;
    if (std::abs(c) < kTiny) c = kTiny;
    d = 1.0 / d;
    h *= d * c;
    aa = -(a + m) * (a + b + m) * x / ((a + m2) * (a + m2 + 1.0));
    d = 1.0 + aa * d;
    if (std::abs(d) < kTiny) d = kTiny;
    c = 1.0 + aa / c;
    if (std::abs(c) < kTiny) c = kTiny;
    d = 1.0 / d;
    const double step = d * c;
    h *= step;
    if (std::abs(step - 1.0) < kEpsilon) break;
  }
  return h;
}

// The p at which the increasing function tail(p) reaches `target`, by
// bisection on [0, 1] to float precision and beyond.
template <typename Tail>
double Solve(const Tail& tail, double target) {
  double lo = 0.0, hi = 1.0;
  for (int i = 0; i < 60; ++i) {
    const double mid = 0.5 * (lo + hi);
    (tail(mid) < target ? lo : hi) = mid;
  }
  return 0.5 * (lo + hi);
}

CountIntervals Compute(int n, double confidence) {
  CountIntervals out;
  out.sample_count = n;
  out.confidence = confidence;
  out.low.assign(size_t(n) + 1, 0.0f);
  out.high.assign(size_t(n) + 1, 1.0f);
  const double alpha = 0.5 * (1.0 - confidence);  // each side
  // Clopper-Pearson for count j: low(j) solves P(Bin(n, p) >= j) = alpha,
  // high(j) solves P(Bin(n, p) <= j) = alpha, i.e. P(Bin >= j + 1) = 1 - alpha.
  auto clopper_low = [&](int j) {
    if (j <= 0) return 0.0;
    return Solve([&](double p) { return RegularizedIncompleteBeta(j, n - j + 1, p); }, alpha);
  };
  auto clopper_high = [&](int j) {
    if (j >= n) return 1.0;
    return Solve([&](double p) { return RegularizedIncompleteBeta(j + 1, n - j, p); }, 1.0 - alpha);
  };
  // One count wider: k's limits are those of k - 1 and k + 1. Rounded
  // outwards to float.
  ParallelFor(size_t(n) + 1, 64, [&](size_t begin, size_t end) {
    for (size_t k = begin; k < end; ++k) {
      const double low = clopper_low(int(k) - 1), high = clopper_high(int(k) + 1);
      out.low[k] = std::nextafter(static_cast<float>(low), -1.0f);
      out.high[k] = std::nextafter(static_cast<float>(high), 2.0f);
      out.low[k] = std::clamp(out.low[k], 0.0f, 1.0f);
      out.high[k] = std::clamp(out.high[k], 0.0f, 1.0f);
    }
  });
  return out;
}

}  // namespace

double RegularizedIncompleteBeta(double a, double b, double x) {
  VISQ_CHECK(a > 0.0 && b > 0.0);
  if (x <= 0.0) return 0.0;
  if (x >= 1.0) return 1.0;
  const double log_front =
      std::lgamma(a + b) - std::lgamma(a) - std::lgamma(b) + a * std::log(x) + b * std::log1p(-x);
  if (x < (a + 1.0) / (a + b + 2.0)) return std::exp(log_front) * BetaContinuedFraction(a, b, x) / a;
  return 1.0 - std::exp(log_front) * BetaContinuedFraction(b, a, 1.0 - x) / b;
}

std::shared_ptr<const CountIntervals> StratifiedCountIntervals(int sample_count, double confidence) {
  VISQ_CHECK(sample_count >= 1 && confidence > 0.0 && confidence < 1.0);
  static std::mutex mutex;
  static std::deque<std::shared_ptr<const CountIntervals>> recent;  // most recent first
  {
    std::lock_guard lock(mutex);
    for (const auto& t : recent)
      if (t->sample_count == sample_count && t->confidence == confidence) return t;
  }
  auto made = std::make_shared<const CountIntervals>(Compute(sample_count, confidence));
  std::lock_guard lock(mutex);
  recent.push_front(made);
  if (recent.size() > 8) recent.pop_back();
  return made;
}

}  // namespace visq::sampling
