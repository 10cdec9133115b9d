#include "scene/gltf_loader.h"

#include <stdexcept>
#include <cmath>
#include <cstring>
#include <functional>
#include <set>
#include <stdexcept>

#include <absl/strings/str_join.h>
#include <glm/gtc/matrix_transform.hpp>
#include <glm/gtc/quaternion.hpp>
#include <glm/gtc/type_ptr.hpp>
#include <tiny_gltf.h>

namespace visq {
namespace {

// Required extensions that only change shading, which visq does not model:
// a scene that requires them is still exact for visibility.
bool IsIgnorableRequiredExtension(const std::string& name) {
  return name.rfind("KHR_materials_", 0) == 0 || name.rfind("KHR_texture_", 0) == 0 ||
         name == "KHR_lights_punctual";
}

// Images are dropped: decoding them would only cost time and memory.
bool SkipImage(tinygltf::Image*, const int, std::string*, std::string*, int, int,
               const unsigned char*, int, void*) {
  return true;
}

Status Invalid(const std::string& what) { return absl::InvalidArgumentError(what); }

// A typed, bounds-checked view of one accessor's elements (sparse applied).
class AccessorReader {
 public:
  static StatusOr<AccessorReader> Create(const tinygltf::Model& model, int accessor_index,
                                         std::string label) {
    if (accessor_index < 0 || accessor_index >= static_cast<int>(model.accessors.size()))
      return Invalid(absl::StrCat(label, ": accessor ", accessor_index, " out of range"));
    AccessorReader reader;
    reader.label_ = std::move(label);
    reader.accessor_ = &model.accessors[accessor_index];
    const auto& acc = *reader.accessor_;
    reader.components_ = tinygltf::GetNumComponentsInType(acc.type);
    reader.component_bytes_ = tinygltf::GetComponentSizeInBytes(acc.componentType);
    if (reader.components_ <= 0 || reader.component_bytes_ <= 0)
      return Invalid(absl::StrCat(reader.label_, ": unsupported accessor type"));
    const size_t element_bytes = size_t(reader.components_) * reader.component_bytes_;
    if (acc.bufferView >= 0) {
      if (acc.bufferView >= static_cast<int>(model.bufferViews.size()))
        return Invalid(absl::StrCat(reader.label_, ": bufferView ", acc.bufferView, " out of range"));
      const auto& view = model.bufferViews[acc.bufferView];
      if (view.buffer < 0 || view.buffer >= static_cast<int>(model.buffers.size()))
        return Invalid(absl::StrCat(reader.label_, ": buffer ", view.buffer, " out of range"));
      const auto& buffer = model.buffers[view.buffer].data;
      const int stride = acc.ByteStride(view);
      if (stride <= 0) return Invalid(absl::StrCat(reader.label_, ": invalid byteStride"));
      reader.stride_ = stride;
      const size_t begin = view.byteOffset + acc.byteOffset;
      const size_t needed = acc.count == 0 ? 0 : (acc.count - 1) * size_t(stride) + element_bytes;
      if (view.byteOffset + view.byteLength > buffer.size() || acc.byteOffset + needed > view.byteLength)
        return Invalid(absl::StrCat(reader.label_, ": accessor reads past the end of its buffer"));
      reader.data_ = buffer.data() + begin;
    }
    if (acc.sparse.isSparse) VISQ_RETURN_IF_ERROR(reader.LoadSparse(model));
    return reader;
  }

  size_t count() const { return accessor_->count; }
  int components() const { return components_; }
  int component_type() const { return accessor_->componentType; }

  // Component c of element i as a double (integers converted exactly).
  double Get(size_t i, int c) const {
    if (!sparse_.empty()) {
      auto it = sparse_.find(i);
      if (it != sparse_.end()) return ReadComponent(it->second + c * component_bytes_);
    }
    if (data_ == nullptr) return 0.0;  // sparse accessor without a base view
    return ReadComponent(data_ + i * stride_ + c * component_bytes_);
  }

