#include "deploy_files.h"

#include <fstream>
#include <sstream>

namespace visq::deploy_testing {

namespace fs = std::filesystem;

std::string Read(const fs::path& path) {
  std::ifstream in(path);
  std::stringstream text;
  text << in.rdbuf();
  return text.str();
}

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

std::map<std::string, std::string> DockerEnv() {
  std::map<std::string, std::string> env;
  for (const auto& instruction : DockerInstructions()) {
    std::istringstream words(instruction);
    std::string verb;
    words >> verb;
    if (verb != "ENV") continue;
    for (std::string w; words >> w;)
      if (const size_t eq = w.find('='); eq != std::string::npos) env[w.substr(0, eq)] = w.substr(eq + 1);
  }
  return env;
}

std::multimap<std::string, YAML::Node> Manifests() {
  std::multimap<std::string, YAML::Node> out;
  for (const auto& entry : fs::recursive_directory_iterator(kSource / "deploy/k8s")) {
    if (!entry.is_regular_file() || entry.path().extension() != ".yaml") continue;
    for (const YAML::Node& doc : YAML::LoadAllFromFile(entry.path().string()))
      if (doc && doc.IsMap()) out.emplace(doc["kind"].as<std::string>(), doc);
  }
  return out;
}

std::vector<std::pair<std::string, YAML::Node>> PodSpecs() {
  std::vector<std::pair<std::string, YAML::Node>> out;
  for (const auto& [kind, doc] : Manifests()) {
    if (kind == "Pod") out.emplace_back(doc["metadata"]["name"].as<std::string>(), doc["spec"]);
    if (kind == "Deployment" || kind == "StatefulSet" || kind == "DaemonSet" || kind == "Job")
      out.emplace_back(doc["metadata"]["name"].as<std::string>(), doc["spec"]["template"]["spec"]);
  }
  return out;
}

std::vector<YAML::Node> ContainersOf(const YAML::Node& pod) {
  std::vector<YAML::Node> out;
  for (const char* list : {"initContainers", "containers", "ephemeralContainers"})
    if (pod[list])
      for (const auto& c : pod[list]) out.push_back(c);
  return out;
}

YAML::Node FindManifest(const std::string& kind, const std::string& name) {
  for (const auto& [k, doc] : Manifests())
    if (k == kind && doc["metadata"]["name"].as<std::string>() == name) return doc;
  return YAML::Node();
}

std::map<std::string, std::string> EnvOf(const YAML::Node& container) {
  std::map<std::string, std::string> env;
  for (const auto& e : container["env"])
    if (e["value"]) env[e["name"].as<std::string>()] = e["value"].as<std::string>();
  return env;
}

}  // namespace visq::deploy_testing
