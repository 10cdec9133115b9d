// Per-texel bounds from what a texel's samples show. With one independent
// uniform sample in each of N equal-area cells (ErrorBound::rigorous), a
// texel's count of visible samples is Poisson-binomial: a sum of N
// independent Bernoulli trials whose mean is N times the true visible
// fraction. Its tails beyond one count of the mean are no heavier than those
// of the binomial with the same mean (Hoeffding 1956, "On the distribution of
// the number of successes in independent trials", Theorem 4), so the
// binomial's Clopper-Pearson limits, taken one count wider, hold for it at
// the same confidence. A texel whose 256 samples are all visible is then
// within 0.022 of 1 at 95 %, where Hoeffding's worst case states 0.085.
#pragma once

#include <cstdint>
#include <memory>
#include <mutex>
#include <vector>

namespace visq::sampling {

// The limits for counts k in [0, sample_count]: for k visible samples of
// sample_count, with probability >= confidence, Low(k) <= true visible
// fraction <= High(k). Each limit is computed the first time a map needs it
// (a map of 65,536 samples needs a few of the 65,537 counts) and kept.
class CountIntervals {
 public:
  CountIntervals(int sample_count, double confidence);
  int sample_count() const { return sample_count_; }
  double confidence() const { return confidence_; }
  // Computes the limits of `counts` not computed yet. Thread-safe; after it
  // returns, this thread may read those counts' limits.
  void Prepare(const std::vector<int>& counts);
  float Low(int k) const;
  float High(int k) const;

 private:
  int sample_count_;
  double confidence_;
  std::mutex mutex_;
  std::vector<float> low_, high_;
  std::vector<uint8_t> ready_;
};

// The limits for (sample_count, confidence), 1..65536 samples and a
// confidence in (0, 1); the last few kept. Thread-safe.
std::shared_ptr<CountIntervals> StratifiedCountIntervals(int sample_count, double confidence);

// Regularized incomplete beta function I_x(a, b), a, b > 0, x in [0, 1]:
// the binomial's tail, P(Bin(n, p) >= k) = I_p(k, n - k + 1).
double RegularizedIncompleteBeta(double a, double b, double x);

}  // namespace visq::sampling
