// Uploads that used to end the server: the real visq-server on loopback, a
// LoadScene stream written by hand as a hostile client would, and the
// server's health asked afterwards.
#include <chrono>
#include <cstring>
#include <filesystem>
#include <optional>
#include <thread>

#include <grpcpp/generic/generic_stub.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include "repository_files.h"
#include "server_process.h"
#include "test_support.h"
#include "visq/v1/visq.grpc.pb.h"
#include "visq_client.h"

namespace visq {
namespace {

using client::Client;
using testing::ScratchDir;
using testing::ServerProcess;

// One LoadScene upload: a header, then `chunks` (file, data), then the end
// of the stream.
grpc::Status Upload(Client& client, const std::string& name, const std::string& main_file,
                    const std::vector<std::pair<std::string, std::string>>& chunks) {
  std::unique_ptr<grpc::ClientContext> context = client.NewContext();
  v1::SceneInfo response;
  std::unique_ptr<grpc::ClientWriter<v1::LoadSceneRequest>> writer = client.stub().LoadScene(context.get(), &response);
  v1::LoadSceneRequest header;
  header.mutable_header()->set_name(name);
  header.mutable_header()->set_upload_main_file(main_file);
  writer->Write(header);
  for (const auto& [file, data] : chunks) {
    v1::LoadSceneRequest chunk;
    chunk.mutable_chunk()->set_file(file);
    chunk.mutable_chunk()->set_data(data);
    if (!writer->Write(chunk)) break;
  }
  writer->WritesDone();
  return writer->Finish();
}

// One triangle as a .gltf and its .bin: a complete upload on its own.
std::vector<std::pair<std::string, std::string>> TriangleFiles() {
  const float positions[9] = {0, 0, 0, 1, 0, 0, 0, 1, 0};
  const uint16_t indices[4] = {0, 1, 2, 0};
  std::string bin(sizeof(positions) + sizeof(indices), '\0');
  std::memcpy(bin.data(), positions, sizeof(positions));
  std::memcpy(bin.data() + sizeof(positions), indices, sizeof(indices));
  const std::string gltf =
      R"({"asset":{"version":"2.0"},"scenes":[{"nodes":[0]}],"scene":0,"nodes":[{"mesh":0}],
     "meshes":[{"primitives":[{"attributes":{"POSITION":0},"indices":1}]}],
     "buffers":[{"uri":"t.bin","byteLength":44}],
     "bufferViews":[{"buffer":0,"byteOffset":0,"byteLength":36},{"buffer":0,"byteOffset":36,"byteLength":6}],
     "accessors":[{"bufferView":0,"componentType":5126,"count":3,"type":"VEC3","min":[0,0,0],"max":[1,1,0]},
                  {"bufferView":1,"componentType":5123,"count":3,"type":"SCALAR"}]})";
  return {{"t.bin", bin}, {"t.gltf", gltf}};
}

// A length-delimited field on the wire: tag, length (one byte), bytes.
std::string LengthDelimited(int field, const std::string& bytes) {
  EXPECT_LT(bytes.size(), 128u);
  return std::string(1, static_cast<char>(field << 3 | 2)) + static_cast<char>(bytes.size()) + bytes;
}

// A LoadScene stream of messages as bytes on the wire, left open after the
// last one: the client has not said it is done, so nothing may commit. The
// server's answer, or the deadline's.
grpc::Status UploadLeftOpen(const std::string& address, const std::vector<std::string>& messages) {
  auto channel = grpc::CreateChannel(address, grpc::InsecureChannelCredentials());
  grpc::GenericStub stub(channel);
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(15));
  grpc::CompletionQueue queue;
  auto call = stub.PrepareCall(&context, "/visq.v1.VisibilityService/LoadScene", &queue);
  auto wait = [&queue](intptr_t expected) {
    void* tag = nullptr;
    bool ok = false;
    queue.Next(&tag, &ok);
    EXPECT_EQ(reinterpret_cast<intptr_t>(tag), expected);
    return ok;
  };
  call->StartCall(reinterpret_cast<void*>(1));
  wait(1);
  for (const std::string& message : messages) {
    grpc::Slice slice(message.data(), message.size());
    grpc::ByteBuffer buffer(&slice, 1);
    call->Write(buffer, reinterpret_cast<void*>(2));
    if (!wait(2)) break;
  }
  grpc::ByteBuffer response;
  call->Read(&response, reinterpret_cast<void*>(3));
  wait(3);
  grpc::Status status;
  call->Finish(&status, reinterpret_cast<void*>(4));
  wait(4);
  queue.Shutdown();
  void* tag;
  bool ok;
  while (queue.Next(&tag, &ok)) {
  }
  return status;
}

