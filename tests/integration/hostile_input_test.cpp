// Hostile and unusual input, end to end: the real visq-server on
// loopback, driven through the real client and raw gRPC calls, with hostile
// files generated here. Each test names the attack it shows.
#include <signal.h>
#include <sys/mount.h>
#include <sys/wait.h>

#include <atomic>
#include <bit>
#include <chrono>
#include <cmath>
#include <cstring>
#include <fstream>
#include <sstream>
#include <thread>

#include <grpcpp/generic/generic_stub.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include "proto_builders.h"
#include "scene/gltf_writer.h"
#include "scene/sample_scenes.h"
#include "raw_grpc_call.h"
#include "repository_files.h"
#include "server_process.h"
#include "test_support.h"
#include "visq/v1/visq.grpc.pb.h"
#include "visq_client.h"

namespace visq {
namespace {

namespace fs = std::filesystem;
using client::Client;
using testing::RawBidiCall;
using testing::ScratchDir;
using testing::ServerProcess;
using testing::SetPatch;
using testing::StagingEntries;
using testing::StoredSceneNames;

// One triangle: positions (x0,0,0) (1,0,0) (0,1,0), indices 0 1 2, in a
// 44-byte buffer.
std::string TriangleBuffer(float x0) {
  const float positions[9] = {x0, 0, 0, 1, 0, 0, 0, 1, 0};
  const uint16_t indices[4] = {0, 1, 2, 0};
  std::string bin(sizeof(positions) + sizeof(indices), '\0');
  std::memcpy(bin.data(), positions, sizeof(positions));
  std::memcpy(bin.data() + sizeof(positions), indices, sizeof(indices));
  return bin;
}

std::string TriangleJson(const std::string& uri, const std::string& nodes = R"([{"mesh":0}])") {
  return R"({"asset":{"version":"2.0"},"scenes":[{"nodes":[0]}],"scene":0,"nodes":)" + nodes +
         R"(,"meshes":[{"primitives":[{"attributes":{"POSITION":0},"indices":1}]}],
     "buffers":[{"uri":")" + uri + R"(","byteLength":44}],
     "bufferViews":[{"buffer":0,"byteOffset":0,"byteLength":36},{"buffer":0,"byteOffset":36,"byteLength":6}],
     "accessors":[{"bufferView":0,"componentType":5126,"count":3,"type":"VEC3","min":[0,0,0],"max":[1,1,0]},
                  {"bufferView":1,"componentType":5123,"count":3,"type":"SCALAR"}]})";
}

std::string ReadText(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  std::stringstream text;
  text << in.rdbuf();
  return text.str();
}

// A LoadScene stream written by hand, as a hostile client would.
struct RawUpload {
  RawUpload(Client& client, const std::string& name, const std::string& main_file, uint64_t expected_bytes)
      : context(client.NewContext()) {
    writer = client.stub().LoadScene(context.get(), &response);
    v1::LoadSceneRequest header;
    header.mutable_header()->set_name(name);
    header.mutable_header()->set_upload_main_file(main_file);
    header.mutable_header()->set_expected_bytes(expected_bytes);
    writer->Write(header);
  }
  bool Send(const std::string& file, const std::string& data) {
    v1::LoadSceneRequest chunk;
    chunk.mutable_chunk()->set_file(file);
    chunk.mutable_chunk()->set_data(data);
    return writer->Write(chunk);
  }
  grpc::Status Finish() {
    writer->WritesDone();
    return writer->Finish();
  }
  std::unique_ptr<grpc::ClientContext> context;
  v1::SceneInfo response;
  std::unique_ptr<grpc::ClientWriter<v1::LoadSceneRequest>> writer;
};

class HostileInputTest : public ::testing::Test {
 protected:
  void SetUp() override { Start({"--seed-samples"}); }
  void Start(std::vector<std::string> args) {
    server_ = ServerProcess::Start({repo_.path(), std::move(args)});
    ASSERT_NE(server_, nullptr);
    client_ = std::make_unique<Client>(client::ClientOptions{.address = server_->address()});
  }
  void Restart() {
    client_.reset();
    ASSERT_EQ(server_->Stop(), 0) << server_->Log();
    Start({});
  }
  bool Alive() { return client_->ListScenes().ok(); }

  ScratchDir repo_;
  std::unique_ptr<ServerProcess> server_;
  std::unique_ptr<Client> client_;
};

