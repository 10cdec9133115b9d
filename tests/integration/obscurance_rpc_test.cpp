// The obscurance RPCs end to end through the real server and client, on the
// generated Cornell box: the bake's range, progress and determinism, the
// client's shard merge against the whole bake, node moves and the update,
// the preview render (and its CLI), the export onto a real scene's mesh,
// and bad input.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <numbers>
#include <set>

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>
#include <stb_image.h>

#include "absl/strings/str_cat.h"
#include "scene/gltf_loader.h"
#include "scene/gltf_writer.h"
#include "scene/sample_scenes.h"
#include "proto_builders.h"
#include "shared_server_suite.h"
#include "test_support.h"
#include "visq_client.h"

namespace visq {
namespace {

using client::Client;

// Copies of the Cornell box under other names, so the tests that move
// nodes do not disturb each other or the sample.
constexpr const char* kBoundsScene = "cornell_bounds";
constexpr const char* kUpdateScene = "cornell_update";
constexpr const char* kPreviewScene = "cornell_preview";

using testing::Translation;

class ObscuranceRpcTest : public testing::SharedServerSuite<ObscuranceRpcTest> {
 public:
  // Stored copies of the Cornell box: one to move, one to measure bounds,
  // one to preview (unbaked until its test bakes it).
  static void PrepareRepository(const std::filesystem::path& repo) {
    for (const char* name : {kBoundsScene, kUpdateScene, kPreviewScene}) {
      std::filesystem::create_directories(repo / name);
      ASSERT_TRUE(WriteGltfFile(MakeCornellBox(), repo / name / (std::string(name) + ".gltf")).ok());
    }
  }