// A header and a complete triangle upload, as wire bytes.
std::vector<std::string> TriangleUploadMessages(const std::string& name) {
  v1::LoadSceneRequest header;
  header.mutable_header()->set_name(name);
  header.mutable_header()->set_upload_main_file("t.gltf");
  std::vector<std::string> messages{header.SerializeAsString()};
  for (const auto& [file, data] : TriangleFiles()) {
    v1::LoadSceneRequest chunk;
    chunk.mutable_chunk()->set_file(file);
    chunk.mutable_chunk()->set_data(data);
    messages.push_back(chunk.SerializeAsString());
  }
  return messages;
}

// Nothing of scene `name` in the repository: not in the catalog, no staging.
void ExpectNothingStored(const std::filesystem::path& repo, const std::string& name) {
  const std::vector<std::string> stored = testing::StoredSceneNames(repo);
  EXPECT_EQ(std::count(stored.begin(), stored.end(), name), 0) << name;
  EXPECT_EQ(testing::StagingEntries(repo), 0);
}

// A chunk whose file name is not UTF-8 does not parse as a LoadSceneRequest.
// gRPC's generated reader reported it as the end of the stream, so the
// chunks before it were stored and acknowledged OK while the client was
// still sending; now the upload fails naming the field.
TEST(HostileUploads, ChunkThatDoesNotParseFailsTheUploadInsteadOfCommittingIt) {
  ScratchDir repo;
  auto server = ServerProcess::Start({repo.path(), {}});
  ASSERT_NE(server, nullptr);
  Client client(client::ClientOptions{.address = server->address()});

  std::vector<std::string> messages = TriangleUploadMessages("utf8");
  messages.push_back(LengthDelimited(2, LengthDelimited(1, "\xff\xfe.bin") + LengthDelimited(2, "abcd")));
  const grpc::Status status = UploadLeftOpen(server->address(), messages);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << status.error_message();
  EXPECT_NE(status.error_message().find("chunk.file: invalid UTF-8"), std::string::npos) << status.error_message();

  EXPECT_EQ(client.GetScene("utf8").status().code(), absl::StatusCode::kNotFound);
  ExpectNothingStored(repo.path(), "utf8");
  // The same upload, ended cleanly, is stored: only the bad message failed it.
  ASSERT_EQ(Upload(client, "utf8", "t.gltf", TriangleFiles()).error_code(), grpc::StatusCode::OK);
  EXPECT_TRUE(client.GetScene("utf8").ok());
  EXPECT_EQ(server->Stop(), 0) << server->Log();
}

// A message cut short (a chunk announcing 32 bytes and carrying 3) is not
// the end of the stream either.
TEST(HostileUploads, TruncatedMessageFailsTheUploadInsteadOfCommittingIt) {
  ScratchDir repo;
  auto server = ServerProcess::Start({repo.path(), {}});
  ASSERT_NE(server, nullptr);
  Client client(client::ClientOptions{.address = server->address()});

  std::vector<std::string> messages = TriangleUploadMessages("cut");
  messages.push_back(std::string("\x12\x20\x0a\x01x", 5));
  const grpc::Status status = UploadLeftOpen(server->address(), messages);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << status.error_message();
  EXPECT_NE(status.error_message().find("truncated or malformed"), std::string::npos) << status.error_message();

  EXPECT_EQ(client.GetScene("cut").status().code(), absl::StatusCode::kNotFound);
  ExpectNothingStored(repo.path(), "cut");
  EXPECT_EQ(server->Stop(), 0) << server->Log();
}