// Item 1: buffer URIs that leave the upload load nothing, and nothing is stored.
TEST_F(HostileInputTest, BufferUrisOutsideTheUploadAreRefused) {
  // Files the URIs aim at: beside the repository, in it, and in the server's
  // working directory (tinygltf's default callbacks fall back to "./").
  const std::string secret = TriangleBuffer(7777.0f);
  std::ofstream(repo_.path().parent_path() / "visq-secret.bin", std::ios::binary) << secret;
  std::ofstream(repo_.path() / "visq-secret.bin", std::ios::binary) << secret;
  const std::string absolute = (repo_.path() / "visq-secret.bin").string();
  for (const std::string& uri : std::vector<std::string>{"../visq-secret.bin", "../../visq-secret.bin", "%2e%2e/visq-secret.bin",
                                "%2e%2e%2f%2e%2e%2fvisq-secret.bin", absolute, "visq-secret.bin"}) {
    RawUpload upload(*client_, "escape", "main.gltf", 0);
    const std::string json = TriangleJson(uri);
    upload.Send("main.gltf", json);
    const grpc::Status status = upload.Finish();
    EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << uri << ": " << status.error_message();
    if (uri[0] != '/') {  // the message may echo the URI, never more of the server's folders
      EXPECT_EQ(status.error_message().find(repo_.path().string()), std::string::npos)
        << "the message shows the server's repository path: " << status.error_message();
    }
    EXPECT_EQ(client_->GetScene("escape").status().code(), absl::StatusCode::kNotFound) << uri;
  }
  EXPECT_FALSE(fs::exists(repo_.path() / "escape"));
  // The same upload with its buffer inside still works.
  RawUpload good(*client_, "inside", "main.gltf", 0);
  good.Send("main.gltf", TriangleJson("buffers/tri.bin"));
  good.Send("buffers/tri.bin", TriangleBuffer(3.0f));
  ASSERT_TRUE(good.Finish().ok());
  auto info = client_->GetScene("inside");
  ASSERT_TRUE(info.ok()) << info.status();
  EXPECT_DOUBLE_EQ(info->bounds_max().x(), 3.0);
}

// Item 3: a name with a newline cannot forge a log line.
TEST_F(HostileInputTest, NamesCannotForgeLogLines) {
  const std::string forged = "2026-01-01T00:00:00.000 info FORGED LINE";
  EXPECT_FALSE(client_->LoadFromRepository("x\n" + forged).ok());
  EXPECT_FALSE(client_->GetScene("y\r\n" + forged).ok());
  const std::string log = server_->Log();
  EXPECT_EQ(log.find("\n" + forged), std::string::npos) << log;
  EXPECT_NE(log.find("x\\n" + forged), std::string::npos) << "the name is logged, escaped:\n" << log;
}

// Items 6 and 11: a deep chain and a DAG that expands are refused without a
// crash; in the repository they are skipped and the server still starts.
TEST_F(HostileInputTest, DeepAndExpandingNodeGraphsAreRefused) {
  std::string chain = "[";
  for (int i = 0; i < 5000; ++i) chain += (i ? "," : "") + (i + 1 < 5000 ? "{\"children\":[" + std::to_string(i + 1) + "]}" : std::string("{\"mesh\":0}"));
  chain += "]";
  std::string dag = "[";
  for (int i = 0; i < 30; ++i) dag += "{\"children\":[" + std::to_string(i + 1) + "," + std::to_string(i + 1) + "]},";
  dag += "{\"mesh\":0}]";
  struct Case {
    const char* name;
    std::string nodes;
    grpc::StatusCode code;
  };
  for (const Case& c : {Case{"chain", chain, grpc::StatusCode::INVALID_ARGUMENT},
                        Case{"dag", dag, grpc::StatusCode::RESOURCE_EXHAUSTED}}) {
    const auto start = std::chrono::steady_clock::now();
    RawUpload upload(*client_, c.name, "main.gltf", 0);
    upload.Send("main.gltf", TriangleJson("tri.bin", c.nodes));
    upload.Send("tri.bin", TriangleBuffer(0.0f));
    const grpc::Status status = upload.Finish();
    EXPECT_EQ(status.error_code(), c.code) << c.name << ": " << status.error_message();
    EXPECT_LT(std::chrono::steady_clock::now() - start, std::chrono::seconds(10)) << "refused before flattening";
    EXPECT_TRUE(Alive()) << server_->Log();
    // Placed in the repository by hand, the file is skipped at start.
    fs::create_directories(repo_.path() / c.name);
    std::ofstream(repo_.path() / c.name / "main.gltf") << TriangleJson("tri.bin", c.nodes);
    std::ofstream(repo_.path() / c.name / "tri.bin", std::ios::binary) << TriangleBuffer(0.0f);
  }
  Restart();
  EXPECT_TRUE(Alive());
  EXPECT_NE(server_->Log().find("scene 'chain' from the repository not loaded"), std::string::npos) << server_->Log();
  EXPECT_TRUE(client_->GetScene("cornell_box_visq").ok()) << "the other scenes still load";
}

