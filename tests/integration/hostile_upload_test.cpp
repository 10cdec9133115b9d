// Uploads that used to end the server: the real visq-server on loopback, a
// LoadScene stream written by hand as a hostile client would, and the
// server's health asked afterwards.
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

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
  EXPECT_FALSE(std::filesystem::exists(repo.path() / "folder"));
  EXPECT_EQ(server->Stop(), 0) << server->Log();
}

}  // namespace
}  // namespace visq
