#include "sampling/count_intervals.h"

#include <algorithm>
#include <bit>
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

// The counts in [0, largest] whose entry is not computed yet, each once
// (marked 2, "listed", until its computation marks it 1).
std::vector<int> ListMissing(const std::vector<int>& counts, int largest, std::vector<uint8_t>& ready) {
  std::vector<int> missing;
  for (int k : counts) {
    VISQ_CHECK(k >= 0 && k <= largest);
    if (ready[size_t(k)] == 0) {
      ready[size_t(k)] = 2;
      missing.push_back(k);
    }
  }
  return missing;
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
  const std::vector<int> missing = ListMissing(counts, sample_count_, ready_);
  const int n = sample_count_;
  const double alpha = 0.5 * (1.0 - confidence_);  // each side
  // Clopper-Pearson for count j: low(j) solves P(Bin(n, p) >= j) = alpha,
  // i.e. I_p(j, n - j + 1) = alpha; high(j) solves P(Bin(n, p) <= j) =
  // alpha, i.e. I_p(j + 1, n - j) = 1 - alpha. Count k takes the limits of
  // k - 1 and k + 1 (one count wider), rounded outwards to float.
  // Where every trial agrees (k = n, or k = 0) the tail is known without
  // Hoeffding's theorem: n trials all succeed with probability prod(p_i) <=
  // exp(-sum(1 - p_i)), at most alpha where the mean lies ln(1 / alpha)
  // counts below n (3.7 at 95 %, against about 5.6 one count wider).
  const double agreeing = std::log(1.0 / alpha) / n;
  ParallelFor(missing.size(), 16, [&](size_t begin, size_t end) {
    for (size_t i = begin; i < end; ++i) {
      const int k = missing[i];
      const int below = k - 1, above = k + 1;
      double low = below <= 0 ? 0.0 : BetaQuantile(below, n - below + 1, alpha);
      double high = above >= n ? 1.0 : BetaQuantile(above + 1, n - above, 1.0 - alpha);
      if (k == n) low = std::max(low, 1.0 - agreeing);
      if (k == 0) high = std::min(high, agreeing);
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

double BennettDeviation(double variance, double delta) {
  VISQ_CHECK(variance >= 0.0 && delta > 0.0 && delta < 1.0);
  const double budget = std::log(2.0 / delta);  // two tails
  if (variance == 0.0) return 0.0;
  // V h(t / V) = budget, h(u) = (1 + u) ln(1 + u) - u, increasing in t.
  auto exponent = [&](double t) {
    const double u = t / variance;
    return variance * ((1.0 + u) * std::log1p(u) - u);
  };
  double lo = 0.0, hi = 1.0;
  while (exponent(hi) < budget) hi *= 2.0;
  for (int i = 0; i < 200 && hi - lo > 1e-12 * hi; ++i) {
    const double mid = 0.5 * (lo + hi);
    (exponent(mid) < budget ? lo : hi) = mid;
  }
  return hi;
}

SplitPairBounds::SplitPairBounds(int pairs, int unpaired, int samples, double delta_pairs, double delta_count)
    : pairs_(pairs),
      unpaired_(unpaired),
      samples_(samples),
      delta_pairs_(delta_pairs),
      delta_count_(delta_count),
      deviation_(size_t(pairs) + 1, 1.0f),
      ready_(size_t(pairs) + 1, 0) {
  VISQ_CHECK(pairs >= 0 && unpaired >= 0 && samples >= 2 * pairs + unpaired && samples >= 1);
  VISQ_CHECK(delta_pairs > 0.0 && delta_count > 0.0 && delta_pairs + delta_count < 1.0);
  if (pairs > 0) pair_limits_ = StratifiedCountIntervals(pairs, 1.0 - 2.0 * delta_pairs);
}

void SplitPairBounds::Prepare(const std::vector<int>& split_counts) {
  std::lock_guard lock(mutex_);
  const std::vector<int> missing = ListMissing(split_counts, pairs_, ready_);
  if (missing.empty()) return;
  if (pair_limits_) pair_limits_->Prepare(missing);
  for (const int k : missing) {
    // The variance can exceed neither its bound from the pairs nor a
    // quarter per sample.
    const double from_pairs = pair_limits_ ? double(pair_limits_->High(k)) * pairs_ : 0.0;
    const double variance = std::min(from_pairs + 0.25 * unpaired_, 0.25 * samples_);
    const double deviation = BennettDeviation(variance, delta_count_) / samples_;
    deviation_[size_t(k)] = std::nextafter(static_cast<float>(deviation), 2.0f);
    ready_[size_t(k)] = 1;
  }
}

float SplitPairBounds::Deviation(int split_pairs) const {
  VISQ_DCHECK_EQ(int(ready_[size_t(split_pairs)]), 1);
  return deviation_[size_t(split_pairs)];
}

std::shared_ptr<SplitPairBounds> CachedSplitPairBounds(int pairs, int unpaired, int samples, double delta_pairs,
                                                       double delta_count) {
  static std::mutex mutex;
  static std::deque<std::shared_ptr<SplitPairBounds>> recent;  // most recent first
  std::lock_guard lock(mutex);
  for (const auto& b : recent)
    if (b->pairs() == pairs && b->unpaired() == unpaired && b->samples() == samples &&
        b->delta_pairs() == delta_pairs && b->delta_count() == delta_count)
      return b;
  recent.push_front(std::make_shared<SplitPairBounds>(pairs, unpaired, samples, delta_pairs, delta_count));
  if (recent.size() > 8) recent.pop_back();
  return recent.front();
}

namespace {

// Bit 2i of the result is set where pair (2i, 2i + 1) of `bits` is split;
// `count` is how many of the word's 32 samples exist.
constexpr uint32_t kEvenBits = 0x55555555u;
uint32_t PairsInWord(int count) {
  const int whole_pairs = std::clamp(count, 0, 32) / 2;
  return whole_pairs >= 16 ? kEvenBits : (kEvenBits & ((1u << (2 * whole_pairs)) - 1u));
}

}  // namespace

int SplitPairs(std::span<const uint32_t> blocked, int sample_count) {
  int split = 0;
  for (size_t w = 0; w < blocked.size(); ++w) {
    const uint32_t word = blocked[w];
    split += std::popcount((word ^ (word >> 1)) & PairsInWord(sample_count - 32 * int(w)));
  }
  return split;
}

int SplitPairsAtMost(std::span<const uint32_t> answer, std::span<const uint32_t> sure, int sample_count) {
  VISQ_DCHECK_EQ(answer.size(), sure.size());
  int split = 0;
  for (size_t w = 0; w < answer.size(); ++w) {
    const uint32_t unsure = answer[w] & ~sure[w];
    const uint32_t maybe = (answer[w] ^ (answer[w] >> 1)) | unsure | (unsure >> 1);
    split += std::popcount(maybe & PairsInWord(sample_count - 32 * int(w)));
  }
  return split;
}

}  // namespace visq::sampling