// Item 7: coordinates whose float conversion overflows are refused by name.
TEST_F(HostileInputTest, FarCoordinatesAreRefusedNotAnAbort) {
  for (double far : {1e39, 1e308}) {
    for (v1::VisibilityMethod method : {v1::RAYCAST, v1::RASTER}) {
      v1::HiddenSampleMapRequest request;
      request.mutable_scene()->set_name("cornell_box_visq");
      SetPatch(request.mutable_source(), {far, far, far}, {0.5, 0, 0}, {0, 0, 0.5});
      request.mutable_samples()->set_count(32);
      SetPatch(request.mutable_receiver(), {-0.999, 0.001, -0.999}, {1.998, 0, 0}, {0, 0, 1.998});
      request.set_width(8);
      request.set_height(8);
      request.set_method(method);
      auto map = client_->ComputeHiddenSampleMap(request);
      EXPECT_EQ(map.status().code(), absl::StatusCode::kInvalidArgument) << far << ": " << map.status();
      EXPECT_NE(std::string(map.status().message()).find("origin"), std::string::npos) << map.status();

      v1::PatchVisibilityRequest patches;
      patches.mutable_scene()->set_name("cornell_box_visq");
      SetPatch(patches.mutable_source(), {far, far, far}, {0.5, 0, 0}, {0, 0, 0.5});
      SetPatch(patches.mutable_receiver(), {-0.999, 0.001, -0.997}, {1.998, 0, 0}, {0, 0, 1.998});
      patches.set_source_columns(4);
      patches.set_source_rows(4);
      patches.set_receiver_columns(4);
      patches.set_receiver_rows(4);
      patches.set_method(method);
      EXPECT_EQ(client_->PatchVisibility(patches).status().code(), absl::StatusCode::kInvalidArgument) << far;
    }
  }
  EXPECT_TRUE(Alive()) << server_->Log();
}

// A long computation: a RAYCAST PatchVisibility of 64^2 x 512^2
// pairs (a billion segments, about a minute on two cores).
v1::PatchVisibilityRequest BillionSegmentRaycast() {
  v1::PatchVisibilityRequest request;
  request.mutable_scene()->set_name("cornell_box_visq");
  SetPatch(request.mutable_source(), {-0.25, 1.99, -0.25}, {0.5, 0, 0}, {0, 0, 0.5});
  SetPatch(request.mutable_receiver(), {-0.999, 0.001, -0.997}, {1.998, 0, 0}, {0, 0, 1.998});
  request.set_source_columns(64);
  request.set_source_rows(64);
  request.set_receiver_columns(512);
  request.set_receiver_rows(512);
  request.set_method(v1::RAYCAST);
  return request;
}

// Item 17: work that has started stops when its deadline passes. The
// issue's case: a RAYCAST PatchVisibility of 64^2 x 512^2 pairs (a billion
// segments) with a 100 ms deadline computed on for 54 s after the client gave
// up. Now the server's own closing line for it comes within seconds.
TEST_F(HostileInputTest, StartedWorkStopsAtItsDeadline) {
  const v1::PatchVisibilityRequest request = BillionSegmentRaycast();
  Client impatient({.address = server_->address(), .deadline = std::chrono::milliseconds(300)});
  const auto start = std::chrono::steady_clock::now();
  EXPECT_EQ(impatient.PatchVisibility(request).status().code(), absl::StatusCode::kDeadlineExceeded);
  bool closed = false;
  while (!closed && std::chrono::steady_clock::now() - start < std::chrono::seconds(20)) {
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
    const std::string log = server_->Log();
    closed = log.find("PatchVisibility] CANCELLED") != std::string::npos ||
             log.find("PatchVisibility] DEADLINE_EXCEEDED") != std::string::npos;
  }
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  EXPECT_TRUE(closed) << "the server still computes " << seconds << " s after the deadline:\n" << server_->Log();
  RecordProperty("stopped_after_s", std::to_string(seconds));
  EXPECT_TRUE(Alive());
}

// Item 18: calls that compute nothing never queue behind calls that do.
// With one compute thread busy on a long RAYCAST, ListScenes, GetScene and
// GetStats still answer before that computation ends.
TEST(HostileServerSetup, MetadataCallsDoNotWaitForComputations) {
  ScratchDir repo;
  auto server = ServerProcess::Start({repo.path(), {"--seed-samples", "--worker-threads", "1"}});
  ASSERT_NE(server, nullptr);
  const v1::PatchVisibilityRequest request = BillionSegmentRaycast();
  std::atomic<bool> computation_done{false};
  std::thread computation([&] {
    Client busy({.address = server->address(), .deadline = std::chrono::seconds(5)});
    (void)busy.PatchVisibility(request);
    computation_done = true;
  });
  std::this_thread::sleep_for(std::chrono::milliseconds(500));  // the only compute thread is now taken
  Client metadata({.address = server->address()});
  EXPECT_TRUE(metadata.ListScenes().ok());
  EXPECT_TRUE(metadata.GetScene("cornell_box_visq").ok());
  EXPECT_TRUE(metadata.GetStats().ok());
  EXPECT_FALSE(computation_done.load()) << "the metadata calls waited for the computation";
  computation.join();
}

