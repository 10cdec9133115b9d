// Ask by error end to end: requests that give an AccuracyTarget
// instead of a count, through the real server and client, on the generated
// Cornell box. The answers are checked against the exact Plücker method run
// by the same server (PLUCKER_EXACT), never against the method chosen.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <string>

#include <glm/glm.hpp>
#include <gtest/gtest.h>

#include "shared_server_suite.h"
#include "proto_builders.h"
#include "test_support.h"
#include "visq_client.h"

namespace visq {
namespace {

using client::Client;

using testing::SetPatch;

// Patch visibility from a light patch over the tall box onto the whole
// floor, over a columns x rows receiver grid.
v1::PatchVisibilityRequest CornellFloorPatches(uint32_t columns, uint32_t rows) {
  v1::PatchVisibilityRequest request;
  request.mutable_scene()->set_name("cornell_box_visq");
  SetPatch(request.mutable_source(), {-0.25, 1.99, -0.25}, {0.5, 0, 0}, {0, 0, 0.5});
  SetPatch(request.mutable_receiver(), {-0.999, 0.001, -0.999}, {1.998, 0, 0}, {0, 0, 1.998});
  request.set_receiver_columns(columns);
  request.set_receiver_rows(rows);
  return request;
}

class AccuracyTargetTest : public testing::SharedServerSuite<AccuracyTargetTest> {
 protected:

  // A light patch over the tall box onto the floor beside it: partly shadowed.
  static v1::HiddenSampleMapRequest ShadowedFloor(uint32_t size) {
    v1::HiddenSampleMapRequest request;
    request.mutable_scene()->set_name("cornell_box_visq");
    SetPatch(request.mutable_source(), {-0.25, 1.99, -0.25}, {0.5, 0, 0}, {0, 0, 0.5});
    SetPatch(request.mutable_receiver(), {-0.999, 0.001, -0.999}, {1.998, 0, 0}, {0, 0, 1.998});
    request.set_width(size);
    request.set_height(size);
    return request;
  }

