// Per-texel bounds from what a texel's samples show. With one independent
// uniform sample in each of N equal-area cells (ErrorBound::rigorous), a
// texel's count of visible samples is Poisson-binomial: a sum of N
// independent Bernoulli trials whose mean is N times the true visible
// fraction. Its tails beyond one count of the mean are no heavier than those
// of the binomial with the same mean (Hoeffding 1956, "On the distribution of
// the number of successes in independent trials", Theorem 4), so the
// binomial's Clopper-Pearson limits, taken one count wider, hold for it at
// the same confidence. Where every sample agrees the tail is direct (all n
// visible with probability <= exp(-n (1 - fraction))): a texel whose 256
// samples are all visible is within ln(40) / 256 = 0.0144 of 1 at 95 %,
// where Hoeffding's worst case states 0.085.
#pragma once

#include <cstdint>
#include <memory>
#include <mutex>
#include <span>
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

// The count alone cannot see stratification: a penumbra texel's count is
// bounded as if its samples were binomial, while only the cells that a
// shadow edge crosses vary (the error falls as N^-3/4, not N^-1/2). What
// the samples show of that: pair the cells (2i, 2i + 1), neighbours along a
// row of the pattern, and count the pairs whose samples disagree. For
// independent samples of visibility probabilities p and q, a pair disagrees
// with probability p + q - 2pq = p(1 - p) + q(1 - q) + (p - q)^2, never
// less than the pair's variance, and the pairs are independent. So K split
// pairs of P bound the count's variance V, with probability >= 1 - delta_pairs,
// by the Clopper-Pearson upper limit of K (one count wider, as above) times
// P, plus 1/4 for each unpaired cell; Bennett's inequality then bounds the
// count's deviation at that variance with probability >= 1 - delta_count.
// The two events together fail with probability <= delta_pairs + delta_count.
// See docs/texel-bounds.md for the figures.
class SplitPairBounds {
 public:
  // `pairs` disjoint pairs and `unpaired` single cells among `samples`
  // independent samples (every cell of every map summed into the count).
  SplitPairBounds(int pairs, int unpaired, int samples, double delta_pairs, double delta_count);
  int pairs() const { return pairs_; }
  int unpaired() const { return unpaired_; }
  int samples() const { return samples_; }
  double delta_pairs() const { return delta_pairs_; }
  double delta_count() const { return delta_count_; }
  // Computes the deviations of split-pair counts not computed yet.
  // Thread-safe; afterwards this thread may read those counts'.
  void Prepare(const std::vector<int>& split_counts);
  // With split_pairs of the pairs split: |visible count / samples - true
  // visible fraction| <= Deviation(split_pairs), except with probability
  // <= delta_pairs + delta_count. Rounded up to float.
  float Deviation(int split_pairs) const;

 private:
  int pairs_, unpaired_, samples_;
  double delta_pairs_, delta_count_;
  std::shared_ptr<CountIntervals> pair_limits_;  // null without pairs
  std::mutex mutex_;
  std::vector<float> deviation_;
  std::vector<uint8_t> ready_;
};

// The bounds for (pairs, unpaired, samples, deltas); the last few kept.
// Thread-safe.
std::shared_ptr<SplitPairBounds> CachedSplitPairBounds(int pairs, int unpaired, int samples, double delta_pairs,
                                                       double delta_count);

// Pairs (2i, 2i + 1), 2i + 1 < sample_count, of a texel's blocked bits
// (bit i of word i / 32) with one bit set and one clear.
int SplitPairs(std::span<const uint32_t> blocked, int sample_count);
// With the Hough lookup's two masks (sure blocked within answer): the most
// pairs that can be split for any true set between them.
int SplitPairsAtMost(std::span<const uint32_t> answer, std::span<const uint32_t> sure, int sample_count);

// Bennett's inequality for a sum of independent terms within 1 of their
// means and of total variance `variance`: the t with P(|sum - mean| >= t)
// <= delta, rounded up.
double BennettDeviation(double variance, double delta);

// Regularized incomplete beta function I_x(a, b), a, b > 0, x in [0, 1]:
// the binomial's tail, P(Bin(n, p) >= k) = I_p(k, n - k + 1).
double RegularizedIncompleteBeta(double a, double b, double x);

}  // namespace visq::sampling