 protected:
  static v1::ComputeObscurancesRequest SmallBake(const std::string& scene) {
    v1::ComputeObscurancesRequest request;
    request.mutable_scene()->set_name(scene);
    request.set_resolution(32);
    request.set_d_max(1.0);
    request.set_direction_count(8);
    request.set_seed(5);
    // The paper's bake (progress, shards, updates, previews); the server's
    // own choice is tested apart.
    request.set_method(v1::ComputeObscurancesRequest::DEPTH_PEELING);
    return request;
  }
};

// With no method, a whole bake of D directions runs the faster here of the
// depth peeling with D directions and the ray-cast estimator with D rays a
// patch (the same bound figure); the answer says which and lists both; a
// shard's range only the bake can make.
TEST_F(ObscuranceRpcTest, ABakeNamingNoMethodRunsTheFasterOfTwoAtTheSameBound) {
  v1::ComputeObscurancesRequest request = SmallBake("cornell_box_visq");
  request.clear_method();
  auto bake = client_->ComputeObscurances(request);
  ASSERT_TRUE(bake.ok()) << bake.status();
  const v1::Accuracy& accuracy = bake->figures.accuracy();
  EXPECT_TRUE(accuracy.method() == "obscurance-depth-peeling" || accuracy.method() == "obscurance-raycast")
      << accuracy.method();
  EXPECT_NE(accuracy.note().find("no method named"), std::string::npos) << accuracy.note();
  ASSERT_GE(accuracy.plans_size(), 1);
  bool chosen_listed = false;
  for (const v1::PlanEstimate& plan : accuracy.plans()) {
    EXPECT_TRUE(plan.meets_target());
    EXPECT_GE(plan.predicted_ms(), 0.0);
    EXPECT_DOUBLE_EQ(plan.error_bound(), accuracy.plans(0).error_bound()) << "the same bound figure";
    const char* count = plan.method() == "obscurance-raycast" ? "rays_per_patch" : "directions";
    ASSERT_TRUE(plan.parameters().contains(count)) << plan.method();
    EXPECT_EQ(plan.parameters().at(count), 8.0);
    chosen_listed |= plan.method() == accuracy.method();
  }
  EXPECT_TRUE(chosen_listed);
  EXPECT_TRUE(bake->figures.update_ready()) << "either way a whole bake, ready for updates";
  size_t estimated = 0;
  for (size_t t = 0; t < bake->estimated.size(); ++t) {
    if (!bake->estimated[t]) continue;
    ++estimated;
    EXPECT_GE(bake->w[3 * t], 0.0f);
    EXPECT_LE(bake->w[3 * t], 1.0f);
  }
  EXPECT_GT(estimated, 100u);

  v1::ComputeObscurancesRequest shard = request;
  shard.set_total_directions(16);
  shard.set_partial_only(true);
  auto partial = client_->ComputeObscurances(shard);
  ASSERT_TRUE(partial.ok()) << partial.status();
  EXPECT_EQ(partial->figures.accuracy().method(), "obscurance-depth-peeling");
}

TEST_F(ObscuranceRpcTest, BakeGivesWInRangeWithProgress) {
  uint32_t progress_seen = 0, last_done = 0;
  auto bake = client_->ComputeObscurances(SmallBake("cornell_box_visq"), [&](const v1::ObscuranceProgress& p) {
    ++progress_seen;
    EXPECT_EQ(p.directions_total(), 8u);
    EXPECT_GE(p.directions_done(), last_done);
    last_done = p.directions_done();
  });
  ASSERT_TRUE(bake.ok()) << bake.status();
  const auto& f = bake->figures;
  EXPECT_GE(progress_seen, 1u);
  EXPECT_EQ(progress_seen, bake->progress_messages);
  EXPECT_EQ(f.atlas().width(), 32u);
  EXPECT_EQ(f.atlas().height(), 32u);
  EXPECT_FALSE(f.atlas().from_lightmap_uvs()) << "the generated box has no TEXCOORD_1";
  EXPECT_EQ(f.channels(), 1u);
  EXPECT_TRUE(f.update_ready());
  ASSERT_EQ(f.ranges_size(), 1);
  EXPECT_EQ(f.ranges(0).first(), 0u);
  EXPECT_EQ(f.ranges(0).count(), 8u);
  EXPECT_EQ(f.accuracy().method(), "obscurance-depth-peeling");
  EXPECT_GT(f.accuracy().error_bound(), 0.0);
  EXPECT_FALSE(f.accuracy().note().empty());
  EXPECT_GT(f.timing().total_ms(), 0.0);
  ASSERT_EQ(bake->w.size(), 32u * 32u * 3u);
  ASSERT_EQ(bake->intensity.size(), 32u * 32u * 3u);
  ASSERT_EQ(bake->estimated.size(), 32u * 32u);
  size_t estimated = 0;
  double sum = 0;
  for (size_t t = 0; t < bake->estimated.size(); ++t) {
    if (!bake->estimated[t]) continue;
    ++estimated;
    for (int c = 0; c < 3; ++c) {
      EXPECT_GE(bake->w[3 * t + c], 0.0f) << "texel " << t;
      EXPECT_LE(bake->w[3 * t + c], 1.0f) << "texel " << t;
    }
    sum += bake->w[3 * t];
  }
  EXPECT_GT(estimated, 100u);
  EXPECT_EQ(f.estimated_texels(), estimated);
  // A closed box with d_max 1 (half its size) occludes a good part of every hemisphere.
  EXPECT_LT(sum / estimated, 0.99);
  EXPECT_GT(sum / estimated, 0.2);
}

// want_errors: every texel, triangle and vertex gets its own half-width. The
// answer's single bound is the widest own bound among the elements it
// covers, and the counts it states outside are exactly those whose own bound
// exceeds it; the triangles' own bounds hold against a bake with eight times
// the directions.
TEST_F(ObscuranceRpcTest, EachElementCarriesItsOwnBoundWhenAsked) {
  v1::ComputeObscurancesRequest request = SmallBake("cornell_box_visq");
  request.set_want_averages(true);
  auto plain = client_->ComputeObscurances(request);
  ASSERT_TRUE(plain.ok()) << plain.status();
  EXPECT_TRUE(plain->w_error.empty() && plain->triangle_w_error.empty() && plain->vertex_w_error.empty())
      << "errors are sent only when asked";
  request.set_want_errors(true);
  auto bake = client_->ComputeObscurances(request);
  ASSERT_TRUE(bake.ok()) << bake.status();
  const size_t texels = 32 * 32, triangles = bake->triangle_w.size() / 3, vertices = bake->vertex_w.size() / 3;
  ASSERT_EQ(bake->w_error.size(), texels);
  ASSERT_EQ(bake->triangle_w_error.size(), triangles);
  ASSERT_EQ(bake->vertex_w_error.size(), vertices);
  EXPECT_EQ(bake->w, plain->w) << "asking for errors changes no W";
  const double stated = bake->figures.accuracy().error_bound();
  const auto& parameters = bake->figures.accuracy().parameters();
  size_t texels_outside = 0, texels_covered = 0;
  float widest_covered = 0;
  for (size_t t = 0; t < texels; ++t) {
    if (!bake->estimated[t]) {
      EXPECT_EQ(bake->w_error[t], 1.0f) << "a filled texel has no samples: W's whole range";
      continue;
    }
    EXPECT_GT(bake->w_error[t], 0.0f) << "texel " << t;
    EXPECT_LE(bake->w_error[t], 1.0f) << "texel " << t;
    if (bake->w_error[t] > stated) {
      ++texels_outside;
    } else {
      ++texels_covered;
      widest_covered = std::max(widest_covered, bake->w_error[t]);
    }
  }
  size_t triangles_outside = 0;
  float widest = widest_covered;
  for (float e : bake->triangle_w_error) {
    EXPECT_TRUE(e > 0.0f && e <= 1.0f) << e;
    triangles_outside += e > stated;
    if (e <= stated) widest = std::max(widest, e);
  }
  for (float e : bake->vertex_w_error) {
    EXPECT_TRUE(e > 0.0f && e <= 1.0f) << e;
    if (e <= stated) widest = std::max(widest, e);
  }
  ASSERT_TRUE(parameters.contains("texels_outside_bound") && parameters.contains("triangles_outside_bound"))
      << bake->figures.accuracy().DebugString();
  EXPECT_EQ(parameters.at("texels_outside_bound"), static_cast<double>(texels_outside));
  // Triangles no sample reached carry 1 and are not counted among the sampled.
  EXPECT_EQ(parameters.at("triangles_outside_bound") + parameters.at("triangles_without_samples"),
            static_cast<double>(triangles_outside));
  EXPECT_GT(texels_covered, texels_outside) << "most texels rest on a quarter of the directions";
  EXPECT_EQ(widest, static_cast<float>(stated)) << "the bound is its widest covered element's, no looser";
  std::printf("stated %.4f: %zu texels covered, %zu outside; %zu of %zu triangles outside\n", stated, texels_covered,
              texels_outside, triangles_outside, triangles);
  std::vector<float> sorted = bake->triangle_w_error;
  std::sort(sorted.begin(), sorted.end());
  ASSERT_TRUE(parameters.contains("triangle_bound_median"));
  EXPECT_NEAR(parameters.at("triangle_bound_median"), sorted[sorted.size() / 2], 1e-6);

  v1::ComputeObscurancesRequest finer = request;
  finer.set_direction_count(64);
  auto reference = client_->ComputeObscurances(finer);
  ASSERT_TRUE(reference.ok()) << reference.status();
  size_t held = 0;
  for (size_t t = 0; t < triangles; ++t) {
    const double difference = std::abs(bake->triangle_w[3 * t] - reference->triangle_w[3 * t]);
    held += difference <= bake->triangle_w_error[t] + reference->triangle_w_error[t];
  }
  EXPECT_GE(held, 0.95 * triangles) << held << " of " << triangles << " triangles within their bounds";
}

TEST_F(ObscuranceRpcTest, SameSeedSameBitsAndShardsMergeExactly) {
  v1::ComputeObscurancesRequest request = SmallBake("cornell_box_visq");
  auto a = client_->ComputeObscurances(request);
  auto b = client_->ComputeObscurances(request);
  ASSERT_TRUE(a.ok()) << a.status();
  ASSERT_TRUE(b.ok()) << b.status();
  ASSERT_EQ(a->w.size(), b->w.size());
  EXPECT_EQ(std::memcmp(a->w.data(), b->w.data(), a->w.size() * sizeof(float)), 0) << "same seed, same bits";

  // The whole bake's partial sums, and two shards [0, 4) + [4, 8) merged by the client.
  request.set_partial_only(true);
  auto whole = client_->ComputeObscurances(request);
  ASSERT_TRUE(whole.ok()) << whole.status();
  EXPECT_TRUE(whole->w.empty());
  ASSERT_EQ(whole->partial.counts.size(), 32u * 32u);
  auto merged = client::ShardedBake(std::vector<Client*>{client_.get()}, SmallBake("cornell_box_visq"), 2);
  ASSERT_TRUE(merged.ok()) << merged.status();
  EXPECT_EQ(merged->partial.fingerprint, whole->partial.fingerprint);
  ASSERT_EQ(merged->partial.ranges.size(), 1u);
  EXPECT_EQ(merged->partial.ranges[0].first, 0u);
  EXPECT_EQ(merged->partial.ranges[0].count, 8u);
  EXPECT_EQ(merged->partial.sums, whole->partial.sums) << "the merge must equal the whole bake bit for bit";
  EXPECT_EQ(merged->partial.counts, whole->partial.counts);

  // Overlapping shards do not merge.
  obscurance::ObscurancePartial twice = whole->partial;
  EXPECT_EQ(client::MergeObscurancePartials(twice, whole->partial).code(), absl::StatusCode::kInvalidArgument);
}

TEST_F(ObscuranceRpcTest, SetNodeTransformBumpsVersionAndMovesBounds) {
  auto before = client_->GetScene(kBoundsScene, /*include_nodes=*/true);
  ASSERT_TRUE(before.ok()) << before.status();
  EXPECT_NEAR(before->bounds_max().y(), 2.0, 1e-6);  // glTF positions are floats
  v1::SetNodeTransformRequest request;
  request.mutable_scene()->set_name(kBoundsScene);
  request.set_node_name("tall_box");
  for (double v : Translation(0, 1.5, 0)) request.add_world_matrix(v);
  auto moved = client_->SetNodeTransform(request);
  ASSERT_TRUE(moved.ok()) << moved.status();
  EXPECT_GT(moved->version(), before->version());
  EXPECT_NEAR(moved->bounds_max().y(), 2.7, 1e-6) << "the 1.2 high box now reaches 1.5 + 1.2";
  EXPECT_FALSE(moved->persisted()) << "moves are in memory only";
  auto after = client_->GetScene(kBoundsScene);
  ASSERT_TRUE(after.ok()) << after.status();
  EXPECT_EQ(after->version(), moved->version());
  EXPECT_NEAR(after->bounds_max().y(), 2.7, 1e-6);
  EXPECT_NE(after->content_hash(), before->content_hash());
  // A request naming the old version now fails.
  request.mutable_scene()->set_version(before->version());
  EXPECT_EQ(client_->SetNodeTransform(request).status().code(), absl::StatusCode::kFailedPrecondition);
}

TEST_F(ObscuranceRpcTest, UpdateAfterMoveChangesOnlyAffectedTexels) {
  v1::ComputeObscurancesRequest bake_request = SmallBake(kUpdateScene);
  bake_request.set_d_max(0.5);
  auto bake = client_->ComputeObscurances(bake_request);
  ASSERT_TRUE(bake.ok()) << bake.status();
  ASSERT_TRUE(bake->figures.update_ready());

  v1::SetNodeTransformRequest move;
  move.mutable_scene()->set_name(kUpdateScene);
  move.set_node_name("short_box");
  for (double v : Translation(-0.05, 0, 0.2)) move.add_world_matrix(v);
  auto moved = client_->SetNodeTransform(move);
  ASSERT_TRUE(moved.ok()) << moved.status();

  v1::UpdateObscurancesRequest request;
  request.mutable_scene()->set_name(kUpdateScene);
  request.set_want_full_w(true);
  auto update = client_->UpdateObscurances(request);
  ASSERT_TRUE(update.ok()) << update.status();
  EXPECT_EQ(update->from_version(), bake->figures.scene_version());
  EXPECT_EQ(update->scene_version(), moved->version());
  EXPECT_EQ(update->moves_applied(), 1u);
  EXPECT_GT(update->texels_size(), 0) << "the box's own patches at least";
  EXPECT_LT(update->texels_size(), 32 * 32) << "not the whole atlas";
  EXPECT_EQ(update->w_size(), 3 * update->texels_size());
  EXPECT_GT(update->rays(), 0u);
  ASSERT_EQ(update->full_w_size(), 32 * 32 * 3);
  const std::set<uint32_t> changed(update->texels().begin(), update->texels().end());
  size_t unchanged = 0;
  for (uint32_t t = 0; t < 32 * 32; ++t) {
    if (changed.count(t)) continue;
    ++unchanged;
    for (int c = 0; c < 3; ++c) {
      const float now = update->full_w(static_cast<int>(3 * t + c)), baked = bake->w[3 * t + c];
      ASSERT_EQ(std::memcmp(&now, &baked, sizeof(float)), 0) << "texel " << t << " is not in the changed list";
    }
  }
  EXPECT_GT(unchanged, 0u);
  for (int i = 0; i < update->texels_size(); ++i) {
    EXPECT_EQ(update->full_w(static_cast<int>(3 * update->texels(i))), update->w(3 * i));
    EXPECT_GE(update->w(3 * i), 0.0f);
    EXPECT_LE(update->w(3 * i), 1.0f);
  }

  // Every listed element states its own bound: a recomputed texel's follows
  // its rays' values (Chernoff's or the empirical Bernstein half-width, each
  // at half the risk: never wider than Hoeffding's at half the risk, and
  // tighter than Hoeffding's at the full risk where the values barely vary),
  // a refilled one's 1 (no sample of its own).
  ASSERT_EQ(update->w_error_size(), update->texels_size());
  ASSERT_EQ(update->triangle_w_error_size(), update->triangles_size());
  ASSERT_EQ(update->vertex_w_error_size(), update->vertices_size());
  EXPECT_EQ(update->accuracy().confidence(), 0.95);
  const double rays = static_cast<double>(update->rays_per_patch());
  const float hoeffding = static_cast<float>(std::sqrt(std::log(2.0 / (1.0 - 0.95)) / (2.0 * rays)));
  const float hoeffding_half_risk = static_cast<float>(std::sqrt(std::log(2.0 / 0.025) / (2.0 * rays)));
  int own = 0, tighter = 0;
  for (float e : update->w_error()) {
    EXPECT_TRUE(e == 1.0f || (e > 0.0f && e <= hoeffding_half_risk * (1 + 1e-6f))) << e << " vs " << hoeffding_half_risk;
    own += e < 1.0f;
    tighter += e < hoeffding;
  }
  EXPECT_GT(own, 0) << "the box's own patches are recomputed";
  EXPECT_GT(tighter, own / 4) << "most recomputed patches' rays barely vary";
  for (float e : update->triangle_w_error()) EXPECT_TRUE(e > 0.0f && e <= 1.0f) << e;
  for (float e : update->vertex_w_error()) EXPECT_TRUE(e > 0.0f && e <= 1.0f) << e;
  EXPECT_EQ(update->accuracy().parameters().at("texels_without_samples"), update->texels_size() - own);

  // The bounds hold against an independent reference: a ray-cast bake of
  // the moved scene with 4,096 rays a patch (its own half-width 0.021).
  v1::ComputeObscurancesRequest reference_request = bake_request;
  reference_request.set_method(v1::ComputeObscurancesRequest::RAYCAST);
  reference_request.clear_direction_count();
  reference_request.set_rays_per_patch(4096);
  reference_request.set_want_averages(true);
  reference_request.set_want_errors(true);
  auto reference = client_->ComputeObscurances(reference_request);
  ASSERT_TRUE(reference.ok()) << reference.status();
  int checked = 0, held = 0;
  for (int i = 0; i < update->texels_size(); ++i) {
    const uint32_t t = update->texels(i);
    if (update->w_error(i) >= 1.0f || reference->w_error[t] >= 1.0f) continue;
    ++checked;
    held += std::abs(update->w(3 * i) - reference->w[3 * t]) <= update->w_error(i) + reference->w_error[t];
  }
  int triangles_checked = 0, triangles_held = 0;
  for (int i = 0; i < update->triangles_size(); ++i) {
    const uint32_t t = update->triangles(i);
    if (update->triangle_w_error(i) >= 1.0f || reference->triangle_w_error[t] >= 1.0f) continue;
    ++triangles_checked;
    triangles_held += std::abs(update->triangle_w(3 * i) - reference->triangle_w[3 * t]) <=
                      update->triangle_w_error(i) + reference->triangle_w_error[t];
  }
  ASSERT_GT(checked, 0);
  // Each holds at 0.95 (both sides together at least 0.9); a few misses
  // among some dozens of elements are the confidence, not a fault.
  EXPECT_GE(held, 0.9 * checked) << held << " of " << checked << " texels";
  EXPECT_GE(triangles_held, 0.9 * triangles_checked) << triangles_held << " of " << triangles_checked << " triangles";
  RecordProperty("update_bounds", absl::StrCat(held, " of ", checked, " texels, ", triangles_held, " of ",
                                               triangles_checked, " triangles within both bounds"));

  // Nothing moved since: nothing to do.
  request.set_want_full_w(false);
  auto again = client_->UpdateObscurances(request);
  ASSERT_TRUE(again.ok()) << again.status();
  EXPECT_EQ(again->moves_applied(), 0u);
  EXPECT_EQ(again->texels_size(), 0);
  EXPECT_EQ(again->scene_version(), moved->version());
}

TEST_F(ObscuranceRpcTest, UpdateWithoutBakeFails) {
  v1::UpdateObscurancesRequest request;
  request.mutable_scene()->set_name(kBoundsScene);
  const Status status = client_->UpdateObscurances(request).status();
  EXPECT_EQ(status.code(), absl::StatusCode::kFailedPrecondition) << status;
  request.mutable_scene()->set_name("nope");
  EXPECT_EQ(client_->UpdateObscurances(request).status().code(), absl::StatusCode::kNotFound);
}

TEST_F(ObscuranceRpcTest, CancelledBakeStopsAndTheServerGoesOn) {
  // A bake far longer than the deadline: the server stops it between
  // directions, and the GPU is free for the next request at once.
  Client impatient(client::ClientOptions{.address = server_->address(), .deadline = std::chrono::milliseconds(300)});
  v1::ComputeObscurancesRequest big = SmallBake("cornell_box_visq");
  big.set_resolution(512);
  big.set_direction_count(100000);
  const auto start = std::chrono::steady_clock::now();
  const Status status = impatient.ComputeObscurances(big).status();
  EXPECT_EQ(status.code(), absl::StatusCode::kDeadlineExceeded) << status;
  auto next = client_->ComputeObscurances(SmallBake("cornell_box_visq"));
  ASSERT_TRUE(next.ok()) << next.status();
  EXPECT_LT(std::chrono::steady_clock::now() - start, std::chrono::seconds(20));
}

// The preview's camera: above the open front (z = +1) of the box, looking
// down at the back of the floor between the two boxes; the top rows look
// over the ceiling's front edge into empty space.
constexpr double kEye[3] = {0.0, 1.9, 3.0};
constexpr double kForward[3] = {0.0, -1.7, -4.0};
constexpr uint32_t kPreviewWidth = 160, kPreviewHeight = 120;
constexpr double kPreviewFov = 60.0;

v1::ObscurancePreviewRequest PreviewRequest(const std::string& scene) {
  v1::ObscurancePreviewRequest request;
  request.mutable_scene()->set_name(scene);
  auto set = [](const double (&v)[3], v1::Vec3* out) {
    out->set_x(v[0]);
    out->set_y(v[1]);
    out->set_z(v[2]);
  };
  set(kEye, request.mutable_camera_position());
  set(kForward, request.mutable_camera_forward());
  request.set_vertical_fov_deg(kPreviewFov);
  request.set_width(kPreviewWidth);
  request.set_height(kPreviewHeight);
  return request;
}

// The pixel (x, y from the top) that sees world point `p` under the
// preview's camera (up +y): an independent pinhole projection.
std::pair<uint32_t, uint32_t> PixelOf(const glm::dvec3& p) {
  const glm::dvec3 eye(kEye[0], kEye[1], kEye[2]);
  const glm::dvec3 f = glm::normalize(glm::dvec3(kForward[0], kForward[1], kForward[2]));
  const glm::dvec3 r = glm::normalize(glm::cross(f, glm::dvec3(0, 1, 0)));
  const glm::dvec3 u = glm::cross(r, f);
  const glm::dvec3 d = p - eye;
  const double tan_y = std::tan(kPreviewFov * std::numbers::pi / 360.0);
  const double aspect = double(kPreviewWidth) / kPreviewHeight;
  const double ndc_x = glm::dot(d, r) / (glm::dot(d, f) * tan_y * aspect);
  const double ndc_y = glm::dot(d, u) / (glm::dot(d, f) * tan_y);
  return {static_cast<uint32_t>((ndc_x + 1) / 2 * kPreviewWidth),
          static_cast<uint32_t>((1 - ndc_y) / 2 * kPreviewHeight)};
}

// Mean of the first channel over the 3 x 3 pixels around `p` (all covered).
double MeanAround(const client::ObscurancePreview& image, const glm::dvec3& p) {
  const auto [px, py] = PixelOf(p);
  double sum = 0;
  for (uint32_t y = py - 1; y <= py + 1; ++y)
    for (uint32_t x = px - 1; x <= px + 1; ++x) {
      const size_t i = size_t{y} * kPreviewWidth + x;
      EXPECT_EQ(image.covered[i], 1) << "pixel " << x << ", " << y;
      sum += image.rgb[3 * i];
    }
  return sum / 9;
}

TEST_F(ObscuranceRpcTest, PreviewShowsWAndNeedsACurrentBake) {
  // No bake yet: nothing to show.
  Status status = client_->RenderObscurancePreview(PreviewRequest(kPreviewScene)).status();
  EXPECT_EQ(status.code(), absl::StatusCode::kFailedPrecondition) << status;
  EXPECT_NE(std::string(status.message()).find("ComputeObscurances"), std::string::npos) << status;

  v1::ComputeObscurancesRequest bake_request = SmallBake(kPreviewScene);
  bake_request.set_resolution(64);
  bake_request.set_direction_count(32);
  auto bake = client_->ComputeObscurances(bake_request);
  ASSERT_TRUE(bake.ok()) << bake.status();
  ASSERT_TRUE(bake->figures.update_ready());

  auto preview = client_->RenderObscurancePreview(PreviewRequest(kPreviewScene));
  ASSERT_TRUE(preview.ok()) << preview.status();
  const auto& f = preview->figures;
  ASSERT_EQ(f.width(), kPreviewWidth);
  ASSERT_EQ(f.height(), kPreviewHeight);
  EXPECT_EQ(f.solution_version(), bake->figures.scene_version());
  EXPECT_EQ(f.quantity(), v1::ObscurancePreviewRequest::W);
  ASSERT_EQ(preview->rgb.size(), size_t{kPreviewWidth} * kPreviewHeight * 3);
  ASSERT_EQ(preview->covered.size(), size_t{kPreviewWidth} * kPreviewHeight);
  size_t covered = 0;
  for (size_t i = 0; i < preview->covered.size(); ++i) {
    if (preview->covered[i]) {
      ++covered;
      for (int c = 0; c < 3; ++c) {
        EXPECT_GE(preview->rgb[3 * i + c], 0.0f) << "pixel " << i;
        EXPECT_LE(preview->rgb[3 * i + c], 1.0f) << "pixel " << i;
      }
    } else {
      for (int c = 0; c < 3; ++c) EXPECT_EQ(preview->rgb[3 * i + c], 0.0f) << "background pixel " << i;
    }
  }
  EXPECT_GT(covered, preview->covered.size() / 3) << "the box fills much of the view";
  // The top row looks 7 degrees up from 0.1 under the ceiling's height,
  // crossing that height 2.2 in front of the box: empty space.
  for (uint32_t x = 0; x < kPreviewWidth; ++x) EXPECT_EQ(preview->covered[x], 0) << "top row, column " << x;

  // Open floor in front of the tall box against the floor / back-wall
  // corner between the boxes (seen through the gap between them): the
  // corner is obscured.
  const double open_floor = MeanAround(*preview, {-0.5, 0.0, 0.6});
  const double corner = MeanAround(*preview, {0.0, 0.0, -1.0});
  EXPECT_GT(open_floor, corner + 0.05) << "open floor W " << open_floor << ", corner W " << corner;

  // The intensity: I = R I_A W, non-negative, same coverage.
  v1::ObscurancePreviewRequest intensity_request = PreviewRequest(kPreviewScene);
  intensity_request.set_quantity(v1::ObscurancePreviewRequest::INTENSITY);
  auto intensity = client_->RenderObscurancePreview(intensity_request);
  ASSERT_TRUE(intensity.ok()) << intensity.status();
  EXPECT_EQ(intensity->figures.quantity(), v1::ObscurancePreviewRequest::INTENSITY);
  EXPECT_EQ(intensity->covered, preview->covered);
  for (float v : intensity->rgb) ASSERT_GE(v, 0.0f);

  // A move makes a version the solution does not match until the update.
  v1::SetNodeTransformRequest move;
  move.mutable_scene()->set_name(kPreviewScene);
  move.set_node_name("short_box");
  for (double v : Translation(-0.05, 0, 0.2)) move.add_world_matrix(v);
  auto moved = client_->SetNodeTransform(move);
  ASSERT_TRUE(moved.ok()) << moved.status();
  status = client_->RenderObscurancePreview(PreviewRequest(kPreviewScene)).status();
  EXPECT_EQ(status.code(), absl::StatusCode::kFailedPrecondition) << status;
  EXPECT_NE(std::string(status.message()).find("UpdateObscurances"), std::string::npos) << status;
  v1::UpdateObscurancesRequest update;
  update.mutable_scene()->set_name(kPreviewScene);
  auto updated = client_->UpdateObscurances(update);
  ASSERT_TRUE(updated.ok()) << updated.status();
  auto after = client_->RenderObscurancePreview(PreviewRequest(kPreviewScene));
  ASSERT_TRUE(after.ok()) << after.status();
  EXPECT_EQ(after->figures.solution_version(), moved->version());

  // The CLI writes the picture.
  testing::ScratchDir out;
  const std::filesystem::path png = out.path() / "preview.png";
  const std::string command = std::string(VISQ_CLI_BINARY) + " obscurance-preview " + kPreviewScene +
                              " --camera-position 0,1.9,3 --camera-forward 0,-1.7,-4 --width 160 --height 120" +
                              " --quantity w --json --png " + png.string() + " --server " + server_->address();
  int exit_status = 0;
  const std::string output = testing::RunCommand(command, &exit_status);
  ASSERT_EQ(exit_status, 0) << output;
  EXPECT_NE(output.find("covered_pixels"), std::string::npos) << output;
  ASSERT_TRUE(std::filesystem::exists(png)) << output;
  EXPECT_GT(std::filesystem::file_size(png), 100u);
}

// The bake put on the mesh: the exported UVs, applied to the W atlas,
// give back every triangle's W, and the exported glTF carries those UVs
// and W on the scene's own geometry. A real scene (Kenney's palm: thin
// fronds, node TRS with non-uniform scale) with an atlas the server built.
TEST_F(ObscuranceRpcTest, ExportedUvsAndGltfPutTheBakeOnTheMesh) {
  VISQ_REQUIRE_SHARED_SCENES(scenes);
  const std::filesystem::path palm = scenes / "tree_kenney/tree_palmDetailedTall.glb";
  ASSERT_TRUE(client_->UploadScene(palm, "palm_export", /*replace=*/true).ok());
  v1::ExportObscurancesRequest request;
  request.mutable_scene()->set_name("palm_export");
  request.set_want_atlas_uvs(true);
  request.set_want_gltf(true);
  Status before = client_->ExportObscurances(request).status();
  EXPECT_EQ(before.code(), absl::StatusCode::kFailedPrecondition) << before;

  v1::ComputeObscurancesRequest bake_request = SmallBake("palm_export");
  bake_request.set_resolution(128);
  bake_request.set_direction_count(16);
  bake_request.set_d_max(0.5);
  bake_request.set_want_averages(true);
  auto bake = client_->ComputeObscurances(bake_request);
  ASSERT_TRUE(bake.ok()) << bake.status();
  auto exported = client_->ExportObscurances(request);
  ASSERT_TRUE(exported.ok()) << exported.status();
  const auto& f = exported->figures;
  const uint32_t width = f.width(), height = f.height();
  ASSERT_EQ(width, bake->figures.atlas().width());
  ASSERT_EQ(height, bake->figures.atlas().height());
  EXPECT_FALSE(f.from_lightmap_uvs());
  const size_t triangles = f.triangles();
  ASSERT_EQ(triangles, 336u);
  ASSERT_EQ(exported->atlas_uv.size(), 6 * triangles);
  ASSERT_EQ(bake->triangle_w.size(), 3 * triangles);

  // W over each triangle's UV triangle (a barycentric grid, nearest texel)
  // is its texels' mean, and the bake's triangle_w the mean of the samples on
  // the triangle itself: two estimates of the triangle's W that differ by
  // their noise and by what the texels it shares with its neighbours mix in,
  // well within the stated bound, and close on average (UVs that put the
  // texels anywhere else would be far off).
  const std::vector<float>& uv = exported->atlas_uv;
  const double bound = bake->figures.accuracy().error_bound();
  double worst = 0, mean = 0;
  size_t beyond = 0;
  for (size_t t = 0; t < triangles; ++t) {
    constexpr int kSteps = 40;
    double sum = 0;
    int samples = 0;
    for (int i = 0; i < kSteps; ++i)
      for (int j = 0; i + j < kSteps; ++j) {
        const double a = (i + 1.0 / 3.0) / kSteps, b = (j + 1.0 / 3.0) / kSteps, c = 1.0 - a - b;
        const double u = a * uv[6 * t] + b * uv[6 * t + 2] + c * uv[6 * t + 4];
        const double v = a * uv[6 * t + 1] + b * uv[6 * t + 3] + c * uv[6 * t + 5];
        const uint32_t x = std::min<uint32_t>(width - 1, static_cast<uint32_t>(u * width));
        const uint32_t y = std::min<uint32_t>(height - 1, static_cast<uint32_t>(v * height));
        sum += bake->w[3 * (size_t(y) * width + x)];
        ++samples;
      }
    const double difference = std::abs(sum / samples - bake->triangle_w[3 * t]);
    worst = std::max(worst, difference);
    mean += difference / triangles;
    beyond += difference > bound;
  }
  std::printf("W through the exported UVs against triangle_w: mean %.4f, worst %.4f, %zu of %zu beyond %.4f\n", mean,
              worst, beyond, triangles, bound);
  EXPECT_LT(mean, 0.02) << "W sampled through the exported UVs against triangle_w";
  EXPECT_LE(beyond, triangles / 20) << "W sampled through the exported UVs against triangle_w";
  RecordProperty("w_through_uvs_max_error", std::to_string(worst));

  // The glTF: the scene's geometry, indexed, with the UVs as TEXCOORD_1
  // (after the palm's own TEXCOORD_0) and W as the occlusion texture; its
  // validity and the trip into Blender are tests/gltf_export's.
  testing::ScratchDir dir;
  const std::filesystem::path glb = dir.path() / "baked.glb";
  std::ofstream(glb, std::ios::binary)
      .write(reinterpret_cast<const char*>(exported->glb.data()), static_cast<std::streamsize>(exported->glb.size()));
  StatusOr<Scene> baked = LoadGltfFile(glb);
  ASSERT_TRUE(baked.ok()) << baked.status();
  StatusOr<Scene> original = LoadGltfFile(palm);
  ASSERT_TRUE(original.ok()) << original.status();
  ASSERT_EQ(baked->triangles.size(), triangles);
  ASSERT_EQ(baked->lightmap_uvs.size(), baked->positions.size());
  double position_error = 0, uv_error = 0;
  for (size_t t = 0; t < triangles; ++t)
    for (int c = 0; c < 3; ++c) {
      const uint32_t v = baked->triangles[t][c];
      position_error = std::max(position_error, glm::length(baked->positions[v] - original->Vertex(t, c)));
      uv_error = std::max(uv_error, double(glm::length(baked->lightmap_uvs[v] -
                                                       glm::vec2(uv[6 * t + 2 * c], uv[6 * t + 2 * c + 1]))));
    }
  EXPECT_LT(position_error, 1e-5);  // float32 accessors
  EXPECT_EQ(uv_error, 0.0);

  const std::string bytes(exported->glb.begin(), exported->glb.end());
  uint32_t json_length = 0;
  std::memcpy(&json_length, bytes.data() + 12, 4);
  const nlohmann::json doc = nlohmann::json::parse(bytes.substr(20, json_length));
  for (const auto& material : doc["materials"]) {
    EXPECT_EQ(material["occlusionTexture"]["index"], 0);
    EXPECT_EQ(material["occlusionTexture"]["texCoord"], 1);
  }
  const auto& view = doc["bufferViews"][doc["images"][0]["bufferView"].get<size_t>()];
  const size_t bin = 20 + json_length + 8;
  int png_width = 0, png_height = 0, channels = 0;
  unsigned char* pixels = stbi_load_from_memory(
      reinterpret_cast<const unsigned char*>(bytes.data() + bin + view.value("byteOffset", 0)),
      view["byteLength"].get<int>(), &png_width, &png_height, &channels, 3);
  ASSERT_NE(pixels, nullptr);
  ASSERT_EQ(png_width, int(width));
  ASSERT_EQ(png_height, int(height));
  size_t differing = 0;
  for (size_t i = 0; i < size_t(width) * height * 3; ++i)
    differing += pixels[i] != std::lround(std::clamp(bake->w[i], 0.0f, 1.0f) * 255.0f);
  stbi_image_free(pixels);
  EXPECT_EQ(differing, 0u) << "the PNG is W in 8 bits, row 0 on top";

  // The CLI writes the same glTF, and the UVs as a (triangles, 3, 2) array.
  const std::filesystem::path cli_glb = dir.path() / "cli.glb", cli_uv = dir.path() / "uv.npy";
  int exit_status = 0;
  const std::string output = testing::RunCommand(std::string(VISQ_CLI_BINARY) + " obscurance-export palm_export --gltf " +
                                                     cli_glb.string() + " --uv-npy " + cli_uv.string() + " --server " +
                                                     server_->address(),
                                                 &exit_status);
  ASSERT_EQ(exit_status, 0) << output;
  std::ifstream cli_in(cli_glb, std::ios::binary);
  EXPECT_EQ(std::string(std::istreambuf_iterator<char>(cli_in), {}), bytes);
  std::ifstream npy(cli_uv, std::ios::binary);
  const std::string npy_bytes(std::istreambuf_iterator<char>(npy), {});
  EXPECT_NE(npy_bytes.find("'shape': (336, 3, 2)"), std::string::npos) << npy_bytes.substr(0, 128);

  // Asking for nothing is refused by the fields.
  v1::ExportObscurancesRequest nothing;
  nothing.mutable_scene()->set_name("palm_export");
  Status refused = client_->ExportObscurances(nothing).status();
  EXPECT_EQ(refused.code(), absl::StatusCode::kInvalidArgument) << refused;
  EXPECT_NE(std::string(refused.message()).find("want_atlas_uvs"), std::string::npos) << refused;
  // Vertex colours colour the glb, and are refused without it.
  v1::ExportObscurancesRequest colours_alone;
  colours_alone.mutable_scene()->set_name("palm_export");
  colours_alone.set_want_atlas_uvs(true);
  colours_alone.set_want_vertex_colors(true);
  refused = client_->ExportObscurances(colours_alone).status();
  EXPECT_EQ(refused.code(), absl::StatusCode::kInvalidArgument) << refused;
  EXPECT_NE(std::string(refused.message()).find("want_vertex_colors"), std::string::npos) << refused;
}

TEST_F(ObscuranceRpcTest, PreviewRejectsABadCamera) {
  v1::ObscurancePreviewRequest nan = PreviewRequest("cornell_box_visq");
  nan.mutable_camera_position()->set_y(std::nan(""));
  Status status = client_->RenderObscurancePreview(nan).status();
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument) << status;
  EXPECT_NE(std::string(status.message()).find("camera.position"), std::string::npos) << status;

