// libFuzzer target: the validation the server applies to names and upload
// file names before touching the disk. Whatever it accepts must stay inside
// the repository.
#include <cstdint>
#include <filesystem>
#include <string>

#include "core/scene_repository.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  static const std::filesystem::path root = [] {
    auto d = std::filesystem::temp_directory_path() / "visq-fuzz-repo";
    std::filesystem::create_directories(d);
    return d;
  }();
  static auto repository = visq::core::SceneRepository::Open(root);
  const std::string input(reinterpret_cast<const char*>(data), size);
  const size_t split = input.find('\n');
  const std::string name = input.substr(0, split);
  const std::string file = split == std::string::npos ? "scene.gltf" : input.substr(split + 1);

  if (visq::core::SceneRepository::ValidateName(name).ok()) {
    // An accepted name is one path component inside the repository.
    if (name.find('/') != std::string::npos || name == "." || name == "..") __builtin_trap();
  }
  auto staging = (*repository)->BeginUpload(name, file, 1 << 16);
  if (staging.ok()) {
    visq::Status appended = (*staging)->Append(file, "x");
    if (appended.ok()) {
      const auto resolved = std::filesystem::weakly_canonical((*staging)->main_file());
      if (resolved.string().rfind(root.string(), 0) != 0) __builtin_trap();
    }
  }
  return 0;
}