// An upload whose main file no chunk carries is the client's mistake: it
// was NOT_FOUND ("cannot open"), as if the server had lost a file; now it is
// INVALID_ARGUMENT naming the header's field, and nothing is stored.
TEST(HostileUploads, MainFileNeverSentIsInvalidArgumentNamingTheField) {
  ScratchDir repo;
  auto server = ServerProcess::Start({repo.path(), {}});
  ASSERT_NE(server, nullptr);
  Client client(client::ClientOptions{.address = server->address()});

  for (const auto& chunks : {std::vector<std::pair<std::string, std::string>>{{"t.bin", "abcd"}},
                             std::vector<std::pair<std::string, std::string>>{}}) {
    const grpc::Status status = Upload(client, "nomain", "a.gltf", chunks);
    EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << status.error_message();
    EXPECT_NE(status.error_message().find("header.upload_main_file 'a.gltf': never sent"), std::string::npos)
        << status.error_message();
    ExpectNothingStored(repo.path(), "nomain");
  }
  EXPECT_EQ(server->Stop(), 0) << server->Log();
}

// A LoadScene stream held open by the test: messages written as wire bytes,
// the answer awaited for at most a given time, cancelled with the object.
class OpenUpload {
 public:
  OpenUpload(const std::string& address, const std::vector<std::string>& messages)
      : channel_(grpc::CreateChannel(address, grpc::InsecureChannelCredentials())), stub_(channel_) {
    context_.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(60));
    call_ = stub_.PrepareCall(&context_, "/visq.v1.VisibilityService/LoadScene", &queue_);
    call_->StartCall(reinterpret_cast<void*>(1));
    Next(std::chrono::seconds(10));
    for (const std::string& message : messages) {
      grpc::Slice slice(message.data(), message.size());
      grpc::ByteBuffer buffer(&slice, 1);
      call_->Write(buffer, reinterpret_cast<void*>(2));
      if (!Next(std::chrono::seconds(10)).value_or(false)) break;
    }
    call_->Read(&response_, reinterpret_cast<void*>(3));
  }
  ~OpenUpload() {
    context_.TryCancel();
    if (!finishing_) {
      call_->Finish(&status_, reinterpret_cast<void*>(4));
    }
    queue_.Shutdown();
    void* tag;
    bool ok;
    while (queue_.Next(&tag, &ok)) {
    }
  }
  // The call's status once the server has ended it within `wait`; nullopt
  // while it is still open.
  std::optional<grpc::Status> Ended(std::chrono::milliseconds wait) {
    if (!read_done_) {
      if (!Next(wait)) return std::nullopt;
      read_done_ = true;
    }
    finishing_ = true;
    call_->Finish(&status_, reinterpret_cast<void*>(4));
    if (!Next(std::chrono::seconds(10))) return std::nullopt;
    return status_;
  }

 private:
  // The next completion's ok, or nullopt when none came within `wait`.
  std::optional<bool> Next(std::chrono::milliseconds wait) {
    void* tag = nullptr;
    bool ok = false;
    if (queue_.AsyncNext(&tag, &ok, std::chrono::system_clock::now() + wait) != grpc::CompletionQueue::GOT_EVENT)
      return std::nullopt;
    return ok;
  }

  std::shared_ptr<grpc::Channel> channel_;
  grpc::GenericStub stub_;
  grpc::ClientContext context_;
  grpc::CompletionQueue queue_;
  std::unique_ptr<grpc::GenericClientAsyncReaderWriter> call_;
  grpc::ByteBuffer response_;
  grpc::Status status_;
  bool read_done_ = false;
  bool finishing_ = false;
};

// The staging folders in the repository: one per upload in flight.
int StagingFolders(const std::filesystem::path& repo) { return testing::StagingEntries(repo); }