 private:
  double ReadComponent(const unsigned char* p) const {
    switch (accessor_->componentType) {
      case TINYGLTF_COMPONENT_TYPE_BYTE: { int8_t v; std::memcpy(&v, p, 1); return v; }
      case TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE: return *p;
      case TINYGLTF_COMPONENT_TYPE_SHORT: { int16_t v; std::memcpy(&v, p, 2); return v; }
      case TINYGLTF_COMPONENT_TYPE_UNSIGNED_SHORT: { uint16_t v; std::memcpy(&v, p, 2); return v; }
      case TINYGLTF_COMPONENT_TYPE_UNSIGNED_INT: { uint32_t v; std::memcpy(&v, p, 4); return v; }
      case TINYGLTF_COMPONENT_TYPE_FLOAT: { float v; std::memcpy(&v, p, 4); return v; }
      default: return std::nan("");
    }
  }

  Status LoadSparse(const tinygltf::Model& model) {
    const auto& sparse = accessor_->sparse;
    const size_t element_bytes = size_t(components_) * component_bytes_;
    auto view_bytes = [&](int view_index, size_t offset, size_t bytes,
                          const char* part) -> StatusOr<const unsigned char*> {
      if (view_index < 0 || view_index >= static_cast<int>(model.bufferViews.size()))
        return Invalid(absl::StrCat(label_, ": sparse ", part, " bufferView out of range"));
      const auto& view = model.bufferViews[view_index];
      if (view.buffer < 0 || view.buffer >= static_cast<int>(model.buffers.size()) ||
          view.byteOffset + view.byteLength > model.buffers[view.buffer].data.size() ||
          offset + bytes > view.byteLength)
        return Invalid(absl::StrCat(label_, ": sparse ", part, " read past the end of its buffer"));
      return model.buffers[view.buffer].data.data() + view.byteOffset + offset;
    };
    if (sparse.count < 0 || size_t(sparse.count) > accessor_->count)
      return Invalid(absl::StrCat(label_, ": sparse count ", sparse.count, " out of range"));
    const int index_bytes = tinygltf::GetComponentSizeInBytes(sparse.indices.componentType);
    if (index_bytes <= 0) return Invalid(absl::StrCat(label_, ": sparse index type invalid"));
    VISQ_ASSIGN_OR_RETURN(const unsigned char* indices,
                          view_bytes(sparse.indices.bufferView, sparse.indices.byteOffset,
                                     size_t(sparse.count) * index_bytes, "indices"));
    VISQ_ASSIGN_OR_RETURN(const unsigned char* values,
                          view_bytes(sparse.values.bufferView, sparse.values.byteOffset,
                                     size_t(sparse.count) * element_bytes, "values"));
    for (int k = 0; k < sparse.count; ++k) {
      uint32_t index = 0;
      std::memcpy(&index, indices + size_t(k) * index_bytes, index_bytes);  // little endian
      if (index >= accessor_->count)
        return Invalid(absl::StrCat(label_, ": sparse index ", index, " out of range"));
      sparse_[index] = values + size_t(k) * element_bytes;
    }
    return absl::OkStatus();
  }

  std::string label_;
  const tinygltf::Accessor* accessor_ = nullptr;
  const unsigned char* data_ = nullptr;
  size_t stride_ = 0;
  int components_ = 0;
  int component_bytes_ = 0;
  std::map<size_t, const unsigned char*> sparse_;
};

glm::dmat4 LocalMatrix(const tinygltf::Node& node) {
  if (node.matrix.size() == 16) return glm::make_mat4(node.matrix.data());  // column-major
  glm::dmat4 m(1.0);
  if (node.translation.size() == 3)
    m = glm::translate(m, glm::dvec3(node.translation[0], node.translation[1], node.translation[2]));
  if (node.rotation.size() == 4)  // glTF stores (x, y, z, w); glm's constructor takes w first
    m *= glm::mat4_cast(glm::dquat(node.rotation[3], node.rotation[0], node.rotation[1], node.rotation[2]));
  if (node.scale.size() == 3) m = glm::scale(m, glm::dvec3(node.scale[0], node.scale[1], node.scale[2]));
  return m;
}

class SceneBuilder {
 public:
  SceneBuilder(const tinygltf::Model& model, GltfLoadReport& report) : model_(model), report_(report) {}

