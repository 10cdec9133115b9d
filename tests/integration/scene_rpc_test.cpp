// The scene RPCs end to end: a real visq-server process on loopback, the
// real client library and CLI, real files.
#include <signal.h>

#include <atomic>
#include <cstdio>
#include <map>
#include <sstream>
#include <thread>
#include <fstream>
#include <iterator>

#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "common/version.h"
#include "proto_builders.h"
#include "scene/gltf_writer.h"
#include "scene/sample_scenes.h"
#include "repository_files.h"
#include "server_process.h"
#include "test_support.h"
#include "visq_client.h"

namespace visq {
namespace {

namespace fs = std::filesystem;
using client::Client;
using testing::ScratchDir;
using testing::ServerProcess;
using testing::Set;

class SceneRpcTest : public ::testing::Test {
 protected:
  void SetUp() override { StartServer(); }

  void StartServer(std::vector<std::string> extra = {"--seed-samples"}) {
    server_ = ServerProcess::Start({repo_.path(), extra});
    ASSERT_NE(server_, nullptr);
    client_ = std::make_unique<Client>(client::ClientOptions{.address = server_->address()});
  }
  void RestartServer() {
    client_.reset();
    EXPECT_EQ(server_->Stop(), 0) << "server did not exit cleanly:\n" << server_->Log();
    StartServer({});
  }

  // A small generated scene written outside the repository, as a user's file.
  fs::path WriteUserScene(const std::string& file_name, int boxes = 3) {
    Scene scene;
    scene.materials = {{"grey", glm::dvec3(0.5), glm::dvec3(0.0)}};
    for (int i = 0; i < boxes; ++i)
      AddBox(scene, "box" + std::to_string(i), glm::dvec3(i * 2.0, 0, 0), glm::dvec3(i * 2.0 + 1, 1, 1), 0);
    UpdateBounds(scene);
    const fs::path path = user_files_.path() / file_name;
    EXPECT_TRUE(WriteGltfFile(scene, path).ok());
    return path;
  }

  // The resident scenes' names, as ListScenes orders them (empty on error).
  std::vector<std::string> ResidentNames() const {
    auto list = client_->ListScenes();
    EXPECT_TRUE(list.ok()) << list.status();
    std::vector<std::string> names;
    if (list.ok())
      for (const auto& s : list->scenes()) names.push_back(s.name());
    return names;
  }

  // The scenes the repository's catalog holds, and a ".staging" per upload
  // or load in flight.
  std::vector<std::string> RepositoryEntries() const {
    std::vector<std::string> names = testing::StoredSceneNames(repo_.path());
    for (int i = testing::StagingEntries(repo_.path()); i > 0; --i) names.push_back(".staging");
    return names;
  }