// Item 19: NaN and negative sample colours are refused by field.
TEST_F(HostileInputTest, BadSampleColoursAreRefused) {
  for (double bad : {std::nan(""), -1.0, double(INFINITY)}) {
    v1::HiddenSampleMapRequest request;
    request.mutable_scene()->set_name("cornell_box_visq");
    SetPatch(request.mutable_source(), {-0.25, 1.99, -0.25}, {0.5, 0, 0}, {0, 0, 0.5});
    request.mutable_samples()->set_count(4);
    for (int i = 0; i < 4; ++i) testing::Set(request.mutable_samples()->add_sample_colors(), 1, i == 2 ? bad : 1, 1);
    SetPatch(request.mutable_receiver(), {-0.999, 0.001, -0.999}, {1.998, 0, 0}, {0, 0, 1.998});
    request.set_width(8);
    request.set_height(8);
    auto map = client_->ComputeHiddenSampleMap(request);
    EXPECT_EQ(map.status().code(), absl::StatusCode::kInvalidArgument) << bad << ": " << map.status();
    EXPECT_NE(std::string(map.status().message()).find("sample_colors[2]"), std::string::npos) << map.status();
  }
}

// Item 12: work in flight has a memory budget; a request that could never
// fit is refused by name before it allocates, a small one still runs.
TEST(HostileServerSetup, WorkBeyondTheMemoryBudgetIsRefused) {
  ScratchDir repo;
  auto server = ServerProcess::Start({repo.path(), {"--seed-samples", "--max-work-bytes", "8000000"}});
  ASSERT_NE(server, nullptr);
  Client client({.address = server->address()});
  auto request = [](uint32_t size, uint32_t samples) {
    v1::HiddenSampleMapRequest r;
    r.mutable_scene()->set_name("cornell_box_visq");
    SetPatch(r.mutable_source(), {-0.25, 1.99, -0.25}, {0.5, 0, 0}, {0, 0, 0.5});
    r.mutable_samples()->set_count(samples);
    SetPatch(r.mutable_receiver(), {-0.999, 0.001, -0.999}, {1.998, 0, 0}, {0, 0, 1.998});
    r.set_width(size);
    r.set_height(size);
    return r;
  };
  for (v1::VisibilityMethod method : {v1::RASTER, v1::RAYCAST}) {
    v1::HiddenSampleMapRequest big = request(1024, 256);
    big.set_method(method);
    auto refused = client.ComputeHiddenSampleMap(big);
    EXPECT_EQ(refused.status().code(), absl::StatusCode::kResourceExhausted) << refused.status();
    EXPECT_NE(std::string(refused.status().message()).find("--max-work-bytes"), std::string::npos) << refused.status();
    v1::HiddenSampleMapRequest small = request(16, 32);
    small.set_method(method);
    EXPECT_TRUE(client.ComputeHiddenSampleMap(small).ok());
  }
}

// Item 12: a map is sent while it is made, a band of rows at a time. With
// 1 KiB bands (one row of 64 texels), the stream's first message holds the
// sizes and no accuracy, the fractions come one row per message in order,
// and the accuracy and timing come last; the client rebuilds the same bits
// as the ray caster's.
TEST(HostileServerSetup, LargeMapsAreSentABandAtATime) {
  ScratchDir repo;
  auto server = ServerProcess::Start({repo.path(), {"--seed-samples", "--map-band-bytes", "1024"}});
  ASSERT_NE(server, nullptr);
  v1::HiddenSampleMapRequest request;
  request.mutable_scene()->set_name("cornell_box_visq");
  SetPatch(request.mutable_source(), {-0.25, 1.99, -0.25}, {0.5, 0, 0}, {0, 0, 0.5});
  request.mutable_samples()->set_count(32);
  SetPatch(request.mutable_receiver(), {-0.999, 0.001, -0.999}, {1.998, 0, 0}, {0, 0, 1.998});
  request.set_width(64);
  request.set_height(64);
  request.set_want_bitmasks(true);
  request.set_method(v1::RASTER);  // the GPU's bands, sized by --map-band-bytes

  auto stub = v1::VisibilityService::NewStub(grpc::CreateChannel(server->address(), grpc::InsecureChannelCredentials()));
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(120));
  auto reader = stub->HiddenSampleMap(&context, request);
  std::vector<v1::HiddenSampleMapResponse> messages;
  for (v1::HiddenSampleMapResponse m; reader->Read(&m);) messages.push_back(m);
  ASSERT_TRUE(reader->Finish().ok());
  ASSERT_GE(messages.size(), 3u);
  EXPECT_EQ(messages.front().width(), 64u);
  EXPECT_EQ(messages.front().words_per_texel(), 1u);
  EXPECT_EQ(messages.front().source_samples_size(), 32);
  EXPECT_FALSE(messages.front().has_accuracy()) << "the bound needs every band";
  EXPECT_TRUE(messages.back().has_accuracy());
  EXPECT_TRUE(messages.back().has_timing());
  uint64_t next_texel = 0;
  for (const v1::HiddenSampleMapResponse& m : messages) {
    if (m.visible_fraction_size() == 0) continue;
    EXPECT_EQ(m.offset(), next_texel);
    EXPECT_EQ(m.visible_fraction_size(), 64) << "one band, one row";
    next_texel += m.visible_fraction_size();
  }
  EXPECT_EQ(next_texel, 64u * 64u);

  Client client({.address = server->address()});
  request.set_method(v1::RASTER);
  auto raster = client.ComputeHiddenSampleMap(request);
  request.set_method(v1::RAYCAST);
  auto raycast = client.ComputeHiddenSampleMap(request);
  ASSERT_TRUE(raster.ok()) << raster.status();
  ASSERT_TRUE(raycast.ok()) << raycast.status();
  ASSERT_EQ(raster->blocked_bits.size(), raycast->blocked_bits.size());
  size_t differing = 0;
  for (size_t w = 0; w < raster->blocked_bits.size(); ++w)
    differing += std::popcount(raster->blocked_bits[w] ^ raycast->blocked_bits[w]);
  EXPECT_LE(differing, 64u * 64u * 32u / 10000u) << "the ray-cast bits, float ties aside";
  EXPECT_EQ(raster->visible_fraction.size(), 64u * 64u);
  EXPECT_EQ(raster->figures.accuracy().method(), "raster-exact-lookup");
  EXPECT_GT(raster->figures.timing().total_ms(), 0.0);
}

