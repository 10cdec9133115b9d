#include "scene/gltf_writer.h"

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstring>
#include <map>
#include <sstream>
#include <tuple>

#include <absl/strings/str_cat.h>

#include <tiny_gltf.h>

namespace visq {
namespace {

template <typename T>
size_t AppendBytes(std::vector<unsigned char>& buffer, const std::vector<T>& values) {
  // glTF wants 4-byte aligned views.
  while (buffer.size() % 4 != 0) buffer.push_back(0);
  const size_t offset = buffer.size();
  buffer.resize(offset + values.size() * sizeof(T));
  std::memcpy(buffer.data() + offset, values.data(), values.size() * sizeof(T));
  return offset;
}

int AddView(tinygltf::Model& model, size_t offset, size_t length, int target) {
  tinygltf::BufferView view;
  view.buffer = 0;
  view.byteOffset = offset;
  view.byteLength = length;
  view.target = target;
  model.bufferViews.push_back(view);
  return static_cast<int>(model.bufferViews.size() - 1);
}

tinygltf::Model BuildModel(const Scene& placed_scene, const GltfExtras& extras) {
  const Scene& scene = placed_scene.Flattened();
  tinygltf::Model model;
  model.asset.version = "2.0";
  model.asset.generator = "visq";
  model.buffers.emplace_back();
  std::vector<unsigned char>& bytes = model.buffers[0].data;

  bool uses_emissive_strength = false;
  for (const auto& m : scene.materials) {
    tinygltf::Material material;
    material.name = m.name;
    material.doubleSided = true;
    material.pbrMetallicRoughness.baseColorFactor = {m.reflectivity.r, m.reflectivity.g, m.reflectivity.b, 1.0};
    material.pbrMetallicRoughness.metallicFactor = 0.0;
    const double peak = std::max({m.emission.r, m.emission.g, m.emission.b});
    if (peak > 0.0) {
      // emissiveFactor is clamped to [0, 1] by glTF; the strength carries the rest.
      const double strength = std::max(peak, 1.0);
      material.emissiveFactor = {m.emission.r / strength, m.emission.g / strength, m.emission.b / strength};
      if (strength > 1.0) {
        tinygltf::Value::Object ext;
        ext["emissiveStrength"] = tinygltf::Value(strength);
        material.extensions["KHR_materials_emissive_strength"] = tinygltf::Value(ext);
        uses_emissive_strength = true;
      }
    }
    model.materials.push_back(material);
  }
  if (uses_emissive_strength) model.extensionsUsed.push_back("KHR_materials_emissive_strength");
  // Attributes: each written only where it covers every position (or
  // corner) of the scene; a scene built in code may leave any out.
  const size_t vertex_count = scene.positions.size();
  std::vector<const std::vector<glm::vec2>*> uv_sets;
  for (const auto& set : scene.texcoords) {
    if (set.size() != vertex_count) break;
    uv_sets.push_back(&set);
  }
  if (uv_sets.size() < 2 && scene.lightmap_uvs.size() == vertex_count && vertex_count > 0) {
    uv_sets.resize(std::min<size_t>(uv_sets.size(), 1));
    if (uv_sets.empty()) uv_sets.push_back(&scene.lightmap_uvs);
    uv_sets.push_back(&scene.lightmap_uvs);
  }
  const bool with_normals = scene.normals.size() == vertex_count;
  const bool with_colors = extras.vertex_colors.size() == vertex_count && vertex_count > 0;
  const bool with_occlusion_uv =
      !extras.occlusion_uv.empty() && extras.occlusion_uv.size() == 3 * scene.triangles.size();
  if (!extras.occlusion_png.empty()) {
    std::vector<unsigned char> png(extras.occlusion_png.begin(), extras.occlusion_png.end());
    tinygltf::Image image;
    image.name = "occlusion";
    image.mimeType = "image/png";
    image.bufferView = AddView(model, AppendBytes(bytes, png), png.size(), 0);
    model.images.push_back(image);
    tinygltf::Texture texture;
    texture.source = 0;
    model.textures.push_back(texture);
    for (auto& material : model.materials) {
      material.occlusionTexture.index = 0;
      material.occlusionTexture.texCoord = with_occlusion_uv ? static_cast<int>(uv_sets.size()) : 1;
    }
  }

  // A node far from the origin stores its positions relative to its own
  // centre (rounded to a whole unit, so the offsets add up exactly), moved
  // there by its translation: float32 accessors 1e7 out would round every
  // vertex to 1 unit, the node's translation is a JSON double.
  std::vector<glm::dvec3> offsets(scene.nodes.size(), glm::dvec3(0.0));
  for (size_t n = 0; n < scene.nodes.size(); ++n) {
    const SceneNode& node = scene.nodes[n];
    Bounds box;
    for (uint32_t t = node.first_triangle; t < node.first_triangle + node.triangle_count; ++t)
      for (int c = 0; c < 3; ++c) box.Extend(scene.Vertex(t, c));
    if (box.Empty()) continue;
    const glm::dvec3 centre = glm::round(box.Center());
    if (std::max({std::abs(centre.x), std::abs(centre.y), std::abs(centre.z)}) >= 1024.0) offsets[n] = centre;
  }

  tinygltf::Scene gltf_scene;
  for (size_t n = 0; n < scene.nodes.size(); ++n) {
    const SceneNode& node = scene.nodes[n];
    tinygltf::Node gltf_node;
    gltf_node.name = node.name;
    const glm::dvec3 offset = offsets[n];
    const glm::dvec3 parent_offset = node.parent >= 0 ? offsets[size_t(node.parent)] : glm::dvec3(0.0);
    if (offset != parent_offset)
      gltf_node.translation = {offset.x - parent_offset.x, offset.y - parent_offset.y, offset.z - parent_offset.z};
    if (node.triangle_count > 0) {
      // Primitives: runs of the node's triangles with one material, each
      // with its own compact vertex set. The loader appends a node's
      // primitives in order, so the runs give back the input's primitives
      // and the triangles keep their order (that of the answers' arrays).
      std::vector<std::pair<uint32_t, std::vector<uint32_t>>> by_material;
      for (uint32_t t = node.first_triangle; t < node.first_triangle + node.triangle_count; ++t) {
        if (by_material.empty() || by_material.back().first != scene.triangle_material[t])
          by_material.emplace_back(scene.triangle_material[t], std::vector<uint32_t>{});
        by_material.back().second.push_back(t);
      }
      tinygltf::Mesh mesh;
      mesh.name = node.name;
      for (const auto& [material, tris] : by_material) {
        // Vertices: one per scene position and occlusion UV that the
        // primitive's corners use. Corners of one position share its
        // normal and UVs by construction; positions the input kept apart
        // stay apart, as the artist's mesh had them.
        std::map<std::tuple<uint32_t, uint32_t, uint32_t>, uint32_t> vertex_of;
        std::vector<float> positions, normals, colors, occlusion;
        std::vector<std::vector<float>> uvs(uv_sets.size());
        std::vector<uint32_t> indices;
        glm::dvec3 lo(std::numeric_limits<double>::infinity()), hi(-std::numeric_limits<double>::infinity());
        for (uint32_t t : tris) {
          for (int c = 0; c < 3; ++c) {
            const uint32_t v = scene.triangles[t][c];
            const glm::vec2 atlas = with_occlusion_uv ? extras.occlusion_uv[3 * size_t(t) + c] : glm::vec2(0.0f);
            auto [it, inserted] = vertex_of.emplace(std::tuple{v, std::bit_cast<uint32_t>(atlas.x),
                                                               std::bit_cast<uint32_t>(atlas.y)},
                                                    static_cast<uint32_t>(vertex_of.size()));
            if (inserted) {
              const glm::dvec3 p = scene.positions[v] - offset;
              const glm::vec3 pf(p);
              positions.insert(positions.end(), {pf.x, pf.y, pf.z});
              lo = glm::min(lo, glm::dvec3(pf));
              hi = glm::max(hi, glm::dvec3(pf));
              if (with_normals) normals.insert(normals.end(), {scene.normals[v].x, scene.normals[v].y, scene.normals[v].z});
              for (size_t s = 0; s < uv_sets.size(); ++s) uvs[s].insert(uvs[s].end(), {(*uv_sets[s])[v].x, (*uv_sets[s])[v].y});
              if (with_occlusion_uv) occlusion.insert(occlusion.end(), {atlas.x, atlas.y});
              if (with_colors) {
                const glm::vec3 w = glm::clamp(extras.vertex_colors[v], 0.0f, 1.0f);
                colors.insert(colors.end(), {w.x, w.y, w.z});
              }
            }
            indices.push_back(it->second);
          }
        }
        tinygltf::Primitive prim;
        prim.mode = TINYGLTF_MODE_TRIANGLES;
        prim.material = static_cast<int>(material);
        auto add_attribute = [&](const std::vector<float>& values, int type, int components) {
          tinygltf::Accessor accessor;
          accessor.bufferView = AddView(model, AppendBytes(bytes, values), values.size() * 4, TINYGLTF_TARGET_ARRAY_BUFFER);
          accessor.componentType = TINYGLTF_COMPONENT_TYPE_FLOAT;
          accessor.type = type;
          accessor.count = values.size() / components;
          model.accessors.push_back(accessor);
          return static_cast<int>(model.accessors.size() - 1);
        };
        prim.attributes["POSITION"] = add_attribute(positions, TINYGLTF_TYPE_VEC3, 3);
        model.accessors.back().minValues = {lo.x, lo.y, lo.z};
        model.accessors.back().maxValues = {hi.x, hi.y, hi.z};
        if (with_normals) prim.attributes["NORMAL"] = add_attribute(normals, TINYGLTF_TYPE_VEC3, 3);
        for (size_t s = 0; s < uv_sets.size(); ++s)
          prim.attributes[absl::StrCat("TEXCOORD_", s)] = add_attribute(uvs[s], TINYGLTF_TYPE_VEC2, 2);
        if (with_occlusion_uv)
          prim.attributes[absl::StrCat("TEXCOORD_", uv_sets.size())] = add_attribute(occlusion, TINYGLTF_TYPE_VEC2, 2);
        if (with_colors) prim.attributes["COLOR_0"] = add_attribute(colors, TINYGLTF_TYPE_VEC3, 3);
        tinygltf::Accessor idx;
        idx.bufferView = AddView(model, AppendBytes(bytes, indices), indices.size() * 4,
                                 TINYGLTF_TARGET_ELEMENT_ARRAY_BUFFER);
        idx.componentType = TINYGLTF_COMPONENT_TYPE_UNSIGNED_INT;
        idx.type = TINYGLTF_TYPE_SCALAR;
        idx.count = indices.size();
        model.accessors.push_back(idx);
        prim.indices = static_cast<int>(model.accessors.size() - 1);
        mesh.primitives.push_back(prim);
      }
      model.meshes.push_back(mesh);
      gltf_node.mesh = static_cast<int>(model.meshes.size() - 1);
    }
    model.nodes.push_back(gltf_node);
  }
  for (size_t n = 0; n < scene.nodes.size(); ++n) {
    const int parent = scene.nodes[n].parent;
    if (parent < 0) gltf_scene.nodes.push_back(static_cast<int>(n));
    else model.nodes[parent].children.push_back(static_cast<int>(n));
  }
  model.scenes.push_back(gltf_scene);
  model.defaultScene = 0;
  return model;
}

}  // namespace

Status WriteGltfFile(const Scene& placed_scene, const std::filesystem::path& path) {
  const Scene& scene = placed_scene.Flattened();
  tinygltf::Model model = BuildModel(scene, {});
  const bool binary = path.extension() == ".glb";
  if (!binary) model.buffers[0].uri = path.stem().string() + ".bin";
  tinygltf::TinyGLTF writer;
  if (!writer.WriteGltfSceneToFile(&model, path.string(), /*embedImages=*/false, /*embedBuffers=*/binary,
                                   /*prettyPrint=*/true, /*writeBinary=*/binary))
    return absl::InternalError(absl::StrCat("writing ", path.string(), " failed"));
  return absl::OkStatus();
}

StatusOr<std::string> WriteGlb(const Scene& placed_scene, const GltfExtras& extras) {
  const Scene& scene = placed_scene.Flattened();
  tinygltf::Model model = BuildModel(scene, extras);
  std::ostringstream out;
  tinygltf::TinyGLTF writer;
  if (!writer.WriteGltfSceneToStream(&model, out, /*prettyPrint=*/false, /*writeBinary=*/true))
    return absl::InternalError("writing a binary glTF failed");
  return std::move(out).str();
}

}  // namespace visq
