// Static checks of deploy/, for what can break without a cluster (the image
// itself is built and run by container_test.sh, ./visq.sh test's container
// stage): every path the Dockerfile copies exists, every script it runs is
// the project's, and every manifest has the fields a cluster needs (probes,
// limits, the restricted profile).
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <map>
#include <regex>
#include <set>
#include <sstream>
#include <thread>

#include <gtest/gtest.h>
#include <yaml-cpp/yaml.h>

#include "deploy_files.h"

namespace visq {
namespace {

namespace fs = std::filesystem;
using namespace deploy_testing;

TEST(Dockerfile, EveryCopiedPathAndScriptExists) {
  const auto instructions = DockerInstructions();
  ASSERT_FALSE(instructions.empty());
  // The runtime-prebuilt stage's context is the one container_test.sh
  // makes: install-deps.sh and the two .debs under prebuilt/.
  const std::string container_test = Read(kSource / "tests/deploy/container_test.sh");
  int copies = 0, scripts = 0, prebuilt = 0;
  std::string stage;
  for (const auto& instruction : instructions) {
    std::istringstream words(instruction);
    std::string verb;
    words >> verb;
    if (verb == "FROM") stage = instruction.substr(instruction.rfind(' ') + 1);
    if (verb == "COPY" && instruction.find("--from=") == std::string::npos) {
      std::vector<std::string> args;
      for (std::string w; words >> w;) args.push_back(w);
      ASSERT_GE(args.size(), 2u) << instruction;
      for (size_t i = 0; i + 1 < args.size(); ++i) {
        if (stage == "runtime-prebuilt") {
          EXPECT_TRUE(args[i] == "prebuilt/visq-server.deb" || args[i] == "prebuilt/visq-client.deb") << args[i];
          ++prebuilt;
          continue;
        }
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
  EXPECT_EQ(prebuilt, 2) << "runtime-prebuilt copies the visq-server and visq-client .debs";
  EXPECT_NE(container_test.find("cp \"$server_deb\" \"$tmp/context/prebuilt/visq-server.deb\""), std::string::npos)
      << "container_test.sh must put the .debs where runtime-prebuilt copies them from";
  EXPECT_NE(container_test.find("cp \"$client_deb\" \"$tmp/context/prebuilt/visq-client.deb\""), std::string::npos);
  EXPECT_NE(container_test.find("cp \"$source_dir/deploy/install-deps.sh\" \"$tmp/context/deploy/\""),
            std::string::npos);
  EXPECT_GE(scripts, 1) << "the image must build with the project's own install script";
}

TEST(Dockerfile, RuntimeStageIsSlimNonRootWithGraphicsCapability) {
  const std::string text = Read(kSource / "deploy/Dockerfile");
  EXPECT_NE(text.find("FROM debian:bookworm AS build"), std::string::npos);
  EXPECT_NE(text.find("FROM debian:bookworm-slim AS runtime-base"), std::string::npos);
  EXPECT_NE(text.find("FROM runtime-base AS runtime-prebuilt"), std::string::npos);
  EXPECT_NE(text.find("install-deps.sh --runtime-only"), std::string::npos);
  EXPECT_NE(text.find("install-deps.sh --without-container-tools"), std::string::npos);
  // The last stage is what a build without --target makes: the release.
  EXPECT_NE(text.rfind("FROM runtime-base AS runtime\n"), std::string::npos);
  EXPECT_GT(text.rfind("FROM runtime-base AS runtime\n"), text.rfind("AS runtime-prebuilt"));
  EXPECT_NE(text.find("USER visq"), std::string::npos);
  EXPECT_NE(text.find("NVIDIA_DRIVER_CAPABILITIES=graphics"), std::string::npos);
  EXPECT_NE(text.find("VOLUME /var/lib/visq/scenes"), std::string::npos);
  // The binaries come from the .debs (cmake/Package.cmake), installed with dpkg.
  EXPECT_NE(text.find("ENTRYPOINT [\"/usr/bin/visq-server\"]"), std::string::npos);
  EXPECT_NE(text.find("RUN dpkg -i /tmp/visq-debs/visq-server.deb /tmp/visq-debs/visq-client.deb"), std::string::npos);
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

// The repository names no package mirror's or registry's host: a machine
// takes its mirror from its own apt sources (container_test.sh) and npm its
// registry from its own configuration. The hosts are split here so that
// this file does not name them either.
TEST(Repository, NoFileNamesAPackageMirrorsOrRegistrysHost) {
  const std::vector<std::string> hosts = {std::string("deb.") + "debian.org", std::string("security.") + "debian.org",
                                          std::string("registry.") + "npmjs.org", std::string("pypi.") + "org",
                                          std::string("archive.") + "ubuntu.com"};
  size_t files = 0;
  for (const char* top : {"deploy", "tests", "docs", "client", "server", "lib", "gpu", ".ci", "cmake"}) {
    if (!fs::exists(kSource / top)) continue;
    for (const auto& entry : fs::recursive_directory_iterator(kSource / top)) {
      if (!entry.is_regular_file() || entry.file_size() > (4u << 20)) continue;
      const std::string text = Read(entry.path());
      ++files;
      for (const std::string& host : hosts) EXPECT_EQ(text.find(host), std::string::npos) << entry.path() << ": " << host;
    }
  }
  for (const char* file : {"README.md", "visq.sh", "CMakeLists.txt"}) {
    const std::string text = Read(kSource / file);
    for (const std::string& host : hosts) EXPECT_EQ(text.find(host), std::string::npos) << file << ": " << host;
  }
  EXPECT_GT(files, 100u);
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

// A field set on the container, else on the pod (the container's wins).
YAML::Node Effective(const YAML::Node& pod, const YAML::Node& container, const std::string& field) {
  if (container["securityContext"] && container["securityContext"][field]) return container["securityContext"][field];
  if (pod["securityContext"] && pod["securityContext"][field]) return pod["securityContext"][field];
  return YAML::Node();
}

// The "restricted" Pod Security Standard's required fields, as the
// admission controller checks them (baseline's included: no host
// namespaces, no privileged containers, no hostPath), plus a read-only root
// filesystem.
TEST(Kubernetes, EveryPodMeetsTheRestrictedProfile) {
  const auto pods = PodSpecs();
  ASSERT_GE(pods.size(), 2u);
  static const std::set<std::string> allowed_volumes = {"configMap", "csi", "downwardAPI", "emptyDir", "ephemeral",
                                                        "persistentVolumeClaim", "projected", "secret"};
  for (const auto& [name, pod] : pods) {
    for (const char* host : {"hostNetwork", "hostPID", "hostIPC"})
      EXPECT_FALSE(pod[host] && pod[host].as<bool>()) << name << ": " << host;
    for (const auto& volume : pod["volumes"])
      for (const auto& field : volume) {
        if (field.first.as<std::string>() == "name") continue;
        EXPECT_TRUE(allowed_volumes.count(field.first.as<std::string>()))
            << name << ": volume type " << field.first.as<std::string>() << " is not allowed";
      }
    const auto containers = ContainersOf(pod);
    ASSERT_FALSE(containers.empty()) << name;
    for (const auto& c : containers) {
      const std::string where = name + "/" + c["name"].as<std::string>();
      const YAML::Node sc = c["securityContext"];
      ASSERT_TRUE(sc.IsMap()) << where << ": no securityContext";
      EXPECT_FALSE(sc["privileged"] && sc["privileged"].as<bool>()) << where;
      ASSERT_TRUE(sc["allowPrivilegeEscalation"]) << where;
      EXPECT_FALSE(sc["allowPrivilegeEscalation"].as<bool>()) << where;
      bool drops_all = false;
      for (const auto& cap : sc["capabilities"]["drop"]) drops_all |= cap.as<std::string>() == "ALL";
      EXPECT_TRUE(drops_all) << where << ": capabilities.drop must hold ALL";
      if (sc["capabilities"]["add"]) {
        for (const auto& cap : sc["capabilities"]["add"]) EXPECT_EQ(cap.as<std::string>(), "NET_BIND_SERVICE") << where;
      }
      const YAML::Node non_root = Effective(pod, c, "runAsNonRoot");
      EXPECT_TRUE(non_root && non_root.as<bool>()) << where << ": runAsNonRoot";
      const YAML::Node user = Effective(pod, c, "runAsUser");
      EXPECT_TRUE(user && user.as<int>() > 0) << where << ": runAsUser must be set and not 0";
      const YAML::Node seccomp = Effective(pod, c, "seccompProfile");
      ASSERT_TRUE(seccomp) << where << ": seccompProfile";
      const std::string type = seccomp["type"].as<std::string>();
      EXPECT_TRUE(type == "RuntimeDefault" || type == "Localhost") << where << ": seccompProfile " << type;
      EXPECT_TRUE(sc["readOnlyRootFilesystem"] && sc["readOnlyRootFilesystem"].as<bool>()) << where;
      // A read-only root needs somewhere to write temporary files.
      bool tmp = false;
      for (const auto& mount : c["volumeMounts"]) tmp |= mount["mountPath"].as<std::string>() == "/tmp";
      EXPECT_TRUE(tmp) << where << ": /tmp must be a volume (emptyDir) under a read-only root";
    }
  }
}

TEST(Kubernetes, EveryObjectIsInTheRestrictedNamespace) {
  const auto manifests = Manifests();
  ASSERT_EQ(manifests.count("Namespace"), 1u);
  const YAML::Node ns = manifests.find("Namespace")->second;
  const std::string name = ns["metadata"]["name"].as<std::string>();
  EXPECT_EQ(ns["metadata"]["labels"]["pod-security.kubernetes.io/enforce"].as<std::string>(), "restricted");
  for (const auto& [kind, doc] : manifests) {
    if (kind == "Namespace") continue;
    ASSERT_TRUE(doc["metadata"]["namespace"]) << kind << " " << doc["metadata"]["name"];
    EXPECT_EQ(doc["metadata"]["namespace"].as<std::string>(), name) << kind << " " << doc["metadata"]["name"];
  }
}

TEST(Kubernetes, ImagesArePinned) {
  int images = 0;
  for (const auto& [name, pod] : PodSpecs())
    for (const auto& c : ContainersOf(pod)) {
      const std::string image = c["image"].as<std::string>();
      ++images;
      if (image.find("@sha256:") != std::string::npos) continue;
      const size_t colon = image.rfind(':');
      ASSERT_TRUE(colon != std::string::npos && image.find('/', colon) == std::string::npos)
          << name << ": image " << image << " has no tag";
      const std::string tag = image.substr(colon + 1);
      EXPECT_EQ(tag.find("latest"), std::string::npos) << name << ": image " << image << " floats";
      EXPECT_TRUE(std::regex_search(tag, std::regex(R"(\d+\.\d+\.\d+)"))) << name << ": " << image
                                                                          << " is not a release";
    }
  EXPECT_GE(images, 2);
  const std::string compose = Read(kSource / "deploy/compose.yaml");
  EXPECT_EQ(compose.find(":latest"), std::string::npos) << "compose.yaml names a floating tag";
}

TEST(Kubernetes, EveryDeploymentHasAPodDisruptionBudget) {
  const auto manifests = Manifests();
  int deployments = 0;
  for (const auto& [kind, doc] : manifests) {
    if (kind != "Deployment") continue;
    ++deployments;
    const YAML::Node labels = doc["spec"]["template"]["metadata"]["labels"];
    bool covered = false;
    for (auto [it, end] = manifests.equal_range("PodDisruptionBudget"); it != end; ++it) {
      const YAML::Node pdb = it->second;
      EXPECT_EQ(pdb["apiVersion"].as<std::string>(), "policy/v1");
      EXPECT_TRUE(pdb["spec"]["maxUnavailable"] || pdb["spec"]["minAvailable"]);
      bool matches = pdb["spec"]["selector"]["matchLabels"].size() > 0;
      for (const auto& label : pdb["spec"]["selector"]["matchLabels"])
        matches &= labels[label.first.as<std::string>()] &&
                   labels[label.first.as<std::string>()].as<std::string>() == label.second.as<std::string>();
      covered |= matches;
    }
    EXPECT_TRUE(covered) << doc["metadata"]["name"] << " has no PodDisruptionBudget";
  }
  EXPECT_GE(deployments, 2);
}

// The seconds after --drain-seconds in `args`, or the server's default.
int DrainSeconds(const YAML::Node& args) {
  for (size_t i = 0; i + 1 < args.size(); ++i)
    if (args[i].as<std::string>() == "--drain-seconds") return args[i + 1].as<int>();
  return 10;
}

// server/main.cpp's kExitGrace: how long past the drain the process may
// take before its watchdog ends it.
constexpr int kExitGraceSeconds = 5;

TEST(Kubernetes, TheDrainEndsWithinTheGracePeriod) {
  bool found = false;
  for (const auto& [name, pod] : PodSpecs()) {
    if (name != "visq") continue;
    found = true;
    const int drain = DrainSeconds(pod["containers"][0]["args"]);
    const int grace = pod["terminationGracePeriodSeconds"] ? pod["terminationGracePeriodSeconds"].as<int>() : 30;
    EXPECT_GT(drain, 0);
    // The process's watchdog ends it 5 s after the drain whatever still
    // runs; the grace period leaves it that and a second more.
    EXPECT_GE(grace, drain + kExitGraceSeconds + 1) << "drain " << drain << " s, grace " << grace << " s";
  }
  EXPECT_TRUE(found);
  YAML::Node compose = YAML::LoadFile((kSource / "deploy/compose.yaml").string())["services"]["visq"];
  const int drain = compose["environment"]["VISQ_DRAIN_SECONDS"].as<int>();
  std::string grace = compose["stop_grace_period"].as<std::string>();
  ASSERT_EQ(grace.back(), 's');
  EXPECT_GE(std::stoi(grace), drain + kExitGraceSeconds + 1) << "compose: drain " << drain << " s, stop_grace_period " << grace;
}

// The farm bake (deploy/k8s/farm-bake/): an Indexed Job of shards and a
// merge Job that agree on the shards' folder and count, on volumes every pod
// of both can reach. farm_bake_job_test.cpp runs their commands.
TEST(Kubernetes, TheFarmBakeIsAnIndexedJobAndAMergeOverTheSameShards) {
  const YAML::Node bake = FindManifest("Job", "visq-bake");
  const YAML::Node merge = FindManifest("Job", "visq-bake-merge");
  ASSERT_TRUE(bake && merge);
  EXPECT_EQ(bake["spec"]["completionMode"].as<std::string>(), "Indexed");
  const int completions = bake["spec"]["completions"].as<int>();
  EXPECT_GE(completions, 2);
  EXPECT_GE(bake["spec"]["backoffLimit"].as<int>(), 1) << "a lost pod's index must be rerun";
  for (const YAML::Node& job : {bake, merge}) {
    const YAML::Node pod = job["spec"]["template"]["spec"];
    const std::string restart = pod["restartPolicy"].as<std::string>();
    EXPECT_TRUE(restart == "Never" || restart == "OnFailure") << restart;
    const YAML::Node container = pod["containers"][0];
    auto env = EnvOf(container);
    EXPECT_EQ(std::stoi(env["VISQ_BAKE_PODS"]), completions) << job["metadata"]["name"];
    // The shards' folder lies on the shared claim, mounted where it says.
    std::string shards_mount;
    for (const auto& mount : container["volumeMounts"])
      for (const auto& volume : pod["volumes"])
        if (volume["name"].as<std::string>() == mount["name"].as<std::string>() && volume["persistentVolumeClaim"] &&
            volume["persistentVolumeClaim"]["claimName"].as<std::string>() == "visq-bake-shards")
          shards_mount = mount["mountPath"].as<std::string>();
    ASSERT_FALSE(shards_mount.empty()) << job["metadata"]["name"] << " does not mount visq-bake-shards";
    EXPECT_EQ(env["VISQ_BAKE_SHARDS"].rfind(shards_mount + "/", 0), 0u) << env["VISQ_BAKE_SHARDS"];
    EXPECT_EQ(env["VISQ_BAKE_SHARDS"], EnvOf(bake["spec"]["template"]["spec"]["containers"][0])["VISQ_BAKE_SHARDS"]);
  }
  const YAML::Node claim = FindManifest("PersistentVolumeClaim", "visq-bake-shards");
  ASSERT_TRUE(claim);
  EXPECT_EQ(claim["spec"]["accessModes"][0].as<std::string>(), "ReadWriteMany") << "pods on many nodes write it";
  const YAML::Node baker = bake["spec"]["template"]["spec"]["containers"][0];
  EXPECT_EQ(baker["resources"]["limits"]["nvidia.com/gpu"].as<int>(), 1) << "a GPU per shard";
  const std::string script = YAML::Dump(baker["args"]);
  for (const char* part : {"JOB_COMPLETION_INDEX", "--partial-out", "--first-direction", "--total-directions"})
    EXPECT_NE(script.find(part), std::string::npos) << part;
  EXPECT_NE(YAML::Dump(merge["spec"]["template"]["spec"]["containers"][0]["args"]).find("obscurance-merge"),
            std::string::npos);
  // The bake pods read the replicas' repository, at the path they give it.
  bool repository = false;
  for (const auto& volume : bake["spec"]["template"]["spec"]["volumes"])
    repository |= volume["persistentVolumeClaim"] &&
                  volume["persistentVolumeClaim"]["claimName"].as<std::string>() == "visq-scenes";
  EXPECT_TRUE(repository);
  // `kubectl apply -f deploy/k8s/` is not recursive: it must not start a bake.
  for (const auto& entry : fs::directory_iterator(kSource / "deploy/k8s")) {
    if (entry.is_regular_file()) {
      EXPECT_EQ(Read(entry.path()).find("kind: Job"), std::string::npos) << entry.path();
    }
  }
}

// GPU nodes are usually tainted (nvidia.com/gpu:NoSchedule) so that only
// GPU work lands there: every pod that asks for a GPU (the replicas, the
// farm bake's pods) tolerates the taint and selects GPU nodes by a label; a
// pod that asks for none (the router, the merge) neither tolerates it nor
// selects GPU nodes, so it does not take a GPU node's room.
TEST(Kubernetes, EveryGpuPodToleratesTheGpuTaintAndSelectsGpuNodes) {
  int gpu_pods = 0;
  for (const auto& [name, pod] : PodSpecs()) {
    bool wants_gpu = false;
    for (const auto& c : ContainersOf(pod))
      wants_gpu |= c["resources"]["limits"]["nvidia.com/gpu"] && c["resources"]["limits"]["nvidia.com/gpu"].as<int>() > 0;
    bool tolerates = false;
    for (const auto& t : pod["tolerations"])
      tolerates |= t["key"].as<std::string>() == "nvidia.com/gpu" && t["operator"].as<std::string>() == "Exists" &&
                   t["effect"].as<std::string>() == "NoSchedule";
    const YAML::Node selector = pod["nodeSelector"];
    const bool selects_gpu = selector && selector["nvidia.com/gpu.present"] &&
                             selector["nvidia.com/gpu.present"].as<std::string>() == "true";
    if (!wants_gpu) {
      EXPECT_FALSE(tolerates) << name << " asks for no GPU but tolerates the GPU taint";
      EXPECT_FALSE(selects_gpu) << name << " asks for no GPU but selects GPU nodes";
      continue;
    }
    ++gpu_pods;
    EXPECT_TRUE(tolerates) << name << ": no toleration {nvidia.com/gpu, Exists, NoSchedule}";
    EXPECT_TRUE(selects_gpu) << name << ": no nodeSelector nvidia.com/gpu.present: \"true\"";
  }
  EXPECT_GE(gpu_pods, 2) << "the replicas and the farm bake's pods";
  EXPECT_TRUE(FindManifest("Job", "visq-bake-merge")) << "the merge Job, which needs no GPU, is checked above";
}

// deploy/k8s/optional/: objects a cluster may lack the means for (an
// ingress controller, Prometheus Operator's CRDs), so kept out of
// `kubectl apply -f deploy/k8s/` (which does not recurse into folders).
const fs::path kOptional = kSource / "deploy/k8s/optional";

std::vector<YAML::Node> OptionalManifests(const std::string& kind) {
  std::vector<YAML::Node> out;
  for (const auto& entry : fs::directory_iterator(kOptional))
    if (entry.is_regular_file() && entry.path().extension() == ".yaml")
      for (const YAML::Node& doc : YAML::LoadAllFromFile(entry.path().string()))
        if (doc && doc.IsMap() && doc["kind"].as<std::string>() == kind) out.push_back(doc);
  return out;
}

bool LabelsMatch(const YAML::Node& match_labels, const YAML::Node& labels) {
  if (!match_labels || match_labels.size() == 0) return false;
  for (const auto& label : match_labels) {
    const std::string key = label.first.as<std::string>();
    if (!labels[key] || labels[key].as<std::string>() != label.second.as<std::string>()) return false;
  }
  return true;
}

// The ServiceMonitor selects a Service by its labels and scrapes the port
// the endpoint names: some Service must carry those labels and that port,
// whose target is the visq pods' `metrics` container port (9464, where
// --metrics-address listens), and the Service must select those pods.
TEST(Kubernetes, TheServiceMonitorScrapesTheReplicasMetricsPortThroughAService) {
  const auto monitors = OptionalManifests("ServiceMonitor");
  ASSERT_EQ(monitors.size(), 1u);
  const YAML::Node monitor = monitors[0];
  EXPECT_EQ(monitor["apiVersion"].as<std::string>(), "monitoring.coreos.com/v1");
  EXPECT_EQ(monitor["metadata"]["namespace"].as<std::string>(), "visq");
  const YAML::Node replicas = FindManifest("Deployment", "visq");
  ASSERT_TRUE(replicas);
  const YAML::Node pod_labels = replicas["spec"]["template"]["metadata"]["labels"];
  int metrics_port = 0;
  for (const auto& port : replicas["spec"]["template"]["spec"]["containers"][0]["ports"])
    if (port["name"].as<std::string>() == "metrics") metrics_port = port["containerPort"].as<int>();
  ASSERT_EQ(metrics_port, 9464);
  EXPECT_NE(YAML::Dump(replicas["spec"]["template"]["spec"]["containers"][0]["args"]).find("0.0.0.0:9464"),
            std::string::npos);
  ASSERT_EQ(monitor["spec"]["endpoints"].size(), 1u);
  const YAML::Node endpoint = monitor["spec"]["endpoints"][0];
  const std::string port_name = endpoint["port"].as<std::string>();
  EXPECT_EQ(endpoint["path"].as<std::string>(), "/metrics");
  const auto manifests = Manifests();
  int scraped = 0;
  for (auto [it, end] = manifests.equal_range("Service"); it != end; ++it) {
    const YAML::Node service = it->second;
    if (!LabelsMatch(monitor["spec"]["selector"]["matchLabels"], service["metadata"]["labels"])) continue;
    const std::string name = service["metadata"]["name"].as<std::string>();
    EXPECT_TRUE(LabelsMatch(service["spec"]["selector"], pod_labels)) << name << " does not select the replicas";
    bool has_port = false;
    for (const auto& port : service["spec"]["ports"]) {
      if (port["name"].as<std::string>() != port_name) continue;
      has_port = true;
      const std::string target = port["targetPort"].as<std::string>();
      EXPECT_TRUE(target == "metrics" || target == std::to_string(metrics_port)) << name << " targets " << target;
    }
    EXPECT_TRUE(has_port) << name << " has no port named " << port_name;
    ++scraped;
  }
  EXPECT_EQ(scraped, 1) << "the ServiceMonitor must select exactly one Service (the headless visq-replicas)";
}

// The Ingress carries gRPC over TLS to the router's Service, on the port
// the router listens on, so the scene hashing stays in the path.
TEST(Kubernetes, TheIngressCarriesGrpcOverTlsToTheVisqServicesGrpcPort) {
  const auto ingresses = OptionalManifests("Ingress");
  ASSERT_EQ(ingresses.size(), 1u);
  const YAML::Node ingress = ingresses[0];
  EXPECT_EQ(ingress["apiVersion"].as<std::string>(), "networking.k8s.io/v1");
  EXPECT_EQ(ingress["metadata"]["annotations"]["nginx.ingress.kubernetes.io/backend-protocol"].as<std::string>(),
            "GRPC");
  ASSERT_EQ(ingress["spec"]["tls"].size(), 1u);
  const YAML::Node tls = ingress["spec"]["tls"][0];
  EXPECT_TRUE(tls["secretName"].IsScalar());
  std::set<std::string> tls_hosts;
  for (const auto& host : tls["hosts"]) tls_hosts.insert(host.as<std::string>());
  const YAML::Node service = FindManifest("Service", "visq");
  ASSERT_TRUE(service);
  int backends = 0;
  for (const auto& rule : ingress["spec"]["rules"]) {
    ASSERT_TRUE(rule["host"]) << "a rule without a host has no certificate";
    EXPECT_TRUE(tls_hosts.count(rule["host"].as<std::string>())) << rule["host"] << " is not in tls.hosts";
    for (const auto& path : rule["http"]["paths"]) {
      const YAML::Node backend = path["backend"]["service"];
      EXPECT_EQ(backend["name"].as<std::string>(), "visq");
      bool grpc_port = false;
      for (const auto& port : service["spec"]["ports"]) {
        const bool named = backend["port"]["name"] && backend["port"]["name"].as<std::string>() == port["name"].as<std::string>();
        const bool numbered = backend["port"]["number"] && backend["port"]["number"].as<int>() == port["port"].as<int>();
        if (named || numbered) grpc_port = port["name"].as<std::string>() == "grpc";
      }
      EXPECT_TRUE(grpc_port) << "the backend is not the visq Service's grpc port";
      ++backends;
    }
  }
  EXPECT_GE(backends, 1);
}

// `kubectl apply -f deploy/k8s/` applies the top folder's files only: none
// of them may need what a cluster may lack (an ingress controller, the
// Operator's CRDs), and the optional objects live only below it.
TEST(Kubernetes, TheOptionalManifestsAreNotAppliedByDefault) {
  ASSERT_TRUE(fs::is_directory(kOptional));
  EXPECT_EQ(OptionalManifests("Ingress").size() + OptionalManifests("ServiceMonitor").size(), 2u);
  int files = 0;
  for (const auto& entry : fs::directory_iterator(kSource / "deploy/k8s")) {
    if (!entry.is_regular_file() || entry.path().extension() != ".yaml") continue;
    ++files;
    for (const YAML::Node& doc : YAML::LoadAllFromFile(entry.path().string())) {
      if (!doc || !doc.IsMap()) continue;
      const std::string kind = doc["kind"].as<std::string>();
      EXPECT_TRUE(kind != "Ingress" && kind != "ServiceMonitor" && kind != "Job")
          << entry.path() << " holds a " << kind << ", which is optional";
      EXPECT_EQ(doc["apiVersion"].as<std::string>().find("monitoring.coreos.com"), std::string::npos) << entry.path();
    }
  }
  EXPECT_GE(files, 5);
  const std::string guide = Read(kSource / "docs/deploy.md");
  for (const char* step : {"kubectl apply -f deploy/k8s/optional/ingress.yaml",
                           "deploy/k8s/optional/servicemonitor.yaml"})
    EXPECT_NE(guide.find(step), std::string::npos) << "docs/deploy.md does not say: " << step;
}

// What the manifests cannot know, the deploy guide says: that the image is
// built and pushed to the studio's registry and where its name is set, that
// the repository's claim needs a ReadWriteMany class (and what to do
// without one), and how machines outside the cluster reach it.
TEST(Kubernetes, TheDeployGuideSaysHowToPushTheImageAndThatTheRepositoryNeedsReadWriteMany) {
  const std::string guide = Read(kSource / "docs/deploy.md");
  for (const char* needed :
       {"docker build -f deploy/Dockerfile -t REGISTRY/visq:0.1.0", "docker push REGISTRY/visq:0.1.0",
        "kubectl -n visq set image deployment/visq visq=REGISTRY/visq:0.1.0", "images:",
        "deploy/k8s/farm-bake/obscurance-bake-job.yaml", "ReadWriteMany", "ReadWriteOnce", "Pending",
        "volumeClaimTemplates", "initContainer", "git lfs", "SQLite", "backend-protocol: GRPC",
        "LoadBalancer", "VISQ_TLS_CERT", "nvidia.com/gpu.present"})
    EXPECT_NE(guide.find(needed), std::string::npos) << "docs/deploy.md does not say: " << needed;
  // Every manifest naming the image is named where the guide says to set it.
  int naming = 0;
  for (const auto& entry : fs::recursive_directory_iterator(kSource / "deploy/k8s")) {
    if (!entry.is_regular_file() || Read(entry.path()).find("image: visq:") == std::string::npos) continue;
    ++naming;
    const std::string relative = fs::relative(entry.path(), kSource).generic_string();
    EXPECT_NE(guide.find(relative), std::string::npos) << "docs/deploy.md does not name " << relative;
  }
  EXPECT_GE(naming, 2);
}

// Replicas on several nodes share one repository, so every server that
// opens it (the replicas, the farm bake's pods) reads one PostgreSQL catalog
// from one Secret, and each replica is named by its pod (a start clears only
// its own staging). The Secret is required: a pod without it must not start
// on a SQLite file shared over the network.
TEST(Kubernetes, EveryServerOnTheSharedRepositoryReadsTheCatalogFromOneSecret) {
  const YAML::Node replicas = FindManifest("Deployment", "visq");
  const YAML::Node bake = FindManifest("Job", "visq-bake");
  ASSERT_TRUE(replicas && bake);
  for (const YAML::Node& owner : {replicas, bake}) {
    const std::string name = owner["metadata"]["name"].as<std::string>();
    const YAML::Node container = owner["spec"]["template"]["spec"]["containers"][0];
    auto variable = [&](const std::string& wanted) -> YAML::Node {
      for (const YAML::Node& e : container["env"])
        if (e["name"].as<std::string>() == wanted) return e;
      return YAML::Node(YAML::NodeType::Undefined);
    };
    const YAML::Node catalog = variable("VISQ_CATALOG");
    const YAML::Node replica_id = variable("VISQ_REPLICA_ID");
    ASSERT_TRUE(catalog) << name << " does not set VISQ_CATALOG";
    const YAML::Node secret = catalog["valueFrom"]["secretKeyRef"];
    ASSERT_TRUE(secret) << name << ": the catalog's URI holds a password, so it comes from a Secret";
    EXPECT_EQ(secret["name"].as<std::string>(), "visq-catalog") << name;
    EXPECT_EQ(secret["key"].as<std::string>(), "uri") << name;
    EXPECT_FALSE(secret["optional"] && secret["optional"].as<bool>()) << name;
    ASSERT_TRUE(replica_id) << name << " does not set VISQ_REPLICA_ID";
    EXPECT_EQ(replica_id["valueFrom"]["fieldRef"]["fieldPath"].as<std::string>(), "metadata.name") << name;
  }
  const std::string guide = Read(kSource / "docs/deploy.md");
  EXPECT_NE(guide.find("create secret generic visq-catalog"), std::string::npos)
      << "the deploy guide must give the step that makes the catalog's Secret";
}

// The deploy guide (docs/deploy.md, linked from the README) is where an
// operator reads how to run the compose file.
TEST(Compose, TheTokenSecretIsMadeByAStepTheDeployGuideGivesAndNeverCommitted) {
  YAML::Node compose = YAML::LoadFile((kSource / "deploy/compose.yaml").string());
  const std::string file = compose["secrets"]["visq_token"]["file"].as<std::string>();
  const std::string in_repo = "deploy/" + fs::path(file).filename().string();
  EXPECT_NE(Read(kSource / "docs/deploy.md").find(in_repo), std::string::npos)
      << "docs/deploy.md must say how to make " << in_repo;
  EXPECT_NE(Read(kSource / ".gitignore").find("/" + in_repo), std::string::npos) << in_repo << " must be ignored";
}

// The image's defaults start the real server: with the Dockerfile's ENV and
// nothing else (the volume and port moved to a scratch folder and a free
// port), it reaches SERVING and has made its token in the volume.
TEST(Dockerfile, TheDefaultsStartAndMakeATokenInTheVolume) {
  auto env = DockerEnv();
  ASSERT_TRUE(env.count("VISQ_AUTH_TOKEN_FILE"));
  const std::string volume = "/var/lib/visq/scenes";
  ASSERT_EQ(env["VISQ_SCENE_REPO"], volume);
  ASSERT_EQ(env["VISQ_AUTH_TOKEN_FILE"].rfind(volume + "/", 0), 0u) << "the token must live in the volume";
  ASSERT_EQ(env["VISQ_ADDRESS"], "0.0.0.0:50051");
  const fs::path scratch = fs::temp_directory_path() / ("visq-docker-env-" + std::to_string(::getpid()));
  fs::create_directories(scratch / "scenes");
  for (auto& [key, value] : env)
    if (value.rfind(volume, 0) == 0) value = (scratch / "scenes").string() + value.substr(volume.size());
  env["VISQ_ADDRESS"] = "0.0.0.0:0";
  env["VISQ_PORT_FILE"] = (scratch / "port").string();
  const pid_t pid = ::fork();
  ASSERT_GE(pid, 0);
  if (pid == 0) {
    for (const auto& [key, value] : env) ::setenv(key.c_str(), value.c_str(), 1);
    const std::string log = (scratch / "log").string();
    std::freopen(log.c_str(), "w", stdout);
    std::freopen(log.c_str(), "a", stderr);
    ::execl(VISQ_SERVER_BINARY, VISQ_SERVER_BINARY, static_cast<char*>(nullptr));
    std::_Exit(127);
  }
  bool started = false;
  for (int i = 0; i < 600 && !started; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
    started = Read(scratch / "log").find("health SERVING") != std::string::npos;
    int status = 0;
    if (::waitpid(pid, &status, WNOHANG) == pid) break;
  }
  const std::string log = Read(scratch / "log");
  EXPECT_TRUE(started) << log;
  const fs::path token = env["VISQ_AUTH_TOKEN_FILE"];
  EXPECT_TRUE(fs::exists(token)) << log;
  EXPECT_NE(log.find(token.string()), std::string::npos) << "the log names where the token is\n" << log;
  ::kill(pid, SIGTERM);
  int status = 0;
  ::waitpid(pid, &status, 0);
  EXPECT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0) << log;
  std::error_code ec;
  fs::remove_all(scratch, ec);
}

}  // namespace
}  // namespace visq
