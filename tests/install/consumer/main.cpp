// visq_consumer ADDRESS: waits until the server is SERVING, then prints its
// health and one line per resident scene ("scene NAME TRIANGLES"). The
// bearer token, where the server wants one, comes from $VISQ_TOKEN.
#include <chrono>
#include <cstdio>
#include <cstdlib>

#include <visq/visq_client.h>

int main(int argc, char** argv) {
  if (argc != 2) {
    std::fprintf(stderr, "usage: %s HOST[:PORT]\n", argv[0]);
    return 2;
  }
  visq::client::ClientOptions options;
  options.address = argv[1];
  if (const char* token = std::getenv("VISQ_TOKEN")) options.auth_token = token;
  visq::client::Client client(options);
  if (const visq::Status ready = client.WaitUntilServing(std::chrono::seconds(60)); !ready.ok()) {
    std::fprintf(stderr, "not serving: %s\n", ready.ToString().c_str());
    return 1;
  }
  const visq::StatusOr<grpc::health::v1::HealthCheckResponse::ServingStatus> health = client.Health();
  const visq::StatusOr<visq::v1::ListScenesResponse> scenes = client.ListScenes();
  if (!health.ok() || !scenes.ok()) {
    std::fprintf(stderr, "%s\n", (health.ok() ? scenes.status() : health.status()).ToString().c_str());
    return 1;
  }
  std::printf("health %s\n", grpc::health::v1::HealthCheckResponse::ServingStatus_Name(*health).c_str());
  for (const visq::v1::SceneInfo& scene : scenes->scenes())
    std::printf("scene %s %llu\n", scene.name().c_str(), static_cast<unsigned long long>(scene.triangle_count()));
  return 0;
}
