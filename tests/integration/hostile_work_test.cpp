// Work that used to allocate before it counted itself against
// --max-work-bytes (issue 45, section 3): the obscurance atlas, the
// obscurance preview, Transmittance and LightVisibility with polygons. The
// real visq-server on loopback, scenes written by the test, and the
// server's own peak memory read from /proc.
#include <chrono>
#include <cmath>
#include <cstring>
#include <fstream>
#include <sstream>
#include <string>
#include <thread>

#include <unistd.h>

#include <gtest/gtest.h>

#include "proto_builders.h"
#include "server_process.h"
#include "test_support.h"
#include "visq/v1/visq.pb.h"
#include "visq_client.h"

namespace visq {
namespace {

using client::Client;
using testing::ScratchDir;
using testing::ServerProcess;

// `count` unit quads, one node each, 1.5 apart in y, every one covering the
// whole lightmap ([0, 1]^2 in TEXCOORD_1): each quad's two triangles meet
// every texel of the atlas, at any resolution. About 1.3 KB of glTF for
// four.
std::filesystem::path WriteFullUvQuads(const std::filesystem::path& dir, int count) {
  const float positions[12] = {0, 0, 0, 1, 0, 0, 1, 0, 1, 0, 0, 1};
  const float uvs[8] = {0, 0, 1, 0, 1, 1, 0, 1};
  const uint16_t indices[6] = {0, 2, 1, 0, 3, 2};  // facing +y
  std::string bin(sizeof(positions) + sizeof(uvs) + sizeof(indices), '\0');
  std::memcpy(bin.data(), positions, sizeof(positions));
  std::memcpy(bin.data() + sizeof(positions), uvs, sizeof(uvs));
  std::memcpy(bin.data() + sizeof(positions) + sizeof(uvs), indices, sizeof(indices));
  std::ofstream(dir / "quads.bin", std::ios::binary) << bin;
  std::string nodes, node_list;
  for (int i = 0; i < count; ++i) {
    std::ostringstream node;
    node << (i ? "," : "") << R"({"mesh":0,"name":"quad)" << i << R"(","translation":[0,)" << 1.5 * i << ",0]}";
    nodes += node.str();
    node_list += (i ? "," : "");
    node_list += std::to_string(i);
  }
  std::ofstream(dir / "quads.gltf")
      << R"({"asset":{"version":"2.0"},"scene":0,"scenes":[{"nodes":[)" << node_list << R"(]}],"nodes":[)" << nodes
      << R"(],"meshes":[{"primitives":[{"attributes":{"POSITION":0,"TEXCOORD_1":1},"indices":2}]}],
  "buffers":[{"uri":"quads.bin","byteLength":)"
      << bin.size() << R"(}],
  "bufferViews":[{"buffer":0,"byteOffset":0,"byteLength":48},{"buffer":0,"byteOffset":48,"byteLength":32},
                 {"buffer":0,"byteOffset":80,"byteLength":12}],
  "accessors":[{"bufferView":0,"componentType":5126,"count":4,"type":"VEC3","min":[0,0,0],"max":[1,0,1]},
               {"bufferView":1,"componentType":5126,"count":4,"type":"VEC2"},
               {"bufferView":2,"componentType":5123,"count":6,"type":"SCALAR"}]})";
  return dir / "quads.gltf";
}

// The server's resident and peak resident memory (VmRSS, VmHWM), bytes.
struct Memory {
  uint64_t rss = 0, peak = 0;
};
Memory MemoryOf(int pid) {
  std::ifstream status("/proc/" + std::to_string(pid) + "/status");
  Memory m;
  for (std::string line; std::getline(status, line);) {
    std::istringstream in(line);
    std::string key;
    uint64_t kb = 0;
    in >> key >> kb;
    if (key == "VmRSS:") m.rss = kb * 1024;
    if (key == "VmHWM:") m.peak = kb * 1024;
  }
  return m;
}

// Starts the server's peak resident memory (VmHWM) again from its resident
// memory now (Linux's clear_refs, value 5).
void ResetPeakMemory(int pid) { std::ofstream("/proc/" + std::to_string(pid) + "/clear_refs") << "5"; }

// The server's CPU time so far (user and system), seconds.
double CpuSecondsOf(int pid) {
  std::ifstream stat("/proc/" + std::to_string(pid) + "/stat");
  std::string all((std::istreambuf_iterator<char>(stat)), std::istreambuf_iterator<char>());
  std::istringstream in(all.substr(all.rfind(')') + 2));  // after "pid (comm) "
  std::string field;
  double ticks = 0;
  for (int i = 3; i <= 15 && in >> field; ++i)
    if (i == 14 || i == 15) ticks += std::stod(field);
  return ticks / double(sysconf(_SC_CLK_TCK));
}

double SecondsSince(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
}

v1::ComputeObscurancesRequest Bake(const std::string& scene, uint32_t resolution) {
  v1::ComputeObscurancesRequest request;
  request.mutable_scene()->set_name(scene);
  request.set_resolution(resolution);
  request.set_d_max(1.0);
  request.set_direction_count(4);
  return request;
}

void Set(v1::Vec3* v, double x, double y, double z) {
  v->set_x(x);
  v->set_y(y);
  v->set_z(z);
}

constexpr uint64_t kBudget = 32'000'000;
constexpr uint64_t kMiB = uint64_t{1} << 20;
// Holds a 512^2 ray-cast bake of two full-UV quads (about 100 MB) but not
// its updater and an update together (about 190 MB).
constexpr uint64_t kUpdateBudget = 140 * kMiB;

class HostileWork : public ::testing::Test {
 protected:
  void SetUp() override {
    server_ = ServerProcess::Start(
        {repo_.path(), {"--seed-samples", "--max-work-bytes", std::to_string(kBudget)}});
    ASSERT_NE(server_, nullptr);
    client_ = std::make_unique<Client>(client::ClientOptions{.address = server_->address()});
  }

