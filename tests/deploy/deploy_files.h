// Reading deploy/ as the tests see it: the Dockerfile's instructions and
// ENV, and every Kubernetes manifest with its pod specs.
#pragma once

#include <filesystem>
#include <map>
#include <string>
#include <utility>
#include <vector>

#include <yaml-cpp/yaml.h>

namespace visq::deploy_testing {

inline const std::filesystem::path kSource = VISQ_SOURCE_DIR;

std::string Read(const std::filesystem::path& path);

// Dockerfile instructions, comments dropped, continuation lines joined.
std::vector<std::string> DockerInstructions();
// The Dockerfile's ENV, as the image's defaults.
std::map<std::string, std::string> DockerEnv();

// Every document of every manifest under deploy/k8s (subfolders included),
// by kind.
std::multimap<std::string, YAML::Node> Manifests();
// The pod specs of every workload in the manifests, with the object's name.
std::vector<std::pair<std::string, YAML::Node>> PodSpecs();
std::vector<YAML::Node> ContainersOf(const YAML::Node& pod);
// The manifest object of `kind` named `name`; an empty node if none.
YAML::Node FindManifest(const std::string& kind, const std::string& name);
// A container's env as name -> value (only literal values).
std::map<std::string, std::string> EnvOf(const YAML::Node& container);

}  // namespace visq::deploy_testing
