// Static checks of deploy/: there is no container engine or cluster here,
// so the Dockerfile and manifests are checked for what can break without
// one — every path the Dockerfile copies exists, every script it runs is the
// project's, and every manifest has the fields the issue requires.
#include <filesystem>
#include <fstream>
#include <map>
#include <regex>
#include <sstream>

#include <gtest/gtest.h>
#include <yaml-cpp/yaml.h>

namespace visq {
namespace {

namespace fs = std::filesystem;
const fs::path kSource = VISQ_SOURCE_DIR;

std::string Read(const fs::path& path) {
  std::ifstream in(path);
  std::stringstream text;
  text << in.rdbuf();
  return text.str();
}

// Dockerfile instructions, with continuation lines joined.
std::vector<std::string> DockerInstructions() {
  std::vector<std::string> out;
  std::istringstream in(Read(kSource / "deploy/Dockerfile"));
  std::string line, current;
  while (std::getline(in, line)) {
    if (line.empty() || line[0] == '#') continue;
    if (!line.empty() && line.back() == '\\') {
      current += line.substr(0, line.size() - 1) + " ";
      continue;
    }
    out.push_back(current + line);
    current.clear();
  }
  return out;
}

TEST(Dockerfile, EveryCopiedPathAndScriptExists) {
  const auto instructions = DockerInstructions();
  ASSERT_FALSE(instructions.empty());
  int copies = 0, scripts = 0;
  for (const auto& instruction : instructions) {
    std::istringstream words(instruction);
    std::string verb;
    words >> verb;
    if (verb == "COPY" && instruction.find("--from=") == std::string::npos) {
      std::vector<std::string> args;
      for (std::string w; words >> w;) args.push_back(w);
      ASSERT_GE(args.size(), 2u) << instruction;
      for (size_t i = 0; i + 1 < args.size(); ++i) {
        EXPECT_TRUE(fs::exists(kSource / args[i])) << "COPY source missing: " << args[i];
        ++copies;
      }
    }
    if (verb == "RUN") {
      static const std::regex script(R"((deploy/[A-Za-z0-9_./-]+\.sh))");
      for (std::sregex_iterator it(instruction.begin(), instruction.end(), script), end; it != end; ++it) {
        EXPECT_TRUE(fs::exists(kSource / (*it)[1].str())) << "script missing: " << (*it)[1];
        ++scripts;
      }
    }
  }
  EXPECT_GT(copies, 5);
  EXPECT_GE(scripts, 1) << "the image must build with the project's own install script";
}

TEST(Dockerfile, RuntimeStageIsSlimNonRootWithGraphicsCapability) {
  const std::string text = Read(kSource / "deploy/Dockerfile");
  EXPECT_NE(text.find("FROM debian:bookworm AS build"), std::string::npos);
  EXPECT_NE(text.find("FROM debian:bookworm-slim AS runtime"), std::string::npos);
  EXPECT_NE(text.find("install-deps.sh --runtime-only"), std::string::npos);
  EXPECT_NE(text.find("USER visq"), std::string::npos);
  EXPECT_NE(text.find("NVIDIA_DRIVER_CAPABILITIES=graphics"), std::string::npos);
  EXPECT_NE(text.find("VOLUME /var/lib/visq/scenes"), std::string::npos);
  EXPECT_NE(text.find("ENTRYPOINT [\"/usr/local/bin/visq-server\"]"), std::string::npos);
}

TEST(Compose, ServiceHasVolumeGpuAndLoopbackPort) {
  YAML::Node compose = YAML::LoadFile((kSource / "deploy/compose.yaml").string());
  YAML::Node visq = compose["services"]["visq"];
  ASSERT_TRUE(visq.IsMap());
  EXPECT_EQ(visq["build"]["dockerfile"].as<std::string>(), "deploy/Dockerfile");
  EXPECT_EQ(visq["ports"][0].as<std::string>().rfind("127.0.0.1:", 0), 0u);
  EXPECT_TRUE(visq["volumes"].IsSequence());
  EXPECT_TRUE(visq["deploy"]["resources"]["reservations"]["devices"].IsSequence());
}

// Every document of every manifest in deploy/k8s, by kind.
std::multimap<std::string, YAML::Node> Manifests() {
  std::multimap<std::string, YAML::Node> out;
  for (const auto& entry : fs::directory_iterator(kSource / "deploy/k8s"))
    for (const YAML::Node& doc : YAML::LoadAllFromFile(entry.path().string()))
      if (doc && doc.IsMap()) out.emplace(doc["kind"].as<std::string>(), doc);
  return out;
}

TEST(Kubernetes, ManifestsParseAndHaveApiVersionKindAndName) {
  const auto manifests = Manifests();
  EXPECT_GE(manifests.size(), 5u);
  for (const auto& [kind, doc] : manifests) {
    EXPECT_TRUE(doc["apiVersion"].IsScalar()) << kind;
    EXPECT_TRUE(doc["metadata"]["name"].IsScalar()) << kind;
  }
  for (const char* kind : {"Deployment", "Service", "PersistentVolumeClaim", "ConfigMap"})
    EXPECT_GE(manifests.count(kind), 1u) << kind;
}

TEST(Kubernetes, VisqDeploymentHasGpuProbesLimitsAndTheRepositoryVolume) {
  const auto manifests = Manifests();
  const YAML::Node* visq = nullptr;
  for (const auto& [kind, doc] : manifests)
    if (kind == "Deployment" && doc["metadata"]["name"].as<std::string>() == "visq") visq = &doc;
  ASSERT_NE(visq, nullptr);
  const YAML::Node pod = (*visq)["spec"]["template"]["spec"];
  EXPECT_TRUE(pod["securityContext"]["runAsNonRoot"].as<bool>());
  const YAML::Node container = pod["containers"][0];
  EXPECT_EQ(container["resources"]["limits"]["nvidia.com/gpu"].as<int>(), 1);
  EXPECT_TRUE(container["resources"]["limits"]["memory"].IsScalar());
  for (const char* probe : {"startupProbe", "readinessProbe", "livenessProbe"})
    EXPECT_EQ(container[probe]["grpc"]["port"].as<int>(), 50051) << probe << " must be a native gRPC probe";
  EXPECT_GE(container["startupProbe"]["periodSeconds"].as<int>() *
                container["startupProbe"]["failureThreshold"].as<int>(),
            300)
      << "the startup probe must allow minutes for large scenes";
  bool mounts_claim = false;
  for (const auto& volume : pod["volumes"])
    if (volume["persistentVolumeClaim"]) mounts_claim |= volume["persistentVolumeClaim"]["claimName"].IsScalar();
  EXPECT_TRUE(mounts_claim);
  const std::string env = YAML::Dump(container["env"]);
  EXPECT_NE(env.find("graphics"), std::string::npos) << "NVIDIA_DRIVER_CAPABILITIES must include graphics";
}

TEST(Kubernetes, RouterHashesTheSceneHeader) {
  const auto manifests = Manifests();
  bool found = false;
  for (const auto& [kind, doc] : manifests) {
    if (kind != "ConfigMap") continue;
    const YAML::Node envoy = YAML::Load(doc["data"]["envoy.yaml"].as<std::string>());
    const YAML::Node cluster = envoy["static_resources"]["clusters"][0];
    EXPECT_EQ(cluster["lb_policy"].as<std::string>(), "RING_HASH");
    const std::string routes = YAML::Dump(envoy["static_resources"]["listeners"]);
    EXPECT_NE(routes.find("x-visq-scene"), std::string::npos);
    found = true;
  }
  EXPECT_TRUE(found);
}

}  // namespace
}  // namespace visq