  // RESOURCE_EXHAUSTED naming the budget's flag and `field`, well under a
  // second, and the server's peak memory grown by less than `most` (the
  // request's own parse included).
  template <typename Call>
  void ExpectRefusedBeforeWork(const std::string& field, Call call, uint64_t most = 64 * kMiB) {
    const Memory before = MemoryOf(server_->pid());
    const auto start = std::chrono::steady_clock::now();
    const Status status = call();
    const double seconds = SecondsSince(start);
    const Memory after = MemoryOf(server_->pid());
    EXPECT_EQ(status.code(), absl::StatusCode::kResourceExhausted) << status;
    EXPECT_NE(std::string(status.message()).find("--max-work-bytes"), std::string::npos) << status;
    EXPECT_NE(std::string(status.message()).find(field), std::string::npos) << status;
    EXPECT_LT(seconds, 0.5) << status;
    EXPECT_LT(after.peak, std::max(before.peak, before.rss + most))
        << "peak RSS " << before.peak << " -> " << after.peak << " bytes";
    std::cout << "[ refused  ] " << field << " in " << seconds << " s, peak RSS " << before.peak / kMiB << " -> "
              << after.peak / kMiB << " MiB: " << status.message() << "\n";
  }

  ScratchDir repo_;
  ScratchDir files_;
  std::unique_ptr<ServerProcess> server_;
  std::unique_ptr<Client> client_;
};

// Four full-UV quads (a 1.3 KB .gltf) at 4096^2 are 67M triangle-texel
// fragments: the atlas cost 2.2 GB and 24 CPU-s before the bake's refusal.
// Now its bound is found from the UVs and refused before any fragment
// exists, whichever path builds it (the method's probes, a chosen method,
// a built atlas); a small atlas of the same scene still bakes.
TEST_F(HostileWork, ObscuranceAtlasBeyondTheBudgetIsRefusedBeforeItIsBuilt) {
  ASSERT_TRUE(client_->UploadScene(WriteFullUvQuads(files_.path(), 4), "quads").ok());
  for (auto method : {v1::ComputeObscurancesRequest::METHOD_UNSPECIFIED, v1::ComputeObscurancesRequest::RAYCAST,
                      v1::ComputeObscurancesRequest::DEPTH_PEELING}) {
    for (bool built : {false, true}) {
      SCOPED_TRACE(::testing::Message() << "method " << method << (built ? ", built atlas" : ", TEXCOORD_1"));
      v1::ComputeObscurancesRequest big = Bake("quads", 4096);
      big.set_method(method);
      big.set_force_built_atlas(built);
      ExpectRefusedBeforeWork("resolution", [&] { return client_->ComputeObscurances(big).status(); });
    }
  }
  v1::ComputeObscurancesRequest small = Bake("quads", 32);
  auto baked = client_->ComputeObscurances(small);
  ASSERT_TRUE(baked.ok()) << baked.status();
  EXPECT_TRUE(baked->figures.atlas().from_lightmap_uvs());
}

// A legal but large atlas (four full-UV quads at 4096^2 under the default
// budget) ran 30 s past a 2 s deadline; now the build asks the call between
// rows of texels and stops within about a second of the deadline.
TEST(HostileWorkDeadline, DeadlineStopsALargeObscuranceAtlasBuild) {
  ScratchDir repo, files;
  // The ray-cast bake reserves about 7.5 GB for what it would hold after the
  // atlas (its batches, the updater, the answer): a budget of its own, so
  // that a machine with less memory than that does not refuse it before the
  // atlas, whose build, stopped by the deadline, is what this test watches.
  auto server = ServerProcess::Start({repo.path(), {"--max-work-bytes", std::to_string(uint64_t{16} << 30)}});
  ASSERT_NE(server, nullptr);
  Client uploader({.address = server->address()});
  ASSERT_TRUE(uploader.UploadScene(WriteFullUvQuads(files.path(), 4), "quads").ok());
  Client impatient({.address = server->address(), .deadline = std::chrono::seconds(2)});
  for (auto method : {v1::ComputeObscurancesRequest::RAYCAST, v1::ComputeObscurancesRequest::METHOD_UNSPECIFIED}) {
    SCOPED_TRACE(::testing::Message() << "method " << method);
    v1::ComputeObscurancesRequest big = Bake("quads", 4096);
    big.set_method(method);
    const auto start = std::chrono::steady_clock::now();
    const Status status = impatient.ComputeObscurances(big).status();
    const double seconds = SecondsSince(start);
    EXPECT_EQ(status.code(), absl::StatusCode::kDeadlineExceeded) << status;
    EXPECT_LT(seconds, 3.0) << status;
    // Nothing goes on after the answer: from a second after it, the
    // server is idle (a build going on would burn a core's second).
    std::this_thread::sleep_for(std::chrono::seconds(1));
    const double cpu_before = CpuSecondsOf(server->pid());
    std::this_thread::sleep_for(std::chrono::seconds(1));
    const double cpu_after = CpuSecondsOf(server->pid());
    std::cout << "[ deadline ] 2 s deadline answered at " << seconds << " s (" << status.message()
              << "); CPU a second later: " << cpu_after - cpu_before << " s in 1 s\n";
    EXPECT_LT(cpu_after - cpu_before, 0.3) << "the build went on past the deadline";
  }
  // What stopped was the atlas's build (the server logs the call's end).
  EXPECT_NE(server->Log().find("obscurance atlas, "), std::string::npos) << server->Log();
  // The server is free again: a small bake answers.
  v1::ComputeObscurancesRequest small = Bake("quads", 16);
  small.set_method(v1::ComputeObscurancesRequest::RAYCAST);
  EXPECT_TRUE(uploader.ComputeObscurances(small).ok());
}

v1::ComputeObscurancesRequest RaycastBake(const std::string& scene, uint32_t resolution, uint32_t rays) {
  v1::ComputeObscurancesRequest request = Bake(scene, resolution);
  request.set_method(v1::ComputeObscurancesRequest::RAYCAST);
  request.set_rays_per_patch(rays);
  return request;
}

// A ray-cast bake traced its rays in batches of 4,096 texels whatever
// rays_per_patch was, and reserved only its per-texel arrays: not the
// batches, nor the updater a whole bake leaves behind, nor the answer's
// bounds and copies. At 64^2 and 2,048 rays a patch (two full-UV quads,
// one batch of 8.4M rays) the server's peak grew by 1,090 MiB under a
// 256 MiB budget. Now a batch holds about 65,536 rays, and what the bake
// holds is reserved before it starts: the peak grows by less than the
// budget plus a slack for the process's own (thread stacks, malloc's
// arenas, the answer's messages in gRPC).
TEST(HostileWorkBudget, RaycastBakeStaysWithinItsReservation) {
  constexpr uint64_t kBudgetBytes = 256 * kMiB, kSlack = 64 * kMiB;
  ScratchDir repo, files;
  auto server = ServerProcess::Start({repo.path(), {"--max-work-bytes", std::to_string(kBudgetBytes)}});
  ASSERT_NE(server, nullptr);
  Client client({.address = server->address()});
  ASSERT_TRUE(client.UploadScene(WriteFullUvQuads(files.path(), 2), "quads").ok());
  ResetPeakMemory(server->pid());
  const Memory before = MemoryOf(server->pid());
  const auto start = std::chrono::steady_clock::now();
  auto baked = client.ComputeObscurances(RaycastBake("quads", 64, 2048));
  const double seconds = SecondsSince(start);
  ASSERT_TRUE(baked.ok()) << baked.status();
  const Memory after = MemoryOf(server->pid());
  const uint64_t growth = after.peak > before.rss ? after.peak - before.rss : 0;
  std::cout << "[ measured ] 64^2 x 2048 rays in " << seconds << " s: peak RSS grew by " << growth / kMiB
            << " MiB (budget " << kBudgetBytes / kMiB << " MiB, slack " << kSlack / kMiB << " MiB)\n";
  EXPECT_LT(growth, kBudgetBytes + kSlack);
  EXPECT_EQ(baked->figures.estimated_texels(), 64u * 64u);
}

// UpdateObscurances took no reservation, though its moves' merged changes,
// its answer and its candidate search may hold every texel of the bake's
// atlas. Now it reserves that before its first move, beside what the
// bake's updater keeps for as long as it lives (a lasting reservation,
// which a request does not wait for): under a budget that holds the bake
// but not the bake's updater and an update together, the update is
// refused at once by name, and after a smaller bake (whose updater
// replaces the first) an update answers.
TEST(HostileWorkBudget, ObscuranceUpdateBeyondTheBudgetIsRefused) {
  ScratchDir repo, files;
  auto server = ServerProcess::Start({repo.path(), {"--max-work-bytes", std::to_string(kUpdateBudget)}});
  ASSERT_NE(server, nullptr);
  Client client({.address = server->address()});
  ASSERT_TRUE(client.UploadScene(WriteFullUvQuads(files.path(), 2), "quads").ok());
  double update_seconds = 0;
  auto update_after_bake = [&](uint32_t resolution) {
    auto baked = client.ComputeObscurances(RaycastBake("quads", resolution, 16));
    EXPECT_TRUE(baked.ok()) << baked.status();
    if (!baked.ok()) return Status(baked.status());
    EXPECT_TRUE(baked->figures.update_ready());
    v1::SetNodeTransformRequest move;
    move.mutable_scene()->set_name("quads");
    move.set_node_name("quad1");
    for (double v : testing::Translation(0.1, 1.5, 0)) move.add_world_matrix(v);
    EXPECT_TRUE(client.SetNodeTransform(move).ok());
    v1::UpdateObscurancesRequest update;
    update.mutable_scene()->set_name("quads");
    const auto start = std::chrono::steady_clock::now();
    const Status status = client.UpdateObscurances(update).status();
    update_seconds = SecondsSince(start);
    return status;
  };
  const Status refused = update_after_bake(512);
  std::cout << "[ refused  ] update after a 512^2 bake, in " << update_seconds << " s: " << refused.message()
            << "\n";
  EXPECT_EQ(refused.code(), absl::StatusCode::kResourceExhausted) << refused;
  EXPECT_NE(std::string(refused.message()).find("--max-work-bytes"), std::string::npos) << refused;
  EXPECT_LT(update_seconds, 0.5);
  const Status small = update_after_bake(64);
  EXPECT_TRUE(small.ok()) << small;
}

// What a ray-cast bake holds grows with rays_per_patch (a sampler per ray
// on each thread that makes a patch's rays) and with the atlas (the
// updater's patch balls, index and tallies, its copies of the scene and
// the result): a bake whose whole is beyond the budget is refused before
// its atlas exists, naming the flag and the fields. One full-UV quad at
// 256^2 and 16,384 rays a patch was accepted on its per-texel arrays
// alone (about 10 MB of this 32 MB budget), to trace batches of 4,096
// texels' rays: 67M rays, some 8.8 GB.
TEST_F(HostileWork, RaycastBakeBeyondTheBudgetIsRefusedBeforeItStarts) {
  ASSERT_TRUE(client_->UploadScene(WriteFullUvQuads(files_.path(), 1), "quad").ok());
  ExpectRefusedBeforeWork("rays_per_patch",
                          [&] { return client_->ComputeObscurances(RaycastBake("quad", 256, 16384)).status(); });
  auto small = client_->ComputeObscurances(RaycastBake("quad", 32, 64));
  ASSERT_TRUE(small.ok()) << small.status();
}

// RenderObscurancePreview at 4096^2 held about 0.8 GB unreserved (the GL
// target, its read-back and the answer): now reserved before the copies,
// and refused when it could never fit; a small one still renders.
TEST_F(HostileWork, ObscurancePreviewBeyondTheBudgetIsRefused) {
  ASSERT_TRUE(client_->UploadScene(WriteFullUvQuads(files_.path(), 2), "quads").ok());
  v1::ComputeObscurancesRequest bake = Bake("quads", 32);
  bake.set_method(v1::ComputeObscurancesRequest::RAYCAST);
  ASSERT_TRUE(client_->ComputeObscurances(bake).ok());
  v1::ObscurancePreviewRequest request;
  request.mutable_scene()->set_name("quads");
  Set(request.mutable_camera_position(), 0.5, 5, 3);
  Set(request.mutable_camera_forward(), 0, -1, -0.5);
  request.set_width(4096);
  request.set_height(4096);
  ExpectRefusedBeforeWork("width x height", [&] { return client_->RenderObscurancePreview(request).status(); });
  request.set_width(64);
  request.set_height(48);
  auto small = client_->RenderObscurancePreview(request);
  ASSERT_TRUE(small.ok()) << small.status();
  EXPECT_EQ(small->rgb.size(), 64u * 48u * 3u);
}

// Transmittance for a 4096^2 receiver added 669 MB unreserved; now refused
// by name; a small receiver still answers.
TEST_F(HostileWork, TransmittanceBeyondTheBudgetIsRefused) {
  v1::TransmittanceRequest request;
  request.mutable_scene()->set_name("cornell_box_visq");
  request.set_light_kind(v1::TransmittanceRequest::DIRECTIONAL);
  Set(request.mutable_light_direction(), 0, -1, 0);
  auto* absorber = request.add_absorbers();
  absorber->set_node("short_box");
  absorber->set_absorption(2.0);
  Set(request.mutable_receiver()->mutable_origin(), -0.999, 0.001, -0.999);
  Set(request.mutable_receiver()->mutable_edge_u(), 1.998, 0, 0);
  Set(request.mutable_receiver()->mutable_edge_v(), 0, 0, 1.998);
  request.set_receiver_width(4096);
  request.set_receiver_height(4096);
  ExpectRefusedBeforeWork("receiver_width x receiver_height",
                          [&] { return client_->Transmittance(request).status(); });
  request.set_receiver_width(16);
  request.set_receiver_height(16);
  auto small = client_->Transmittance(request);
  ASSERT_TRUE(small.ok()) << small.status();
  EXPECT_EQ(small->transmittance_size(), 256);
}

// LightVisibility with polygons for 200,000 points added 100 MB
// unreserved, and a light of 1,024 vertices makes each visible polygon
// 24 KB: 10,000 points in the open were 0.25 GB of polygons and more as
// messages. Now the answers' bound is reserved first and refused by name
// when it could never fit; a small batch still answers.
TEST_F(HostileWork, LightVisibilityPolygonsBeyondTheBudgetAreRefused) {
  auto light = [](int vertices) {
    v1::LightVisibilityRequest request;
    request.mutable_scene()->set_name("cornell_box_visq");
    // Counter-clockwise from below: it shines down.
    for (int k = 0; k < vertices; ++k) {
      const double a = 2.0 * 3.14159265358979 * (k + 0.5) / vertices + 3.14159265358979 * 1.25;
      Set(request.mutable_light()->add_vertices(), 0.35 * std::cos(a), 1.99, 0.35 * std::sin(a));
    }
    request.set_want_polygons(true);
    return request;
  };
  // side x side points over the floor's open front strip.
  auto add_points = [](v1::LightVisibilityRequest& request, int side) {
    for (int i = 0; i < side; ++i)
      for (int j = 0; j < side; ++j) {
        auto* p = request.add_points();
        Set(p->mutable_position(), -0.99 + 1.98 * (i + 0.5) / side, 0.001, 0.6 + 0.39 * (j + 0.5) / side);
        Set(p->mutable_normal(), 0, 1, 0);
      }
  };
  v1::LightVisibilityRequest round = light(1024);
  add_points(round, 100);
  ExpectRefusedBeforeWork("want_polygons", [&] { return client_->LightVisibility(round).status(); });
  v1::LightVisibilityRequest many = light(4);
  add_points(many, 448);  // 200,704 points: its own parse is about 60 MB
  ExpectRefusedBeforeWork("want_polygons", [&] { return client_->LightVisibility(many).status(); }, 128 * kMiB);
  v1::LightVisibilityRequest small = light(1024);
  add_points(small, 4);
  auto answer = client_->LightVisibility(small);
  ASSERT_TRUE(answer.ok()) << answer.status();
  ASSERT_EQ(answer->points_size(), 16);
  ASSERT_GT(answer->points(0).visible_fraction(), 0.0);
  ASSERT_GT(answer->points(0).visible_polygons_size(), 0);
  EXPECT_GE(answer->points(0).visible_polygons(0).vertices_size(), 100);
}

}  // namespace
}  // namespace visq