  Status Build(Scene& scene) {
    scene_ = &scene;
    VISQ_RETURN_IF_ERROR(BuildMaterials());
    // Roots: the default scene, else the first, else every parentless node.
    std::vector<int> roots;
    if (!model_.scenes.empty()) {
      int chosen = model_.defaultScene;
      if (chosen < 0 || chosen >= static_cast<int>(model_.scenes.size())) chosen = 0;
      roots = model_.scenes[chosen].nodes;
      if (model_.scenes.size() > 1)
        report_.dropped.push_back(absl::StrCat(model_.scenes.size() - 1, " non-default scene(s)"));
    } else {
      std::vector<bool> has_parent(model_.nodes.size(), false);
      for (const auto& node : model_.nodes)
        for (int child : node.children)
          if (child >= 0 && child < static_cast<int>(has_parent.size())) has_parent[child] = true;
      for (size_t i = 0; i < model_.nodes.size(); ++i)
        if (!has_parent[i]) roots.push_back(static_cast<int>(i));
    }
    std::vector<bool> on_path(model_.nodes.size(), false);
    for (int root : roots) VISQ_RETURN_IF_ERROR(VisitNode(root, -1, glm::dmat4(1.0), on_path));
    if (scene.triangles.empty()) return Invalid("scene has no triangles");
    if (!all_primitives_have_lightmap_uvs_) {
      if (!scene.lightmap_uvs.empty())
        report_.dropped.push_back("TEXCOORD_1 (not present on every primitive)");
      scene.lightmap_uvs.clear();
    }
    for (const auto& p : scene.positions) scene.bounds.Extend(p);
    return absl::OkStatus();
  }

 private:
  Status BuildMaterials() {
    for (size_t i = 0; i < model_.materials.size(); ++i) {
      const auto& m = model_.materials[i];
      Material material;
      material.name = m.name;
      const auto& base = m.pbrMetallicRoughness.baseColorFactor;
      if (base.size() >= 3) material.reflectivity = {base[0], base[1], base[2]};
      double strength = 1.0;
      auto ext = m.extensions.find("KHR_materials_emissive_strength");
      if (ext != m.extensions.end() && ext->second.Has("emissiveStrength"))
        strength = ext->second.Get("emissiveStrength").GetNumberAsDouble();
      if (m.emissiveFactor.size() >= 3)
        material.emission = strength * glm::dvec3(m.emissiveFactor[0], m.emissiveFactor[1], m.emissiveFactor[2]);
      for (int c = 0; c < 3; ++c)
        if (!std::isfinite(material.reflectivity[c]) || !std::isfinite(material.emission[c]))
          return Invalid(absl::StrCat("materials[", i, "]: non-finite color"));
      scene_->materials.push_back(std::move(material));
    }
    return absl::OkStatus();
  }

  uint32_t DefaultMaterial() {
    if (default_material_ < 0) {
      default_material_ = static_cast<int>(scene_->materials.size());
      scene_->materials.push_back(Material{"default", glm::dvec3(1.0), glm::dvec3(0.0)});
    }
    return static_cast<uint32_t>(default_material_);
  }

  Status VisitNode(int index, int parent, const glm::dmat4& parent_world, std::vector<bool>& on_path) {
    if (index < 0 || index >= static_cast<int>(model_.nodes.size()))
      return Invalid(absl::StrCat("node index ", index, " out of range"));
    if (on_path[index]) return Invalid(absl::StrCat("nodes[", index, "]: cycle in the node hierarchy"));
    on_path[index] = true;
    const auto& node = model_.nodes[index];
    const glm::dmat4 world = parent_world * LocalMatrix(node);
    for (int c = 0; c < 4; ++c)
      for (int r = 0; r < 4; ++r)
        if (!std::isfinite(world[c][r])) return Invalid(absl::StrCat("nodes[", index, "]: non-finite transform"));

    const uint32_t node_id = static_cast<uint32_t>(scene_->nodes.size());
    scene_->nodes.push_back(SceneNode{node.name, index, parent, world,
                                      static_cast<uint32_t>(scene_->triangles.size()), 0});
    if (node.mesh >= 0) {
      if (node.mesh >= static_cast<int>(model_.meshes.size()))
        return Invalid(absl::StrCat("nodes[", index, "].mesh ", node.mesh, " out of range"));
      const auto& mesh = model_.meshes[node.mesh];
      for (size_t p = 0; p < mesh.primitives.size(); ++p)
        VISQ_RETURN_IF_ERROR(AddPrimitive(mesh.primitives[p], world, node_id,
                                          absl::StrCat("meshes[", node.mesh, "].primitives[", p, "]")));
    }
    scene_->nodes[node_id].triangle_count =
        static_cast<uint32_t>(scene_->triangles.size()) - scene_->nodes[node_id].first_triangle;
    for (int child : node.children) VISQ_RETURN_IF_ERROR(VisitNode(child, static_cast<int>(node_id), world, on_path));
    on_path[index] = false;
    return absl::OkStatus();
  }