// Item 12, for voxel grids: 1024 x 1024 columns go out in bands of 2^18
// columns (whole in depth) while the rest is drawn; the first message holds
// the sizes and the accuracy, the last the counts and the timing.
TEST_F(HostileInputTest, VoxelGridsAreSentABandAtATime) {
  v1::VoxelizeRequest request;
  request.mutable_scene()->set_name("cornell_box_visq");
  request.set_width(1024);
  request.set_height(1024);
  request.set_slices(32);
  request.set_mode(v1::VoxelizeRequest::SOLID);
  auto stub = v1::VisibilityService::NewStub(grpc::CreateChannel(server_->address(), grpc::InsecureChannelCredentials()));
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(120));
  auto reader = stub->Voxelize(&context, request);
  std::vector<v1::VoxelizeResponse> messages;
  for (v1::VoxelizeResponse m; reader->Read(&m);) messages.push_back(m);
  ASSERT_TRUE(reader->Finish().ok());
  ASSERT_GE(messages.size(), 3u);
  EXPECT_EQ(messages.front().width(), 1024u);
  EXPECT_TRUE(messages.front().has_accuracy());
  EXPECT_EQ(messages.front().occupied_voxels(), 0u) << "the count needs every band";
  EXPECT_GT(messages.back().occupied_voxels(), 0u);
  EXPECT_TRUE(messages.back().has_timing());
  uint64_t next_word = 0;
  int bit_messages = 0;
  for (const v1::VoxelizeResponse& m : messages) {
    if (m.bits_size() == 0) continue;
    EXPECT_EQ(m.offset(), next_word);
    EXPECT_LE(m.bits_size(), 1 << 18) << "a band at most";
    next_word += m.bits_size();
    ++bit_messages;
  }
  EXPECT_EQ(next_word, 1024u * 1024u);
  EXPECT_EQ(bit_messages, 4);
  auto grid = client_->Voxelize(request);
  ASSERT_TRUE(grid.ok()) << grid.status();
  EXPECT_EQ(grid->figures.occupied_voxels(), messages.back().occupied_voxels());
  EXPECT_TRUE(grid->figures.has_accuracy());
  EXPECT_EQ(grid->bits.size(), 1024u * 1024u);
}

// Item 12, for volumetric images: a 1024 x 512 image goes out in bands of
// at most 256 rows (the band's memory) as the traversal makes them; figures
// first, the timing last.
TEST_F(HostileInputTest, VolumetricImagesAreSentABandAtATime) {
  v1::VolumetricShadowRequest request;
  request.mutable_scene()->set_name("cornell_box_visq");
  testing::Set(request.mutable_camera_position(), 0, 1, 3.5);
  testing::Set(request.mutable_camera_forward(), 0, 0, -1);
  testing::Set(request.mutable_light_direction(), 0.3, -0.6, -1.0);
  request.set_width(1024);
  request.set_height(512);
  request.set_shadow_map_size(256);
  request.set_scattering(0.2);
  request.set_extinction(0.2);
  auto stub = v1::VisibilityService::NewStub(grpc::CreateChannel(server_->address(), grpc::InsecureChannelCredentials()));
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(120));
  auto reader = stub->VolumetricShadow(&context, request);
  std::vector<v1::VolumetricShadowResponse> messages;
  for (v1::VolumetricShadowResponse m; reader->Read(&m);) messages.push_back(m);
  ASSERT_TRUE(reader->Finish().ok());
  ASSERT_GE(messages.size(), 3u);
  EXPECT_EQ(messages.front().width(), 1024u);
  EXPECT_TRUE(messages.front().has_accuracy());
  EXPECT_FALSE(messages.front().has_timing());
  EXPECT_TRUE(messages.back().has_timing());
  uint64_t next = 0;
  int chunks = 0;
  for (const v1::VolumetricShadowResponse& m : messages) {
    if (m.inscattering_size() == 0) continue;
    EXPECT_EQ(m.offset(), next);
    // Bands of whole rows, sized by their time, never past the 256 rows
    // that the band's memory allows.
    EXPECT_EQ(m.inscattering_size() % (1024 * 3), 0) << "whole rows";
    EXPECT_LE(m.inscattering_size(), 1024 * 256 * 3) << "at most one band of 256 rows";
    next += m.inscattering_size();
    ++chunks;
  }
  EXPECT_EQ(next, 1024u * 512u * 3u);
  EXPECT_GE(chunks, 2);
  auto image = client_->VolumetricShadow(request);
  ASSERT_TRUE(image.ok()) << image.status();
  EXPECT_EQ(image->inscattering.size(), 1024u * 512u * 3u);
  EXPECT_TRUE(image->figures.has_timing());
  EXPECT_EQ(image->figures.width(), 1024u);
}

