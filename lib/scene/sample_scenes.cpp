#include "scene/sample_scenes.h"

#include "scene/gltf_writer.h"

namespace visq {

void AddQuad(Scene& scene, const std::string& node_name, const glm::dvec3& origin, const glm::dvec3& u,
             const glm::dvec3& v, uint32_t material) {
  const uint32_t base = static_cast<uint32_t>(scene.positions.size());
  scene.positions.insert(scene.positions.end(), {origin, origin + u, origin + u + v, origin + v});
  const uint32_t node = static_cast<uint32_t>(scene.nodes.size());
  scene.nodes.push_back(SceneNode{node_name, static_cast<int>(node), -1, glm::dmat4(1.0),
                                  static_cast<uint32_t>(scene.triangles.size()), 2});
  for (const glm::uvec3& t : {glm::uvec3(0, 1, 2), glm::uvec3(0, 2, 3)}) {
    scene.triangles.push_back(t + base);
    scene.triangle_material.push_back(material);
    scene.triangle_node.push_back(node);
  }
}

void AddBox(Scene& scene, const std::string& node_name, const glm::dvec3& lo, const glm::dvec3& hi,
            uint32_t material) {
  const uint32_t base = static_cast<uint32_t>(scene.positions.size());
  for (int i = 0; i < 8; ++i)
    scene.positions.emplace_back(i & 1 ? hi.x : lo.x, i & 2 ? hi.y : lo.y, i & 4 ? hi.z : lo.z);
  // Corner i has bit 0 = x, bit 1 = y, bit 2 = z; faces wound outward.
  static constexpr glm::uvec3 kFaces[12] = {
      {0, 2, 3}, {0, 3, 1},  // -z
      {4, 5, 7}, {4, 7, 6},  // +z
      {0, 4, 6}, {0, 6, 2},  // -x
      {1, 3, 7}, {1, 7, 5},  // +x
      {0, 1, 5}, {0, 5, 4},  // -y
      {2, 6, 7}, {2, 7, 3},  // +y
  };
  const uint32_t node = static_cast<uint32_t>(scene.nodes.size());
  scene.nodes.push_back(SceneNode{node_name, static_cast<int>(node), -1, glm::dmat4(1.0),
                                  static_cast<uint32_t>(scene.triangles.size()), 12});
  for (const auto& f : kFaces) {
    scene.triangles.push_back(f + base);
    scene.triangle_material.push_back(material);
    scene.triangle_node.push_back(node);
  }
}

void AddTriangle(Scene& scene, const std::string& node_name, const glm::dvec3& a, const glm::dvec3& b,
                 const glm::dvec3& c, uint32_t material) {
  const uint32_t base = static_cast<uint32_t>(scene.positions.size());
  scene.positions.insert(scene.positions.end(), {a, b, c});
  const uint32_t node = static_cast<uint32_t>(scene.nodes.size());
  scene.nodes.push_back(SceneNode{node_name, static_cast<int>(node), -1, glm::dmat4(1.0),
                                  static_cast<uint32_t>(scene.triangles.size()), 1});
  scene.triangles.emplace_back(base, base + 1, base + 2);
  scene.triangle_material.push_back(material);
  scene.triangle_node.push_back(node);
}

Scene SceneOfTriangles(std::span<const std::array<glm::dvec3, 3>> triangles) {
  Scene scene;
  scene.materials = {{"grey", glm::dvec3(0.5), glm::dvec3(0.0)}};
  scene.nodes.push_back(SceneNode{"triangles", 0, -1, glm::dmat4(1.0), 0, static_cast<uint32_t>(triangles.size())});
  scene.positions.reserve(3 * triangles.size());
  for (const auto& t : triangles) {
    const uint32_t base = static_cast<uint32_t>(scene.positions.size());
    scene.positions.insert(scene.positions.end(), t.begin(), t.end());
    scene.triangles.emplace_back(base, base + 1, base + 2);
  }
  scene.triangle_material.assign(triangles.size(), 0);
  scene.triangle_node.assign(triangles.size(), 0);
  UpdateBounds(scene);
  return scene;
}

void UpdateBounds(Scene& scene) {
  scene.bounds = Bounds{};
  for (const auto& p : scene.positions) scene.bounds.Extend(p);
}

Scene MakeCornellBox() {
  Scene scene;
  scene.materials = {
      {"white", glm::dvec3(0.725, 0.71, 0.68), glm::dvec3(0.0)},
      {"red", glm::dvec3(0.63, 0.065, 0.05), glm::dvec3(0.0)},
      {"green", glm::dvec3(0.14, 0.45, 0.091), glm::dvec3(0.0)},
      {"light", glm::dvec3(0.78), glm::dvec3(17.0, 12.0, 4.0)},
  };
  const double s = 2.0;
  // Walls face the inside of the box.
  AddQuad(scene, "floor", {-1, 0, -1}, {0, 0, s}, {s, 0, 0}, 0);
  AddQuad(scene, "ceiling", {-1, s, -1}, {s, 0, 0}, {0, 0, s}, 0);
  AddQuad(scene, "back_wall", {-1, 0, -1}, {s, 0, 0}, {0, s, 0}, 0);
  AddQuad(scene, "left_wall", {-1, 0, -1}, {0, s, 0}, {0, 0, s}, 1);
  AddQuad(scene, "right_wall", {1, 0, -1}, {0, 0, s}, {0, s, 0}, 2);
  // The light faces down, a hair under the ceiling so the two never coincide.
  AddQuad(scene, "light", {-0.25, s - 0.005, -0.25}, {0.5, 0, 0}, {0, 0, 0.5}, 3);
  AddBox(scene, "short_box", {0.1, 0.0, 0.05}, {0.7, 0.6, 0.65}, 0);
  AddBox(scene, "tall_box", {-0.7, 0.0, -0.65}, {-0.1, 1.2, -0.05}, 0);
  UpdateBounds(scene);
  return scene;
}

Status WriteSampleScenes(const std::filesystem::path& repository) {
  const std::string name = "cornell_box_visq";
  const auto folder = repository / name;
  std::error_code ec;
  if (std::filesystem::exists(folder, ec)) return absl::OkStatus();
  // Written next to the repository's scenes under a hidden name, then
  // renamed, like an upload: a crash never leaves half a sample.
  const auto staging = repository / (".staging-sample-" + name);
  std::filesystem::remove_all(staging, ec);
  std::filesystem::create_directories(staging, ec);
  if (ec) return absl::InternalError(absl::StrCat("create ", staging.string(), ": ", ec.message()));
  VISQ_RETURN_IF_ERROR(WriteGltfFile(MakeCornellBox(), staging / (name + ".gltf")));
  std::filesystem::rename(staging, folder, ec);
  if (ec) return absl::InternalError(absl::StrCat("rename to ", folder.string(), ": ", ec.message()));
  return absl::OkStatus();
}

}  // namespace visq