  Status AddPrimitive(const tinygltf::Primitive& prim, const glm::dmat4& world, uint32_t node_id,
                      const std::string& label) {
    const int mode = prim.mode < 0 ? TINYGLTF_MODE_TRIANGLES : prim.mode;
    if (mode != TINYGLTF_MODE_TRIANGLES && mode != TINYGLTF_MODE_TRIANGLE_STRIP &&
        mode != TINYGLTF_MODE_TRIANGLE_FAN) {
      ++report_.ignored_primitives;
      return absl::OkStatus();
    }
    auto pos_it = prim.attributes.find("POSITION");
    if (pos_it == prim.attributes.end()) return Invalid(absl::StrCat(label, ": no POSITION attribute"));
    VISQ_ASSIGN_OR_RETURN(AccessorReader positions,
                          AccessorReader::Create(model_, pos_it->second, label + ".POSITION"));
    if (positions.components() != 3 || positions.component_type() != TINYGLTF_COMPONENT_TYPE_FLOAT)
      return Invalid(absl::StrCat(label, ".POSITION: must be VEC3 float (quantized positions unsupported)"));

    // Vertices: transformed to world space and appended.
    const uint32_t base = static_cast<uint32_t>(scene_->positions.size());
    for (size_t i = 0; i < positions.count(); ++i) {
      const glm::dvec3 local(positions.Get(i, 0), positions.Get(i, 1), positions.Get(i, 2));
      if (!std::isfinite(local.x) || !std::isfinite(local.y) || !std::isfinite(local.z))
        return Invalid(absl::StrCat(label, ".POSITION[", i, "]: NaN or Inf coordinate"));
      scene_->positions.push_back(glm::dvec3(world * glm::dvec4(local, 1.0)));
    }
    auto uv_it = prim.attributes.find("TEXCOORD_1");
    if (uv_it == prim.attributes.end()) {
      all_primitives_have_lightmap_uvs_ = false;
    } else if (all_primitives_have_lightmap_uvs_) {
      VISQ_ASSIGN_OR_RETURN(AccessorReader uvs, AccessorReader::Create(model_, uv_it->second, label + ".TEXCOORD_1"));
      if (uvs.count() != positions.count() || uvs.components() != 2)
        return Invalid(absl::StrCat(label, ".TEXCOORD_1: must be VEC2 with one per position"));
      const bool normalized = model_.accessors[uv_it->second].normalized;
      const double scale = !normalized ? 1.0
                           : uvs.component_type() == TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE ? 1.0 / 255.0
                           : uvs.component_type() == TINYGLTF_COMPONENT_TYPE_UNSIGNED_SHORT ? 1.0 / 65535.0
                                                                                             : 1.0;
      scene_->lightmap_uvs.resize(base);
      for (size_t i = 0; i < uvs.count(); ++i)
        scene_->lightmap_uvs.emplace_back(uvs.Get(i, 0) * scale, uvs.Get(i, 1) * scale);
    }

    // Corner indices: given, or implicit 0..n-1.
    std::vector<uint32_t> corners;
    if (prim.indices >= 0) {
      VISQ_ASSIGN_OR_RETURN(AccessorReader indices, AccessorReader::Create(model_, prim.indices, label + ".indices"));
      const int type = indices.component_type();
      if (indices.components() != 1 ||
          (type != TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE && type != TINYGLTF_COMPONENT_TYPE_UNSIGNED_SHORT &&
           type != TINYGLTF_COMPONENT_TYPE_UNSIGNED_INT))
        return Invalid(absl::StrCat(label, ".indices: must be SCALAR u8/u16/u32"));
      corners.resize(indices.count());
      for (size_t i = 0; i < corners.size(); ++i) {
        const double v = indices.Get(i, 0);
        if (v >= static_cast<double>(positions.count()))
          return Invalid(absl::StrCat(label, ".indices[", i, "]: ", static_cast<uint64_t>(v),
                                      " out of range (", positions.count(), " vertices)"));
        corners[i] = static_cast<uint32_t>(v);
      }
    } else {
      corners.resize(positions.count());
      for (size_t i = 0; i < corners.size(); ++i) corners[i] = static_cast<uint32_t>(i);
    }

    // Triangles: strips and fans unrolled; a mirroring transform flips winding
    // so that counter-clockwise stays front-facing in world space.
    const bool mirrored = glm::determinant(glm::dmat3(world)) < 0.0;
    const uint32_t material = prim.material >= 0 && prim.material < static_cast<int>(scene_->materials.size())
                                  ? static_cast<uint32_t>(prim.material)
                                  : DefaultMaterial();
    auto emit = [&](uint32_t a, uint32_t b, uint32_t c) {
      if (mirrored) std::swap(b, c);
      scene_->triangles.emplace_back(base + a, base + b, base + c);
      scene_->triangle_material.push_back(material);
      scene_->triangle_node.push_back(node_id);
    };
    const size_t n = corners.size();
    if (mode == TINYGLTF_MODE_TRIANGLES) {
      for (size_t i = 0; i + 2 < n; i += 3) emit(corners[i], corners[i + 1], corners[i + 2]);
    } else if (mode == TINYGLTF_MODE_TRIANGLE_STRIP) {
      for (size_t i = 0; i + 2 < n; ++i) {
        if (i % 2 == 0) emit(corners[i], corners[i + 1], corners[i + 2]);
        else emit(corners[i + 1], corners[i], corners[i + 2]);
      }
    } else {
      for (size_t i = 1; i + 1 < n; ++i) emit(corners[0], corners[i], corners[i + 1]);
    }
    return absl::OkStatus();
  }