// Waits up to 5 s for the repository to hold `count` staging folders.
bool WaitForStagingFolders(const std::filesystem::path& repo, int count) {
  const auto give_up = std::chrono::steady_clock::now() + std::chrono::seconds(5);
  while (StagingFolders(repo) != count) {
    if (std::chrono::steady_clock::now() > give_up) return false;
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  return true;
}

// An upload that sends its header and a chunk, then nothing: it held its
// stream, a descriptor and a staging folder for as long as its client
// liked. Past --upload-idle-seconds it is aborted and its staging removed,
// while the client still holds the stream open.
TEST(HostileUploads, UploadThatSendsNothingIsAbortedAfterTheIdleLimit) {
  ScratchDir repo;
  auto server = ServerProcess::Start({repo.path(), {"--upload-idle-seconds", "1"}});
  ASSERT_NE(server, nullptr);

  std::vector<std::string> messages = TriangleUploadMessages("idle");
  messages.pop_back();  // header and t.bin; t.gltf never comes
  const auto start = std::chrono::steady_clock::now();
  OpenUpload upload(server->address(), messages);
  ASSERT_TRUE(WaitForStagingFolders(repo.path(), 1)) << server->Log();
  const std::optional<grpc::Status> status = upload.Ended(std::chrono::seconds(6));
  ASSERT_TRUE(status.has_value()) << "the idle upload was still open after 6 s";
  EXPECT_FALSE(status->ok());
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  EXPECT_GE(seconds, 0.9);
  EXPECT_TRUE(WaitForStagingFolders(repo.path(), 0)) << "the aborted upload's staging folder stayed";
  // The client sees CANCELLED at once; the server's log line, which names
  // the flag, follows the removal of the staging folder.
  const auto give_up = std::chrono::steady_clock::now() + std::chrono::seconds(5);
  while (server->Log().find("--upload-idle-seconds") == std::string::npos && std::chrono::steady_clock::now() < give_up)
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  EXPECT_NE(server->Log().find("--upload-idle-seconds"), std::string::npos) << server->Log();

  // An upload that keeps sending is not idle, however long it takes.
  Client client(client::ClientOptions{.address = server->address()});
  ASSERT_EQ(Upload(client, "busy", "t.gltf", TriangleFiles()).error_code(), grpc::StatusCode::OK);
  EXPECT_EQ(server->Stop(), 0) << server->Log();
}

// Uploads left open count against --max-uploads-per-client and
// --max-uploads-in-flight: the next one is RESOURCE_EXHAUSTED naming the
// flag (it used to be accepted, until the server ran out of descriptors),
// and a place freed is a place taken again.
TEST(HostileUploads, UploadsBeyondTheCapsAreRefused) {
  for (const std::string flag : {"--max-uploads-per-client", "--max-uploads-in-flight"}) {
    SCOPED_TRACE(flag);
    ScratchDir repo;
    const std::string other =
        flag == "--max-uploads-per-client" ? "--max-uploads-in-flight" : "--max-uploads-per-client";
    auto server = ServerProcess::Start({repo.path(), {flag, "2", other, "100"}});
    ASSERT_NE(server, nullptr);
    Client client(client::ClientOptions{.address = server->address()});

    std::vector<std::string> header = TriangleUploadMessages("held");
    header.resize(1);
    {
      auto first = std::make_unique<OpenUpload>(server->address(), header);
      OpenUpload second(server->address(), header);
      ASSERT_TRUE(WaitForStagingFolders(repo.path(), 2)) << server->Log();
      const grpc::Status refused = Upload(client, "third", "t.gltf", TriangleFiles());
      EXPECT_EQ(refused.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED) << refused.error_message();
      EXPECT_NE(refused.error_message().find(flag), std::string::npos) << refused.error_message();
      EXPECT_FALSE(client.GetScene("third").ok());

      first.reset();  // cancelled: its place is free again
      ASSERT_TRUE(WaitForStagingFolders(repo.path(), 1)) << server->Log();
      const grpc::Status accepted = Upload(client, "third", "t.gltf", TriangleFiles());
      EXPECT_TRUE(accepted.ok()) << accepted.error_message();
    }
    EXPECT_TRUE(WaitForStagingFolders(repo.path(), 0)) << server->Log();
    EXPECT_EQ(server->Stop(), 0) << server->Log();
  }
}

// A triangle placed by node 0 with `node` (its JSON) and, when `scales` is
// not empty, one EXT_mesh_gpu_instancing instance per scale.
std::vector<std::pair<std::string, std::string>> PlacedTriangleFiles(const std::string& node,
                                                                     const std::vector<float>& scales) {
  std::string bin = TriangleFiles()[0].second;
  for (float s : scales)
    for (int k = 0; k < 3; ++k) bin.append(reinterpret_cast<const char*>(&s), sizeof(s));
  const std::string instancing =
      scales.empty() ? "" : R"(,"extensions":{"EXT_mesh_gpu_instancing":{"attributes":{"SCALE":2}}})";
  std::string gltf = R"({"asset":{"version":"2.0"},"extensionsUsed":["EXT_mesh_gpu_instancing"],
     "scenes":[{"nodes":[0]}],"scene":0,"nodes":[{"mesh":0)" + node + instancing + R"(}],
     "meshes":[{"primitives":[{"attributes":{"POSITION":0},"indices":1}]}],
     "buffers":[{"uri":"t.bin","byteLength":)" + std::to_string(bin.size()) + R"(}],
     "bufferViews":[{"buffer":0,"byteOffset":0,"byteLength":36},{"buffer":0,"byteOffset":36,"byteLength":6},
                    {"buffer":0,"byteOffset":44,"byteLength":)" + std::to_string(bin.size() - 44) + R"(}],
     "accessors":[{"bufferView":0,"componentType":5126,"count":3,"type":"VEC3","min":[0,0,0],"max":[1,1,0]},
                  {"bufferView":1,"componentType":5123,"count":3,"type":"SCALAR"})";
  if (!scales.empty())
    gltf += R"(,{"bufferView":2,"componentType":5126,"count":)" + std::to_string(scales.size()) + R"(,"type":"VEC3"})";
  gltf += "]}";
  return {{"t.bin", bin}, {"t.gltf", gltf}};
}

// Instances scaled by 1e-40 were accepted (their condition number is 1),
// and a RAYCAST over them spun forever in Embree, whose float inverse of
// the transform overflows. A placement that shrinks its mesh below 1e-15
// is now refused, an instance's as a node's, naming which.
TEST(HostileUploads, PlacementsScaledBelowFloatPrecisionAreRefused) {
  ScratchDir repo;
  auto server = ServerProcess::Start({repo.path(), {}});
  ASSERT_NE(server, nullptr);
  Client client(client::ClientOptions{.address = server->address()});

  grpc::Status status = Upload(client, "tiny_instances", "t.gltf", PlacedTriangleFiles("", {1.0f, 1e-40f}));
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << status.error_message();
  EXPECT_NE(status.error_message().find(
                "nodes[0].extensions.EXT_mesh_gpu_instancing.attributes: instance 1: scales its mesh by"),
            std::string::npos)
      << status.error_message();
  status = Upload(client, "tiny_instances", "t.gltf", PlacedTriangleFiles("", {1.0f, 1e-16f}));
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << status.error_message();

  status = Upload(client, "tiny_node", "t.gltf", PlacedTriangleFiles(R"(,"scale":[1e-40,1e-40,1e-40])", {}));
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << status.error_message();
  EXPECT_NE(status.error_message().find("nodes[0]: scales its mesh by"), std::string::npos)
      << status.error_message();
  ExpectNothingStored(repo.path(), "tiny_instances");
  ExpectNothingStored(repo.path(), "tiny_node");

  // Small scales that float holds are kept.
  status = Upload(client, "small_instances", "t.gltf", PlacedTriangleFiles("", {1.0f, 1e-6f}));
  EXPECT_TRUE(status.ok()) << status.error_message();
  status = Upload(client, "small_node", "t.gltf", PlacedTriangleFiles(R"(,"scale":[1e-9,1e-9,1e-9])", {}));
  EXPECT_TRUE(status.ok()) << status.error_message();
  EXPECT_EQ(server->Stop(), 0) << server->Log();
}

// One chunk named "a.gltf/x" makes the main file "a.gltf" a folder: the
// loader read it through an ifstream, libstdc++ threw (EISDIR), nothing
// caught it, and the server aborted.
TEST(HostileUploads, MainFileThatIsAFolderFailsTheUploadNotTheServer) {
  ScratchDir repo;
  auto server = ServerProcess::Start({repo.path(), {}});
  ASSERT_NE(server, nullptr);
  Client client(client::ClientOptions{.address = server->address()});

  const grpc::Status status = Upload(client, "folder", "a.gltf", {{"a.gltf/x", "abcd"}});
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << status.error_message();
  EXPECT_NE(status.error_message().find("a.gltf: not a regular file"), std::string::npos) << status.error_message();

  auto health = client.Health();
  ASSERT_TRUE(health.ok()) << health.status() << "\n" << server->Log();
  EXPECT_EQ(*health, grpc::health::v1::HealthCheckResponse::SERVING);
  EXPECT_EQ(client.GetScene("folder").status().code(), absl::StatusCode::kNotFound);
  // Nothing of it is stored: the repository holds no scene of that name.
  EXPECT_TRUE(testing::StoredSceneNames(repo.path()).empty());
  EXPECT_EQ(server->Stop(), 0) << server->Log();
}

}  // namespace
}  // namespace visq