// Item 17: a long rendering that is still wanted does not hold the GL
// thread: its stages and its traversal's bands of rows are GL jobs of their
// own, so another client's small map answers between them instead of
// waiting for the whole rendering.
TEST(HostileServerSetup, LongRenderingsLetOtherQueriesThrough) {
  ScratchDir repo;
  auto server = ServerProcess::Start({repo.path(), {"--seed-samples"}});
  ASSERT_NE(server, nullptr);
  v1::VolumetricShadowRequest heavy;
  heavy.mutable_scene()->set_name("cornell_box_visq");
  testing::Set(heavy.mutable_camera_position(), 0, 1, 3.5);
  testing::Set(heavy.mutable_camera_forward(), 0, 0, -1);
  testing::Set(heavy.mutable_light_direction(), 0.3, -0.6, -1.0);
  heavy.set_width(4096);
  heavy.set_height(4096);
  heavy.set_shadow_map_size(4096);
  heavy.set_scattering(0.2);
  heavy.set_extinction(0.2);
  heavy.set_method(v1::VolumetricShadowRequest::RAY_MARCHING);

  Client client({.address = server->address(), .deadline = std::chrono::seconds(280)});
  auto stats = client.GetStats();
  ASSERT_TRUE(stats.ok()) << stats.status();
  // On a real GPU the rendering takes well under a second: nothing to share.
  if (!stats->gpu_software()) GTEST_SKIP() << "a hardware GPU renders 4096 x 4096 too fast to show the sharing";

  auto stub = v1::VisibilityService::NewStub(grpc::CreateChannel(server->address(), grpc::InsecureChannelCredentials()));
  grpc::ClientContext heavy_context;
  heavy_context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(300));
  std::atomic<bool> heavy_done{false};
  grpc::Status heavy_status;
  std::thread rendering([&] {
    auto reader = stub->VolumetricShadow(&heavy_context, heavy);
    for (v1::VolumetricShadowResponse m; reader->Read(&m);) {
    }
    heavy_status = reader->Finish();
    heavy_done = true;
  });
  // Until the rendering has the GL thread (its first stage is logged when it
  // ends, so wait on the request having arrived and a little more).
  std::this_thread::sleep_for(std::chrono::seconds(2));
  v1::HiddenSampleMapRequest small;
  small.mutable_scene()->set_name("cornell_box_visq");
  SetPatch(small.mutable_source(), {-0.25, 1.99, -0.25}, {0.5, 0, 0}, {0, 0, 0.5});
  small.mutable_samples()->set_count(16);
  SetPatch(small.mutable_receiver(), {-0.999, 0.001, -0.999}, {1.998, 0, 0}, {0, 0, 1.998});
  small.set_width(8);
  small.set_height(8);
  const auto start = std::chrono::steady_clock::now();
  auto map = client.ComputeHiddenSampleMap(small);
  const double waited_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  const bool rendering_still_running = !heavy_done.load();
  heavy_context.TryCancel();
  rendering.join();
  ASSERT_TRUE(map.ok()) << map.status();
  RecordProperty("small_map_s", std::to_string(waited_s));
  EXPECT_TRUE(rendering_still_running) << "the small map waited " << waited_s << " s for the whole rendering";
  EXPECT_EQ(heavy_status.error_code(), grpc::StatusCode::CANCELLED) << heavy_status.error_message();
  EXPECT_TRUE(client.ListScenes().ok());
}

