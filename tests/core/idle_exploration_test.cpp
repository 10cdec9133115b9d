// The idle explorer with the planner's real ChooseFastest and CostModel:
// probes stand in for the queries (their cost is what they return), and
// the explorer's own thread runs them.
#include "core/idle_exploration.h"

#include <atomic>
#include <chrono>
#include <memory>
#include <string>
#include <thread>

#include <gtest/gtest.h>

namespace visq::core {
namespace {

using std::chrono::milliseconds;

// Waits up to 10 s for `done`.
template <typename Done>
bool Eventually(Done done) {
  const auto until = std::chrono::steady_clock::now() + std::chrono::seconds(10);
  while (!done()) {
    if (std::chrono::steady_clock::now() > until) return false;
    std::this_thread::sleep_for(milliseconds(2));
  }
  return true;
}

// A method costing `ms_per_unit` ms per unit of work, whose probes count
// their runs (shared, since the explorer may run them after the option
// that made them is gone).
EqualAnswerOption CountedOption(const std::string& method, double work, double ms_per_unit,
                                std::shared_ptr<std::atomic<int>> runs) {
  EqualAnswerOption option;
  option.plan.method = method;
  option.plan.cost_key = "scene/map/" + method;
  option.plan.work = work;
  for (double probe_work : {16.0, 256.0})
    option.probes.push_back({probe_work, 0.0, [=](const CallOptions&) -> StatusOr<double> {
                               ++*runs;
                               return probe_work * ms_per_unit;
                             }});
  option.probes_outlive_the_call = true;
  return option;
}

// A method whose probe takes `takes` unless its call stops first (polled
// as the GL worker polls between jobs); `started` counts its starts.
EqualAnswerOption SlowOption(const std::string& method, milliseconds takes, std::shared_ptr<std::atomic<int>> started) {
  EqualAnswerOption option;
  option.plan.method = method;
  option.plan.cost_key = "scene/map/" + method;
  option.plan.work = 1e6;
  option.probes.push_back({16.0, 0.0, [=](const CallOptions& call) -> StatusOr<double> {
                             ++*started;
                             const auto until = std::chrono::steady_clock::now() + takes;
                             while (std::chrono::steady_clock::now() < until) {
                               VISQ_RETURN_IF_ERROR(call.stop.Check("the slow probe"));
                               std::this_thread::sleep_for(milliseconds(1));
                             }
                             return double(takes.count());
                           }});
  option.probes_outlive_the_call = true;
  return option;
}

TEST(IdleExploration, ASmallRequestLeavesItsProbeToIdleTimeAndTheNextRequestWeighsIt) {
  CostModel model;
  IdleExplorer explorer(model, {.quiet_ms = 5.0, .probe_budget_ms = 2000.0});
  auto raycast_runs = std::make_shared<std::atomic<int>>(0), raster_runs = std::make_shared<std::atomic<int>>(0);
  // 100 ms a request by the ray caster: a 25 ms share, under the smallest
  // budget a probe runs with inside a request where idle time can take it.
  const std::vector<EqualAnswerOption> options = {CountedOption("raycast", 1e4, 0.01, raycast_runs),
                                                  CountedOption("raster", 1e4, 0.001, raster_runs)};
  explorer.CallBegan();
  auto first = ChooseFastest(model, options, {}, &explorer);
  ASSERT_TRUE(first.ok()) << first.status();
  EXPECT_EQ(first->chosen_plan().method, "raycast");
  EXPECT_EQ(first->plans.size(), 1u);
  std::this_thread::sleep_for(milliseconds(30));
  EXPECT_EQ(*raster_runs, 0) << "no probe runs while a call is in flight";
  EXPECT_EQ(explorer.figures().pending, 1u);
  explorer.CallEnded();
  ASSERT_TRUE(Eventually([&] { return explorer.figures().probes_run == 1; }));
  EXPECT_GT(model.Observations("scene/map/raster"), 0u);

  explorer.CallBegan();
  const int raster_runs_before = *raster_runs;
  auto second = ChooseFastest(model, options, {}, &explorer);
  ASSERT_TRUE(second.ok()) << second.status();
  EXPECT_EQ(second->chosen_plan().method, "raster") << "weighed from what idle time measured";
  EXPECT_EQ(*raster_runs, raster_runs_before) << "and not probed again inside the request";
  explorer.CallEnded();
}

TEST(IdleExploration, ACallArrivingStopsTheProbeWhichRunsAgainAtTheNextQuietSpell) {
  CostModel model;
  IdleExplorer explorer(model, {.quiet_ms = 5.0, .probe_budget_ms = 5000.0});
  auto started = std::make_shared<std::atomic<int>>(0);
  explorer.Offer(SlowOption("raster", milliseconds(300), started), 0);
  ASSERT_TRUE(Eventually([&] { return *started == 1; }));
  explorer.CallBegan();
  ASSERT_TRUE(Eventually([&] { return explorer.figures().probes_preempted == 1; }));
  EXPECT_EQ(explorer.figures().pending, 1u) << "it waits for the next quiet spell";
  EXPECT_EQ(model.CutProbes("scene/map/raster"), 0) << "a probe a call stopped says nothing of the method";
  std::this_thread::sleep_for(milliseconds(50));
  EXPECT_EQ(*started, 1) << "nothing starts while the call is in flight";
  explorer.CallEnded();
  ASSERT_TRUE(Eventually([&] { return explorer.figures().probes_run == 1; }));
  // Started again, and run twice (a method's first probe in the process
  // pays one-time costs: ChooseFastest keeps the cheaper of two runs).
  EXPECT_EQ(*started, 3);
  EXPECT_EQ(model.Observations("scene/map/raster"), 1u);
  EXPECT_EQ(explorer.figures().pending, 0u);
}

TEST(IdleExploration, AProbeStoppedTwiceByCallsIsLeftAsCutAtTheLongestItRan) {
  CostModel model;
  IdleExplorer explorer(model, {.quiet_ms = 5.0, .probe_budget_ms = 60000.0});
  auto started = std::make_shared<std::atomic<int>>(0);
  explorer.Offer(SlowOption("raster", milliseconds(60000), started), 0);
  for (int stop = 1; stop <= IdleExplorer::kMostPreemptions; ++stop) {
    ASSERT_TRUE(Eventually([&] { return *started == stop; }));
    std::this_thread::sleep_for(milliseconds(30));
    explorer.CallBegan();
    ASSERT_TRUE(Eventually([&] { return explorer.figures().probes_preempted == uint64_t(stop); }));
    explorer.CallEnded();
  }
  EXPECT_EQ(explorer.figures().pending, 0u);
  EXPECT_EQ(explorer.figures().probes_dropped, 1u);
  EXPECT_EQ(model.CutProbes("scene/map/raster"), 1);
  std::this_thread::sleep_for(milliseconds(50));
  EXPECT_EQ(*started, IdleExplorer::kMostPreemptions) << "not started again";
  explorer.Offer(SlowOption("raster", milliseconds(60000), started), 0);
  EXPECT_EQ(explorer.figures().pending, 0u) << "nor taken again for a while";
}

TEST(IdleExploration, AProbePastItsBudgetIsRecordedAsCut) {
  CostModel model;
  IdleExplorer explorer(model, {.quiet_ms = 5.0, .probe_budget_ms = 40.0});
  auto started = std::make_shared<std::atomic<int>>(0);
  explorer.Offer(SlowOption("raster", milliseconds(60000), started), 0);
  ASSERT_TRUE(Eventually([&] { return explorer.figures().probes_run == 1; }));
  EXPECT_EQ(model.CutProbes("scene/map/raster"), 1);
  EXPECT_EQ(model.Observations("scene/map/raster"), 0u);
  EXPECT_EQ(explorer.figures().pending, 0u) << "a cut probe is not queued again";
}

TEST(IdleExploration, ANewerOfferForTheSameMethodReplacesTheOlderAndTheQueueIsBounded) {
  CostModel model;
  IdleExplorer explorer(model, {.quiet_ms = 60000.0, .probe_budget_ms = 1000.0, .max_pending = 3});
  explorer.CallBegan();  // never quiet: the queue only fills
  auto runs = std::make_shared<std::atomic<int>>(0);
  for (int i = 0; i < 2; ++i) explorer.Offer(CountedOption("raster", 1e4, 0.001, runs), 0);
  EXPECT_EQ(explorer.figures().pending, 1u);
  for (const char* method : {"a", "b", "c", "d"}) explorer.Offer(CountedOption(method, 1e4, 0.001, runs), 0);
  EXPECT_EQ(explorer.figures().pending, 3u);
  EXPECT_EQ(explorer.figures().probes_dropped, 2u);
  EXPECT_EQ(*runs, 0);
}

TEST(IdleExploration, DestroyingTheExplorerStopsTheProbeItRuns) {
  CostModel model;
  auto started = std::make_shared<std::atomic<int>>(0);
  const auto start = std::chrono::steady_clock::now();
  {
    IdleExplorer explorer(model, {.quiet_ms = 0.0, .probe_budget_ms = 60000.0});
    explorer.Offer(SlowOption("raster", milliseconds(60000), started), 0);
    ASSERT_TRUE(Eventually([&] { return *started == 1; }));
  }
  EXPECT_LT(std::chrono::steady_clock::now() - start, std::chrono::seconds(10));
  EXPECT_EQ(model.CutProbes("scene/map/raster"), 0);
}

}  // namespace
}  // namespace visq::core
