// The accuracy planner's cost model and choice rules, on numbers
// whose right answer is known by hand.
#include "core/accuracy_planner.h"

#include <atomic>
#include <chrono>
#include <cmath>
#include <fstream>
#include <string>
#include <thread>

#include <gtest/gtest.h>

#include "test_support.h"

namespace visq::core {
namespace {

TEST(CostModel, PredictsNothingBeforeAnObservation) {
  CostModel model;
  EXPECT_FALSE(model.Predict("scene/kind/method", 100.0).has_value());
}

// Past the cap, the series least recently used goes. Before, the first by
// name went: one a plan had just probed could go before the plan predicted
// it, and a plan with no prediction was weighed as taking 0 ms.
TEST(CostModel, PastItsSeriesCapTheLeastRecentlyUsedSeriesGoes) {
  CostModel model;
  for (size_t i = 0; i < CostModel::kSeriesKept; ++i) model.Record("s/k/" + std::to_string(1000000 + i), 10.0, 1.0);
  ASSERT_TRUE(model.Predict("s/k/1000000", 10.0).has_value());  // the first by name, just used
  model.Record("s/k/new", 10.0, 1.0);
  EXPECT_TRUE(model.Predict("s/k/1000000", 10.0).has_value()) << "the series a plan just used was dropped";
  EXPECT_FALSE(model.Predict("s/k/1000001", 10.0).has_value()) << "the least recently used series was kept";
  EXPECT_TRUE(model.Predict("s/k/new", 10.0).has_value());
}

TEST(CostModel, OneObservationIsTakenAsProportional) {
  CostModel model;
  model.Record("s/k/m", 100.0, 50.0);
  ASSERT_TRUE(model.Predict("s/k/m", 400.0).has_value());
  EXPECT_DOUBLE_EQ(*model.Predict("s/k/m", 400.0), 200.0);
  EXPECT_FALSE(model.Predict("s/k/other", 400.0).has_value()) << "series are separate";
}

TEST(CostModel, FitsAFixedCostAndARate) {
  CostModel model;
  // ms = 10 + 0.5 * work, exactly.
  for (double work : {10.0, 100.0, 1000.0}) model.Record("s", work, 10.0 + 0.5 * work);
  EXPECT_NEAR(*model.Predict("s", 4000.0), 2010.0, 1e-6);
}

TEST(CostModel, ANegativeFittedSlopeFallsBackToProportional) {
  CostModel model;
  // A cache warming up: the larger run was faster.
  model.Record("s", 10.0, 100.0);
  model.Record("s", 100.0, 20.0);
  const double predicted = *model.Predict("s", 110.0);
  EXPECT_NEAR(predicted, 120.0 / 110.0 * 110.0, 1e-9);
}

// Two units: ms = 2 + 0.5 x work + 3 x extra, exactly. Probes that grow
// both units together cannot tell them apart; a third observation that
// grows one alone can, and the fit then extrapolates each by its own rate.
TEST(CostModel, FitsTwoUnitsOfWorkEachAtItsOwnRate) {
  CostModel model;
  auto cost = [](double work, double extra) { return 2.0 + 0.5 * work + 3.0 * extra; };
  model.Record("s", 10.0, cost(10.0, 1.0), 1.0);
  model.Record("s", 100.0, cost(100.0, 4.0), 4.0);
  model.Record("s", 400.0, cost(400.0, 100.0), 100.0);
  EXPECT_NEAR(*model.Predict("s", 1e5, 10.0), cost(1e5, 10.0), 1e-6);
  EXPECT_NEAR(*model.Predict("s", 0.0, 1000.0), cost(0.0, 1000.0), 1e-6) << "the extra unit alone";
}

// A fit with a negative coefficient is refused for the closest one without
// it: never a negative prediction, and never below what one unit alone
// explains. A warm cache's run (nothing of the first unit, much of the
// second, cheaply) does not make the second unit's rate negative.
TEST(CostModel, TwoUnitsNeverFitANegativeRate) {
  CostModel model;
  model.Record("s", 1000.0, 1000.0, 64.0);  // cold: the work is the cost
  model.Record("s", 4000.0, 4000.0, 256.0);
  model.Record("s", 0.0, 1.0, 4096.0);  // warm: answered from the cache
  const double cold = *model.Predict("s", 8000.0, 4096.0);
  const double warm = *model.Predict("s", 0.0, 4096.0);
  EXPECT_GT(cold, 4000.0);
  EXPECT_GE(warm, 0.0);
  EXPECT_LT(warm, 100.0) << "the warm run's own cost, not the cold runs' per point";
  for (double work : {0.0, 10.0, 1e6})
    for (double extra : {0.0, 1.0, 1e6}) EXPECT_GE(*model.Predict("s", work, extra), 0.0);
}

// A run that cost more than twice a larger one paid for something else
// (its method's programs compiled): fitted, it would become a rate.
TEST(CostModel, ARunThatCostMoreThanTwiceALargerOneIsLeftOutOfTheFit) {
  CostModel model;
  auto cost = [](double work, double extra) { return 1e-5 * work + 0.005 * extra; };
  model.Record("s", 16.0 * 256, 100.0 + cost(16.0 * 256, 256.0), 256.0);  // and 100 ms of compiling
  model.Record("s", 256.0 * 1024, cost(256.0 * 1024, 1024.0), 1024.0);
  model.Record("s", 4096.0 * 1024, cost(4096.0 * 1024, 1024.0), 1024.0);
  EXPECT_NEAR(*model.Predict("s", 65536.0 * 1024, 1024.0), cost(65536.0 * 1024, 1024.0), 1e-6);
}

// A run of no work (the exact method answering every point from its
// trees' stores) is kept: it is the fixed cost, alone or beside the rates.
TEST(CostModel, ARunOfNoWorkMeasuresTheFixedCost) {
  CostModel model;
  model.Record("one", 0.0, 2.0);
  model.Record("one", 0.0, 4.0);
  EXPECT_DOUBLE_EQ(*model.Predict("one", 0.0), 3.0);
  auto cost = [](double work, double extra) { return 2.0 + 1.0 * work + 0.5 * extra; };
  model.Record("two", 0.0, cost(0, 0), 0.0);
  model.Record("two", 100.0, cost(100, 0), 0.0);
  model.Record("two", 0.0, cost(0, 400), 400.0);
  EXPECT_NEAR(*model.Predict("two", 0.0, 0.0), 2.0, 1e-9);
  EXPECT_NEAR(*model.Predict("two", 50.0, 1000.0), cost(50, 1000), 1e-9);

  // Two probes fit exactly without a fixed part; a run of no work is then
  // predicted at the cheapest run measured, not at 0 ms.
  model.Record("probed", 1000.0, 100.0, 64.0);
  model.Record("probed", 0.0, 30.0, 40.0);
  EXPECT_DOUBLE_EQ(*model.Predict("probed", 0.0, 0.0), 30.0);

  // Points that get cheaper as there are more of them fit a large fixed
  // part; a run of no work costs what such runs cost, not that part.
  model.Record("falling", 5000.0, 100.0, 64.0);
  model.Record("falling", 0.0, 60.0, 40.0);      // 1.5 ms a point, sparse
  model.Record("falling", 0.0, 540.0, 4000.0);   // 0.135 ms a point, dense
  EXPECT_GT(*model.Predict("falling", 0.0, 1.0), 20.0) << "the fit's fixed part";
  EXPECT_DOUBLE_EQ(*model.Predict("falling", 0.0, 0.0), 60.0) << "the cheapest run measured";
  model.Record("falling", 0.0, 3.0, 0.0);
  model.Record("falling", 0.0, 5.0, 0.0);
  EXPECT_DOUBLE_EQ(*model.Predict("falling", 0.0, 0.0), 4.0) << "what runs of no work cost";
}

TEST(CostModel, ObservationsOutliveTheModelInItsFile) {
  testing::ScratchDir dir;
  const std::filesystem::path file = dir.path() / "costs.tsv";
  {
    CostModel model;
    model.PersistTo(file);  // absent: nothing read
    EXPECT_FALSE(model.Predict("s/a", 1.0));
    model.Record("s/a", 10.0, 30.0);
    model.Record("s/a", 20.0, 50.0);
    model.Record("s/b", 4.0, 8.0);
    model.Record("s/d", 10.0, 20.0, 2.0);  // two units: a fourth column
    model.Record("s/d", 0.0, 5.0, 5.0);
    model.Record("bad\tname", 1.0, 1.0);  // the file's separator: not kept
  }
  {
    std::ofstream append(file, std::ios::app);
    append << "junk line\n" << "s/c\tnan\t3\n" << "s/c\t-1\t3\n" << "\t1\t2\n";
  }
  CostModel restored;
  restored.PersistTo(file);
  EXPECT_EQ(restored.Observations("s/a"), 2u);
  EXPECT_EQ(restored.Observations("s/b"), 1u);
  EXPECT_EQ(restored.Observations("s/c"), 0u);
  EXPECT_EQ(restored.Observations("bad\tname"), 0u);
  EXPECT_EQ(restored.Observations("s/d"), 2u);
  EXPECT_DOUBLE_EQ(*restored.Predict("s/d", 20.0, 1.0), 37.0);  // 1.8 x work + 1 x extra, as fitted before
  EXPECT_DOUBLE_EQ(*restored.Predict("s/a", 40.0), 90.0);  // 10 + 2 x 40, as fitted before
  EXPECT_DOUBLE_EQ(*restored.Predict("s/b", 2.0), 4.0);
}

// A file larger than any model's (a stray or hostile one) is not read into
// memory; the model starts empty and replaces it at its next record.
TEST(CostModel, AFileLargerThanAnyModelsIsLeftUnread) {
  testing::ScratchDir dir;
  const std::filesystem::path file = dir.path() / "costs.tsv";
  {
    std::ofstream out(file);
    out << "s/a\t10\t30\n";
  }
  std::filesystem::resize_file(file, kMaxCostModelFileBytes + 1);  // sparse: no disk used
  CostModel model;
  model.PersistTo(file);
  EXPECT_EQ(model.Observations("s/a"), 0u);
  model.Record("s/b", 1.0, 2.0);
  EXPECT_LT(std::filesystem::file_size(file), 1024u);
}

TEST(CostModel, KeepsOnlyRecentObservations) {
  CostModel model;
  for (int i = 0; i < 100; ++i) model.Record("s", 10.0, 1000.0);  // a slow past
  for (int i = 0; i < 16; ++i) model.Record("s", 10.0, 1.0);      // the machine now
  EXPECT_DOUBLE_EQ(*model.Predict("s", 10.0), 1.0);
}

TEST(HoeffdingSamplesNeeded, MatchesTheBoundItInverts) {
  const double n = HoeffdingSamplesNeeded(0.05, 0.95);
  EXPECT_EQ(n, 738.0);  // ceil(ln(40) / (2 * 0.0025))
  EXPECT_LE(std::sqrt(std::log(2.0 / 0.05) / (2.0 * n)), 0.05);
  EXPECT_GT(std::sqrt(std::log(2.0 / 0.05) / (2.0 * (n - 1))), 0.05);
  EXPECT_TRUE(std::isinf(HoeffdingSamplesNeeded(0.05, 1.0))) << "no sample count gives a worst-case bound";
}

std::vector<Plan> ThreePlans() {
  std::vector<Plan> plans(3);
  plans[0].method = "coarse";
  plans[0].error_bound = 0.1;
  plans[0].predicted_ms = 1.0;
  plans[1].method = "fine";
  plans[1].error_bound = 0.01;
  plans[1].predicted_ms = 100.0;
  plans[2].method = "exact";
  plans[2].error_bound = 0.0;
  plans[2].predicted_ms = 1000.0;
  return plans;
}

TEST(ChoosePlan, AnErrorTargetTakesTheCheapestPlanMeetingIt) {
  std::vector<Plan> plans = ThreePlans();
  auto chosen = ChoosePlan(plans, {.max_error = 0.05});
  ASSERT_TRUE(chosen.ok()) << chosen.status();
  EXPECT_EQ(plans[*chosen].method, "fine");
  EXPECT_FALSE(plans[0].meets_target);
  EXPECT_TRUE(plans[1].meets_target);
  EXPECT_TRUE(plans[2].meets_target);
}

TEST(ChoosePlan, AnErrorTargetOverTheBudgetIsOutOfRange) {
  std::vector<Plan> plans = ThreePlans();
  auto chosen = ChoosePlan(plans, {.max_error = 0.05, .time_budget_ms = 50.0});
  ASSERT_EQ(chosen.status().code(), absl::StatusCode::kOutOfRange);
  EXPECT_NE(chosen.status().message().find("fine"), std::string::npos) << chosen.status();
}

TEST(ChoosePlan, AnUnreachableErrorNamesTheBestPlan) {
  std::vector<Plan> plans = ThreePlans();
  plans.pop_back();  // no exact method for this request
  auto chosen = ChoosePlan(plans, {.max_error = 0.001});
  ASSERT_EQ(chosen.status().code(), absl::StatusCode::kOutOfRange);
  EXPECT_NE(chosen.status().message().find("fine"), std::string::npos) << chosen.status();
}

TEST(ChoosePlan, ABudgetAloneBuysTheMostAccuratePlanThatFits) {
  std::vector<Plan> plans = ThreePlans();
  auto chosen = ChoosePlan(plans, {.time_budget_ms = 500.0});
  ASSERT_TRUE(chosen.ok());
  EXPECT_EQ(plans[*chosen].method, "fine");
  chosen = ChoosePlan(plans, {.time_budget_ms = 5000.0});
  ASSERT_TRUE(chosen.ok());
  EXPECT_EQ(plans[*chosen].method, "exact");
  // Nothing fits: the cheapest answers, and no plan claims to meet the budget.
  chosen = ChoosePlan(plans, {.time_budget_ms = 0.5});
  ASSERT_TRUE(chosen.ok());
  EXPECT_EQ(plans[*chosen].method, "coarse");
  for (const Plan& p : plans) EXPECT_FALSE(p.meets_target);
}

TEST(ValidateAccuracyTarget, NamesTheBadField) {
  EXPECT_TRUE(ValidateAccuracyTarget({.max_error = 0.01}).ok());
  auto message = [](AccuracyTarget t) { return std::string(ValidateAccuracyTarget(t).message()); };
  EXPECT_NE(message({.max_error = -1}).find("target.max_error"), std::string::npos);
  EXPECT_NE(message({.max_error = NAN}).find("target.max_error"), std::string::npos);
  EXPECT_NE(message({.max_error = 0.1, .confidence = 1.5}).find("target.confidence"), std::string::npos);
  EXPECT_NE(message({.time_budget_ms = -3}).find("target.time_budget_ms"), std::string::npos);
  EXPECT_NE(message({}).find("neither"), std::string::npos);
}

// ---------------------------------------------------------------------------
// ChooseFastest: the server's choice for a request that names no method.
// Each option's probe is a real run of `ms_per_unit` x work, measured as
// such (no clock), or one that works until its call stops, as a GL job cut
// at its deadline does.

EqualAnswerOption Option(const std::string& method, double work, double ms_per_unit, int* probes_run) {
  EqualAnswerOption option;
  option.plan.method = method;
  option.plan.cost_key = "scene/map/" + method;
  option.plan.work = work;
  for (double probe_work : {16.0, 256.0})
    option.probes.push_back({probe_work, 0.0, [=](const CallOptions&) -> StatusOr<double> {
                               ++*probes_run;
                               return probe_work * ms_per_unit;
                             }});
  return option;
}

// A method whose probe never finishes before its budget: it polls its
// call's stop, as the GL worker does between jobs.
EqualAnswerOption EndlessOption(const std::string& method, double work, int* probes_run) {
  EqualAnswerOption option;
  option.plan.method = method;
  option.plan.cost_key = "scene/map/" + method;
  option.plan.work = work;
  option.probes.push_back({16.0, 0.0, [=](const CallOptions& call) -> StatusOr<double> {
                             ++*probes_run;
                             while (!call.stop.Stopped()) std::this_thread::sleep_for(std::chrono::milliseconds(1));
                             return call.stop.Check("the endless probe");
                           }});
  return option;
}

TEST(ChooseFastest, ProbesEachNewMethodAndRunsThePredictedFastest) {
  CostModel model;
  int raycast_probes = 0, raster_probes = 0;
  // 1e5 units of work: the ray caster at 0.01 ms a unit (1 s), the
  // rasterizer at 0.001 (0.1 s), its probe well inside 0.25 s.
  std::vector<EqualAnswerOption> options;
  options.push_back(Option("raycast", 1e5, 0.01, &raycast_probes));
  options.push_back(Option("raster", 1e5, 0.001, &raster_probes));
  auto report = ChooseFastest(model, options, {});
  ASSERT_TRUE(report.ok()) << report.status();
  ASSERT_EQ(report->plans.size(), 2u);
  EXPECT_EQ(report->chosen_plan().method, "raster");
  EXPECT_NEAR(report->chosen_plan().predicted_ms, 100.0, 1e-6);
  EXPECT_EQ(report->reason, PlanReport::Reason::kFastestOfEqualAnswers);
  EXPECT_GT(raycast_probes, 0);
  EXPECT_GT(raster_probes, 0);
  // Measured once, predicted from then on: no probe runs again.
  const int before = raycast_probes + raster_probes;
  report = ChooseFastest(model, options, {});
  ASSERT_TRUE(report.ok());
  EXPECT_EQ(report->chosen_plan().method, "raster");
  EXPECT_EQ(raycast_probes + raster_probes, before);
}

TEST(ChooseFastest, AProbePastItsShareOfTheBestPlanIsCutAndItsMethodLeftOut) {
  CostModel model;
  int raycast_probes = 0, raster_probes = 0;
  std::vector<EqualAnswerOption> options;
  // The ray caster: 400 ms for the request, so the rasterizer's probe gets
  // 100 ms.
  options.push_back(Option("raycast", 4e4, 0.01, &raycast_probes));
  options.push_back(EndlessOption("raster", 4e4, &raster_probes));
  const auto start = std::chrono::steady_clock::now();
  auto report = ChooseFastest(model, options, {});
  const double ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
  ASSERT_TRUE(report.ok()) << report.status();
  ASSERT_EQ(report->plans.size(), 1u);
  EXPECT_EQ(report->chosen_plan().method, "raycast");
  ASSERT_EQ(report->cut_probes.size(), 1u);
  EXPECT_EQ(report->cut_probes[0], "raster");
  EXPECT_EQ(raster_probes, 1);
  EXPECT_GE(ms, 100.0 * 0.9);
  EXPECT_LT(ms, 1000.0) << "the probe stops at its budget";
  EXPECT_EQ(model.Observations("scene/map/raster"), 0u) << "a cut probe measured nothing";
  // The first cut may have paid one-time costs: the next request probes
  // again (with what the first set aside), and a second cut backs off.
  EXPECT_EQ(model.CutProbeBudget("scene/map/raster"), 0.0);
  report = ChooseFastest(model, options, {});
  ASSERT_TRUE(report.ok());
  EXPECT_EQ(raster_probes, 2);
  EXPECT_EQ(report->chosen_plan().method, "raycast");
  EXPECT_GE(model.CutProbeBudget("scene/map/raster"), kProbeShareOfBest * 400.0);
  // The same request again: the cut method is not probed at the same budget.
  report = ChooseFastest(model, options, {});
  ASSERT_TRUE(report.ok());
  EXPECT_EQ(raster_probes, 2);
  EXPECT_EQ(report->chosen_plan().method, "raycast");
}

TEST(ChooseFastest, SmallRequestsSetCreditAsideUntilAProbeIsAffordable) {
  CostModel model;
  int raycast_probes = 0, raster_probes = 0;
  // 8 ms a request: a 2 ms share each, under the smallest probe budget.
  std::vector<EqualAnswerOption> options;
  options.push_back(Option("raycast", 800, 0.01, &raycast_probes));
  options.push_back(Option("raster", 800, 0.001, &raster_probes));
  int requests = 0;
  while (raster_probes == 0 && requests < 20) {
    auto report = ChooseFastest(model, options, {});
    ASSERT_TRUE(report.ok()) << report.status();
    ++requests;
    if (raster_probes == 0) {
      EXPECT_EQ(report->chosen_plan().method, "raycast");
    }
  }
  // 2 ms a request reaches kSmallestProbeBudgetMs at the fifth.
  EXPECT_EQ(requests, int(std::ceil(kSmallestProbeBudgetMs / (kProbeShareOfBest * 8.0))));
  auto report = ChooseFastest(model, options, {});
  ASSERT_TRUE(report.ok());
  EXPECT_EQ(report->chosen_plan().method, "raster");
  EXPECT_DOUBLE_EQ(model.ExplorationCredit("scene/map/raster"), 0.0) << "the credit was spent";
}

TEST(ChooseFastest, AMethodThatCannotAnswerIsLeftOutAndNoneLeftIsRefused) {
  CostModel model;
  int probes = 0;
  EqualAnswerOption imprecise = Option("raster", 1e4, 0.001, &probes);
  imprecise.probes = {{16.0, 0.0, [](const CallOptions&) -> StatusOr<double> {
                         return absl::FailedPreconditionError("float32 cannot resolve this request");
                       }}};
  auto report = ChooseFastest(model, {imprecise}, {});
  EXPECT_EQ(report.status().code(), absl::StatusCode::kFailedPrecondition);
  report = ChooseFastest(model, {Option("raycast", 1e4, 0.01, &probes), imprecise}, {});
  ASSERT_TRUE(report.ok()) << report.status();
  ASSERT_EQ(report->plans.size(), 1u);
  EXPECT_EQ(report->chosen_plan().method, "raycast");
}

// A raster map's cost: a pass over the scene per sample, whatever the
// receiver (`per_pass` ms a sample), and a little per fragment; the first
// run also compiles the method's programs (`one_time_ms`).
EqualAnswerOption PassesAndFragmentsOption(const std::string& method, double points, double samples, double per_pass,
                                           double per_fragment, double one_time_ms, int* probes_run) {
  EqualAnswerOption option;
  option.plan.method = method;
  option.plan.cost_key = "scene/map/" + method;
  option.plan.work = points * samples;
  option.plan.extra_work = samples;
  auto cost = [=](double probe_points) {
    return [=](const CallOptions&) -> StatusOr<double> {
      const double ms = per_pass * samples + per_fragment * probe_points * samples + (*probes_run == 0 ? one_time_ms : 0.0);
      ++*probes_run;
      return ms;
    };
  };
  for (double probe_points : {16.0, 256.0}) option.probes.push_back({probe_points * samples, samples, cost(probe_points)});
  return option;
}

// The Cornell box on llvmpipe at 256 x 256 texels and 1,024 samples: one
// pass costs 0.1 ms and a fragment next to nothing, so the rasterizer
// (about 140 ms) beats the ray caster (1 s). Its first probe of 16 texels
// also compiled its programs (100 ms), which extrapolated by the texels
// predicted the map at minutes; run again, the probe costs its passes.
TEST(ChooseFastest, AFirstProbeThatPaidOneTimeCostsIsRunAgainAndTheCheaperKept) {
  CostModel model;
  int raycast_probes = 0, raster_probes = 0;
  std::vector<EqualAnswerOption> options;
  options.push_back(Option("raycast", 65536.0 * 1024.0, 1.5e-5, &raycast_probes));
  options.push_back(PassesAndFragmentsOption("raster", 65536.0, 1024.0, 0.1, 1e-9, 100.0, &raster_probes));
  auto report = ChooseFastest(model, options, {});
  ASSERT_TRUE(report.ok()) << report.status();
  EXPECT_GE(raster_probes, 2);
  EXPECT_EQ(report->chosen_plan().method, "raster");
  EXPECT_LT(report->chosen_plan().predicted_ms, 2.0 * (0.1 * 1024.0 + 1e-9 * 65536.0 * 1024.0));
}

// A method measured at one size: each later request's share buys its next
// probe, until two sizes separate its passes from its fragments.
TEST(ChooseFastest, AMethodMeasuredAtOneSizeProbesTheNextSizeOnALaterRequest) {
  CostModel model;
  int raycast_probes = 0, raster_probes = 0;
  // A small map first: the larger probe (256 texels) is too large a share
  // of a 1,000-texel request, so the rasterizer is measured at 16 only.
  std::vector<EqualAnswerOption> small;
  small.push_back(Option("raycast", 1000.0 * 1024.0, 1e-4, &raycast_probes));
  small.push_back(PassesAndFragmentsOption("raster", 1000.0, 1024.0, 0.1, 1e-6, 0.0, &raster_probes));
  ASSERT_TRUE(ChooseFastest(model, small, {}).ok());
  EXPECT_EQ(model.DistinctSizes("scene/map/raster"), 1u);
  const int after_small = raster_probes;
  // A large map: the rasterizer's prediction from one size is the safe
  // side's (all of it per fragment); the request's share buys the second.
  std::vector<EqualAnswerOption> large;
  large.push_back(Option("raycast", 65536.0 * 1024.0, 1e-4, &raycast_probes));
  large.push_back(PassesAndFragmentsOption("raster", 65536.0, 1024.0, 0.1, 1e-6, 0.0, &raster_probes));
  auto report = ChooseFastest(model, large, {});
  ASSERT_TRUE(report.ok()) << report.status();
  EXPECT_EQ(raster_probes, after_small + 1);
  EXPECT_EQ(model.DistinctSizes("scene/map/raster"), 2u);
  EXPECT_EQ(report->chosen_plan().method, "raster");
  const double truth = 0.1 * 1024.0 + 1e-6 * 65536.0 * 1024.0;
  EXPECT_NEAR(report->chosen_plan().predicted_ms, truth, 0.01 * truth);
}

// A method's first run in the process that compiles its programs past the
// probe's whole budget (one GL job is not cut inside): its runs stop at
// their call's stop as the GL worker does, and this one completed late.
// The runs after it measure the method in a budget of their own; before,
// the repeat found the deadline passed, the slow run was kept and the
// rasterizer predicted at 256 times it (a 64 x 64 Cornell map at 5 s,
// where it takes 7 ms).
TEST(ChooseFastest, AFirstRunPastTheBudgetLeavesTheRunsAfterItABudgetOfTheirOwn) {
  CostModel model;
  int raycast_probes = 0, raster_runs = 0;
  constexpr double kPoints = 64.0 * 64.0, kSamples = 256.0, kPerPass = 0.01, kPerFragment = 1e-6;
  constexpr double kOneTimeMs = 150.0;  // over the 100 ms share below
  EqualAnswerOption raster;
  raster.plan.method = "raster";
  raster.plan.cost_key = "scene/map/raster";
  raster.plan.work = kPoints * kSamples;
  raster.plan.extra_work = kSamples;
  for (double probe_points : {16.0, 256.0}) {
    raster.probes.push_back({probe_points * kSamples, kSamples, [=, &raster_runs](const CallOptions& call) -> StatusOr<double> {
                               VISQ_RETURN_IF_ERROR(call.stop.Check("the raster probe"));
                               double ms = kPerPass * kSamples + kPerFragment * probe_points * kSamples;
                               if (raster_runs++ == 0) {
                                 std::this_thread::sleep_for(std::chrono::duration<double, std::milli>(kOneTimeMs));
                                 ms += kOneTimeMs;
                               }
                               return ms;
                             }});
  }
  std::vector<EqualAnswerOption> options;
  options.push_back(Option("raycast", 4e4, 0.01, &raycast_probes));  // 400 ms: the rasterizer's probe gets 100
  options.push_back(std::move(raster));
  auto report = ChooseFastest(model, options, {});
  ASSERT_TRUE(report.ok()) << report.status();
  EXPECT_EQ(raster_runs, 3) << "the first run, its repeat and the larger probe";
  EXPECT_EQ(model.DistinctSizes("scene/map/raster"), 2u);
  EXPECT_EQ(report->chosen_plan().method, "raster");
  const double truth = kPerPass * kSamples + kPerFragment * kPoints * kSamples;
  EXPECT_NEAR(report->chosen_plan().predicted_ms, truth, 0.05 * truth);
}

TEST(ChooseFastest, ACancelledCallStopsChoosing) {
  CostModel model;
  int probes = 0;
  std::atomic<bool> cancelled{true};
  CallOptions call;
  call.stop.cancelled = &cancelled;
  auto report = ChooseFastest(model, {Option("raycast", 1e4, 0.01, &probes)}, call);
  EXPECT_EQ(report.status().code(), absl::StatusCode::kCancelled);
  EXPECT_EQ(probes, 0);
}

}  // namespace
}  // namespace visq::core