  std::vector<float> ExactFractions(v1::HiddenSampleMapRequest request) {
    request.clear_target();
    request.mutable_samples()->set_count(0);
    request.set_method(v1::PLUCKER_EXACT);
    auto exact = client_->ComputeHiddenSampleMap(request);
    EXPECT_TRUE(exact.ok()) << exact.status();
    if (!exact.ok()) return {};
    EXPECT_EQ(exact->figures.accuracy().method(), "plucker-exact");
    EXPECT_EQ(exact->figures.accuracy().error_bound(), 0.0);
    return exact->visible_fraction;
  }
};

// The fraction of texels whose answer is outside the stated bound around the
// exact value: at most 1 - confidence in expectation.
double ShareOutsideBound(const std::vector<float>& answer, const std::vector<float>& exact, double bound) {
  size_t outside = 0;
  for (size_t j = 0; j < answer.size(); ++j)
    if (std::abs(double(answer[j]) - exact[j]) > bound + 1e-6) ++outside;
  return double(outside) / double(answer.size());
}

TEST_F(AccuracyTargetTest, HiddenSampleMapMeetsAnErrorTargetAndSaysWhatItChose) {
  v1::HiddenSampleMapRequest request = ShadowedFloor(24);
  request.mutable_target()->set_max_error(0.05);
  auto answer = client_->ComputeHiddenSampleMap(request);
  ASSERT_TRUE(answer.ok()) << answer.status();
  const v1::Accuracy& accuracy = answer->figures.accuracy();
  EXPECT_LE(accuracy.error_bound(), 0.05);
  EXPECT_DOUBLE_EQ(accuracy.confidence(), accuracy.method() == "plucker-exact" ? 1.0 : 0.95);
  ASSERT_GT(accuracy.plans_size(), 3) << "raster, raycast and exact plans weighed";
  EXPECT_GT(accuracy.predicted_ms(), 0.0);
  // The chosen plan is among those weighed, meets the target and is the
  // cheapest of those that do.
  double cheapest_meeting = 1e300;
  bool chosen_listed = false;
  for (const v1::PlanEstimate& plan : accuracy.plans()) {
    if (plan.meets_target()) cheapest_meeting = std::min(cheapest_meeting, plan.predicted_ms());
    // The answer's parameters hold the plan's and more (the estimate's
    // spread, whether the target was met); a plan topped up with more maps
    // keeps its own count as planned_samples.
    if (plan.method() == accuracy.method()) {
      bool same = true;
      for (const auto& [name, value] : plan.parameters()) {
        const std::string key = name == "samples" && accuracy.parameters().contains("planned_samples")
                                    ? "planned_samples"
                                    : name;
        same = same && accuracy.parameters().contains(key) && accuracy.parameters().at(key) == value;
      }
      if (same) {
        chosen_listed = true;
        EXPECT_TRUE(plan.meets_target());
        EXPECT_LE(plan.error_bound(), 0.05);
      }
    }
  }
  EXPECT_TRUE(chosen_listed) << accuracy.DebugString();
  EXPECT_DOUBLE_EQ(accuracy.predicted_ms(), cheapest_meeting);
  EXPECT_EQ(accuracy.parameters().at("target_met"), 1.0) << accuracy.DebugString();

  const std::vector<float> exact = ExactFractions(request);
  ASSERT_EQ(exact.size(), answer->visible_fraction.size());
  EXPECT_LE(ShareOutsideBound(answer->visible_fraction, exact, accuracy.error_bound()), 0.05 + 0.03);
}

TEST_F(AccuracyTargetTest, ATimeBudgetAloneGetsTheMostAccuratePlanPredictedToFit) {
  v1::HiddenSampleMapRequest request = ShadowedFloor(16);
  request.mutable_target()->set_time_budget_ms(5000);
  auto generous = client_->ComputeHiddenSampleMap(request);
  ASSERT_TRUE(generous.ok()) << generous.status();
  request.mutable_target()->set_time_budget_ms(1e-6);
  auto tiny = client_->ComputeHiddenSampleMap(request);
  ASSERT_TRUE(tiny.ok()) << tiny.status();

  // Nothing fits a nanosecond: the cheapest plan answers, and says it does
  // not meet the budget; a generous budget buys an answer at least as good.
  bool tiny_chosen_meets = true;
  for (const v1::PlanEstimate& plan : tiny->figures.accuracy().plans()) tiny_chosen_meets &= !plan.meets_target();
  EXPECT_TRUE(tiny_chosen_meets) << "no plan fits 1 ns";
  EXPECT_LE(generous->figures.accuracy().error_bound(), tiny->figures.accuracy().error_bound());
  for (const v1::PlanEstimate& plan : generous->figures.accuracy().plans()) {
    if (plan.meets_target()) {
      EXPECT_GE(plan.error_bound(), generous->figures.accuracy().error_bound());
    }
  }
}

// A target tighter than one map's 4096 samples reach (about 0.021) still
// has sampled plans: several maps with independent jitter, their counts
// added. An explicit count beyond 4096 answers with that many samples and a
// bound tighter than one map's.
TEST_F(AccuracyTargetTest, TightTargetsHaveSampledPlansBeyondOneMap) {
  v1::HiddenSampleMapRequest request = ShadowedFloor(12);
  request.mutable_target()->set_max_error(0.012);
  auto answer = client_->ComputeHiddenSampleMap(request);
  ASSERT_TRUE(answer.ok()) << answer.status();
  bool sampled_beyond_one_map = false;
  for (const v1::PlanEstimate& plan : answer->figures.accuracy().plans())
    if (plan.method() != "plucker-exact" && plan.parameters().contains("samples") &&
        plan.parameters().at("samples") > 4096 && plan.meets_target())
      sampled_beyond_one_map = true;
  EXPECT_TRUE(sampled_beyond_one_map) << answer->figures.accuracy().DebugString();
  EXPECT_LE(answer->figures.accuracy().error_bound(), 0.012);

  v1::HiddenSampleMapRequest explicit_count = ShadowedFloor(12);
  explicit_count.set_method(v1::RAYCAST);
  explicit_count.mutable_samples()->set_count(12288);
  auto three_maps = client_->ComputeHiddenSampleMap(explicit_count);
  ASSERT_TRUE(three_maps.ok()) << three_maps.status();
  EXPECT_EQ(three_maps->figures.sample_count(), 12288u);
  EXPECT_LT(three_maps->figures.accuracy().error_bound(), 0.012);
  const std::vector<float> exact = ExactFractions(explicit_count);
  EXPECT_LE(ShareOutsideBound(three_maps->visible_fraction, exact, three_maps->figures.accuracy().error_bound()), 0.05);
}

TEST_F(AccuracyTargetTest, UnreachableTargetsAreOutOfRangeAndNamed) {
  // Bitmasks rule out the exact method; 4096 samples reach only about 0.021.
  v1::HiddenSampleMapRequest request = ShadowedFloor(8);
  request.set_want_bitmasks(true);
  request.mutable_target()->set_max_error(0.001);
  auto answer = client_->ComputeHiddenSampleMap(request);
  ASSERT_EQ(answer.status().code(), absl::StatusCode::kOutOfRange) << answer.status();
  EXPECT_NE(answer.status().message().find("no method reaches"), std::string::npos) << answer.status();

  // Reachable, but not within a nanosecond (the exact method's probes
  // answer and store all 64 points; a call over stored points takes about
  // 12 us, once predicted below 1 us from two noisy runs under ASan).
  request.set_want_bitmasks(false);
  request.mutable_target()->set_max_error(0.05);
  request.mutable_target()->set_time_budget_ms(1e-6);
  answer = client_->ComputeHiddenSampleMap(request);
  ASSERT_EQ(answer.status().code(), absl::StatusCode::kOutOfRange) << answer.status();
  EXPECT_NE(answer.status().message().find("over the budget"), std::string::npos) << answer.status();
}

TEST_F(AccuracyTargetTest, BadTargetsAreInvalidArgumentsNamingTheField) {
  v1::HiddenSampleMapRequest request = ShadowedFloor(8);
  request.mutable_target()->set_max_error(2.0);
  auto answer = client_->ComputeHiddenSampleMap(request);
  ASSERT_EQ(answer.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(answer.status().message().find("target.max_error"), std::string::npos) << answer.status();

  request.mutable_target()->set_max_error(0.0);
  answer = client_->ComputeHiddenSampleMap(request);
  ASSERT_EQ(answer.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(answer.status().message().find("target"), std::string::npos) << answer.status();

  request.mutable_target()->set_max_error(0.05);
  request.mutable_samples()->set_count(64);
  answer = client_->ComputeHiddenSampleMap(request);
  ASSERT_EQ(answer.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(answer.status().message().find("samples.count"), std::string::npos) << answer.status();

  request.mutable_samples()->set_count(0);
  request.set_method(v1::RAYCAST);
  answer = client_->ComputeHiddenSampleMap(request);
  ASSERT_EQ(answer.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(answer.status().message().find("method"), std::string::npos) << answer.status();

  // The exact method has no samples, hence no bitmasks.
  request.clear_target();
  request.set_method(v1::PLUCKER_EXACT);
  request.set_want_bitmasks(true);
  answer = client_->ComputeHiddenSampleMap(request);
  ASSERT_EQ(answer.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(answer.status().message().find("want_bitmasks"), std::string::npos) << answer.status();
}

TEST_F(AccuracyTargetTest, PatchVisibilityTargetAgainstTheExactMeanOfTheReceiverSamples) {
  v1::PatchVisibilityRequest request = CornellFloorPatches(12, 12);
  v1::PatchVisibilityRequest exact_request = request;
  exact_request.set_method(v1::PLUCKER_EXACT);
  auto exact = client_->PatchVisibility(exact_request);
  ASSERT_TRUE(exact.ok()) << exact.status();
  EXPECT_TRUE(exact->source_visible().empty()) << "the exact method has no source samples";
  ASSERT_EQ(exact->receiver_visible_size(), 144);

  // With pairs asked for, only sampled methods qualify.
  request.mutable_target()->set_max_error(0.06);
  request.mutable_target()->set_confidence(0.99);
  request.set_unblocked_limit(4);
  auto sampled = client_->PatchVisibility(request);
  ASSERT_TRUE(sampled.ok()) << sampled.status();
  EXPECT_NE(sampled->accuracy().method(), "plucker-exact");
  EXPECT_LE(sampled->accuracy().error_bound(), 0.06);
  EXPECT_DOUBLE_EQ(sampled->accuracy().confidence(), 0.99) << "the bound is stated at the confidence asked for";
  EXPECT_GE(sampled->accuracy().parameters().at("source_columns") * sampled->accuracy().parameters().at("source_rows"),
            sampled->accuracy().parameters().at("samples"));
  EXPECT_NEAR(sampled->mutual_visible_fraction(), exact->mutual_visible_fraction(), sampled->accuracy().error_bound());
}

TEST_F(AccuracyTargetTest, ObscuranceTargetsChooseTheDirectionCount) {
  v1::ComputeObscurancesRequest request;
  request.mutable_scene()->set_name("cornell_box_visq");
  request.set_resolution(32);
  request.set_d_max(0.5);
  request.mutable_target()->set_max_error(0.1);
  auto bake = client_->ComputeObscurances(request, nullptr);
  ASSERT_TRUE(bake.ok()) << bake.status();
  const v1::Accuracy& accuracy = bake->figures.accuracy();
  EXPECT_LE(accuracy.error_bound(), 0.1);
  // Both methods weighed: the GPU bake by directions, Embree by rays per patch.
  bool weighed_bake = false, weighed_rays = false;
  for (const v1::PlanEstimate& plan : accuracy.plans()) {
    weighed_bake |= plan.method() == "obscurance-depth-peeling";
    weighed_rays |= plan.method() == "obscurance-raycast";
  }
  EXPECT_TRUE(weighed_bake && weighed_rays) << accuracy.DebugString();
  // Hoeffding at 0.1 and 95 % wants 185 samples; the stated bound covers
  // the elements resting on a quarter of the count, so 740 per patch, the
  // least count that meets it, as directions or as rays.
  const char* count = accuracy.method() == "obscurance-raycast" ? "rays_per_patch" : "directions";
  EXPECT_EQ(accuracy.parameters().at(count), 740.0);
  if (accuracy.method() == "obscurance-raycast") EXPECT_NEAR(bake->figures.mean_samples_per_patch(), 740.0, 1e-9);
  else EXPECT_EQ(bake->partial.DirectionCount(), 740u);
  // The chosen plan's bound is the most its answer may state.
  bool found = false;
  for (const v1::PlanEstimate& plan : accuracy.plans())
    if (plan.method() == accuracy.method() && plan.parameters().at(count) == 740.0) {
      found = true;
      EXPECT_LE(plan.error_bound(), 0.1);
      EXPECT_LE(accuracy.error_bound(), plan.error_bound() * (1 + 1e-6));
    }
  EXPECT_TRUE(found) << accuracy.DebugString();
  EXPECT_TRUE(bake->figures.update_ready());

  // A shard range cannot take a target.
  request.set_first_direction(8);
  request.set_total_directions(64);
  auto shard = client_->ComputeObscurances(request, nullptr);
  ASSERT_EQ(shard.status().code(), absl::StatusCode::kInvalidArgument) << shard.status();
}

// The exact method lights the receiver whichever way the light's polygon
// winds: a clockwise triangle, checked against Embree on 4096 samples.
// Beside each texel's bound, a jittered map states an estimate: the normal
// approximation at the variance its split pairs estimate (where every
// sample agrees, what agreeing samples can hide). Against the exact
// fractions, in the penumbra (where the answer is uncertain) it is tighter
// than the bound and still covers most texels; it is never above the bound.
TEST_F(AccuracyTargetTest, AJitteredMapStatesAnEstimateBesideItsBounds) {
  v1::HiddenSampleMapRequest request = ShadowedFloor(32);
  request.set_method(v1::RAYCAST);
  request.mutable_samples()->set_count(1024);
  request.set_want_texel_error(true);
  auto map = client_->ComputeHiddenSampleMap(request);
  ASSERT_TRUE(map.ok()) << map.status();
  const v1::Accuracy& accuracy = map->figures.accuracy();
  ASSERT_TRUE(accuracy.has_estimate()) << accuracy.DebugString();
  EXPECT_LT(accuracy.estimate(), accuracy.error_bound());
  EXPECT_NE(accuracy.note().find("an estimate, not a bound"), std::string::npos) << accuracy.note();
  ASSERT_TRUE(accuracy.parameters().contains("texel_estimate_median"));
  ASSERT_EQ(map->figures.texel_estimate_size(), map->figures.texel_error_size());
  ASSERT_EQ(static_cast<size_t>(map->figures.texel_estimate_size()), map->visible_fraction.size());

  const std::vector<float> exact = ExactFractions(request);
  ASSERT_EQ(exact.size(), map->visible_fraction.size());
  size_t penumbra = 0, estimate_covers = 0, bound_holds = 0;
  std::vector<double> errors, estimates;
  for (size_t j = 0; j < exact.size(); ++j) {
    const float estimate = map->figures.texel_estimate(int(j)), bound = map->figures.texel_error(int(j));
    EXPECT_LE(estimate, bound) << "texel " << j;
    EXPECT_LE(estimate, accuracy.estimate()) << "texel " << j;
    if (exact[j] <= 1e-6 || exact[j] >= 1 - 1e-6) continue;
    const double error = std::abs(double(map->visible_fraction[j]) - exact[j]);
    ++penumbra;
    estimate_covers += error <= estimate + 1e-6;
    bound_holds += error <= bound + 1e-6;
    errors.push_back(error);
    estimates.push_back(estimate);
  }
  ASSERT_GE(penumbra, 40u) << "the floor beside the tall box has a penumbra";
  std::sort(errors.begin(), errors.end());
  std::sort(estimates.begin(), estimates.end());
  const double median_error = errors[errors.size() / 2], median_estimate = estimates[estimates.size() / 2];
  RecordProperty("penumbra_texels", std::to_string(penumbra));
  RecordProperty("estimate_coverage", std::to_string(double(estimate_covers) / penumbra));
  RecordProperty("median_estimate_over_median_error", std::to_string(median_estimate / median_error));
  EXPECT_GE(double(bound_holds) / penumbra, 0.95 - 0.03);
  // Nominally 95 %; split pairs estimate the variance from above, so the
  // estimate covers at least about that on shadow edges.
  EXPECT_GE(double(estimate_covers) / penumbra, 0.85) << estimate_covers << " of " << penumbra;
  EXPECT_LT(median_estimate, 6.0 * median_error) << "the estimate follows the error, not the worst case";
}

// A target may be on the estimate: the planner predicts the estimate a plan
// will state from two small maps of the same request, so far fewer samples
// meet it than Hoeffding's worst case asks; the answer states both and says
// whether the estimate met the target.
TEST_F(AccuracyTargetTest, ATargetOnTheEstimateIsPlannedByItsPredictionAndSaysWhetherItWasMet) {
  v1::HiddenSampleMapRequest request = ShadowedFloor(24);
  request.mutable_target()->set_max_error(0.01);
  request.mutable_target()->set_guarantee(v1::AccuracyTarget::ESTIMATE);
  auto answer = client_->ComputeHiddenSampleMap(request);
  ASSERT_TRUE(answer.ok()) << answer.status();
  const v1::Accuracy& accuracy = answer->figures.accuracy();
  ASSERT_TRUE(accuracy.parameters().contains("target_met")) << accuracy.DebugString();
  // Hoeffding at 0.01 and 95 % needs 18,445 samples; the estimate's plans
  // meet it with a fraction of that.
  double fewest_meeting = 1e300;
  for (const v1::PlanEstimate& plan : accuracy.plans())
    if (plan.meets_target() && plan.parameters().contains("samples"))
      fewest_meeting = std::min(fewest_meeting, plan.parameters().at("samples"));
  EXPECT_LT(fewest_meeting, 18445.0 / 4) << accuracy.DebugString();
  if (accuracy.method() != "plucker-exact") {
    ASSERT_TRUE(accuracy.has_estimate()) << accuracy.DebugString();
    EXPECT_EQ(accuracy.parameters().at("target_met"), accuracy.estimate() <= 0.01 ? 1.0 : 0.0)
        << accuracy.DebugString();
    EXPECT_GT(accuracy.error_bound(), accuracy.estimate()) << "the bound is stated beside it";
  } else {
    EXPECT_EQ(accuracy.parameters().at("target_met"), 1.0);
  }

  // The same target on the bound: planned by the bound the same probes
  // predict, which needs more samples than the estimate, and the answer's
  // bound meets it (topped up where the prediction missed).
  request.mutable_target()->set_guarantee(v1::AccuracyTarget::RIGOROUS);
  auto rigorous = client_->ComputeHiddenSampleMap(request);
  ASSERT_TRUE(rigorous.ok()) << rigorous.status();
  EXPECT_LE(rigorous->figures.accuracy().error_bound(), 0.01);
  EXPECT_EQ(rigorous->figures.accuracy().parameters().at("target_met"), 1.0);
  double fewest_on_bound = 1e300;
  for (const v1::PlanEstimate& plan : rigorous->figures.accuracy().plans())
    if (plan.meets_target() && plan.parameters().contains("samples"))
      fewest_on_bound = std::min(fewest_on_bound, plan.parameters().at("samples"));
  EXPECT_LE(fewest_meeting, fewest_on_bound);
}

TEST_F(AccuracyTargetTest, AnEstimateTargetWhereNoEstimateCanBeMadeIsRefusedNamingTheGuarantee) {
  auto expect_refused = [](const absl::Status& status, const char* why) {
    EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument) << why << ": " << status;
    EXPECT_NE(status.message().find("target.guarantee"), std::string::npos) << why << ": " << status;
  };
  v1::HiddenSampleMapRequest regular = ShadowedFloor(8);
  regular.mutable_samples()->set_pattern(v1::SamplingSpec::REGULAR);
  regular.mutable_target()->set_max_error(0.05);
  regular.mutable_target()->set_guarantee(v1::AccuracyTarget::ESTIMATE);
  expect_refused(client_->ComputeHiddenSampleMap(regular).status(), "regular samples have no variance to estimate");

  v1::HiddenSampleMapRequest worst_case = ShadowedFloor(8);
  worst_case.mutable_target()->set_max_error(0.05);
  worst_case.mutable_target()->set_confidence(1.0);
  worst_case.mutable_target()->set_guarantee(v1::AccuracyTarget::ESTIMATE);
  expect_refused(client_->ComputeHiddenSampleMap(worst_case).status(), "an estimate has no worst case");

  v1::HiddenSampleMapRequest unknown = ShadowedFloor(8);
  unknown.mutable_target()->set_max_error(0.05);
  unknown.mutable_target()->set_guarantee(static_cast<v1::AccuracyTarget::Guarantee>(7));
  expect_refused(client_->ComputeHiddenSampleMap(unknown).status(), "an unknown guarantee");

  v1::PatchVisibilityRequest patches = CornellFloorPatches(4, 4);
  patches.mutable_target()->set_max_error(0.05);
  patches.mutable_target()->set_guarantee(v1::AccuracyTarget::ESTIMATE);
  expect_refused(client_->PatchVisibility(patches).status(), "PatchVisibility's source grid is regular");
}

// A bake's target on the estimate: only the rays state one, and a covered
// texel's estimate is at most the worst case's, so fewer rays meet it than
// the bound's plans ask; the answer states it beside the bound.
TEST_F(AccuracyTargetTest, AnObscuranceTargetOnTheEstimateChoosesRaysAndStatesTheEstimate) {
  v1::ComputeObscurancesRequest request;
  request.mutable_scene()->set_name("cornell_box_visq");
  request.set_resolution(32);
  request.set_d_max(0.5);
  request.mutable_target()->set_max_error(0.1);
  request.mutable_target()->set_guarantee(v1::AccuracyTarget::ESTIMATE);
  auto bake = client_->ComputeObscurances(request, nullptr);
  ASSERT_TRUE(bake.ok()) << bake.status();
  const v1::Accuracy& accuracy = bake->figures.accuracy();
  EXPECT_EQ(accuracy.method(), "obscurance-raycast");
  ASSERT_TRUE(accuracy.has_estimate()) << accuracy.DebugString();
  EXPECT_LE(accuracy.estimate(), 0.1);
  EXPECT_EQ(accuracy.parameters().at("target_met"), 1.0);
  for (const v1::PlanEstimate& plan : accuracy.plans()) EXPECT_EQ(plan.method(), "obscurance-raycast");

  request.mutable_target()->set_guarantee(v1::AccuracyTarget::RIGOROUS);
  auto rigorous = client_->ComputeObscurances(request, nullptr);
  ASSERT_TRUE(rigorous.ok()) << rigorous.status();
  double fewest_on_bound = 1e300, fewest_on_estimate = 1e300;
  for (const v1::PlanEstimate& plan : rigorous->figures.accuracy().plans())
    if (plan.meets_target() && plan.parameters().contains("rays_per_patch"))
      fewest_on_bound = std::min(fewest_on_bound, plan.parameters().at("rays_per_patch"));
  for (const v1::PlanEstimate& plan : accuracy.plans())
    if (plan.meets_target()) fewest_on_estimate = std::min(fewest_on_estimate, plan.parameters().at("rays_per_patch"));
  EXPECT_LT(fewest_on_estimate, fewest_on_bound);
}

TEST_F(AccuracyTargetTest, ExactMethodTakesPolygonLightsOfEitherWinding) {
  v1::HiddenSampleMapRequest request = ShadowedFloor(8);
  for (auto [s, t] : {std::pair{0.1, 0.1}, std::pair{0.5, 0.9}, std::pair{0.9, 0.1}}) {  // clockwise in (s, t)
    auto* vertex = request.mutable_samples()->add_polygon_uv();
    vertex->set_x(s);
    vertex->set_y(t);
  }
  request.set_method(v1::PLUCKER_EXACT);
  auto exact = client_->ComputeHiddenSampleMap(request);
  ASSERT_TRUE(exact.ok()) << exact.status();
  request.set_method(v1::RAYCAST);
  request.mutable_samples()->set_count(4096);
  auto sampled = client_->ComputeHiddenSampleMap(request);
  ASSERT_TRUE(sampled.ok()) << sampled.status();
  ASSERT_EQ(exact->visible_fraction.size(), sampled->visible_fraction.size());
  EXPECT_LE(ShareOutsideBound(sampled->visible_fraction, exact->visible_fraction,
                              sampled->figures.accuracy().error_bound()),
            0.05 + 0.03);
  double mean_exact = 0.0;
  for (float f : exact->visible_fraction) mean_exact += f;
  EXPECT_GT(mean_exact, 0.1 * double(exact->visible_fraction.size())) << "the floor sees the light";
}

TEST_F(AccuracyTargetTest, RaycastObscurancesAgreeWithTheGpuBakeWithinTheirErrors) {
  v1::ComputeObscurancesRequest request;
  request.mutable_scene()->set_name("cornell_box_visq");
  request.set_resolution(64);
  request.set_d_max(0.5);
  request.set_direction_count(256);
  auto bake = client_->ComputeObscurances(request, nullptr);
  ASSERT_TRUE(bake.ok()) << bake.status();
  request.set_direction_count(0);
  request.set_method(v1::ComputeObscurancesRequest::RAYCAST);
  request.set_rays_per_patch(256);
  auto rays = client_->ComputeObscurances(request, nullptr);
  ASSERT_TRUE(rays.ok()) << rays.status();
  EXPECT_EQ(rays->figures.accuracy().method(), "obscurance-raycast");
  EXPECT_TRUE(rays->figures.update_ready()) << "a ray-cast estimate is a whole solution for updates";
  ASSERT_EQ(rays->w.size(), bake->w.size());
  // Two estimates of the same patch values. Their mean difference over the
  // estimated texels measures 0.022 here: the boxes stand on the floor, and
  // at the contact the bundles' pixels and the per-patch rays see different
  // slivers (tests/obscurance lifts the box for its 0.01 comparison). Still
  // far below either per-texel figure (about 0.085 at 256 samples).
  double sum = 0.0;
  size_t n = 0;
  for (size_t t = 0; t < rays->estimated.size(); ++t)
    if (rays->estimated[t] && bake->estimated[t]) {
      sum += double(rays->w[3 * t]) - bake->w[3 * t];
      ++n;
    }
  ASSERT_GT(n, 50u);
  EXPECT_LT(std::abs(sum / double(n)), 0.035);

  // A range or partial sums belong to the bake.
  request.set_partial_only(true);
  auto partial = client_->ComputeObscurances(request, nullptr);
  ASSERT_EQ(partial.status().code(), absl::StatusCode::kInvalidArgument) << partial.status();
}

// GPU_RAYCAST traces the estimator's own rays (same seed, same origins and
// directions) on the GPU: every closest hit is Embree's but for float ties,
// so the two estimates agree texel for texel up to such a tie.
TEST_F(AccuracyTargetTest, GpuRaysGiveTheRaycastObscurancesTexelForTexel) {
  v1::ComputeObscurancesRequest request;
  request.mutable_scene()->set_name("cornell_box_visq");
  request.set_resolution(48);
  request.set_d_max(0.5);
  request.set_color_bleeding(true);
  request.set_rays_per_patch(32);
  request.set_method(v1::ComputeObscurancesRequest::RAYCAST);
  auto embree = client_->ComputeObscurances(request, nullptr);
  ASSERT_TRUE(embree.ok()) << embree.status();
  request.set_method(v1::ComputeObscurancesRequest::GPU_RAYCAST);
  auto gpu_rays = client_->ComputeObscurances(request, nullptr);
  ASSERT_TRUE(gpu_rays.ok()) << gpu_rays.status();
  EXPECT_EQ(gpu_rays->figures.accuracy().method(), "obscurance-gpu-raycast");
  EXPECT_DOUBLE_EQ(gpu_rays->figures.accuracy().error_bound(), embree->figures.accuracy().error_bound());
  ASSERT_EQ(gpu_rays->w.size(), embree->w.size());
  size_t estimated = 0, differ = 0;
  for (size_t t = 0; t < embree->estimated.size(); ++t) {
    if (!embree->estimated[t]) continue;
    ++estimated;
    bool same = true;
    for (int c = 0; c < 3; ++c) same = same && std::abs(double(gpu_rays->w[3 * t + c]) - embree->w[3 * t + c]) < 1e-5;
    differ += !same;
  }
  std::printf("GPU rays: %zu of %zu estimated texels differ from RAYCAST's\n", differ, estimated);
  ASSERT_GT(estimated, 100u);
  EXPECT_LE(differ, estimated / 200) << "one ray's tie moves a texel by a 32nd of a ray's value";
}

// The exact method's cost is predicted per request, from probes of its own
// points on its own trees (issue 44, section 3): behind the glass vase's
// flowers, where the method costs tens of times the ray caster's, a target
// request routes around it, and its predicted time follows what it then
// measures. A suite of its own, so that its server's cost model and caches
// start empty.
class ExactPredictionTest : public testing::SharedServerSuite<ExactPredictionTest> {
 protected:
  // A light over dense geometry onto the floor under it, 32 x 32 texels.
  struct Case {
    const char* name;
    const char* file;  // under the shared scenes
    glm::dvec3 light_origin, light_u, light_v, floor_origin, floor_u, floor_v;
  };
  static v1::HiddenSampleMapRequest FloorMap(const Case& c, const std::string& scene) {
    v1::HiddenSampleMapRequest request;
    request.mutable_scene()->set_name(scene);
    SetPatch(request.mutable_source(), c.light_origin, c.light_u, c.light_v);
    SetPatch(request.mutable_receiver(), c.floor_origin, c.floor_u, c.floor_v);
    request.set_width(32);
    request.set_height(32);
    return request;
  }

  double ComputeMs(v1::HiddenSampleMapRequest request, v1::VisibilityMethod method, uint32_t samples) {
    request.clear_target();
    request.set_method(method);
    request.mutable_samples()->set_count(samples);
    auto answer = client_->ComputeHiddenSampleMap(request);
    EXPECT_TRUE(answer.ok()) << answer.status();
    return answer.ok() ? answer->figures.timing().compute_ms() : -1.0;
  }
};

// Predicted against measured, within a generous factor: the machine may be
// loaded between the probes and the run (two cores shared by builds and
// other tests), and tens of ms either way are noise there (the Cornell box's
// exact map, predicted at 1.7 ms, once measured 14.9 ms under a full ctest
// beside a build). The 2x goal is the bench's
// (visq_bench_default_method --exact), not a test's. A prediction from a
// probe cut at its budget (`lower_bound`) says only that the method costs
// at least that much.
void ExpectWithinFactor(double predicted_ms, double measured_ms, double factor, const std::string& what,
                        bool lower_bound = false) {
  constexpr double kSlackMs = 25.0;
  EXPECT_LE(predicted_ms, factor * measured_ms + kSlackMs) << what;
  if (!lower_bound) {
    EXPECT_LE(measured_ms, factor * predicted_ms + kSlackMs) << what;
  }
}

// The exact plan among those weighed: its predicted ms, and whether its
// probe was cut (its prediction then a lower bound); -1 without one.
std::pair<double, bool> ExactPlanPrediction(const v1::Accuracy& accuracy) {
  for (const v1::PlanEstimate& plan : accuracy.plans())
    if (plan.method() == "plucker-exact") return {plan.predicted_ms(), plan.parameters().contains("probe_cut")};
  return {-1.0, false};
}

// The glass vase's flowers under a light (the foliage), and the bunny under
// a small one (where the old scene-wide fit predicted the exact plan at 11
// ms and chose it; it took 4.9 s, 5.5x the ray caster).
TEST_F(ExactPredictionTest, AFoliageTargetRoutesAroundTheExactMethodWhereItIsSlower) {
  VISQ_REQUIRE_SHARED_SCENES(scenes);
  const Case cases[] = {
      {"flowers", "foliage_glass_vase_flowers/GlassVaseFlowers.gltf", {-0.1, 0.35, -0.15}, {0.3, 0, 0},
       {0, 0, 0.25}, {-0.15, 0.001, -0.2}, {0, 0, 0.35}, {0.45, 0, 0}},
      {"bunny", "bunny/bunny.gltf", {-0.05, 0.3, -0.05}, {0.1, 0, 0}, {0, 0, 0.1}, {-0.2, 0.03, -0.2},
       {0, 0, 0.4}, {0.4, 0, 0}},
  };
  for (const Case& c : cases) {
    SCOPED_TRACE(c.name);
    // The same scene twice: one for the target request, one for the methods
    // run by name, each starting cold (trees, stores and cost model are per
    // scene name).
    const std::string target_scene = std::string(c.name) + "_target", named_scene = std::string(c.name) + "_named";
    for (const std::string& name : {target_scene, named_scene}) {
      auto info = client_->UploadScene(scenes / c.file, name);
      ASSERT_TRUE(info.ok()) << info.status();
    }
    v1::HiddenSampleMapRequest request = FloorMap(c, target_scene);
    request.mutable_target()->set_max_error(0.02);
    auto target = client_->ComputeHiddenSampleMap(request);
    ASSERT_TRUE(target.ok()) << target.status();
    const v1::Accuracy& accuracy = target->figures.accuracy();
    const auto [exact_predicted, exact_cut] = ExactPlanPrediction(accuracy);
    ASSERT_GT(exact_predicted, 0.0) << accuracy.DebugString();

    // Both methods by name on the other copy, cold: the exact map, and the
    // sampled plan the target chose (or the ray caster at the count the
    // target needs, when the exact method was chosen).
    uint32_t samples = 4640;  // Hoeffding at 0.02 and 95 %, rounded up to 32
    v1::VisibilityMethod sampled = v1::RAYCAST;
    if (accuracy.method() != "plucker-exact") {
      samples = uint32_t(accuracy.parameters().at("samples"));
      if (accuracy.method() != "raycast") sampled = v1::RASTER;
    }
    const double exact_cold_ms = ComputeMs(FloorMap(c, named_scene), v1::PLUCKER_EXACT, 0);
    const double sampled_ms = ComputeMs(FloorMap(c, named_scene), sampled, samples);
    ASSERT_GT(exact_cold_ms, 0.0);
    ASSERT_GT(sampled_ms, 0.0);
    std::printf("%s 32x32 +-0.02: chose %s (%.1f ms computed); exact predicted %.1f ms, run by name %.1f ms cold; "
                "%s %u by name %.1f ms\n",
                c.name, accuracy.method().c_str(), target->figures.timing().compute_ms(), exact_predicted,
                exact_cold_ms, v1::VisibilityMethod_Name(sampled).c_str(), samples, sampled_ms);
    if (exact_cold_ms > 3.0 * sampled_ms) {
      EXPECT_NE(accuracy.method(), "plucker-exact")
          << "the exact method measured " << exact_cold_ms / sampled_ms << "x the sampled plan: "
          << accuracy.DebugString();
    }

    // The prediction against what the exact plan costs from where the
    // target call's probes left the trees and stores (or its own time, if
    // chosen).
    double exact_ms = target->figures.timing().compute_ms();
    if (accuracy.method() != "plucker-exact") exact_ms = ComputeMs(FloorMap(c, target_scene), v1::PLUCKER_EXACT, 0);
    std::printf("%s: the exact plan from where the probes left it: predicted %.1f ms, computed %.1f ms\n", c.name,
                exact_predicted, exact_ms);
    // 10x: the trees refine lazily, so the probes' points cost more than
    // the batch's later ones, and a probe cut at its budget averages over a
    // few dozen points (the bunny: 3-8x over; the scene-wide fit this
    // replaced was 460x under there and chose the exact method).
    ExpectWithinFactor(exact_predicted, exact_ms, 10.0, "the exact plan's predicted ms against its compute ms",
                       exact_cut);

    // A second request on the same scene, under a smaller light further
    // along: its own penumbra, predicted from its own probes (a scene-wide
    // fit of the first request mispredicted such requests 5-7x).
    Case moved = c;
    moved.light_origin += 0.4 * c.light_u + 0.3 * c.light_v;
    moved.light_u *= 0.5;
    moved.light_v *= 0.5;
    v1::HiddenSampleMapRequest second = FloorMap(moved, target_scene);
    second.mutable_target()->set_max_error(0.02);
    auto again = client_->ComputeHiddenSampleMap(second);
    ASSERT_TRUE(again.ok()) << again.status();
    const auto [again_predicted, again_cut] = ExactPlanPrediction(again->figures.accuracy());
    double again_ms = again->figures.timing().compute_ms();
    if (again->figures.accuracy().method() != "plucker-exact")
      again_ms = ComputeMs(FloorMap(moved, target_scene), v1::PLUCKER_EXACT, 0);
    std::printf("%s, the smaller light: chose %s; the exact plan predicted %.1f ms%s, computed %.1f ms\n", c.name,
                again->figures.accuracy().method().c_str(), again_predicted, again_cut ? " (probe cut)" : "",
                again_ms);
    ExpectWithinFactor(again_predicted, again_ms, 10.0, "a second request: the exact plan's predicted ms", again_cut);
  }
}

// Where the exact method is chosen (the Cornell box: a few dozen
// triangles), its predicted time is its compute time within a generous
// factor, on the first request and on another request after it.
TEST_F(ExactPredictionTest, WhereTheExactMethodIsChosenItsPredictionFollowsItsTime) {
  int chosen = 0;
  for (auto [x, size] : {std::pair{-0.999, 1.998}, std::pair{-0.9, 0.8}}) {
    v1::HiddenSampleMapRequest request;
    request.mutable_scene()->set_name("cornell_box_visq");
    SetPatch(request.mutable_source(), {-0.25, 1.99, -0.25}, {0.5, 0, 0}, {0, 0, 0.5});
    SetPatch(request.mutable_receiver(), {x, 0.001, x}, {size, 0, 0}, {0, 0, size});
    request.set_width(24);
    request.set_height(24);
    request.mutable_target()->set_max_error(0.01);
    auto answer = client_->ComputeHiddenSampleMap(request);
    ASSERT_TRUE(answer.ok()) << answer.status();
    const v1::Accuracy& accuracy = answer->figures.accuracy();
    std::printf("cornell %.3f m: chose %s, predicted %.2f ms, computed %.2f ms\n", size, accuracy.method().c_str(),
                accuracy.predicted_ms(), answer->figures.timing().compute_ms());
    if (accuracy.method() != "plucker-exact") continue;
    ++chosen;
    ExpectWithinFactor(accuracy.predicted_ms(), answer->figures.timing().compute_ms(), 4.0,
                       "cornell: the chosen exact plan's predicted ms against its compute ms");
  }
  EXPECT_GT(chosen, 0) << "a 0.01 target on the Cornell box wants 18,445 rays a texel; the exact method is cheaper";

  // A request over a light and points whose answers are all stored (here
  // by a run of the exact method by name): a look-up a point, and the
  // call's fixed cost once. Priced from 4 stored points, each carried that
  // cost (45 ms predicted for 4,096 points that took 1.2 ms), and a ray cast
  // 69x slower was chosen.
  v1::HiddenSampleMapRequest floor;
  floor.mutable_scene()->set_name("cornell_box_visq");
  SetPatch(floor.mutable_source(), {-0.25, 1.99, -0.25}, {0.5, 0, 0}, {0, 0, 0.5});
  SetPatch(floor.mutable_receiver(), {-0.999, 0.001, -0.999}, {1.998, 0, 0}, {0, 0, 1.998});
  floor.set_width(64);
  floor.set_height(64);
  floor.set_method(v1::PLUCKER_EXACT);
  ASSERT_TRUE(client_->ComputeHiddenSampleMap(floor).ok());
  floor.set_method(v1::METHOD_UNSPECIFIED);
  floor.mutable_target()->set_max_error(0.03);
  auto stored = client_->ComputeHiddenSampleMap(floor);
  ASSERT_TRUE(stored.ok()) << stored.status();
  const v1::Accuracy& stored_accuracy = stored->figures.accuracy();
  std::printf("cornell 64 x 64, every point stored: chose %s, predicted %.2f ms, computed %.2f ms\n",
              stored_accuracy.method().c_str(), stored_accuracy.predicted_ms(), stored->figures.timing().compute_ms());
  EXPECT_EQ(stored_accuracy.method(), "plucker-exact") << stored_accuracy.DebugString();
  if (stored_accuracy.method() == "plucker-exact")
    ExpectWithinFactor(stored_accuracy.predicted_ms(), stored->figures.timing().compute_ms(), 4.0,
                       "cornell, every point stored: the exact plan's predicted ms against its compute ms");

  // Patch visibility weighs the exact method through the same probes (its
  // receiver grid as the batch's points).
  v1::PatchVisibilityRequest patches = CornellFloorPatches(20, 20);
  patches.mutable_target()->set_max_error(0.01);
  auto grid = client_->PatchVisibility(patches);
  ASSERT_TRUE(grid.ok()) << grid.status();
  bool weighed_exact = false;
  for (const v1::PlanEstimate& plan : grid->accuracy().plans()) weighed_exact |= plan.method() == "plucker-exact";
  EXPECT_TRUE(weighed_exact) << grid->accuracy().DebugString();
  std::printf("cornell patches 20 x 20: chose %s, predicted %.2f ms, computed %.2f ms\n",
              grid->accuracy().method().c_str(), grid->accuracy().predicted_ms(), grid->timing().compute_ms());
  if (grid->accuracy().method() == "plucker-exact")
    ExpectWithinFactor(grid->accuracy().predicted_ms(), grid->timing().compute_ms(), 4.0,
                       "cornell patches: the chosen exact plan's predicted ms against its compute ms");
}

// Planned by the request's own probes, on either guarantee, the answer meets
// the target: where the prediction missed, more maps were added before the
// answer was sent. Behind the glass vase's flowers the exact method is slow,
// so the sampled plans are chosen; their answers are checked against the
// exact map.
TEST_F(ExactPredictionTest, PredictedPlansMeetTheTargetOnEitherGuarantee) {
  VISQ_REQUIRE_SHARED_SCENES(scenes);
  // Calls of their own deadline: under a sanitizer, or on two cores shared
  // with a build, the exact reference map alone can take tens of seconds
  // (once 63 s for the whole test, against the default 60 s a call).
  client_ = std::make_unique<client::Client>(
      client::ClientOptions{.address = server_->address(), .deadline = std::chrono::minutes(5)});
  const Case flowers = {"flowers", "foliage_glass_vase_flowers/GlassVaseFlowers.gltf", {-0.1, 0.35, -0.15},
                        {0.3, 0, 0}, {0, 0, 0.25}, {-0.15, 0.001, -0.2}, {0, 0, 0.35}, {0.45, 0, 0}};
  // Each request on a copy of its own, cold: the exact method's trees and
  // stores, which make a repeated request cheap there, are per scene.
  auto info = client_->UploadScene(scenes / flowers.file, "flowers_reference");
  ASSERT_TRUE(info.ok()) << info.status();
  v1::HiddenSampleMapRequest exact_request = FloorMap(flowers, "flowers_reference");
  exact_request.set_method(v1::PLUCKER_EXACT);
  auto exact = client_->ComputeHiddenSampleMap(exact_request);
  ASSERT_TRUE(exact.ok()) << exact.status();

  int sampled = 0, topped_up = 0;
  for (const double max_error : {0.05, 0.02, 0.01}) {
    for (const auto guarantee : {v1::AccuracyTarget::RIGOROUS, v1::AccuracyTarget::ESTIMATE}) {
      const std::string copy = "flowers_" + std::to_string(sampled + topped_up) + "_" + std::to_string(max_error) +
                               "_" + v1::AccuracyTarget::Guarantee_Name(guarantee);
      auto uploaded = client_->UploadScene(scenes / flowers.file, copy);
      ASSERT_TRUE(uploaded.ok()) << uploaded.status();
      v1::HiddenSampleMapRequest request = FloorMap(flowers, copy);
      request.mutable_target()->set_max_error(max_error);
      request.mutable_target()->set_guarantee(guarantee);
      request.set_want_texel_error(true);
      auto answer = client_->ComputeHiddenSampleMap(request);
      ASSERT_TRUE(answer.ok()) << answer.status();
      const v1::Accuracy& accuracy = answer->figures.accuracy();
      const bool on_estimate = guarantee == v1::AccuracyTarget::ESTIMATE;
      const std::string where =
          "max_error " + std::to_string(max_error) + ", " + v1::AccuracyTarget::Guarantee_Name(guarantee);
      EXPECT_EQ(accuracy.parameters().at("target_met"), 1.0) << where << ": " << accuracy.DebugString();
      const auto parameter = [&](const char* name) {
        return accuracy.parameters().contains(name) ? accuracy.parameters().at(name) : 0.0;
      };
      const double stated = on_estimate ? accuracy.estimate() : accuracy.error_bound();
      size_t outside_bound = 0, outside_estimate = 0;
      if (accuracy.method() != "plucker-exact") {
        ++sampled;
        EXPECT_LE(stated, max_error) << where;
        ASSERT_EQ(answer->visible_fraction.size(), exact->visible_fraction.size());
        ASSERT_EQ(static_cast<size_t>(answer->figures.texel_error_size()), exact->visible_fraction.size());
        for (size_t j = 0; j < exact->visible_fraction.size(); ++j) {
          const double error = std::abs(double(answer->visible_fraction[j]) - exact->visible_fraction[j]);
          outside_bound += error > answer->figures.texel_error(int(j)) + 1e-6;
          outside_estimate += error > answer->figures.texel_estimate(int(j)) + 1e-6;
        }
        // Each texel's bound holds at 95 %.
        EXPECT_LE(double(outside_bound) / exact->visible_fraction.size(), 0.05 + 0.03) << where;
        if (parameter("planned_samples") > 0) {
          ++topped_up;
          EXPECT_GT(parameter("samples"), parameter("planned_samples")) << where;
          EXPECT_NE(accuracy.note().find("more maps"), std::string::npos) << where << ": " << accuracy.note();
        }
      }
      std::printf("flowers %s: %s, %.0f samples planned, %.0f ran, states %.4f; %zu texels outside their bound, "
                  "%zu outside their estimate, of %zu\n",
                  where.c_str(), accuracy.method().c_str(),
                  parameter("planned_samples") > 0 ? parameter("planned_samples") : parameter("samples"),
                  parameter("samples"), stated, outside_bound, outside_estimate, exact->visible_fraction.size());
    }
  }
  RecordProperty("sampled_answers", std::to_string(sampled));
  RecordProperty("topped_up", std::to_string(topped_up));
  EXPECT_GE(sampled, 3) << "behind the flowers the sampled plans are the cheaper";
}

}  // namespace
}  // namespace visq