// Item 15: a full disk is RESOURCE_EXHAUSTED, and the message names no
// folder of the server's. The repository is a 256 KiB tmpfs (needs root;
// skipped, saying so, where mounting is not allowed).
TEST(HostileServerSetup, FullDiskIsResourceExhausted) {
  ScratchDir dir;
  const fs::path repo = dir.path() / "small-disk";
  fs::create_directories(repo);
  if (::mount("visq-test", repo.c_str(), "tmpfs", 0, "size=256k") != 0)
    GTEST_SKIP() << "cannot mount a small tmpfs here (" << std::strerror(errno) << "): needs root";
  // Unmounted however the test ends, before the scratch folder goes.
  struct Unmount {
    fs::path path;
    ~Unmount() { ::umount2(path.c_str(), MNT_DETACH); }
  } unmount{repo};
  {
    auto server = ServerProcess::Start({repo, {}});
    ASSERT_NE(server, nullptr);
    Client client({.address = server->address()});
    RawUpload upload(client, "big", "main.gltf", 0);
    upload.Send("main.gltf", TriangleJson("tri.bin"));
    const std::string megabyte(1 << 20, 'x');
    upload.Send("tri.bin", megabyte);
    const grpc::Status status = upload.Finish();
    EXPECT_EQ(status.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED) << status.error_message();
    EXPECT_EQ(status.error_message().find(repo.string()), std::string::npos) << status.error_message();
    EXPECT_EQ(client.GetScene("big").status().code(), absl::StatusCode::kNotFound);
    EXPECT_EQ(StagingEntries(repo), 0) << "staging left behind";
    EXPECT_TRUE(StoredSceneNames(repo).empty());
  }
}

// Item 13: an upload that is cancelled, or that ends short of what its header
// announced, stores nothing.
TEST_F(HostileInputTest, CancelledOrShortUploadsStoreNothing) {
  const std::string json = TriangleJson("tri.bin");
  const std::string bin = TriangleBuffer(0.0f);
  {
    RawUpload upload(*client_, "cancelled", "main.gltf", json.size() + bin.size());
    upload.Send("main.gltf", json);
    upload.Send("tri.bin", bin);
    std::this_thread::sleep_for(std::chrono::milliseconds(200));
    upload.context->TryCancel();
    EXPECT_FALSE(upload.writer->Finish().ok());
  }
  {
    RawUpload upload(*client_, "short", "main.gltf", json.size() + bin.size() + 100);
    upload.Send("main.gltf", json);
    upload.Send("tri.bin", bin);
    const grpc::Status status = upload.Finish();
    EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << status.error_message();
    EXPECT_NE(status.error_message().find("expected_bytes"), std::string::npos) << status.error_message();
  }
  std::this_thread::sleep_for(std::chrono::milliseconds(500));
  for (const char* name : {"cancelled", "short"}) {
    EXPECT_EQ(client_->GetScene(name).status().code(), absl::StatusCode::kNotFound) << name;
    const std::vector<std::string> stored = StoredSceneNames(repo_.path());
    EXPECT_EQ(std::count(stored.begin(), stored.end(), name), 0) << name;
  }
  Restart();
  for (const char* name : {"cancelled", "short"})
    EXPECT_EQ(client_->GetScene(name, false, /*load_if_stored=*/true).status().code(), absl::StatusCode::kNotFound);
}

// Item 14: an upload named like another scene's stored file destroys nothing.
TEST_F(HostileInputTest, UploadNamedLikeAStoredFileDestroysNothing) {
  ASSERT_TRUE(WriteGltfFile(MakeCornellBox(), repo_.path() / "x.glb").ok());
  ASSERT_TRUE(client_->LoadFromRepository("x").ok());
  RawUpload upload(*client_, "x.glb", "main.gltf", 0);
  upload.Send("main.gltf", TriangleJson("tri.bin"));
  upload.Send("tri.bin", TriangleBuffer(0.0f));
  const grpc::Status status = upload.Finish();
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << status.error_message();
  EXPECT_EQ(StoredSceneNames(repo_.path()), (std::vector<std::string>{"cornell_box_visq", "x"}));
  Restart();
  auto x = client_->GetScene("x", false, true);
  ASSERT_TRUE(x.ok()) << x.status();
  EXPECT_EQ(x->triangle_count(), MakeCornellBox().TriangleCount());
}

// Item 16: versions do not repeat after a restart, and a stored scene keeps
// the version it was stored with.
TEST_F(HostileInputTest, VersionsSurviveRestarts) {
  RawUpload first(*client_, "probe", "main.gltf", 0);
  first.Send("main.gltf", TriangleJson("tri.bin"));
  first.Send("tri.bin", TriangleBuffer(0.0f));
  ASSERT_TRUE(first.Finish().ok());
  const uint64_t stored = first.response.version();
  Restart();
  auto after = client_->GetScene("probe");
  ASSERT_TRUE(after.ok()) << after.status();
  EXPECT_EQ(after->version(), stored) << "the same stored scene, the same version";
  ASSERT_TRUE(client_->UnloadScene("probe", /*delete_from_repository=*/true).ok());
  Restart();
  RawUpload second(*client_, "probe", "main.gltf", 0);
  second.Send("main.gltf", TriangleJson("tri.bin"));
  second.Send("tri.bin", TriangleBuffer(5.0f));
  ASSERT_TRUE(second.Finish().ok());
  EXPECT_GT(second.response.version(), stored) << "(probe, " << stored << ") named another scene before";
}