  ScratchDir repo_;
  ScratchDir user_files_;
  std::unique_ptr<ServerProcess> server_;
  std::unique_ptr<Client> client_;
};

TEST_F(SceneRpcTest, HealthIsServingAndSampleSceneIsResident) {
  auto health = client_->Health();
  ASSERT_TRUE(health.ok()) << health.status();
  EXPECT_EQ(*health, grpc::health::v1::HealthCheckResponse::SERVING);
  auto service_health = client_->Health("visq.v1.VisibilityService");
  ASSERT_TRUE(service_health.ok()) << service_health.status();
  EXPECT_EQ(*service_health, grpc::health::v1::HealthCheckResponse::SERVING);

  auto list = client_->ListScenes();
  ASSERT_TRUE(list.ok()) << list.status();
  ASSERT_EQ(list->scenes_size(), 1);
  EXPECT_EQ(list->scenes(0).name(), "cornell_box_visq");
  EXPECT_EQ(list->scenes(0).triangle_count(), 36u);
  EXPECT_EQ(list->scenes(0).emissive_triangle_count(), 2u);
}

TEST_F(SceneRpcTest, UploadInfoReplaceUnload) {
  const fs::path file = WriteUserScene("boxes.gltf");
  auto info = client_->UploadScene(file, "boxes");
  ASSERT_TRUE(info.ok()) << info.status();
  EXPECT_EQ(info->triangle_count(), 36u);
  EXPECT_GE(info->version(), 1u);
  EXPECT_TRUE(info->persisted());
  EXPECT_EQ(info->content_hash().size(), 32u);
  EXPECT_EQ(info->memory().gpu_bytes(), 0u) << "nothing should be on the GPU before a GPU query";

  auto with_nodes = client_->GetScene("boxes", true);
  ASSERT_TRUE(with_nodes.ok()) << with_nodes.status();
  ASSERT_EQ(with_nodes->nodes_size(), 3);
  EXPECT_EQ(with_nodes->nodes(1).name(), "box1");
  EXPECT_EQ(with_nodes->nodes(1).triangle_count(), 12u);
  EXPECT_DOUBLE_EQ(with_nodes->bounds_max().x(), 5.0);

  auto again = client_->UploadScene(file, "boxes");
  EXPECT_EQ(again.status().code(), absl::StatusCode::kAlreadyExists) << again.status();

  auto replaced = client_->UploadScene(WriteUserScene("more.glb", 5), "boxes", /*replace=*/true);
  ASSERT_TRUE(replaced.ok()) << replaced.status();
  EXPECT_GT(replaced->version(), info->version());
  EXPECT_EQ(replaced->triangle_count(), 60u);

  auto unloaded = client_->UnloadScene("boxes");
  ASSERT_TRUE(unloaded.ok()) << unloaded.status();
  EXPECT_FALSE(unloaded->deleted_from_repository());
  EXPECT_EQ(client_->GetScene("boxes").status().code(), absl::StatusCode::kNotFound);
  EXPECT_EQ(client_->UnloadScene("boxes").status().code(), absl::StatusCode::kNotFound);

  // Still stored: it can be loaded back by name.
  auto reloaded = client_->LoadFromRepository("boxes");
  ASSERT_TRUE(reloaded.ok()) << reloaded.status();
  EXPECT_EQ(reloaded->triangle_count(), 60u);
  EXPECT_EQ(reloaded->version(), replaced->version()) << "the stored content keeps the version it was stored with";
}

TEST_F(SceneRpcTest, LoadByNameFromRepository) {
  // A scene placed in the repository by hand, as a single .glb.
  const fs::path glb = WriteUserScene("hand.glb", 2);
  fs::copy_file(glb, repo_.path() / "hand_placed.glb");
  auto info = client_->LoadFromRepository("hand_placed");
  ASSERT_TRUE(info.ok()) << info.status();
  EXPECT_EQ(info->triangle_count(), 24u);
  EXPECT_EQ(client_->LoadFromRepository("no_such_scene").status().code(), absl::StatusCode::kNotFound);
}

TEST_F(SceneRpcTest, RestartKeepsUploadedScenesAndDeleteForgetsThem) {
  auto kept = client_->UploadScene(WriteUserScene("kept.gltf"), "kept");
  ASSERT_TRUE(kept.ok()) << kept.status();
  auto doomed = client_->UploadScene(WriteUserScene("doomed.gltf", 1), "doomed");
  ASSERT_TRUE(doomed.ok()) << doomed.status();
  auto deleted = client_->UnloadScene("doomed", /*delete_from_repository=*/true);
  ASSERT_TRUE(deleted.ok()) << deleted.status();
  EXPECT_TRUE(deleted->deleted_from_repository());

  RestartServer();
  EXPECT_EQ(ResidentNames(), (std::vector<std::string>{"cornell_box_visq", "kept"}));
  auto info = client_->GetScene("kept");
  ASSERT_TRUE(info.ok());
  EXPECT_EQ(info->content_hash(), kept->content_hash());
}

TEST_F(SceneRpcTest, BadNamesAreRejectedAndLeaveNothingBehind) {
  const fs::path file = WriteUserScene("x.gltf");
  for (const std::string& name : std::vector<std::string>{"../escape", "a/b", "..", ".hidden", "", "white space", std::string(200, 'a')}) {
    auto info = client_->UploadScene(file, name.empty() ? " " : name);
    EXPECT_EQ(info.status().code(), absl::StatusCode::kInvalidArgument) << "name '" << name << "': " << info.status();
    EXPECT_EQ(client_->LoadFromRepository(name).status().code(), absl::StatusCode::kInvalidArgument) << name;
  }
  EXPECT_EQ(RepositoryEntries(), (std::vector<std::string>{"cornell_box_visq"}));
}

TEST_F(SceneRpcTest, MalformedUploadIsInvalidAndLeavesServerAndOtherScenesUntouched) {
  const auto before = client_->GetScene("cornell_box_visq");
  ASSERT_TRUE(before.ok());
  const fs::path bad = user_files_.path() / "broken.gltf";
  std::ofstream(bad) << R"({"asset": {"version": "2.0"}, "meshes": [ {)";
  auto info = client_->UploadScene(bad, "broken");
  EXPECT_EQ(info.status().code(), absl::StatusCode::kInvalidArgument) << info.status();
  EXPECT_NE(std::string(info.status().message()).find("malformed"), std::string::npos) << info.status();

  // A NaN vertex in an otherwise valid file.
  Scene nan_scene = MakeCornellBox();
  nan_scene.positions[3].y = std::numeric_limits<double>::quiet_NaN();
  ASSERT_TRUE(WriteGltfFile(nan_scene, user_files_.path() / "nan.gltf").ok());
  auto nan_info = client_->UploadScene(user_files_.path() / "nan.gltf", "nan");
  EXPECT_EQ(nan_info.status().code(), absl::StatusCode::kInvalidArgument) << nan_info.status();
  EXPECT_NE(std::string(nan_info.status().message()).find("NaN"), std::string::npos) << nan_info.status();

  EXPECT_EQ(RepositoryEntries(), (std::vector<std::string>{"cornell_box_visq"})) << "no partial scene stored";
  const auto after = client_->GetScene("cornell_box_visq");
  ASSERT_TRUE(after.ok());
  EXPECT_EQ(after->content_hash(), before->content_hash());
  EXPECT_EQ(after->version(), before->version());
  EXPECT_EQ(client_->Health().value(), grpc::health::v1::HealthCheckResponse::SERVING);
}

TEST_F(SceneRpcTest, ProtocolMisuseIsInvalidArgument) {
  // A chunk before any header.
  {
    auto context = client_->NewContext();
    v1::SceneInfo info;
    auto writer = client_->stub().LoadScene(context.get(), &info);
    v1::LoadSceneRequest chunk;
    chunk.mutable_chunk()->set_file("x.gltf");
    chunk.mutable_chunk()->set_data("{}");
    writer->Write(chunk);
    writer->WritesDone();
    EXPECT_EQ(writer->Finish().error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  }
  // A chunk whose file name climbs out of the upload.
  {
    auto context = client_->NewContext();
    v1::SceneInfo info;
    auto writer = client_->stub().LoadScene(context.get(), &info);
    v1::LoadSceneRequest header;
    header.mutable_header()->set_name("climber");
    header.mutable_header()->set_upload_main_file("scene.gltf");
    writer->Write(header);
    v1::LoadSceneRequest chunk;
    chunk.mutable_chunk()->set_file("../../etc/passwd");
    chunk.mutable_chunk()->set_data("x");
    writer->Write(chunk);
    writer->WritesDone();
    const grpc::Status status = writer->Finish();
    EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << status.error_message();
  }
  // An empty stream.
  {
    auto context = client_->NewContext();
    v1::SceneInfo info;
    auto writer = client_->stub().LoadScene(context.get(), &info);
    writer->WritesDone();
    EXPECT_EQ(writer->Finish().error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  }
  EXPECT_EQ(RepositoryEntries(), (std::vector<std::string>{"cornell_box_visq"}));
}

// Textures cost the server nothing: the client does not send them, and a
// client that does finds them not stored. What was dropped is said.
TEST_F(SceneRpcTest, TexturesAreNeitherSentNorStored) {
  const fs::path gltf = WriteUserScene("textured.gltf");
  {
    std::ifstream in(gltf);
    nlohmann::json doc = nlohmann::json::parse(in);
    doc["images"] = {{{"uri", "albedo.png"}}};
    doc["textures"] = {{{"source", 0}}};
    std::ofstream(gltf) << doc.dump();
  }
  const std::string texture(1 << 20, 'x');  // stands for a large image
  std::ofstream(user_files_.path() / "albedo.png", std::ios::binary) << texture;

  auto info = client_->UploadScene(gltf, "textured");
  ASSERT_TRUE(info.ok()) << info.status();
  EXPECT_EQ(testing::StoredFiles(repo_.path(), "textured"),
            (std::vector<std::string>{"textured.bin", "textured.gltf"}));

  // A client that sends every file, the image too.
  auto context = client_->NewContext();
  v1::SceneInfo sent;
  auto writer = client_->stub().LoadScene(context.get(), &sent);
  v1::LoadSceneRequest header;
  header.mutable_header()->set_name("textured_raw");
  header.mutable_header()->set_upload_main_file("textured.gltf");
  ASSERT_TRUE(writer->Write(header));
  for (const char* file : {"textured.gltf", "textured.bin", "albedo.png"}) {
    std::ifstream in(user_files_.path() / file, std::ios::binary);
    v1::LoadSceneRequest chunk;
    chunk.mutable_chunk()->set_file(file);
    chunk.mutable_chunk()->set_data(std::string(std::istreambuf_iterator<char>(in), {}));
    ASSERT_TRUE(writer->Write(chunk));
  }
  writer->WritesDone();
  const grpc::Status status = writer->Finish();
  ASSERT_TRUE(status.ok()) << status.error_message();
  EXPECT_EQ(testing::StoredFiles(repo_.path(), "textured_raw"),
            (std::vector<std::string>{"textured.bin", "textured.gltf"}));
  EXPECT_THAT(std::vector<std::string>(sent.dropped().begin(), sent.dropped().end()),
              ::testing::Contains("1 uploaded file(s) the geometry does not use"));
}

TEST_F(SceneRpcTest, UploadLimitIsResourceExhausted) {
  RestartServer();
  client_.reset();
  server_->Stop();
  StartServer({"--max-upload-bytes", "1000"});
  auto info = client_->UploadScene(WriteUserScene("big.gltf", 10), "big");
  EXPECT_EQ(info.status().code(), absl::StatusCode::kResourceExhausted) << info.status();
  EXPECT_NE(std::string(info.status().message()).find("--max-upload-bytes"), std::string::npos);
}

TEST_F(SceneRpcTest, CliListsScenesAsJson) {
  const std::string command = std::string(VISQ_CLI_BINARY) + " list --json --server " + server_->address();
  int exit_status = 0;
  const std::string output = testing::RunCommand(command, &exit_status);
  ASSERT_EQ(exit_status, 0) << output;
  const auto json = nlohmann::json::parse(output);
  ASSERT_EQ(json["scenes"].size(), 1u) << output;
  EXPECT_EQ(json["scenes"][0]["name"], "cornell_box_visq");
  EXPECT_EQ(json["scenes"][0]["triangle_count"], 36) << "uint64 fields are numbers in the CLI's JSON";
}

TEST_F(SceneRpcTest, SponzaUploadsInChunksAndSurvivesRestart) {
  VISQ_REQUIRE_SHARED_SCENES(scenes);
  auto info = client_->UploadScene(scenes / "sponza_dabrovic/sponza.gltf");
  ASSERT_TRUE(info.ok()) << info.status();
  EXPECT_EQ(info->name(), "sponza");
  EXPECT_EQ(info->triangle_count(), 66454u);
  RestartServer();
  auto after = client_->GetScene("sponza");
  ASSERT_TRUE(after.ok()) << after.status();
  EXPECT_EQ(after->triangle_count(), 66454u);
  EXPECT_EQ(after->content_hash(), info->content_hash());
}

}  // namespace
}  // namespace visq

namespace visq {
namespace {

// Runs a shell command, failing the test if it fails.
void Shell(const std::string& command) {
  const int rc = std::system((command + " >/dev/null 2>&1").c_str());
  ASSERT_EQ(rc, 0) << command;
}

TEST(ServerSecurity, BearerTokenIsRequiredOnEveryCallButHealth) {
  ScratchDir repo, files;
  std::ofstream(files.path() / "token") << "s3cret-token\n";
  auto server = ServerProcess::Start({repo.path(), {"--seed-samples", "--auth-token-file",
                                                    (files.path() / "token").string()}});
  ASSERT_NE(server, nullptr);
  Client anonymous({.address = server->address()});
  EXPECT_EQ(anonymous.Health().value(), grpc::health::v1::HealthCheckResponse::SERVING) << "probes need no token";
  EXPECT_EQ(anonymous.ListScenes().status().code(), absl::StatusCode::kUnauthenticated);
  EXPECT_EQ(anonymous.GetStats().status().code(), absl::StatusCode::kUnauthenticated);
  EXPECT_EQ(anonymous.LoadFromRepository("cornell_box_visq", true).status().code(),
            absl::StatusCode::kUnauthenticated);
  Client wrong({.address = server->address(), .auth_token = "s3cret-tokem"});
  EXPECT_EQ(wrong.ListScenes().status().code(), absl::StatusCode::kUnauthenticated);
  Client right({.address = server->address(), .auth_token = "s3cret-token"});
  auto list = right.ListScenes();
  ASSERT_TRUE(list.ok()) << list.status();
  EXPECT_EQ(list->scenes_size(), 1);
}

TEST(ServerSecurity, MutualTlsAcceptsOnlyClientsWithACertificate) {
  ScratchDir repo, pki;
  const std::string d = pki.path().string();
  // A CA, a server certificate for localhost and a client certificate.
  Shell("cd " + d + " && openssl req -x509 -newkey rsa:2048 -nodes -keyout ca.key -out ca.pem -days 2 -subj /CN=visq-test-ca");
  Shell("cd " + d + " && openssl req -newkey rsa:2048 -nodes -keyout server.key -out server.csr -subj /CN=localhost"
        " && printf 'subjectAltName=DNS:localhost,IP:127.0.0.1' > san.ext"
        " && openssl x509 -req -in server.csr -CA ca.pem -CAkey ca.key -CAcreateserial -out server.pem -days 2 -extfile san.ext");
  Shell("cd " + d + " && openssl req -newkey rsa:2048 -nodes -keyout client.key -out client.csr -subj /CN=visq-client"
        " && openssl x509 -req -in client.csr -CA ca.pem -CAkey ca.key -CAcreateserial -out client.pem -days 2");
  // ServerProcess polls health without TLS, so it cannot judge readiness
  // here: start it by hand and poll with a TLS client.
  const std::string port_file = d + "/port";
  const std::string command = std::string(VISQ_SERVER_BINARY) + " --address 127.0.0.1:0 --scene-repo " +
                              repo.path().string() + " --port-file " + port_file + " --tls-cert " + d +
                              "/server.pem --tls-key " + d + "/server.key --tls-client-ca " + d + "/ca.pem > " + d +
                              "/server.log 2>&1 & echo $! > " + d + "/pid";
  ASSERT_EQ(std::system(command.c_str()), 0);
  int port = 0;
  for (int i = 0; i < 600 && port == 0; ++i) {
    std::ifstream(port_file) >> port;
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  int pid = 0;
  std::ifstream(d + "/pid") >> pid;
  ASSERT_GT(port, 0);
  const std::string address = "localhost:" + std::to_string(port);
  Client with_cert({.address = address, .tls_ca_file = d + "/ca.pem", .client_cert_file = d + "/client.pem",
                    .client_key_file = d + "/client.key"});
  EXPECT_TRUE(with_cert.WaitUntilServing(std::chrono::seconds(30)).ok());
  EXPECT_TRUE(with_cert.ListScenes().ok());
  Client without_cert({.address = address, .deadline = std::chrono::seconds(5), .tls_ca_file = d + "/ca.pem"});
  EXPECT_FALSE(without_cert.ListScenes().ok());
  Client plaintext({.address = address, .deadline = std::chrono::seconds(5)});
  EXPECT_FALSE(plaintext.ListScenes().ok());
  ::kill(pid, SIGTERM);
}

TEST(ServerSecurity, RefusesToListenBeyondLoopbackWithoutProtection) {
  ScratchDir repo;
  const std::string command = std::string(VISQ_SERVER_BINARY) + " --address 0.0.0.0:0 --scene-repo " +
                              repo.path().string() + " > " + (repo.path() / "log").string() + " 2>&1";
  const int rc = std::system(command.c_str());
  EXPECT_NE(rc, 0);
  std::ifstream in(repo.path() / "log");
  std::stringstream log;
  log << in.rdbuf();
  EXPECT_NE(log.str().find("refusing to listen on 0.0.0.0:0 without TLS or a bearer token"), std::string::npos)
      << log.str();
}

TEST(Versions, BothBinariesPrintTheirVersion) {
  for (const char* binary : {VISQ_SERVER_BINARY, VISQ_CLI_BINARY}) {
    int exit_status = -1;
    const std::string output = testing::RunCommand(std::string(binary) + " --version", &exit_status);
    EXPECT_EQ(exit_status, 0) << binary;
    EXPECT_NE(output.find(kVersion), std::string::npos) << binary << ": " << output;
    EXPECT_NE(output.find(kBuildCommit), std::string::npos) << binary << ": " << output;
  }
}

TEST_F(SceneRpcTest, GetStatsCountsCallsAndNamesTheDevice) {
  ASSERT_TRUE(client_->ListScenes().ok());
  ASSERT_TRUE(client_->ListScenes().ok());
  EXPECT_FALSE(client_->GetScene("missing").ok());
  auto stats = client_->GetStats();
  ASSERT_TRUE(stats.ok()) << stats.status();
  EXPECT_EQ(stats->server_id(), server_->address());
  EXPECT_EQ(stats->server_version(), kVersion);
  EXPECT_EQ(stats->build_commit(), kBuildCommit);
  EXPECT_FALSE(stats->gl_version().empty());
  EXPECT_EQ(stats->scenes_resident(), 1u);
  EXPECT_GT(stats->scene_memory().cpu_bytes(), 0u);
  std::map<std::string, v1::MethodStats> by_method;
  for (const auto& m : stats->methods()) by_method[m.method()] = m;
  EXPECT_EQ(by_method["ListScenes"].calls(), 2u);
  EXPECT_EQ(by_method["ListScenes"].errors(), 0u);
  EXPECT_EQ(by_method["GetScene"].calls(), 1u);
  EXPECT_EQ(by_method["GetScene"].errors(), 1u);
  EXPECT_GE(by_method["ListScenes"].p99_ms(), by_method["ListScenes"].p50_ms());
  EXPECT_GT(by_method["ListScenes"].max_ms(), 0.0);
}

}  // namespace
}  // namespace visq

namespace visq {
namespace {

TEST_F(SceneRpcTest, KillDuringUploadLeavesNoPartialSceneAndKeepsAcknowledgedOnes) {
  auto acknowledged = client_->UploadScene(WriteUserScene("kept.glb"), "kept");
  ASSERT_TRUE(acknowledged.ok()) << acknowledged.status();
  // An upload that never finishes: header and some chunks, then the server dies.
  {
    auto context = client_->NewContext();
    v1::SceneInfo info;
    auto writer = client_->stub().LoadScene(context.get(), &info);
    v1::LoadSceneRequest header;
    header.mutable_header()->set_name("interrupted");
    header.mutable_header()->set_upload_main_file("big.glb");
    ASSERT_TRUE(writer->Write(header));
    v1::LoadSceneRequest chunk;
    chunk.mutable_chunk()->set_file("big.glb");
    chunk.mutable_chunk()->set_data(std::string(1 << 20, 'x'));
    for (int i = 0; i < 4; ++i) ASSERT_TRUE(writer->Write(chunk));
    // Give the server time to write the chunks into its staging folder.
    std::this_thread::sleep_for(std::chrono::milliseconds(300));
    EXPECT_GT(testing::StagingEntries(repo_.path()), 0) << "the upload should be in a staging folder while it runs";
    server_->Kill();
    context->TryCancel();
  }
  client_.reset();
  StartServer({});
  EXPECT_EQ(ResidentNames(), (std::vector<std::string>{"cornell_box_visq", "kept"}));
  EXPECT_EQ(RepositoryEntries(), (std::vector<std::string>{"cornell_box_visq", "kept"}))
      << "the interrupted upload's staging folder must be gone after restart";
  EXPECT_EQ(client_->GetScene("kept")->content_hash(), acknowledged->content_hash());
}

}  // namespace
}  // namespace visq

namespace visq {
namespace {

TEST_F(SceneRpcTest, LightReceiverCellsFlagSetsTheTreesOfABatch) {
  // One receiver cube over the whole scene: a batch spread over the floor
  // gets one tree (the default, 32 a side, gives it one per cube).
  client_.reset();
  server_->Stop();
  StartServer({"--light-receiver-cells", "1"});
  v1::LightVisibilityRequest request;
  request.mutable_scene()->set_name("cornell_box_visq");
  for (const auto& [x, z] : {std::pair{-0.25, -0.25}, {0.25, -0.25}, {0.25, 0.25}, {-0.25, 0.25}})
    Set(request.mutable_light()->add_vertices(), x, 1.99, z);
  for (const double x : {-0.9, -0.3, 0.3, 0.9}) {
    auto* p = request.add_points();
    Set(p->mutable_position(), x, 0.001, 0.5);
    Set(p->mutable_normal(), 0, 1, 0);
  }
  auto answer = client_->LightVisibility(request);
  ASSERT_TRUE(answer.ok()) << answer.status();
  EXPECT_EQ(answer->tree().trees(), 1u);
  EXPECT_EQ(answer->tree().queries(), 4u);
}

TEST_F(SceneRpcTest, SceneAboveTheMemoryCapIsResourceExhausted) {
  client_.reset();
  server_->Stop();
  StartServer({"--max-scene-bytes", "10000"});
  auto info = client_->UploadScene(WriteUserScene("many.glb", 40), "many");
  EXPECT_EQ(info.status().code(), absl::StatusCode::kResourceExhausted) << info.status();
  EXPECT_NE(std::string(info.status().message()).find("--max-scene-bytes"), std::string::npos);
  EXPECT_EQ(RepositoryEntries(), (std::vector<std::string>{"cornell_box_visq"})) << "nothing stored";
}

}  // namespace
}  // namespace visq

namespace visq {
namespace {

// Kill -9 while the GPU bakes: the bake is lost (it was never acknowledged),
// every acknowledged scene is intact after restart, nothing half-written is
// left in the repository, and the restarted server bakes again.
TEST_F(SceneRpcTest, KillDuringBakeKeepsAcknowledgedScenesAndRestartsCleanly) {
  auto acknowledged = client_->UploadScene(WriteUserScene("kept.glb"), "kept");
  ASSERT_TRUE(acknowledged.ok()) << acknowledged.status();
  const std::vector<std::string> stored_before = RepositoryEntries();

  // A bake far longer than the test: 100000 directions of the Cornell box.
  std::atomic<uint32_t> directions_done{0};
  Client baker({.address = server_->address(), .deadline = std::chrono::seconds(120)});
  std::thread bake_thread([&] {
    v1::ComputeObscurancesRequest request;
    request.mutable_scene()->set_name("cornell_box_visq");
    request.set_resolution(64);
    request.set_d_max(0.5);
    request.set_direction_count(100000);
    request.set_method(v1::ComputeObscurancesRequest::DEPTH_PEELING);  // the GPU bake, with its progress
    auto bake = baker.ComputeObscurances(
        request, [&](const v1::ObscuranceProgress& p) { directions_done = p.directions_done(); });
    EXPECT_FALSE(bake.ok()) << "the server died mid-bake";
  });
  for (int i = 0; i < 600 && directions_done < 2; ++i) std::this_thread::sleep_for(std::chrono::milliseconds(50));
  EXPECT_GE(directions_done.load(), 2u) << "the bake should be running when the server is killed";
  server_->Kill();
  bake_thread.join();

  client_.reset();
  StartServer({});
  EXPECT_EQ(ResidentNames(), (std::vector<std::string>{"cornell_box_visq", "kept"}));
  EXPECT_EQ(RepositoryEntries(), stored_before) << "a bake writes nothing to the repository";
  EXPECT_EQ(client_->GetScene("kept")->content_hash(), acknowledged->content_hash());

  // The new process has no bake to update, says so, and bakes again.
  v1::UpdateObscurancesRequest update;
  update.mutable_scene()->set_name("cornell_box_visq");
  EXPECT_EQ(client_->UpdateObscurances(update).status().code(), absl::StatusCode::kFailedPrecondition);
  v1::ComputeObscurancesRequest small;
  small.mutable_scene()->set_name("cornell_box_visq");
  small.set_resolution(16);
  small.set_d_max(0.5);
  small.set_direction_count(4);
  small.set_method(v1::ComputeObscurancesRequest::DEPTH_PEELING);
  auto rebake = client_->ComputeObscurances(small, nullptr);
  ASSERT_TRUE(rebake.ok()) << rebake.status();
  EXPECT_EQ(rebake->partial.DirectionCount(), 4u);
}

}  // namespace
}  // namespace visq