  const tinygltf::Model& model_;
  GltfLoadReport& report_;
  Scene* scene_ = nullptr;
  int default_material_ = -1;
  bool all_primitives_have_lightmap_uvs_ = true;
};

void ReportDroppedContent(const tinygltf::Model& model, GltfLoadReport& report) {
  auto note = [&](size_t count, const char* what) {
    if (count > 0) report.dropped.push_back(absl::StrCat(count, " ", what));
  };
  note(model.textures.size(), "texture(s)");
  note(model.images.size(), "image(s)");
  note(model.skins.size(), "skin(s) (bind pose kept)");
  note(model.animations.size(), "animation(s)");
  note(model.cameras.size(), "camera(s)");
  note(report.ignored_primitives, "point/line primitive(s)");
}

}  // namespace

StatusOr<Scene> LoadGltfFile(const std::filesystem::path& path, GltfLoadReport* report) {
  GltfLoadReport local_report;
  GltfLoadReport& out_report = report ? *report : local_report;

  tinygltf::TinyGLTF loader;
  loader.SetImageLoader(&SkipImage, nullptr);
  tinygltf::Model model;
  std::string error, warning;
  const std::string ext = path.extension().string();
  const bool binary = ext == ".glb" || ext == ".GLB";
  if (!binary && ext != ".gltf" && ext != ".GLTF")
    return Invalid(absl::StrCat(path.filename().string(), ": not a .gltf or .glb file"));
  bool ok = false;
  // tinygltf reports most errors through `error`, but some malformed files
  // make it throw (a GLB buffer without a uri and without a BIN chunk:
  // std::out_of_range from vector::at, found by the glTF fuzz target). An
  // exception escaping here would end the server.
  try {
    ok = binary ? loader.LoadBinaryFromFile(&model, &error, &warning, path.string())
                : loader.LoadASCIIFromFile(&model, &error, &warning, path.string());
  } catch (const std::exception& e) {
    return Invalid(absl::StrCat(path.filename().string(), ": malformed glTF (the parser gave up: ", e.what(), ")"));
  }
  if (!ok) {
    if (error.empty()) error = warning;
    while (!error.empty() && (error.back() == '\n' || error.back() == ' ')) error.pop_back();
    return Invalid(absl::StrCat(path.filename().string(), ": malformed glTF: ", error));
  }
  for (const auto& required : model.extensionsRequired)
    if (!IsIgnorableRequiredExtension(required))
      return Invalid(absl::StrCat(path.filename().string(), ": unsupported required extension ", required));

  Scene scene;
  SceneBuilder builder(model, out_report);
  Status status = builder.Build(scene);
  if (!status.ok()) return Invalid(absl::StrCat(path.filename().string(), ": ", status.message()));
  ReportDroppedContent(model, out_report);
  return scene;
}

}  // namespace visq