// Item 2: with a token set, reflection does not answer callers without it.
// The call is raw (a generic stub): grpc.reflection.v1alpha.ServerReflection
// with a list_services request (field 7, empty string).
grpc::Status ListServicesByReflection(const std::string& address, std::string* answer) {
  const char request[] = {0x3a, 0x00};
  return RawBidiCall(address, "/grpc.reflection.v1alpha.ServerReflection/ServerReflectionInfo",
                     std::string(request, sizeof(request)), answer);
}

TEST(HostileServerSetup, ReflectionNeedsTheTokenWhenOneIsSet) {
  ScratchDir repo, files;
  {
    auto open = ServerProcess::Start({repo.path(), {}});
    ASSERT_NE(open, nullptr);
    std::string answer;
    EXPECT_TRUE(ListServicesByReflection(open->address(), &answer).ok());
    EXPECT_NE(answer.find("visq.v1.VisibilityService"), std::string::npos) << "reflection works without a token";
  }
  std::ofstream(files.path() / "token") << "0123456789abcdef0123456789abcdef\n";
  auto locked = ServerProcess::Start({repo.path(), {"--auth-token-file", (files.path() / "token").string()}});
  ASSERT_NE(locked, nullptr);
  std::string answer;
  const grpc::Status status = ListServicesByReflection(locked->address(), &answer);
  EXPECT_FALSE(status.ok());
  EXPECT_EQ(answer.find("visq.v1.VisibilityService"), std::string::npos) << "reflection answered without the token";
}

// Item 5: a token file with Windows line endings still works.
TEST(HostileServerSetup, TokenFileWithWindowsLineEndings) {
  ScratchDir repo, files;
  std::ofstream(files.path() / "token", std::ios::binary) << "  0123456789abcdef0123456789abcdef\r\n";
  auto server = ServerProcess::Start({repo.path(), {"--seed-samples", "--auth-token-file",
                                                    (files.path() / "token").string()}});
  ASSERT_NE(server, nullptr);
  Client right({.address = server->address(), .auth_token = "0123456789abcdef0123456789abcdef"});
  auto list = right.ListScenes();
  EXPECT_TRUE(list.ok()) << list.status() << "\n" << server->Log();
  std::ofstream(files.path() / "short", std::ios::binary) << "abc\n";
  auto weak = ServerProcess::Start({repo.path(), {"--auth-token-file", (files.path() / "short").string()}});
  ASSERT_NE(weak, nullptr);
  EXPECT_NE(weak->Log().find("use at least 32 random ones"), std::string::npos) << weak->Log();
}

// Runs visq-server with `args` to completion; returns its wait status and log.
int RunServer(const std::vector<std::string>& args, const fs::path& log_path) {
  std::string command = VISQ_SERVER_BINARY;
  for (const auto& a : args) command += " '" + a + "'";
  command += " > '" + log_path.string() + "' 2>&1";
  return std::system(command.c_str());
}

// Item 4: the loopback decision is made on the resolved address.
TEST(HostileServerSetup, LoopbackIsDecidedOnTheResolvedAddress) {
  ScratchDir repo;
  const int rc = RunServer({"--address", "127.0.0.1.invalid:0", "--scene-repo", repo.path().string()},
                           repo.path() / "log");
  EXPECT_TRUE(WIFEXITED(rc) && WEXITSTATUS(rc) != 0) << rc;
  EXPECT_NE(ReadText(repo.path() / "log").find("refusing to listen on 127.0.0.1.invalid:0"), std::string::npos)
      << ReadText(repo.path() / "log");
}

// Item 9: a port in use, or a host that does not resolve, is a message and
// a non-zero exit, not SIGSEGV.
TEST(HostileServerSetup, ListenFailureExitsWithAMessage) {
  ScratchDir repo;
  auto holder = ServerProcess::Start({repo.path(), {}});
  ASSERT_NE(holder, nullptr);
  for (const std::vector<std::string>& args :
       {std::vector<std::string>{"--address", holder->address()},
        std::vector<std::string>{"--address", "no-such-host.invalid:0", "--allow-insecure-remote"}}) {
    ScratchDir other;
    std::vector<std::string> full = args;
    full.insert(full.end(), {"--scene-repo", other.path().string()});
    const int rc = RunServer(full, other.path() / "log");
    const std::string log = ReadText(other.path() / "log");
    ASSERT_TRUE(WIFEXITED(rc)) << "killed by a signal: " << rc << "\n" << log;
    EXPECT_NE(WEXITSTATUS(rc), 0);
    EXPECT_NE(log.find("cannot listen on " + args[1]), std::string::npos) << log;
  }
}

}  // namespace
}  // namespace visq
