#include "sampling/count_intervals.h"

#include <algorithm>
#include <cmath>
#include <deque>

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

// log of the Beta(a, b) density at x in (0, 1).
double LogBetaDensity(double a, double b, double x) {
  return std::lgamma(a + b) - std::lgamma(a) - std::lgamma(b) + (a - 1.0) * std::log(x) + (b - 1.0) * std::log1p(-x);
}

// The x in (0, 1) at which I_x(a, b) = target: Newton's steps on the
// incomplete beta, kept inside a bracket that shrinks with every step, and
// a bisection wherever a step would leave it.
double BetaQuantile(double a, double b, double target) {
  double lo = 0.0, hi = 1.0;
  double x = std::clamp(a / (a + b), 1e-12, 1.0 - 1e-12);
  for (int i = 0; i < 200; ++i) {
    const double f = RegularizedIncompleteBeta(a, b, x) - target;
    if (f < 0.0) lo = x; else hi = x;
    const double density = std::exp(LogBetaDensity(a, b, x));
    double next = density > 0.0 ? x - f / density : 0.5 * (lo + hi);
    if (!(next > lo && next < hi)) next = 0.5 * (lo + hi);
    if (std::abs(next - x) <= 1e-13 * x || hi - lo <= 1e-15) return next;
    x = next;
  }
  return x;
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

CountIntervals::CountIntervals(int sample_count, double confidence)
    : sample_count_(sample_count),
      confidence_(confidence),
      low_(size_t(sample_count) + 1, 0.0f),
      high_(size_t(sample_count) + 1, 1.0f),
      ready_(size_t(sample_count) + 1, 0) {
  VISQ_CHECK(sample_count >= 1 && confidence > 0.0 && confidence < 1.0);
}

void CountIntervals::Prepare(const std::vector<int>& counts) {
  std::lock_guard lock(mutex_);
  std::vector<int> missing;
  for (int k : counts) {
    VISQ_CHECK(k >= 0 && k <= sample_count_);
    if (ready_[size_t(k)] == 0) {
      ready_[size_t(k)] = 2;  // listed once
      missing.push_back(k);
    }
  }
  const int n = sample_count_;
  const double alpha = 0.5 * (1.0 - confidence_);  // each side
  // Clopper-Pearson for count j: low(j) solves P(Bin(n, p) >= j) = alpha,
  // i.e. I_p(j, n - j + 1) = alpha; high(j) solves P(Bin(n, p) <= j) =
  // alpha, i.e. I_p(j + 1, n - j) = 1 - alpha. Count k takes the limits of
  // k - 1 and k + 1 (one count wider), rounded outwards to float.
  ParallelFor(missing.size(), 16, [&](size_t begin, size_t end) {
    for (size_t i = begin; i < end; ++i) {
      const int k = missing[i];
      const int below = k - 1, above = k + 1;
      const double low = below <= 0 ? 0.0 : BetaQuantile(below, n - below + 1, alpha);
      const double high = above >= n ? 1.0 : BetaQuantile(above + 1, n - above, 1.0 - alpha);
      low_[size_t(k)] = std::clamp(std::nextafter(static_cast<float>(low), -1.0f), 0.0f, 1.0f);
      high_[size_t(k)] = std::clamp(std::nextafter(static_cast<float>(high), 2.0f), 0.0f, 1.0f);
      ready_[size_t(k)] = 1;
    }
  });
}

float CountIntervals::Low(int k) const {
  VISQ_DCHECK_EQ(int(ready_[size_t(k)]), 1);
  return low_[size_t(k)];
}

float CountIntervals::High(int k) const {
  VISQ_DCHECK_EQ(int(ready_[size_t(k)]), 1);
  return high_[size_t(k)];
}

std::shared_ptr<CountIntervals> StratifiedCountIntervals(int sample_count, double confidence) {
  VISQ_CHECK(sample_count >= 1 && sample_count <= 65536 && confidence > 0.0 && confidence < 1.0);
  static std::mutex mutex;
  static std::deque<std::shared_ptr<CountIntervals>> recent;  // most recent first
  std::lock_guard lock(mutex);
  for (const auto& t : recent)
    if (t->sample_count() == sample_count && t->confidence() == confidence) return t;
  recent.push_front(std::make_shared<CountIntervals>(sample_count, confidence));
  if (recent.size() > 8) recent.pop_back();
  return recent.front();
}

}  // namespace visq::sampling
