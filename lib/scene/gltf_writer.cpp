#include "scene/gltf_writer.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <map>
#include <sstream>

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

tinygltf::Model BuildModel(const Scene& scene, const GltfExtras& extras) {
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
      material.occlusionTexture.texCoord = 1;
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
      // Primitives: the node's triangles grouped by material, each with its
      // own compact vertex set.
      std::map<uint32_t, std::vector<uint32_t>> by_material;
      for (uint32_t t = node.first_triangle; t < node.first_triangle + node.triangle_count; ++t)
        by_material[scene.triangle_material[t]].push_back(t);
      tinygltf::Mesh mesh;
      mesh.name = node.name;
      for (const auto& [material, tris] : by_material) {
        std::map<uint32_t, uint32_t> remap;
        std::vector<float> positions;
        std::vector<float> uvs;
        std::vector<uint32_t> indices;
        glm::dvec3 lo(std::numeric_limits<double>::infinity()), hi(-std::numeric_limits<double>::infinity());
        for (uint32_t t : tris) {
          for (int c = 0; c < 3; ++c) {
            const uint32_t v = scene.triangles[t][c];
            auto [it, inserted] = remap.emplace(v, static_cast<uint32_t>(remap.size()));
            if (inserted) {
              const glm::dvec3 p = scene.positions[v] - offset;
              const glm::vec3 pf(p);
              positions.insert(positions.end(), {pf.x, pf.y, pf.z});
              lo = glm::min(lo, glm::dvec3(pf));
              hi = glm::max(hi, glm::dvec3(pf));
              if (!scene.lightmap_uvs.empty()) uvs.insert(uvs.end(), {scene.lightmap_uvs[v].x, scene.lightmap_uvs[v].y});
            }
            indices.push_back(it->second);
          }
        }
        tinygltf::Primitive prim;
        prim.mode = TINYGLTF_MODE_TRIANGLES;
        prim.material = static_cast<int>(material);
        tinygltf::Accessor pos;
        pos.bufferView = AddView(model, AppendBytes(bytes, positions), positions.size() * 4, TINYGLTF_TARGET_ARRAY_BUFFER);
        pos.componentType = TINYGLTF_COMPONENT_TYPE_FLOAT;
        pos.type = TINYGLTF_TYPE_VEC3;
        pos.count = positions.size() / 3;
        pos.minValues = {lo.x, lo.y, lo.z};
        pos.maxValues = {hi.x, hi.y, hi.z};
        model.accessors.push_back(pos);
        prim.attributes["POSITION"] = static_cast<int>(model.accessors.size() - 1);
        if (!uvs.empty()) {
          tinygltf::Accessor uv;
          uv.bufferView = AddView(model, AppendBytes(bytes, uvs), uvs.size() * 4, TINYGLTF_TARGET_ARRAY_BUFFER);
          uv.componentType = TINYGLTF_COMPONENT_TYPE_FLOAT;
          uv.type = TINYGLTF_TYPE_VEC2;
          uv.count = uvs.size() / 2;
          model.accessors.push_back(uv);
          prim.attributes["TEXCOORD_1"] = static_cast<int>(model.accessors.size() - 1);
        }
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

Status WriteGltfFile(const Scene& scene, const std::filesystem::path& path) {
  tinygltf::Model model = BuildModel(scene, {});
  const bool binary = path.extension() == ".glb";
  if (!binary) model.buffers[0].uri = path.stem().string() + ".bin";
  tinygltf::TinyGLTF writer;
  if (!writer.WriteGltfSceneToFile(&model, path.string(), /*embedImages=*/false, /*embedBuffers=*/binary,
                                   /*prettyPrint=*/true, /*writeBinary=*/binary))
    return absl::InternalError(absl::StrCat("writing ", path.string(), " failed"));
  return absl::OkStatus();
}

StatusOr<std::string> WriteGlb(const Scene& scene, const GltfExtras& extras) {
  tinygltf::Model model = BuildModel(scene, extras);
  std::ostringstream out;
  tinygltf::TinyGLTF writer;
  if (!writer.WriteGltfSceneToStream(&model, out, /*prettyPrint=*/false, /*writeBinary=*/true))
    return absl::InternalError("writing a binary glTF failed");
  return std::move(out).str();
}

}  // namespace visq
