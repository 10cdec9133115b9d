#include "core/accuracy_planner.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <chrono>
#include <fstream>
#include <limits>
#include <sstream>

#include <spdlog/spdlog.h>

#include "common/job_timing.h"
#include "core/idle_exploration.h"

namespace visq::core {

Status ValidateAccuracyTarget(const AccuracyTarget& target) {
  if (!std::isfinite(target.max_error) || target.max_error < 0.0 || target.max_error >= 1.0)
    return absl::InvalidArgumentError(absl::StrCat("target.max_error: ", target.max_error, " is not in [0, 1)"));
  if (!std::isfinite(target.confidence) || target.confidence <= 0.0 || target.confidence > 1.0)
    return absl::InvalidArgumentError(absl::StrCat("target.confidence: ", target.confidence, " is not in (0, 1]"));
  if (!std::isfinite(target.time_budget_ms) || target.time_budget_ms < 0.0)
    return absl::InvalidArgumentError(
        absl::StrCat("target.time_budget_ms: ", target.time_budget_ms, " is not a finite value >= 0"));
  if (target.max_error == 0.0 && target.time_budget_ms == 0.0)
    return absl::InvalidArgumentError("target: neither max_error nor time_budget_ms is set");
  if (target.wants_estimate() && target.confidence >= 1.0)
    return absl::InvalidArgumentError(
        "target.guarantee: an ESTIMATE has no worst case; give a confidence below 1, or ask for RIGOROUS");
  return absl::OkStatus();
}

std::string CostSeries(const std::string& scene, const std::string& kind, const std::string& method) {
  return absl::StrCat(scene, "/", kind, "/", method);
}

void CostModel::Record(const std::string& series, double work, double ms, double extra) {
  // A run of no work in either unit (the exact method answering from its
  // trees' stores) is kept: it measures the fixed cost.
  if (!std::isfinite(work) || !std::isfinite(ms) || !std::isfinite(extra) || work < 0.0 || extra < 0.0 || ms < 0.0)
    return;
  if (series.find_first_of("\t\n") != std::string::npos) return;  // the file's separators
  std::lock_guard lock(mutex_);
  if (!series_.contains(series) && series_.size() >= kSeriesKept) EvictLeastRecentlyUsedLocked();
  used_at_[series] = ++uses_;
  auto& observations = series_[series];
  observations.push_back({work, ms, extra});
  if (observations.size() > kObservationsKept) observations.pop_front();
  SaveLocked();
}

void CostModel::RecordCutProbe(const std::string& series, double budget_ms) {
  std::lock_guard lock(mutex_);
  if (!cut_probes_.contains(series) && cut_probes_.size() >= kSeriesKept) cut_probes_.erase(cut_probes_.begin());
  CutProbe& kept = cut_probes_[series];
  kept.budget_ms = std::max(kept.budget_ms, budget_ms);
  ++kept.count;
}

double CostModel::CutProbeBudget(const std::string& series) const {
  std::lock_guard lock(mutex_);
  auto it = cut_probes_.find(series);
  return it == cut_probes_.end() || it->second.count < 2 ? 0.0 : it->second.budget_ms;
}

int CostModel::CutProbes(const std::string& series) const {
  std::lock_guard lock(mutex_);
  auto it = cut_probes_.find(series);
  return it == cut_probes_.end() ? 0 : it->second.count;
}

void CostModel::AddExplorationCredit(const std::string& series, double ms) {
  if (!(ms > 0.0) || !std::isfinite(ms)) return;
  std::lock_guard lock(mutex_);
  if (!exploration_credit_.contains(series) && exploration_credit_.size() >= kSeriesKept)
    exploration_credit_.erase(exploration_credit_.begin());
  exploration_credit_[series] += ms;
}

double CostModel::TakeExplorationCredit(const std::string& series) {
  std::lock_guard lock(mutex_);
  auto it = exploration_credit_.find(series);
  if (it == exploration_credit_.end()) return 0.0;
  const double credit = it->second;
  exploration_credit_.erase(it);
  return credit;
}

double CostModel::ExplorationCredit(const std::string& series) const {
  std::lock_guard lock(mutex_);
  auto it = exploration_credit_.find(series);
  return it == exploration_credit_.end() ? 0.0 : it->second;
}

size_t CostModel::Observations(const std::string& series) const {
  std::lock_guard lock(mutex_);
  auto it = series_.find(series);
  return it == series_.end() ? 0 : it->second.size();
}

bool CostModel::FirstProbeOfMethod(const std::string& series, double extra) {
  const size_t after_scene = series.find('/');
  std::lock_guard lock(mutex_);
  return methods_probed_
      .emplace(after_scene == std::string::npos ? series : series.substr(after_scene + 1), extra)
      .second;
}

double CostModel::LargestWork(const std::string& series) const {
  std::lock_guard lock(mutex_);
  auto it = series_.find(series);
  double largest = 0.0;
  if (it != series_.end())
    for (const Observation& o : it->second) largest = std::max(largest, o.work);
  return largest;
}

size_t CostModel::DistinctSizes(const std::string& series) const {
  std::lock_guard lock(mutex_);
  auto it = series_.find(series);
  if (it == series_.end()) return 0;
  std::vector<std::pair<double, double>> sizes;
  for (const Observation& o : it->second) sizes.emplace_back(o.work, o.extra);
  std::sort(sizes.begin(), sizes.end());
  return static_cast<size_t>(std::unique(sizes.begin(), sizes.end()) - sizes.begin());
}

// One observation a line: series, work and ms, tab-separated (Record keeps
// no series holding a tab or newline), then the extra work where there is
// any (a file of one unit reads as before).
void CostModel::PersistTo(const std::filesystem::path& path) {
  std::lock_guard lock(mutex_);
  file_ = path;
  // A file far larger than kSeriesKept x kObservationsKept lines can be is
  // not this model's: it is left unread (and replaced at the next record).
  std::error_code size_error;
  const uintmax_t size = std::filesystem::file_size(path, size_error);
  if (!size_error && size > kMaxCostModelFileBytes) {
    spdlog::warn("cost model: {} is {} bytes, over {}: not read", path.string(), size, kMaxCostModelFileBytes);
    return;
  }
  std::ifstream in(path);
  std::string line;
  size_t read = 0;
  while (in && std::getline(in, line)) {
    const size_t tab1 = line.find('\t'), tab2 = tab1 == std::string::npos ? tab1 : line.find('\t', tab1 + 1);
    if (tab2 == std::string::npos || tab1 == 0) continue;
    double work = 0.0, ms = 0.0, extra = 0.0;
    std::istringstream numbers(line.substr(tab1 + 1));
    if (!(numbers >> work >> ms)) continue;
    if (!(numbers >> extra)) extra = 0.0;
    if (!std::isfinite(work) || !std::isfinite(ms) || !std::isfinite(extra) || work < 0.0 || extra < 0.0 || ms < 0.0)
      continue;
    const std::string series = line.substr(0, tab1);
    if (!series_.contains(series) && series_.size() >= kSeriesKept) continue;
    used_at_[series] = ++uses_;
    auto& observations = series_[series];
    observations.push_back({work, ms, extra});
    if (observations.size() > kObservationsKept) observations.pop_front();
    ++read;
  }
  if (read > 0) spdlog::info("cost model: {} observations of {} series from {}", read, series_.size(), path.string());
}

void CostModel::EvictLeastRecentlyUsedLocked() {
  auto oldest = used_at_.begin();
  for (auto it = used_at_.begin(); it != used_at_.end(); ++it)
    if (it->second < oldest->second) oldest = it;
  if (oldest == used_at_.end()) return;
  series_.erase(oldest->first);
  used_at_.erase(oldest);
}

void CostModel::SaveLocked() const {
  if (file_.empty()) return;
  std::filesystem::path temporary = file_;
  temporary += ".tmp";
  {
    std::ofstream out(temporary, std::ios::trunc);
    out.precision(17);
    for (const auto& [series, observations] : series_)
      for (const Observation& o : observations) {
        out << series << '\t' << o.work << '\t' << o.ms;
        if (o.extra > 0.0) out << '\t' << o.extra;
        out << '\n';
      }
    if (!out) return;
  }
  std::error_code ec;
  std::filesystem::rename(temporary, file_, ec);
  if (ec) spdlog::warn("cost model: cannot write {}: {}", file_.string(), ec.message());
}

namespace {

// ms = c[0] + c[1] * work + c[2] * extra over the terms `use` names, by
// least squares with every coefficient at least 0: each subset of the
// terms is fitted, and the closest non-negative fit wins; among fits as
// close (two observations fit two terms exactly), the one with more
// work terms and then without the fixed part. Three terms at most, so the
// subsets are seven small solves.
std::array<double, 3> FitNonNegative(const std::deque<CostModel::Observation>& observations) {
  constexpr std::array<std::array<bool, 3>, 7> kSubsets = {{{true, true, true},
                                                           {false, true, true},
                                                           {true, true, false},
                                                           {true, false, true},
                                                           {false, true, false},
                                                           {false, false, true},
                                                           {true, false, false}}};
  auto term = [](const CostModel::Observation& o, int k) { return k == 0 ? 1.0 : k == 1 ? o.work : o.extra; };
  double total = 0.0;
  for (const auto& o : observations) total += o.ms * o.ms;
  std::array<double, 3> best = {0.0, 0.0, 0.0};
  double best_residual = std::numeric_limits<double>::infinity();
  for (const auto& use : kSubsets) {
    std::vector<int> terms;
    for (int k = 0; k < 3; ++k)
      if (use[k]) terms.push_back(k);
    const size_t n = terms.size();
    if (observations.size() < n) continue;
    // The normal equations, solved by Gaussian elimination with partial
    // pivoting; a pivot that vanishes against its column means the terms
    // are not independent over these observations.
    double a[3][4] = {};
    for (const auto& o : observations)
      for (size_t i = 0; i < n; ++i) {
        for (size_t j = 0; j < n; ++j) a[i][j] += term(o, terms[i]) * term(o, terms[j]);
        a[i][n] += term(o, terms[i]) * o.ms;
      }
    bool singular = false;
    for (size_t col = 0; col < n && !singular; ++col) {
      size_t pivot = col;
      for (size_t r = col + 1; r < n; ++r)
        if (std::abs(a[r][col]) > std::abs(a[pivot][col])) pivot = r;
      std::swap(a[col], a[pivot]);
      double scale = 0.0;
      for (size_t r = 0; r < n; ++r) scale = std::max(scale, std::abs(a[r][col]));
      if (!(std::abs(a[col][col]) > 1e-12 * scale)) {
        singular = true;
        break;
      }
      for (size_t r = 0; r < n; ++r) {
        if (r == col) continue;
        const double f = a[r][col] / a[col][col];
        for (size_t c = col; c <= n; ++c) a[r][c] -= f * a[col][c];
      }
    }
    if (singular) continue;
    std::array<double, 3> c = {0.0, 0.0, 0.0};
    bool negative = false;
    for (size_t i = 0; i < n; ++i) {
      c[terms[i]] = a[i][n] / a[i][i];
      negative = negative || !(c[terms[i]] >= 0.0);
    }
    if (negative) continue;
    double residual = 0.0;
    for (const auto& o : observations) {
      const double r = o.ms - (c[0] + c[1] * o.work + c[2] * o.extra);
      residual += r * r;
    }
    if (residual < best_residual - 1e-9 * total) {
      best_residual = residual;
      best = c;
    }
  }
  return best;
}

}  // namespace

std::optional<double> CostModel::Predict(const std::string& series, double work, double extra) const {
  std::lock_guard lock(mutex_);
  auto it = series_.find(series);
  if (it == series_.end() || it->second.empty()) return std::nullopt;
  used_at_[series] = ++uses_;
  const auto& observations = it->second;

  const bool two_units = extra > 0.0 || std::any_of(observations.begin(), observations.end(),
                                                    [](const Observation& o) { return o.extra > 0.0; });
  if (two_units) {
    double cheapest = std::numeric_limits<double>::infinity(), idle_sum = 0.0;
    size_t idle_runs = 0;
    for (const Observation& o : observations) {
      cheapest = std::min(cheapest, o.ms);
      if (o.work == 0.0 && o.extra == 0.0) {
        idle_sum += o.ms;
        ++idle_runs;
      }
    }
    // A run of no work in either unit (every answer from the exact method's
    // stores) only looks answers up: it costs what such runs have cost, and
    // at most the cheapest run measured. The fit's fixed part is no guide
    // to it: it also absorbs how a rate falls as the work grows (a lazily
    // refined tree's points get cheaper), which can be 50x such a run.
    if (work == 0.0 && extra == 0.0) return idle_runs > 0 ? idle_sum / double(idle_runs) : cheapest;
    // A run that cost more than twice a run of at least its work in both
    // units paid for something else: one-time costs (a method's first
    // probe compiles its GL programs: 103 ms for 16 Cornell texels against
    // 7 ms for 256 right after), or a machine busy for a moment. Fitted,
    // it turns into a rate and is extrapolated by the request's size.
    std::deque<Observation> kept;
    for (const Observation& o : observations) {
      const bool paid_for_more = std::any_of(observations.begin(), observations.end(), [&](const Observation& other) {
        return other.work >= o.work && other.extra >= o.extra && 2.0 * other.ms < o.ms;
      });
      if (!paid_for_more) kept.push_back(o);
    }
    // Never below the cheapest run the series has measured: a fit of two
    // probes may leave out the fixed part and predict next to nothing.
    const std::array<double, 3> c = FitNonNegative(kept);
    return std::max(cheapest, c[0] + c[1] * work + c[2] * extra);
  }

  // Least squares of ms on work. With one distinct amount of work there is
  // no slope to fit: the cost is taken as proportional, which over-predicts
  // larger requests by the fixed part (the safe side for a budget).
  double n = 0, sw = 0, sm = 0, sww = 0, swm = 0;
  for (const auto& o : observations) {
    n += 1;
    sw += o.work;
    sm += o.ms;
    sww += o.work * o.work;
    swm += o.work * o.ms;
  }
  if (!(sw > 0.0)) return sm / n;  // only runs of no work: their mean is all there is
  const double variance = sww - sw * sw / n;
  double rate = sm / sw, fixed = 0.0;
  if (variance > 1e-9 * sww) {
    const double fitted_rate = (swm - sw * sm / n) / variance;
    const double fitted_fixed = (sm - fitted_rate * sw) / n;
    // A negative slope or intercept is noise (or a cache warming up): keep
    // the proportional model then.
    if (fitted_rate > 0.0 && fitted_fixed >= 0.0) {
      rate = fitted_rate;
      fixed = fitted_fixed;
    }
  }
  return fixed + rate * work;
}

double HoeffdingSamplesNeeded(double max_error, double confidence) {
  if (confidence >= 1.0 || max_error <= 0.0) return std::numeric_limits<double>::infinity();
  return std::ceil(std::log(2.0 / (1.0 - confidence)) / (2.0 * max_error * max_error));
}

namespace {

enum class ProbeOutcome { kMeasured, kCut, kUnusable };

// Runs an option's probes from `first_probe` on within `budget_ms` (and the
// call's own deadline and cancellation), recording each into the model.
// kCut: the first of them ran past the budget (nothing learned); a later
// one that does leaves what the earlier ones measured (kMeasured) and is
// recorded as a cut probe, so that later requests back off before trying it
// again.
StatusOr<ProbeOutcome> ProbeOption(CostModel& model, const EqualAnswerOption& option, size_t first_probe,
                                   double budget_ms, const CallOptions& call, double& probe_ms) {
  const Plan& plan = option.plan;
  auto start = std::chrono::steady_clock::now();
  CallOptions probe_call = call;
  // The budget runs from `from`.
  auto start_budget = [&](std::chrono::steady_clock::time_point from) {
    start = from;
    if (std::isfinite(budget_ms)) {
      const auto budget_end = from + std::chrono::microseconds(static_cast<int64_t>(budget_ms * 1000.0));
      probe_call.stop.deadline = std::min(call.stop.deadline, budget_end);
    }
  };
  start_budget(start);
  const bool fresh = model.Observations(plan.cost_key) == 0;
  for (size_t k = first_probe; k < option.probes.size(); ++k) {
    const EqualAnswerOption::Probe& probe = option.probes[k];
    if (k > 0) {
      // A larger probe only when it is cheap beside the request itself (as
      // predicted by the probes so far, which take their cost as growing
      // with the work: the safe side) and while some budget is left. It is
      // not held to the prediction: one small probe cannot tell a fixed
      // cost from a rate (a pass over the scene from its fragments), which
      // is what the larger one is for; its deadline cuts it.
      const double probe_predicted = model.Predict(plan.cost_key, probe.work, probe.extra).value_or(0.0);
      const double request_predicted = model.Predict(plan.cost_key, plan.work, plan.extra_work).value_or(0.0);
      if (probe_predicted > kNextProbeShareOfRequest * request_predicted) break;
      if (std::isfinite(budget_ms) && 2.0 * MillisecondsSince(start) > budget_ms) break;
    }
    VISQ_RETURN_IF_ERROR(call.stop.Check("choosing a method"));
    const auto probe_start = std::chrono::steady_clock::now();
    StatusOr<double> ms = probe.run(probe_call);
    const double first_run_ms = MillisecondsSince(probe_start);
    probe_ms += first_run_ms;
    const bool first_of_method = model.FirstProbeOfMethod(plan.cost_key, probe.extra);
    if (ms.ok() && k == first_probe && (fresh || first_of_method) &&
        (first_of_method || !std::isfinite(budget_ms) ||
         MillisecondsSince(start) + first_run_ms <= kRepeatProbeShareOfBudget * budget_ms)) {
      const auto again_start = std::chrono::steady_clock::now();
      // The method's first run in this process paid its one-time costs (GL
      // programs compiled: 20 ms for a 4 x 4 Cornell map on llvmpipe, where
      // the next run takes 1 ms), which no later request pays again: the
      // runs that measure the method get the whole budget after them. The
      // first run completed within one GL job of its budget, so this costs
      // a request at most about twice its share.
      if (first_of_method) start_budget(again_start);
      StatusOr<double> again = probe.run(probe_call);
      probe_ms += MillisecondsSince(again_start);
      if (again.ok()) ms = std::min(*ms, *again);
    }
    spdlog::debug("{} probe {} of {} (work {}, {}): {} in {:.1f} ms of a {:.1f} ms budget",
                  call.log_tag.empty() ? "[call]" : call.log_tag, k, plan.method, probe.work, probe.extra,
                  ms.ok() ? "measured" : std::string(ms.status().message()), MillisecondsSince(probe_start),
                  budget_ms);
    if (!ms.ok()) {
      // The call itself still wants its answer: the probe ran out of its
      // budget, not the call.
      if (!call.stop.Stopped() && probe_call.stop.Stopped()) {
        model.RecordCutProbe(plan.cost_key, budget_ms);
        return k > first_probe || !fresh ? ProbeOutcome::kMeasured : ProbeOutcome::kCut;
      }
      if (ms.status().code() == absl::StatusCode::kFailedPrecondition) return ProbeOutcome::kUnusable;
      return ms.status();
    }
    model.Record(plan.cost_key, probe.work, *ms, probe.extra);
  }
  return ProbeOutcome::kMeasured;
}

// The probe that would teach the model most about a measured option: the
// second size of one measured at one size only, or the first larger than
// its largest run for a request kLongestExtrapolation times that; none
// where that probe is not small beside the request.
std::optional<size_t> NextProbeToLearn(const CostModel& model, const EqualAnswerOption& option) {
  const Plan& plan = option.plan;
  const double largest = model.LargestWork(plan.cost_key);
  std::optional<size_t> next;
  if (model.DistinctSizes(plan.cost_key) < 2 && option.probes.size() > 1) {
    next = 1;
  } else if (plan.work > kLongestExtrapolation * largest) {
    for (size_t k = 0; k < option.probes.size() && !next; ++k)
      if (option.probes[k].work > largest) next = k;
  }
  if (!next) return std::nullopt;
  const EqualAnswerOption::Probe& probe = option.probes[*next];
  const double probe_ms = model.Predict(plan.cost_key, probe.work, probe.extra).value_or(0.0);
  const double request_ms = model.Predict(plan.cost_key, plan.work, plan.extra_work).value_or(0.0);
  if (probe_ms > kNextProbeShareOfRequest * request_ms) return std::nullopt;
  return next;
}

}  // namespace

Status ProbeOutsideARequest(CostModel& model, const EqualAnswerOption& option, size_t first_probe, double budget_ms,
                            const CallOptions& call, double& probe_ms) {
  return ProbeOption(model, option, first_probe, budget_ms, call, probe_ms).status();
}

StatusOr<PlanReport> ChooseFastest(CostModel& model, std::vector<EqualAnswerOption> options, const CallOptions& call,
                                   IdleExplorer* idle) {
  PlanReport report;
  report.reason = PlanReport::Reason::kFastestOfEqualAnswers;
  double best_ms = std::numeric_limits<double>::infinity();
  // Where `option`'s probe from `first_probe` on runs at this budget:
  // here, or in idle time (offered to the explorer) where the budget is too
  // small to pay for it or the probe is a larger one of a method already
  // measured, or nowhere where the budget is too small and there is no
  // explorer, or not far above the budget a probe of it was cut at (a
  // method slow here). A larger probe inside a request cost the Sponza and
  // flowers maps 135-200 ms of a 550 ms call for a method 100x slower.
  enum class Probe { kHere, kSkipped, kInIdleTime };
  auto where_to_probe = [&](const EqualAnswerOption& option, size_t first_probe, double budget_ms, bool larger) {
    if (budget_ms < 4.0 * model.CutProbeBudget(option.plan.cost_key)) return Probe::kSkipped;
    const bool idle_takes_it = idle != nullptr && option.probes_outlive_the_call;
    if (!(larger && idle_takes_it) &&
        budget_ms >= (idle_takes_it ? kSmallestInlineProbeBudgetMs : kSmallestProbeBudgetMs))
      return Probe::kHere;
    if (!idle_takes_it) return Probe::kSkipped;
    idle->Offer(option, first_probe);
    return Probe::kInIdleTime;
  };
  for (EqualAnswerOption& option : options) {
    Plan& plan = option.plan;
    if (model.Observations(plan.cost_key) == 0) {
      // This request's share of the best plan, and what the requests before
      // it that could not afford the probe have set aside.
      const double share_ms = std::isfinite(best_ms) ? kProbeShareOfBest * best_ms : best_ms;
      const double budget_ms = share_ms + model.ExplorationCredit(plan.cost_key);
      // Too cheap to learn a new method on yet, or its probe was cut at a
      // budget not far below this one.
      if (const Probe where = where_to_probe(option, 0, budget_ms, false); where != Probe::kHere) {
        model.AddExplorationCredit(plan.cost_key, share_ms);
        (where == Probe::kInIdleTime ? report.left_to_idle_time : report.cut_probes).push_back(plan.method);
        continue;
      }
      const double credit_ms = model.TakeExplorationCredit(plan.cost_key);
      VISQ_ASSIGN_OR_RETURN(const ProbeOutcome outcome,
                            ProbeOption(model, option, 0, budget_ms, call, report.probe_ms));
      if (outcome == ProbeOutcome::kUnusable) continue;
      if (outcome == ProbeOutcome::kCut) {
        // A first cut paid one-time costs: what was set aside stays.
        if (model.CutProbes(plan.cost_key) < 2) model.AddExplorationCredit(plan.cost_key, credit_ms + share_ms);
        report.cut_probes.push_back(plan.method);
        continue;
      }
    } else if (const std::optional<size_t> next = NextProbeToLearn(model, option)) {
      // Measured at one size, or far below this request: its prediction is
      // the safe side's guess (fixed costs taken for rate), which was 1000x
      // a raster map's real cost and 10x the ray caster's. The idle
      // explorer runs the next probe size, or else this request's share
      // buys it.
      const double share_ms = std::isfinite(best_ms) ? kProbeShareOfBest * best_ms : best_ms;
      const double budget_ms = share_ms + model.ExplorationCredit(plan.cost_key);
      if (where_to_probe(option, *next, budget_ms, true) != Probe::kHere) {
        model.AddExplorationCredit(plan.cost_key, share_ms);
      } else {
        model.TakeExplorationCredit(plan.cost_key);
        VISQ_ASSIGN_OR_RETURN(const ProbeOutcome outcome,
                              ProbeOption(model, option, *next, budget_ms, call, report.probe_ms));
        if (outcome == ProbeOutcome::kUnusable) continue;
      }
    }
    plan.predicted_ms = model.Predict(plan.cost_key, plan.work, plan.extra_work).value_or(0.0);
    plan.meets_target = true;  // every option gives the asked answer
    best_ms = std::min(best_ms, plan.predicted_ms);
    report.plans.push_back(std::move(plan));
  }
  if (report.plans.empty()) return absl::FailedPreconditionError("no method can answer this request");
  report.chosen = static_cast<size_t>(
      std::min_element(report.plans.begin(), report.plans.end(),
                       [](const Plan& a, const Plan& b) { return a.predicted_ms < b.predicted_ms; }) -
      report.plans.begin());
  LogChosenPlan(report, call);
  return report;
}

void LogChosenPlan(const PlanReport& report, const CallOptions& call) {
  if (report.plans.empty()) return;
  constexpr double kLongCallMs = 1000.0;
  const Plan& chosen = report.chosen_plan();
  std::string weighed;
  for (size_t i = 0; i < report.plans.size(); ++i)
    if (i != report.chosen)
      absl::StrAppend(&weighed, weighed.empty() ? "; weighed: " : ", ", DescribePlan(report.plans[i]), " ",
                      fmt::format("{:.0f}", report.plans[i].predicted_ms), " ms");
  spdlog::log(chosen.predicted_ms >= kLongCallMs ? spdlog::level::info : spdlog::level::debug,
              "{} plan: {}, predicted {:.0f} ms{}", call.log_tag.empty() ? "[call]" : call.log_tag,
              DescribePlan(chosen), chosen.predicted_ms, weighed);
}

std::string DescribePlan(const Plan& plan) {
  std::string parameters;
  for (const auto& [name, value] : plan.parameters)
    absl::StrAppend(&parameters, parameters.empty() ? "" : ", ", name, ": ", value);
  return parameters.empty() ? plan.method : absl::StrCat(plan.method, " {", parameters, "}");
}

StatusOr<size_t> ChoosePlan(std::vector<Plan>& plans, const AccuracyTarget& target) {
  if (plans.empty()) return absl::FailedPreconditionError("no method can answer this request with a target");
  const bool has_budget = target.time_budget_ms > 0.0;
  auto within_budget = [&](const Plan& p) { return !has_budget || p.predicted_ms <= target.time_budget_ms; };
  auto cheaper = [](const Plan& a, const Plan& b) { return a.predicted_ms < b.predicted_ms; };
  auto more_accurate = [](const Plan& a, const Plan& b) {
    return a.error_bound < b.error_bound || (a.error_bound == b.error_bound && a.predicted_ms < b.predicted_ms);
  };
  const auto index_of = [&](std::vector<Plan>::iterator it) { return static_cast<size_t>(it - plans.begin()); };

  // An error target: the cheapest plan meeting it.
  if (target.max_error > 0.0) {
    for (Plan& p : plans) p.meets_target = p.error_bound <= target.max_error && within_budget(p);
    auto best = plans.end();
    for (auto it = plans.begin(); it != plans.end(); ++it)
      if (it->meets_target && (best == plans.end() || cheaper(*it, *best))) best = it;
    if (best != plans.end()) return index_of(best);
    auto cheapest_accurate = plans.end();
    for (auto it = plans.begin(); it != plans.end(); ++it)
      if (it->error_bound <= target.max_error && (cheapest_accurate == plans.end() || cheaper(*it, *cheapest_accurate)))
        cheapest_accurate = it;
    if (cheapest_accurate != plans.end())
      return absl::OutOfRangeError(absl::StrCat("target: +-", target.max_error, " needs at least ",
                                                DescribePlan(*cheapest_accurate), ", predicted ",
                                                cheapest_accurate->predicted_ms, " ms, over the budget of ",
                                                target.time_budget_ms, " ms"));
    const auto most_accurate = std::min_element(plans.begin(), plans.end(), more_accurate);
    return absl::OutOfRangeError(absl::StrCat("target: no method reaches +-", target.max_error, " at confidence ",
                                              target.confidence, " for this request; the best is ",
                                              DescribePlan(*most_accurate), " with +-", most_accurate->error_bound));
  }

  // A budget alone: the most accurate plan predicted to fit.
  for (Plan& p : plans) p.meets_target = within_budget(p);
  auto best = plans.end();
  for (auto it = plans.begin(); it != plans.end(); ++it)
    if (it->meets_target && (best == plans.end() || more_accurate(*it, *best))) best = it;
  if (best != plans.end()) return index_of(best);
  return index_of(std::min_element(plans.begin(), plans.end(), cheaper));
}

}  // namespace visq::core