  v1::ObscurancePreviewRequest fov = PreviewRequest("cornell_box_visq");
  fov.set_vertical_fov_deg(180);
  status = client_->RenderObscurancePreview(fov).status();
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument) << status;
  EXPECT_NE(std::string(status.message()).find("vertical_fov_deg"), std::string::npos) << status;

  v1::ObscurancePreviewRequest huge = PreviewRequest("cornell_box_visq");
  huge.set_width(100000);
  EXPECT_EQ(client_->RenderObscurancePreview(huge).status().code(), absl::StatusCode::kResourceExhausted);

  v1::ObscurancePreviewRequest parallel = PreviewRequest("cornell_box_visq");
  parallel.mutable_camera_up()->set_y(-1.7);
  parallel.mutable_camera_up()->set_z(-4.0);
  status = client_->RenderObscurancePreview(parallel).status();
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument) << status;
  EXPECT_NE(std::string(status.message()).find("camera.up"), std::string::npos) << status;
}

TEST_F(ObscuranceRpcTest, BadInput) {
  v1::ComputeObscurancesRequest zero = SmallBake("cornell_box_visq");
  zero.set_d_max(0);
  Status status = client_->ComputeObscurances(zero).status();
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(std::string(status.message()).find("d_max"), std::string::npos) << status;
  v1::ComputeObscurancesRequest range = SmallBake("cornell_box_visq");
  range.set_total_directions(4);
  EXPECT_EQ(client_->ComputeObscurances(range).status().code(), absl::StatusCode::kInvalidArgument);

  v1::SetNodeTransformRequest unknown;
  unknown.mutable_scene()->set_name(kBoundsScene);
  unknown.set_node_name("no_such_node");
  for (double v : Translation(0, 0, 0)) unknown.add_world_matrix(v);
  status = client_->SetNodeTransform(unknown).status();
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(std::string(status.message()).find("node_name"), std::string::npos) << status;

  v1::SetNodeTransformRequest nan = unknown;
  nan.set_node_name("short_box");
  nan.set_world_matrix(13, std::nan(""));
  status = client_->SetNodeTransform(nan).status();
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(std::string(status.message()).find("world_matrix[13]"), std::string::npos) << status;

  v1::SetNodeTransformRequest singular = unknown;
  singular.set_node_name("short_box");
  singular.set_world_matrix(0, 0);
  status = client_->SetNodeTransform(singular).status();
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(std::string(status.message()).find("invertible"), std::string::npos) << status;

  v1::SetNodeTransformRequest short_matrix = unknown;
  short_matrix.set_node_name("short_box");
  short_matrix.mutable_world_matrix()->RemoveLast();
  EXPECT_EQ(client_->SetNodeTransform(short_matrix).status().code(), absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace visq
