// The accuracy statements the core writes beside its algorithms: each says
// what its bound is a bound of, and says "estimate" where the samples do not
// support a guarantee.
#include <gtest/gtest.h>

#include <cmath>
#include <string>

#include "core/accuracy_planner.h"
#include "core/accuracy_statement.h"
#include "core/light_visibility_query.h"
#include "core/visibility_sampling_query.h"
#include "core/voxel_query.h"

namespace visq::core {
namespace {

bool Mentions(const std::string& note, const std::string& words) { return note.find(words) != std::string::npos; }

TEST(AccuracyStatement, SampledMapStatesTheLargestTexelBoundWhenItHasPerTexelBounds) {
  sampling::ErrorBound error;
  error.rigorous = true;
  error.confidence = 0.95;
  error.sampling = 0.085;
  error.has_per_texel = true;
  error.per_texel_max = 0.058;
  const AccuracyStatement s =
      SampledVisibilityStatement(error, VisibilityMethod::kRaycast, sampling::LookupMode::kExact, 256);
  EXPECT_EQ(s.method, "raycast");
  EXPECT_EQ(s.error_bound, 0.058);
  EXPECT_EQ(s.confidence, 0.95);
  EXPECT_EQ(s.parameters.at("samples"), 256.0);
  EXPECT_TRUE(Mentions(s.note, "Clopper-Pearson")) << s.note;
  EXPECT_TRUE(Mentions(s.note, "no lookup error")) << s.note;
}

TEST(AccuracyStatement, RegularSamplesGiveAnEstimateNotABound) {
  sampling::ErrorBound error;
  error.rigorous = false;
  error.sampling = 0.1;
  error.lookup_max = 0.02;
  const AccuracyStatement s =
      SampledVisibilityStatement(error, VisibilityMethod::kRaster, sampling::LookupMode::kHough, 64);
  EXPECT_EQ(s.method, "raster-hough-lookup");
  EXPECT_NEAR(s.error_bound, 0.12, 1e-12);  // sampling plus the lookup's own error
  EXPECT_TRUE(Mentions(s.note, "estimate, not a guarantee")) << s.note;
  EXPECT_TRUE(Mentions(s.note, "Hough lookup")) << s.note;
}

TEST(AccuracyStatement, ExactMethodsStateZeroAtFullConfidence) {
  const AccuracyStatement map =
      SampledVisibilityStatement({}, VisibilityMethod::kPluckerExact, sampling::LookupMode::kExact, 0);
  LightVisibilityAnswer exact_answer;
  exact_answer.points.resize(3);
  const AccuracyStatement light = LightVisibilityStatement(exact_answer);
  for (const AccuracyStatement* s : {&map, &light}) {
    EXPECT_EQ(s->method, "plucker-exact");
    EXPECT_EQ(s->error_bound, 0.0);
    EXPECT_EQ(s->confidence, 1.0);
  }
  EXPECT_TRUE(map.parameters.empty());
  EXPECT_EQ(light.parameters.at("shadow_tolerance"), 0.0);
}

TEST(AccuracyStatement, LightVisibilityWithAShadowToleranceStatesItsLargestPointError) {
  LightVisibilityAnswer answer;
  answer.shadow_tolerance = 1e-6;
  answer.points.resize(4);
  answer.points[1].visible_area_fraction_error = 3e-7;
  answer.points[3].visible_area_fraction_error = 8e-7;
  const AccuracyStatement s = LightVisibilityStatement(answer);
  EXPECT_EQ(s.method, "plucker-exact");
  EXPECT_EQ(s.error_bound, 8e-7);
  EXPECT_EQ(s.confidence, 1.0);
  EXPECT_EQ(s.parameters.at("shadow_tolerance"), 1e-6);
  EXPECT_TRUE(Mentions(s.note, "2 of 4 points")) << s.note;
  EXPECT_TRUE(Mentions(s.note, "one-sided")) << s.note;
}

TEST(AccuracyStatement, ConservativeVoxelsAreBoundedByTheVoxelDiagonalStandardOnesAreNot) {
  gpu::VoxelizeResult figures;
  figures.grid.width = 4;
  figures.grid.height = 2;
  figures.grid.slices = 8;
  figures.box.half_extent = glm::dvec3(2.0, 1.0, 4.0);  // voxels of 1 x 1 x 1
  figures.rasterization = gpu::Rasterization::kConservative;
  const AccuracyStatement conservative = VoxelizeStatement(figures);
  EXPECT_EQ(conservative.method, "slicemap-conservative-uniform");
  EXPECT_NEAR(conservative.error_bound, std::sqrt(3.0), 1e-12);
  EXPECT_EQ(conservative.confidence, 1.0);

  figures.rasterization = gpu::Rasterization::kStandard;
  figures.precision = gpu::SlicePrecision::kLocal;
  const AccuracyStatement standard = VoxelizeStatement(figures);
  EXPECT_EQ(standard.method, "slicemap-standard-local");
  EXPECT_LT(standard.error_bound, 0.0);  // no numeric bound, and the note says why
  EXPECT_TRUE(Mentions(standard.note, "no numeric bound")) << standard.note;
  EXPECT_TRUE(Mentions(standard.note, "local precision")) << standard.note;
}

TEST(AccuracyStatement, AChosenPlanAddsItsParametersAndPrediction) {
  PlanReport report;
  Plan cheap;
  cheap.method = "raycast";
  cheap.parameters = {{"samples", 512.0}};
  cheap.predicted_ms = 40.0;
  Plan exact;
  exact.method = "plucker-exact";
  exact.predicted_ms = 900.0;
  report.plans = {exact, cheap};
  report.chosen = 1;
  AccuracyStatement s = SampledVisibilityStatement({}, VisibilityMethod::kRaycast, sampling::LookupMode::kExact, 512);
  AddChosenPlan(report, s);
  EXPECT_EQ(s.parameters.at("samples"), 512.0);
  EXPECT_EQ(s.predicted_ms, 40.0);
  EXPECT_TRUE(Mentions(s.note, "among 2 plans")) << s.note;
  EXPECT_TRUE(Mentions(s.note, "no probing needed")) << s.note;
}

}  // namespace
}  // namespace visq::core
