// The obscurance RPCs end to end through the real server and client, on the
// generated Cornell box: the bake's range, progress and determinism, the
// client's shard merge against the whole bake, node moves and the update,
// and bad input.
#include <chrono>
#include <cmath>
#include <cstring>
#include <set>

#include <gtest/gtest.h>

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

using testing::Translation;

class ObscuranceRpcTest : public testing::SharedServerSuite<ObscuranceRpcTest> {
 public:
  // Two stored copies of the Cornell box: one to move, one to measure bounds.
  static void PrepareRepository(const std::filesystem::path& repo) {
    for (const char* name : {kBoundsScene, kUpdateScene}) {
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
    return request;
  }
};

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
  EXPECT_EQ(moved->version(), before->version() + 1);
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
