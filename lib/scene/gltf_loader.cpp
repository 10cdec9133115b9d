#include "scene/gltf_loader.h"

#include <cmath>
#include <cstring>
#include <fstream>
#include <functional>
#include <iterator>
#include <limits>
#include <map>
#include <new>
#include <optional>
#include <set>
#include <stdexcept>

#include <absl/strings/escaping.h>
#include <absl/strings/numbers.h>
#include <absl/strings/str_join.h>
#include <absl/strings/str_replace.h>
#include <glm/gtc/matrix_inverse.hpp>
#include <glm/gtc/matrix_transform.hpp>
#include <glm/gtc/quaternion.hpp>
#include <glm/gtc/type_ptr.hpp>
#include <nlohmann/json.hpp>
#include <tiny_gltf.h>

#include "common/coordinates.h"
#include "scene/gltf_compression.h"
#include "scene/placement_checks.h"

namespace visq {
namespace {

// Required extensions that visq reads (geometry: compression, quantization
// and instancing), and those that only change shading, which visq does not
// model: a scene that requires them is still exact for visibility.
bool IsSupportedRequiredExtension(const std::string& name) {
  return name == "KHR_mesh_quantization" || name == "EXT_meshopt_compression" ||
         name == "KHR_draco_mesh_compression" || name == "EXT_mesh_gpu_instancing" ||
         name.rfind("KHR_materials_", 0) == 0 || name.rfind("KHR_texture_", 0) == 0 ||
         name == "KHR_lights_punctual";
}

// Images are dropped: decoding them would only cost time and memory.
bool SkipImage(tinygltf::Image*, const int, std::string*, std::string*, int, int,
               const unsigned char*, int, void*) {
  return true;
}

Status Invalid(const std::string& what) { return absl::InvalidArgumentError(what); }

// Lightmap UVs are in [0, 1] (a few texels past it at most); beyond 1024 a
// float UV times the largest atlas resolution no longer names one texel.
constexpr double kMaxLightmapUv = 1024.0;

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
      // Every sum and product is checked: counts, offsets and lengths are
      // the file's own numbers, up to 2^64.
      size_t view_end = 0, needed = 0, accessor_end = 0;
      const bool view_fits = !__builtin_add_overflow(view.byteOffset, view.byteLength, &view_end) &&
                             view_end <= buffer.size();
      // An empty accessor needs no bytes, but its offset must still lie in
      // the view: the pointer it makes must not point outside the buffer.
      const bool accessor_fits =
          (acc.count == 0 || (!__builtin_mul_overflow(acc.count - 1, size_t(stride), &needed) &&
                              !__builtin_add_overflow(needed, element_bytes, &needed))) &&
          !__builtin_add_overflow(acc.byteOffset, needed, &accessor_end) && accessor_end <= view.byteLength;
      if (!view_fits || !accessor_fits)
        return Invalid(absl::StrCat(reader.label_, ": accessor reads past the end of its buffer"));
      const size_t begin = view.byteOffset + acc.byteOffset;  // both bounded above
      reader.data_ = buffer.data() + begin;
    }
    if (acc.sparse.isSparse) VISQ_RETURN_IF_ERROR(reader.LoadSparse(model));
    return reader;
  }

  size_t count() const { return accessor_->count; }
  int components() const { return components_; }
  int component_type() const { return accessor_->componentType; }
  bool is_float() const { return accessor_->componentType == TINYGLTF_COMPONENT_TYPE_FLOAT; }
  bool normalized() const { return accessor_->normalized; }
  // 8- and 16-bit integers, as KHR_mesh_quantization allows for geometry.
  bool is_small_integer() const { return component_bytes_ <= 2; }

  // Component c of element i as the value it stands for: a normalized
  // integer mapped to [0, 1] or [-1, 1] by glTF's rules, anything else as is.
  double Value(size_t i, int c) const {
    const double v = Get(i, c);
    if (!accessor_->normalized) return v;
    switch (accessor_->componentType) {
      case TINYGLTF_COMPONENT_TYPE_BYTE: return std::max(v / 127.0, -1.0);
      case TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE: return v / 255.0;
      case TINYGLTF_COMPONENT_TYPE_SHORT: return std::max(v / 32767.0, -1.0);
      case TINYGLTF_COMPONENT_TYPE_UNSIGNED_SHORT: return v / 65535.0;
      default: return v;
    }
  }

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
      size_t view_end = 0, end = 0;
      if (view.buffer < 0 || view.buffer >= static_cast<int>(model.buffers.size()) ||
          __builtin_add_overflow(view.byteOffset, view.byteLength, &view_end) ||
          view_end > model.buffers[view.buffer].data.size() || __builtin_add_overflow(offset, bytes, &end) ||
          end > view.byteLength)
        return Invalid(absl::StrCat(label_, ": sparse ", part, " read past the end of its buffer"));
      return model.buffers[view.buffer].data.data() + view.byteOffset + offset;
    };
    if (sparse.count < 0 || size_t(sparse.count) > accessor_->count)
      return Invalid(absl::StrCat(label_, ": sparse count ", sparse.count, " out of range"));
    const int index_bytes = tinygltf::GetComponentSizeInBytes(sparse.indices.componentType);
    if (index_bytes <= 0 || index_bytes > 4) return Invalid(absl::StrCat(label_, ": sparse index type invalid"));
    size_t index_total = 0, value_total = 0;
    if (__builtin_mul_overflow(size_t(sparse.count), size_t(index_bytes), &index_total) ||
        __builtin_mul_overflow(size_t(sparse.count), element_bytes, &value_total))
      return Invalid(absl::StrCat(label_, ": sparse count ", sparse.count, " out of range"));
    VISQ_ASSIGN_OR_RETURN(const unsigned char* indices,
                          view_bytes(sparse.indices.bufferView, sparse.indices.byteOffset, index_total,
                                     "indices"));
    VISQ_ASSIGN_OR_RETURN(const unsigned char* values,
                          view_bytes(sparse.values.bufferView, sparse.values.byteOffset, value_total,
                                     "values"));
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

// EXT_mesh_gpu_instancing: a node whose mesh is drawn once per instance,
// each placed by the node's world transform times the instance's own TRS.
// The attributes' accessors, or empty when the node has no instances.
struct InstanceAttributes {
  int translation = -1, rotation = -1, scale = -1;
  bool any() const { return translation >= 0 || rotation >= 0 || scale >= 0; }
};

InstanceAttributes InstanceAttributesOf(const tinygltf::Node& node) {
  InstanceAttributes attributes;
  auto ext = node.extensions.find("EXT_mesh_gpu_instancing");
  if (ext == node.extensions.end() || !ext->second.Has("attributes")) return attributes;
  const tinygltf::Value& a = ext->second.Get("attributes");
  auto index = [&](const char* name) {
    return a.Has(name) && a.Get(name).IsNumber() ? static_cast<int>(a.Get(name).GetNumberAsInt()) : -1;
  };
  attributes.translation = index("TRANSLATION");
  attributes.rotation = index("ROTATION");
  attributes.scale = index("SCALE");
  return attributes;
}

// What a document flattens to, counted from its numbers alone. Nodes may
// share children (a DAG), so a node's subtree is counted once and reused;
// sums saturate instead of wrapping.
struct FlattenedCounts {
  uint64_t triangles = 0;
  uint64_t vertices = 0;
  uint64_t nodes = 0;
  // Meshes placed (a node's mesh, or each of its GPU instances): each costs
  // its matrices and a pass over the mesh even when the mesh has no
  // triangles, so placements are counted on their own.
  uint64_t placements = 0;
  // Bytes of the attributes kept for the export beyond the positions
  // (NORMAL, TEXCOORD_n other than 1): Scene::normals and texcoords.
  uint64_t attribute_bytes = 0;
  int depth = 0;
};

uint64_t SaturatingAdd(uint64_t a, uint64_t b) {
  uint64_t sum = 0;
  return __builtin_add_overflow(a, b, &sum) ? std::numeric_limits<uint64_t>::max() : sum;
}

uint64_t SaturatingMultiply(uint64_t a, uint64_t b) {
  uint64_t product = 0;
  return __builtin_mul_overflow(a, b, &product) ? std::numeric_limits<uint64_t>::max() : product;
}

uint64_t AccessorCount(const tinygltf::Model& model, int accessor) {
  if (accessor < 0 || accessor >= static_cast<int>(model.accessors.size())) return 0;
  return model.accessors[accessor].count;
}

FlattenedCounts MeshCounts(const tinygltf::Model& model, const tinygltf::Mesh& mesh) {
  FlattenedCounts counts;
  for (const auto& prim : mesh.primitives) {
    const int mode = prim.mode < 0 ? TINYGLTF_MODE_TRIANGLES : prim.mode;
    auto position = prim.attributes.find("POSITION");
    if (position == prim.attributes.end()) continue;
    const uint64_t vertices = AccessorCount(model, position->second);
    const uint64_t corners = prim.indices >= 0 ? AccessorCount(model, prim.indices) : vertices;
    uint64_t triangles = 0;
    if (mode == TINYGLTF_MODE_TRIANGLES) triangles = corners / 3;
    else if (mode == TINYGLTF_MODE_TRIANGLE_STRIP || mode == TINYGLTF_MODE_TRIANGLE_FAN)
      triangles = corners >= 2 ? corners - 2 : 0;
    else continue;  // points and lines are not kept
    counts.vertices = SaturatingAdd(counts.vertices, vertices);
    counts.triangles = SaturatingAdd(counts.triangles, triangles);
    uint64_t per_vertex = prim.attributes.count("NORMAL") ? sizeof(glm::vec3) : 0;
    for (int set = 0; set < kMaxKeptTexcoordSets; ++set)
      if (set != 1 && prim.attributes.count(absl::StrCat("TEXCOORD_", set))) per_vertex += sizeof(glm::vec2);
    counts.attribute_bytes = SaturatingAdd(counts.attribute_bytes, SaturatingMultiply(vertices, per_vertex));
  }
  return counts;
}

class SceneBuilder {
 public:
  SceneBuilder(const tinygltf::Model& model, const GltfLoadLimits& limits, GltfLoadReport& report)
      : model_(model), limits_(limits), report_(report) {}

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
    VISQ_RETURN_IF_ERROR(ValidateFlattenedSize(roots));
    mesh_uses_ = MeshUses();
    VISQ_RETURN_IF_ERROR(VisitNodes(roots));
    if (SceneTriangles() == 0) return Invalid("scene has no triangles");
    if (!all_primitives_have_lightmap_uvs_) {
      if (!scene.lightmap_uvs.empty())
        report_.dropped.push_back("TEXCOORD_1 (not present on every primitive)");
      scene.lightmap_uvs.clear();
    }
    // The export's attributes: normals if every primitive had them, the
    // texture coordinate sets that every primitive had.
    if (!all_primitives_have_normals_) {
      if (!scene.normals.empty()) report_.dropped.push_back("NORMAL (not present and valid on every primitive)");
      scene.normals.clear();
    }
    if (scene.texcoords.size() > static_cast<size_t>(texcoord_sets_)) {
      report_.dropped.push_back(absl::StrCat("TEXCOORD_", texcoord_sets_, " and above (not present and valid on "
                                             "every primitive, or beyond ", kMaxKeptTexcoordSets, " sets)"));
      scene.texcoords.resize(texcoord_sets_);
    }
    scene.normals.shrink_to_fit();
    for (auto& set : scene.texcoords) set.shrink_to_fit();
    TrimMeshAttributes();
    // The arrays grew by doubling: up to half of each was slack (20 bytes a
    // triangle on 16 unique copies of Sponza), held while the scene is
    // resident.
    scene.positions.shrink_to_fit();
    scene.triangles.shrink_to_fit();
    scene.triangle_material.shrink_to_fit();
    scene.triangle_node.shrink_to_fit();
    scene.lightmap_uvs.shrink_to_fit();
    return absl::OkStatus();
  }

 private:
  // Refuses cycles, depth beyond the limit, and documents that would
  // flatten beyond the triangle or byte limits, before anything is built.
  // Iterative: a chain of nodes as deep as the file likes cannot exhaust the
  // stack.
  Status ValidateFlattenedSize(const std::vector<int>& roots) {
    const size_t n = model_.nodes.size();
    std::vector<FlattenedCounts> subtree(n);
    std::vector<uint8_t> state(n, 0);  // 0 unvisited, 1 on the path, 2 counted
    std::vector<FlattenedCounts> mesh_counts(model_.meshes.size());
    for (size_t m = 0; m < model_.meshes.size(); ++m) mesh_counts[m] = MeshCounts(model_, model_.meshes[m]);
    struct Frame {
      int node;
      size_t next_child;
    };
    std::vector<Frame> path;
    FlattenedCounts total;
    for (int root : roots) {
      if (root < 0 || root >= static_cast<int>(n)) return Invalid(absl::StrCat("node index ", root, " out of range"));
      if (state[root] != 2) {
        path.push_back({root, 0});
        state[root] = 1;
      }
      while (!path.empty()) {
        Frame& frame = path.back();
        const auto& node = model_.nodes[frame.node];
        if (frame.next_child < node.children.size()) {
          const int child = node.children[frame.next_child++];
          if (child < 0 || child >= static_cast<int>(n))
            return Invalid(absl::StrCat("nodes[", frame.node, "].children: node index ", child, " out of range"));
          if (state[child] == 1) return Invalid(absl::StrCat("nodes[", child, "]: cycle in the node hierarchy"));
          if (state[child] == 0) {
            if (static_cast<int>(path.size()) >= limits_.max_node_depth)
              return Invalid(absl::StrCat("nodes[", child, "]: node hierarchy deeper than ", limits_.max_node_depth,
                                          " levels"));
            state[child] = 1;
            path.push_back({child, 0});
          }
          continue;
        }
        FlattenedCounts counts;
        if (node.mesh >= 0 && node.mesh < static_cast<int>(mesh_counts.size())) {
          counts = mesh_counts[node.mesh];
          counts.placements = 1;
          const InstanceAttributes instances = InstanceAttributesOf(node);
          if (instances.any()) {
            const uint64_t copies = std::max({AccessorCount(model_, instances.translation),
                                              AccessorCount(model_, instances.rotation),
                                              AccessorCount(model_, instances.scale)});
            counts.triangles = SaturatingMultiply(counts.triangles, copies);
            counts.vertices = SaturatingMultiply(counts.vertices, copies);
            counts.attribute_bytes = SaturatingMultiply(counts.attribute_bytes, copies);
            counts.placements = copies;
          }
        }
        counts.nodes = 1;
        for (int child : node.children) {
          const FlattenedCounts& c = subtree[child];
          counts.triangles = SaturatingAdd(counts.triangles, c.triangles);
          counts.vertices = SaturatingAdd(counts.vertices, c.vertices);
          counts.attribute_bytes = SaturatingAdd(counts.attribute_bytes, c.attribute_bytes);
          counts.nodes = SaturatingAdd(counts.nodes, c.nodes);
          counts.placements = SaturatingAdd(counts.placements, c.placements);
          counts.depth = std::max(counts.depth, c.depth);
        }
        counts.depth += 1;
        subtree[frame.node] = counts;
        state[frame.node] = 2;
        path.pop_back();
      }
      const FlattenedCounts& c = subtree[root];
      total.triangles = SaturatingAdd(total.triangles, c.triangles);
      total.vertices = SaturatingAdd(total.vertices, c.vertices);
      total.attribute_bytes = SaturatingAdd(total.attribute_bytes, c.attribute_bytes);
      total.nodes = SaturatingAdd(total.nodes, c.nodes);
      total.placements = SaturatingAdd(total.placements, c.placements);
    }
    if (total.triangles > limits_.max_triangles)
      return absl::ResourceExhaustedError(absl::StrCat("the node hierarchy flattens to ", total.triangles,
                                                       " triangles, above the limit of ", limits_.max_triangles));
    if (total.placements > limits_.max_placements)
      return absl::ResourceExhaustedError(absl::StrCat(
          "the node hierarchy places meshes ", total.placements,
          " times (nodes and EXT_mesh_gpu_instancing instances), above the limit of ", limits_.max_placements));
    if (total.vertices > std::numeric_limits<uint32_t>::max())
      return absl::ResourceExhaustedError(
          absl::StrCat("the node hierarchy flattens to ", total.vertices, " vertices, above 2^32 - 1"));
    // The Scene's per-element sizes (Scene::CpuBytes), before any is made.
    constexpr uint64_t kBytesPerVertex = sizeof(glm::dvec3) + sizeof(glm::vec2);
    constexpr uint64_t kBytesPerTriangle = sizeof(glm::uvec3) + 2 * sizeof(uint32_t);
    constexpr uint64_t kBytesPerNode = sizeof(SceneNode);
    // A placement's matrix while its node is flattened (MeshPlacements),
    // and the placement kept for a repeated mesh (Scene::placements).
    constexpr uint64_t kBytesPerPlacement = sizeof(glm::dmat4) + sizeof(MeshPlacement);
    uint64_t bytes = total.attribute_bytes, part = 0;
    for (auto [count, size] : {std::pair{total.vertices, kBytesPerVertex}, std::pair{total.triangles, kBytesPerTriangle},
                               std::pair{total.nodes, kBytesPerNode},
                               std::pair{total.placements, kBytesPerPlacement}})
      bytes = SaturatingAdd(bytes, __builtin_mul_overflow(count, size, &part) ? ~uint64_t{0} : part);
    if (bytes > limits_.max_scene_bytes)
      return absl::ResourceExhaustedError(absl::StrCat("the node hierarchy flattens to about ", bytes,
                                                       " bytes resident, above the cap of ", limits_.max_scene_bytes,
                                                       " (--max-scene-bytes)"));
    return absl::OkStatus();
  }

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
      // glTF's range, which the obscurance bounds rest on (a ray's value is
      // rho times a reflectivity, in [0, 1]); within a rounding of it, clamped.
      for (int c = 0; c < 3; ++c) {
        if (!(material.reflectivity[c] >= -1e-6 && material.reflectivity[c] <= 1.0 + 1e-6))
          return Invalid(absl::StrCat("materials[", i, "].pbrMetallicRoughness.baseColorFactor[", c, "]: ",
                                      material.reflectivity[c], " is outside glTF's range [0, 1]"));
        material.reflectivity[c] = std::clamp(material.reflectivity[c], 0.0, 1.0);
      }
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

  // Pre-order over the (checked, acyclic, bounded) hierarchy with an explicit
  // stack; a node shared by several parents is flattened once per path.
  Status VisitNodes(const std::vector<int>& roots) {
    struct Pending {
      int index;
      int parent;  // into scene_->nodes
      glm::dmat4 parent_world;
    };
    std::vector<Pending> stack;
    for (auto it = roots.rbegin(); it != roots.rend(); ++it) stack.push_back({*it, -1, glm::dmat4(1.0)});
    while (!stack.empty()) {
      const Pending pending = stack.back();
      stack.pop_back();
      const int index = pending.index;
      const auto& node = model_.nodes[index];
      const glm::dmat4 world = pending.parent_world * LocalMatrix(node);
      for (int c = 0; c < 4; ++c)
        for (int r = 0; r < 4; ++r)
          if (!std::isfinite(world[c][r]))
            return Invalid(absl::StrCat("nodes[", index, "]: non-finite transform"));

      const uint32_t node_id = static_cast<uint32_t>(scene_->nodes.size());
      scene_->nodes.push_back(SceneNode{node.name, index, pending.parent, world, SceneTriangles(), 0});
      if (node.mesh >= 0) {
        if (node.mesh >= static_cast<int>(model_.meshes.size()))
          return Invalid(absl::StrCat("nodes[", index, "].mesh ", node.mesh, " out of range"));
        const auto& mesh = model_.meshes[node.mesh];
        VISQ_ASSIGN_OR_RETURN(std::vector<glm::dmat4> placements, MeshPlacements(node, index, world));
        for (const glm::dmat4& placement : placements) {
          const bool repeated = mesh_uses_[node.mesh] >= 2;
          const MeshKey key{node.mesh, glm::determinant(glm::dmat3(placement)) < 0.0};
          // A mesh already held is placed by its matrix, not read again.
          if (repeated && PlaceHeldMesh(key, placement, node_id)) continue;
          const Unplaced before{static_cast<uint32_t>(scene_->triangles.size()),
                                static_cast<uint32_t>(scene_->positions.size()), report_.ignored_primitives};
          std::vector<glm::dvec3> mesh_positions;
          std::vector<glm::vec3> mesh_normals;
          mesh_positions_ = repeated && !mesh_of_key_.contains(key) ? &mesh_positions : nullptr;
          mesh_normals_ = mesh_positions_ != nullptr ? &mesh_normals : nullptr;
          for (size_t p = 0; p < mesh.primitives.size(); ++p)
            VISQ_RETURN_IF_ERROR(AddPrimitive(mesh.primitives[p], placement, node_id,
                                              absl::StrCat("meshes[", node.mesh, "].primitives[", p, "]")));
          mesh_positions_ = nullptr;
          mesh_normals_ = nullptr;
          if (repeated) HoldPlacement(key, placement, node_id, before, std::move(mesh_positions), std::move(mesh_normals));
        }
      }
      scene_->nodes[node_id].triangle_count = SceneTriangles() - scene_->nodes[node_id].first_triangle;
      for (auto it = node.children.rbegin(); it != node.children.rend(); ++it)
        stack.push_back({*it, static_cast<int>(node_id), world});
    }
    return absl::OkStatus();
  }

  // A placement that shrinks its mesh below what float precision supports
  // (kMinPlacementScale) is refused; one that flattens it to nothing (a
  // zero scale, a hidden mesh) is kept: it is flattened, never instanced.
  static Status CheckPlacementScale(const glm::dmat4& placed, const std::string& label) {
    const double scale = PlacementScale(glm::dmat3(placed));
    if (scale > 0.0 && scale < kMinPlacementScale)
      return Invalid(absl::StrCat(label, ": scales its mesh by ", scale, ", below the ", kMinPlacementScale,
                                  " that float precision supports"));
    return absl::OkStatus();
  }

  // Where a node's mesh is drawn: at the node, or once per instance of
  // EXT_mesh_gpu_instancing (instances are flattened like shared nodes, and
  // were counted before anything was built).
  StatusOr<std::vector<glm::dmat4>> MeshPlacements(const tinygltf::Node& node, int index, const glm::dmat4& world) {
    const InstanceAttributes attributes = InstanceAttributesOf(node);
    if (!attributes.any()) {
      VISQ_RETURN_IF_ERROR(CheckPlacementScale(world, absl::StrCat("nodes[", index, "]")));
      return std::vector<glm::dmat4>{world};
    }
    const std::string label = absl::StrCat("nodes[", index, "].extensions.EXT_mesh_gpu_instancing.attributes");
    struct Attribute {
      int accessor;
      const char* name;
      int components;
    };
    std::optional<size_t> count;
    std::vector<std::optional<AccessorReader>> readers;
    for (const Attribute& a : {Attribute{attributes.translation, "TRANSLATION", 3},
                               Attribute{attributes.rotation, "ROTATION", 4}, Attribute{attributes.scale, "SCALE", 3}}) {
      readers.emplace_back();
      if (a.accessor < 0) continue;
      VISQ_ASSIGN_OR_RETURN(AccessorReader reader,
                            AccessorReader::Create(model_, a.accessor, absl::StrCat(label, ".", a.name)));
      if (reader.components() != a.components || !(reader.is_float() || reader.is_small_integer()))
        return Invalid(absl::StrCat(label, ".", a.name, ": must be VEC", a.components,
                                    " of float or of 8- or 16-bit integers"));
      if (count && *count != reader.count())
        return Invalid(absl::StrCat(label, ".", a.name, ": ", reader.count(), " instances where another attribute has ",
                                    *count));
      count = reader.count();
      readers.back() = std::move(reader);
    }
    std::vector<glm::dmat4> placements;
    placements.reserve(*count);
    for (size_t i = 0; i < *count; ++i) {
      glm::dmat4 instance(1.0);
      if (readers[0]) instance = glm::translate(instance, glm::dvec3(readers[0]->Value(i, 0), readers[0]->Value(i, 1),
                                                                     readers[0]->Value(i, 2)));
      if (readers[1]) {  // (x, y, z, w) in the file; glm's constructor takes w first
        glm::dquat rotation(readers[1]->Value(i, 3), readers[1]->Value(i, 0), readers[1]->Value(i, 1),
                            readers[1]->Value(i, 2));
        // Quantized quaternions are unit only to their step; float ones are
        // taken as written, as a node's rotation is.
        if (!readers[1]->is_float()) rotation = glm::normalize(rotation);
        instance *= glm::mat4_cast(rotation);
      }
      if (readers[2])
        instance = glm::scale(instance, glm::dvec3(readers[2]->Value(i, 0), readers[2]->Value(i, 1),
                                                   readers[2]->Value(i, 2)));
      const glm::dmat4 placed = world * instance;
      for (int c = 0; c < 4; ++c)
        for (int r = 0; r < 4; ++r)
          if (!std::isfinite(placed[c][r]))
            return Invalid(absl::StrCat(label, ": instance ", i, " has a non-finite transform"));
      VISQ_RETURN_IF_ERROR(CheckPlacementScale(placed, absl::StrCat(label, ": instance ", i)));
      placements.push_back(placed);
    }
    return placements;
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
    if (positions.components() != 3 || !(positions.is_float() || positions.is_small_integer()))
      return Invalid(absl::StrCat(label, ".POSITION: must be VEC3 of float, or of 8- or 16-bit integers "
                                         "(KHR_mesh_quantization)"));

    // Vertices: transformed to world space and appended.
    const uint32_t base = static_cast<uint32_t>(scene_->positions.size());
    for (size_t i = 0; i < positions.count(); ++i) {
      const glm::dvec3 local(positions.Value(i, 0), positions.Value(i, 1), positions.Value(i, 2));
      if (!std::isfinite(local.x) || !std::isfinite(local.y) || !std::isfinite(local.z))
        return Invalid(absl::StrCat(label, ".POSITION[", i, "]: NaN or Inf coordinate"));
      const glm::dvec3 placed = PlacePoint(world, local);
      if (!InCoordinateRange(placed))
        return Invalid(absl::StrCat(label, ".POSITION[", i, "]: beyond ±", kMaxCoordinate, " once placed by its nodes"));
      scene_->positions.push_back(placed);
      scene_->bounds.Extend(placed);
      if (mesh_positions_ != nullptr) mesh_positions_->push_back(local);
    }
    auto uv_it = prim.attributes.find("TEXCOORD_1");
    if (uv_it == prim.attributes.end()) {
      all_primitives_have_lightmap_uvs_ = false;
    } else if (all_primitives_have_lightmap_uvs_) {
      VISQ_ASSIGN_OR_RETURN(AccessorReader uvs, AccessorReader::Create(model_, uv_it->second, label + ".TEXCOORD_1"));
      // Integers that are not normalized need a texture transform to
      // become UVs, and visq applies none.
      if (uvs.count() != positions.count() || uvs.components() != 2 ||
          !(uvs.is_float() || (uvs.is_small_integer() && uvs.normalized())))
        return Invalid(absl::StrCat(label, ".TEXCOORD_1: must be VEC2 of float or of normalized 8- or 16-bit "
                                           "integers, one per position"));
      scene_->lightmap_uvs.resize(base);
      for (size_t i = 0; i < uvs.count(); ++i) {
        const double u = uvs.Value(i, 0), v = uvs.Value(i, 1);
        // Baked as they are: a NaN would reach the exported .glb, and the
        // atlas (UV times its resolution, in float) loses the texel beyond
        // kMaxLightmapUv.
        if (!std::isfinite(u) || !std::isfinite(v) || std::abs(u) > kMaxLightmapUv || std::abs(v) > kMaxLightmapUv)
          return Invalid(absl::StrCat(label, ".TEXCOORD_1[", i, "] (accessors[", uv_it->second, "]): (", u, ", ", v,
                                      ") is NaN, Inf or beyond ±", kMaxLightmapUv));
        scene_->lightmap_uvs.emplace_back(u, v);
      }
    }

    KeepExportAttributes(prim, positions.count(), world, label);

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

  // NORMAL and TEXCOORD_n of a primitive whose positions were just
  // appended, kept for the export while every primitive so far has them.
  // Unlike TEXCOORD_1, which the bake reads, an attribute visq does not
  // understand (a wrong type, a count other than the positions', a
  // non-finite value) is dropped with a line in the report, not refused.
  void KeepExportAttributes(const tinygltf::Primitive& prim, size_t count, const glm::dmat4& world,
                            const std::string& label) {
    const size_t base = scene_->positions.size() - count;
    auto reader_of = [&](const char* name, int components) -> std::optional<AccessorReader> {
      auto it = prim.attributes.find(name);
      if (it == prim.attributes.end()) return std::nullopt;
      StatusOr<AccessorReader> reader = AccessorReader::Create(model_, it->second, absl::StrCat(label, ".", name));
      if (!reader.ok() || reader->count() != count || reader->components() != components ||
          !(reader->is_float() || (reader->is_small_integer() && reader->normalized())))
        return std::nullopt;
      return std::move(*reader);
    };
    if (all_primitives_have_normals_) {
      std::optional<AccessorReader> normals = reader_of("NORMAL", 3);
      bool finite = normals.has_value();
      std::vector<glm::vec3> turned;
      if (finite) {
        // World space, as the positions are.
        const glm::dmat3 normal_matrix = glm::inverseTranspose(glm::dmat3(world));
        turned.reserve(count);
        for (size_t i = 0; i < count && finite; ++i) {
          const glm::vec3 n(normals->Value(i, 0), normals->Value(i, 1), normals->Value(i, 2));
          finite = std::isfinite(n.x) && std::isfinite(n.y) && std::isfinite(n.z);
          turned.push_back(UnitNormal(normal_matrix, n));
          if (mesh_normals_ != nullptr) mesh_normals_->push_back(n);
        }
      }
      if (finite && scene_->normals.size() == base) scene_->normals.insert(scene_->normals.end(), turned.begin(), turned.end());
      else all_primitives_have_normals_ = false;
    }
    int sets = 0;
    for (; sets < texcoord_sets_; ++sets) {
      std::optional<AccessorReader> uvs = reader_of(absl::StrCat("TEXCOORD_", sets).c_str(), 2);
      if (!uvs) break;
      std::vector<glm::vec2> values(count);
      bool finite = true;
      for (size_t i = 0; i < count && finite; ++i) {
        values[i] = glm::vec2(uvs->Value(i, 0), uvs->Value(i, 1));
        finite = std::isfinite(values[i].x) && std::isfinite(values[i].y);
      }
      if (!finite) break;
      if (scene_->texcoords.size() <= static_cast<size_t>(sets)) scene_->texcoords.resize(sets + 1);
      std::vector<glm::vec2>& kept = scene_->texcoords[sets];
      if (kept.size() != base) break;  // a set that an earlier primitive lacked
      kept.insert(kept.end(), values.begin(), values.end());
    }
    texcoord_sets_ = std::min(texcoord_sets_, sets);
  }

  // How many times each glTF mesh is placed, counted over the nodes and
  // their GPU instances. Only meshes placed twice or more are recorded as
  // SceneMesh; a node reached by several paths counts once here, so its mesh
  // is flattened only.
  std::vector<uint64_t> MeshUses() const {
    std::vector<uint64_t> uses(model_.meshes.size(), 0);
    for (const auto& node : model_.nodes) {
      if (node.mesh < 0 || node.mesh >= static_cast<int>(uses.size())) continue;
      const InstanceAttributes instances = InstanceAttributesOf(node);
      uses[node.mesh] += instances.any() ? std::max({AccessorCount(model_, instances.translation),
                                                     AccessorCount(model_, instances.rotation),
                                                     AccessorCount(model_, instances.scale)})
                                         : 1;
    }
    return uses;
  }

  // A glTF mesh as placed: a mirroring placement stores its corners in the
  // other order, so mirrored and unmirrored placements are placements of two
  // meshes.
  struct MeshKey {
    int gltf_mesh;
    bool mirrored;
    auto operator<=>(const MeshKey&) const = default;
  };

  // Triangles and positions so far in the whole scene's order: the record's
  // and the placements'.
  uint32_t SceneTriangles() const { return static_cast<uint32_t>(scene_->triangles.size() + placed_triangles_); }
  uint32_t ScenePositions() const { return static_cast<uint32_t>(scene_->positions.size() + placed_positions_); }

  // The record's sizes, and the primitives ignored, before a placement.
  struct Unplaced {
    uint32_t triangles;
    uint32_t positions;
    uint64_t ignored_primitives;
  };

  // One placement of `key` just flattened at the end of the record (from
  // `before`), with `mesh_positions` and `mesh_normals` (mesh space) when it
  // is the key's first: the mesh is kept once (unless too small to be worth
  // an instance) and the placement taken out of the record.
  void HoldPlacement(const MeshKey& key, const glm::dmat4& world, uint32_t node_id, const Unplaced& before,
                     std::vector<glm::dvec3> mesh_positions, std::vector<glm::vec3> mesh_normals) {
    const auto triangle_count = static_cast<uint32_t>(scene_->triangles.size()) - before.triangles;
    const auto position_count = static_cast<uint32_t>(scene_->positions.size()) - before.positions;
    auto [it, added] = mesh_of_key_.try_emplace(key, kFlattenedOnly);
    if (added && triangle_count >= kFewestTrianglesToInstance) {
      it->second = static_cast<uint32_t>(scene_->meshes.size());
      SceneMesh mesh;
      mesh.positions = std::move(mesh_positions);
      mesh.normals = std::move(mesh_normals);
      mesh.triangles.reserve(triangle_count);
      for (uint32_t t = before.triangles; t < before.triangles + triangle_count; ++t)
        mesh.triangles.push_back(scene_->triangles[t] - glm::uvec3(before.positions));
      mesh.triangle_material.assign(scene_->triangle_material.begin() + before.triangles,
                                    scene_->triangle_material.end());
      if (scene_->lightmap_uvs.size() == scene_->positions.size())
        mesh.lightmap_uvs.assign(scene_->lightmap_uvs.begin() + before.positions, scene_->lightmap_uvs.end());
      for (const auto& set : scene_->texcoords) {
        if (set.size() != scene_->positions.size()) break;
        mesh.texcoords.emplace_back(set.begin() + before.positions, set.end());
      }
      scene_->meshes.push_back(std::move(mesh));
      ignored_primitives_of_mesh_.push_back(report_.ignored_primitives - before.ignored_primitives);
    }
    if (it->second == kFlattenedOnly) return;
    const SceneMesh& mesh = scene_->meshes[it->second];
    // The same glTF mesh flattens to the same triangles every time; a
    // placement that did not stays in the record.
    if (mesh.triangles.size() != triangle_count || mesh.positions.size() != position_count) return;
    // The flattened counts fit 32 bits (ValidateFlattenedSize), as SceneTriangles says.
    scene_->placements.push_back(MeshPlacement{it->second, static_cast<uint32_t>(before.triangles + placed_triangles_),
                                               static_cast<uint32_t>(before.positions + placed_positions_), world,
                                               node_id, before.triangles, before.positions});
    placed_triangles_ += triangle_count;
    placed_positions_ += position_count;
    // The record drops what the placement now stands for.
    scene_->triangles.resize(before.triangles);
    scene_->triangle_material.resize(before.triangles);
    scene_->triangle_node.resize(before.triangles);
    auto keep_record_positions = [&](auto& values) {
      if (values.size() > before.positions) values.resize(before.positions);
    };
    keep_record_positions(scene_->positions);
    keep_record_positions(scene_->lightmap_uvs);
    keep_record_positions(scene_->normals);
    for (auto& set : scene_->texcoords) keep_record_positions(set);
  }

  // A later placement of a mesh already held: its positions placed only to
  // check their range and extend the bounds (the primitives were read and
  // checked at the first; their attributes are the mesh's). False when the
  // key's mesh is not held or a position leaves the range (read again, the
  // primitive then names it).
  bool PlaceHeldMesh(const MeshKey& key, const glm::dmat4& world, uint32_t node_id) {
    const auto it = mesh_of_key_.find(key);
    if (it == mesh_of_key_.end() || it->second == kFlattenedOnly) return false;
    const SceneMesh& mesh = scene_->meshes[it->second];
    while (placed_bounds_.size() < scene_->meshes.size())
      placed_bounds_.emplace_back(scene_->meshes[placed_bounds_.size()].positions);
    // Every placed coordinate lies between the placed extremes.
    const Bounds bounds = placed_bounds_[it->second].Of(world, mesh.positions);
    if (!bounds.Empty() && (!InCoordinateRange(bounds.min) || !InCoordinateRange(bounds.max))) return false;
    if (!bounds.Empty()) {
      scene_->bounds.Extend(bounds.min);
      scene_->bounds.Extend(bounds.max);
    }
    scene_->placements.push_back(MeshPlacement{it->second, SceneTriangles(), ScenePositions(), world, node_id,
                                               static_cast<uint32_t>(scene_->triangles.size()),
                                               static_cast<uint32_t>(scene_->positions.size())});
    placed_triangles_ += mesh.triangles.size();
    placed_positions_ += mesh.positions.size();
    report_.ignored_primitives += ignored_primitives_of_mesh_[it->second];
    return true;
  }

  // The meshes' attributes as the scene keeps them (the sets every
  // primitive had), and a mesh placed once flattened after all: it saves
  // nothing held once (a mirrored placement is a mesh of its own).
  void TrimMeshAttributes() {
    for (SceneMesh& mesh : scene_->meshes) {
      if (scene_->normals.empty()) mesh.normals.clear();
      if (scene_->lightmap_uvs.empty()) mesh.lightmap_uvs.clear();
      mesh.texcoords.resize(std::min(mesh.texcoords.size(), scene_->texcoords.size()));
      // Held while the scene is resident: no growth slack.
      mesh.positions.shrink_to_fit();
      mesh.normals.shrink_to_fit();
    }
    scene_->meshes.shrink_to_fit();
    scene_->placements.shrink_to_fit();
    std::vector<uint32_t> uses(scene_->meshes.size(), 0);
    for (const MeshPlacement& placement : scene_->placements) ++uses[placement.mesh];
    if (std::all_of(uses.begin(), uses.end(), [](uint32_t n) { return n >= 2; })) return;
    FlattenPlacements(*scene_);
    std::erase_if(scene_->placements, [&](const MeshPlacement& p) { return uses[p.mesh] < 2; });
    HoldPlacementsOnce(*scene_);
  }

  const tinygltf::Model& model_;
  const GltfLoadLimits& limits_;
  GltfLoadReport& report_;
  Scene* scene_ = nullptr;
  int default_material_ = -1;
  bool all_primitives_have_lightmap_uvs_ = true;
  bool all_primitives_have_normals_ = true;
  int texcoord_sets_ = kMaxKeptTexcoordSets;  // the sets every primitive so far had
  std::vector<uint64_t> mesh_uses_;
  std::vector<glm::dvec3>* mesh_positions_ = nullptr;  // where AddPrimitive copies mesh-space positions, if anywhere
  std::vector<glm::vec3>* mesh_normals_ = nullptr;     // and the file's normals, for the mesh's placements
  // Into Scene::meshes; kFlattenedOnly for a mesh too small to instance.
  static constexpr uint32_t kFlattenedOnly = UINT32_MAX;
  std::map<MeshKey, uint32_t> mesh_of_key_;
  std::vector<PlacedMeshBounds> placed_bounds_;  // per Scene::meshes, in order, once asked
  std::vector<uint64_t> ignored_primitives_of_mesh_;  // per Scene::meshes: ignored at each placement
  uint64_t placed_triangles_ = 0, placed_positions_ = 0;
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

// tinygltf parses JSON (and turns extras into values) recursively: 20,000
// nested brackets overflow its stack. Counted here first, outside strings.
constexpr int kMaxJsonDepth = 256;

bool JsonNestsTooDeep(std::string_view json) {
  int depth = 0;
  bool in_string = false, escaped = false;
  for (char c : json) {
    if (in_string) {
      if (escaped) escaped = false;
      else if (c == '\\') escaped = true;
      else if (c == '"') in_string = false;
      continue;
    }
    if (c == '"') in_string = true;
    else if (c == '[' || c == '{') {
      if (++depth > kMaxJsonDepth) return true;
    } else if (c == ']' || c == '}') {
      --depth;
    }
  }
  return false;
}

// The JSON of a .gltf, or the first (JSON) chunk of a .glb as far as the
// file holds it.
std::string_view JsonPart(const std::string& bytes, bool binary) {
  if (!binary) return bytes;
  if (bytes.size() < 20) return {};
  uint32_t chunk_length = 0;
  std::memcpy(&chunk_length, bytes.data() + 12, 4);  // little endian
  return std::string_view(bytes).substr(20, chunk_length);
}

// The file callbacks tinygltf reads external buffers and images through.
// tinygltf joins the percent-decoded URI to the base folder, then tries the
// working directory ("./" + URI): only the first form, resolving inside the
// root, is ever opened.
class UploadFiles {
 public:
  // `image_uris`: the document's image URIs, percent-decoded. Images are
  // dropped, so their files are never opened (tinygltf would read each
  // whole before handing it to the image loader).
  UploadFiles(const std::filesystem::path& base_dir, const std::filesystem::path& root,
              std::set<std::string> image_uris)
      : base_dir_(base_dir.lexically_normal()), root_(root.lexically_normal()), image_uris_(std::move(image_uris)) {
    std::error_code ec;
    canonical_root_ = std::filesystem::weakly_canonical(root_, ec);
    if (ec) canonical_root_ = root_;
    base_prefix_ = base_dir_.string();
    if (base_prefix_.empty() || base_prefix_.back() != '/') base_prefix_ += '/';
  }

  tinygltf::FsCallbacks Callbacks() {
    return tinygltf::FsCallbacks{&FileExists, &ExpandFilePath, &ReadWholeFile, &WriteWholeFile, this};
  }
  // The first URI refused, and why; empty when none was.
  const std::string& refusal() const { return refusal_; }
  const std::string& base_prefix() const { return base_prefix_; }
  const std::vector<std::filesystem::path>& files_read() const { return files_read_; }

 private:
  static bool Inside(const std::filesystem::path& path, const std::filesystem::path& folder) {
    const std::filesystem::path relative = path.lexically_relative(folder);
    if (relative.empty() || relative == ".") return false;
    for (const auto& part : relative) {
      const std::string s = part.string();
      if (s.empty() || s[0] == '.') return false;  // "..", and the repository's hidden files
    }
    return true;
  }

  // The file a joined path names, or empty (with the refusal recorded) when
  // it is not one of the upload's own files.
  std::filesystem::path Resolve(const std::string& joined) {
    if (joined.rfind(base_prefix_, 0) != 0) return {};  // the working-directory fallback
    const std::string uri = joined.substr(base_prefix_.size());
    auto refuse = [&](const std::string& why) {
      if (refusal_.empty()) refusal_ = absl::StrCat("URI '", absl::CHexEscape(uri), "' ", why);
      return std::filesystem::path();
    };
    if (uri.empty()) return refuse("is empty");
    if (image_uris_.count(uri)) return {};  // an image: never read
    if (uri[0] == '/' || uri.find('\\') != std::string::npos || uri.find('\0') != std::string::npos)
      return refuse("is an absolute path or holds a backslash or NUL");
    const std::filesystem::path lexical = (base_dir_ / uri).lexically_normal();
    if (!Inside(lexical, root_)) return refuse("leaves the scene's own files");
    std::error_code ec;
    const std::filesystem::path resolved = std::filesystem::weakly_canonical(lexical, ec);
    if (ec || !Inside(resolved, canonical_root_)) return refuse("resolves outside the scene's own files");
    if (!std::filesystem::is_regular_file(resolved, ec)) return {};
    return resolved;
  }

  static bool FileExists(const std::string& path, void* self) {
    return !static_cast<UploadFiles*>(self)->Resolve(path).empty();
  }
  // The default expands `~` and environment variables (wordexp): a URI is
  // only ever a name.
  static std::string ExpandFilePath(const std::string& path, void*) { return path; }
  static bool ReadWholeFile(std::vector<unsigned char>* out, std::string* err, const std::string& path,
                            void* self) {
    const std::filesystem::path resolved = static_cast<UploadFiles*>(self)->Resolve(path);
    if (resolved.empty()) {
      if (err) *err += "not one of the scene's files";
      return false;
    }
    std::ifstream file(resolved, std::ios::binary);
    if (!file) {
      if (err) *err += "cannot open";
      return false;
    }
    out->assign(std::istreambuf_iterator<char>(file), std::istreambuf_iterator<char>());
    static_cast<UploadFiles*>(self)->files_read_.push_back(resolved);
    return true;
  }
  static bool WriteWholeFile(std::string* err, const std::string&, const std::vector<unsigned char>&, void*) {
    if (err) *err += "the loader never writes";
    return false;
  }

  std::filesystem::path base_dir_;
  std::filesystem::path root_;
  std::filesystem::path canonical_root_;
  std::string base_prefix_;
  std::set<std::string> image_uris_;
  std::string refusal_;
  std::vector<std::filesystem::path> files_read_;
};

// The image URIs of a document, percent-decoded as tinygltf decodes them
// before it asks for the file.
std::set<std::string> ImageUris(std::string_view json) {
  std::set<std::string> uris;
  if (json.find("\"images\"") == std::string_view::npos) return uris;
  const nlohmann::json document = nlohmann::json::parse(json.begin(), json.end(), nullptr, /*allow_exceptions=*/false);
  if (!document.is_object() || !document.contains("images") || !document["images"].is_array()) return uris;
  for (const auto& image : document["images"]) {
    if (!image.is_object() || !image.contains("uri") || !image["uri"].is_string()) continue;
    const std::string uri = image["uri"].get<std::string>();
    if (uri.rfind("data:", 0) == 0) continue;
    std::string decoded;
    for (size_t i = 0; i < uri.size(); ++i) {
      int value = 0;
      if (uri[i] == '%' && i + 2 < uri.size() && absl::SimpleHexAtoi(uri.substr(i + 1, 2), &value)) {
        decoded.push_back(static_cast<char>(value));
        i += 2;
      } else {
        decoded.push_back(uri[i] == '+' ? ' ' : uri[i]);
      }
    }
    uris.insert(std::move(decoded));
  }
  return uris;
}

StatusOr<Scene> LoadGltfFileOrThrow(const std::filesystem::path& path, GltfLoadReport* report,
                                    const GltfLoadLimits& limits) {
  GltfLoadReport local_report;
  GltfLoadReport& out_report = report ? *report : local_report;
  const std::string file_name = path.filename().string();

  const std::string ext = path.extension().string();
  const bool binary = ext == ".glb" || ext == ".GLB";
  if (!binary && ext != ".gltf" && ext != ".GLTF")
    return Invalid(absl::StrCat(file_name, ": not a .gltf or .glb file"));
  std::error_code ec;
  const std::filesystem::path main_file = std::filesystem::absolute(path, ec).lexically_normal();
  if (ec) return Invalid(absl::StrCat(file_name, ": ", ec.message()));
  // A folder opens as an ifstream, and reading it throws (EISDIR); a FIFO
  // or a device would block or never end. An upload whose chunk is named
  // "a.gltf/x" makes its main file "a.gltf" such a folder.
  const std::filesystem::file_status kind = std::filesystem::status(main_file, ec);
  if (ec || !std::filesystem::exists(kind)) return absl::NotFoundError(absl::StrCat(file_name, ": cannot open"));
  if (!std::filesystem::is_regular_file(kind))
    return Invalid(absl::StrCat(file_name, ": not a regular file (",
                                std::filesystem::is_directory(kind) ? "a folder" : "a special file", ")"));
  std::string bytes;
  {
    std::ifstream file(main_file, std::ios::binary);
    if (!file) return absl::NotFoundError(absl::StrCat(file_name, ": cannot open"));
    bytes.assign(std::istreambuf_iterator<char>(file), std::istreambuf_iterator<char>());
  }
  if (bytes.size() > std::numeric_limits<unsigned>::max())
    return absl::ResourceExhaustedError(absl::StrCat(file_name, ": larger than 4 GiB"));
  if (JsonNestsTooDeep(JsonPart(bytes, binary)))
    return Invalid(absl::StrCat(file_name, ": JSON nested deeper than ", kMaxJsonDepth, " levels"));
  VISQ_ASSIGN_OR_RETURN(bytes, PrepareCompressedDocument(std::move(bytes), binary));
  const std::filesystem::path base_dir = main_file.parent_path();
  UploadFiles files(base_dir, limits.file_root.empty() ? base_dir : std::filesystem::absolute(limits.file_root, ec),
                    ImageUris(JsonPart(bytes, binary)));

  tinygltf::TinyGLTF loader;
  loader.SetImageLoader(&SkipImage, nullptr);
  loader.SetFsCallbacks(files.Callbacks());
  tinygltf::Model model;
  std::string error, warning;
  bool ok = false;
  // tinygltf reports most errors through `error`, but some malformed files
  // make it throw (a GLB buffer without a uri and without a BIN chunk:
  // std::out_of_range from vector::at, found by the glTF fuzz target). An
  // exception escaping here would end the server.
  try {
    const auto* data = reinterpret_cast<const unsigned char*>(bytes.data());
    ok = binary ? loader.LoadBinaryFromMemory(&model, &error, &warning, data, static_cast<unsigned>(bytes.size()),
                                              base_dir.string())
                : loader.LoadASCIIFromString(&model, &error, &warning, bytes.data(),
                                             static_cast<unsigned>(bytes.size()), base_dir.string());
  } catch (const std::exception& e) {
    return Invalid(absl::StrCat(file_name, ": malformed glTF (the parser gave up: ", e.what(), ")"));
  }
  if (!files.refusal().empty()) return Invalid(absl::StrCat(file_name, ": ", files.refusal()));
  if (!ok) {
    if (error.empty()) error = warning;
    while (!error.empty() && (error.back() == '\n' || error.back() == ' ')) error.pop_back();
    // tinygltf's messages name the paths it tried: keep the server's own
    // folders out of what the client sees.
    error = absl::StrReplaceAll(error, {{files.base_prefix(), ""}});
    return Invalid(absl::StrCat(file_name, ": malformed glTF: ", error));
  }
  for (const auto& required : model.extensionsRequired)
    if (!IsSupportedRequiredExtension(required))
      return Invalid(absl::StrCat(file_name, ": unsupported required extension ", required));
  if (Status decoded = DecodeCompressedGeometry(model, limits.max_scene_bytes); !decoded.ok())
    return Status(decoded.code(), absl::StrCat(file_name, ": ", decoded.message()));

  Scene scene;
  SceneBuilder builder(model, limits, out_report);
  Status status = builder.Build(scene);
  if (!status.ok()) return Status(status.code(), absl::StrCat(file_name, ": ", status.message()));
  ReportDroppedContent(model, out_report);
  out_report.files_read = files.files_read();
  return scene;
}

}  // namespace

StatusOr<Scene> LoadGltfFile(const std::filesystem::path& path, GltfLoadReport* report,
                             const GltfLoadLimits& limits) {
  // Every size is checked before it is allocated, but a file is hostile and
  // the libraries underneath throw (a read error of the stream, a decoder's
  // allocation): the caller gets a status naming the file, never an
  // exception (at start, one would end the server on a stored scene).
  const std::string file_name = path.filename().string();
  try {
    return LoadGltfFileOrThrow(path, report, limits);
  } catch (const std::bad_alloc&) {
    return absl::ResourceExhaustedError(absl::StrCat(file_name, ": loading it needs more memory than there is"));
  } catch (const std::exception& e) {
    return absl::InternalError(absl::StrCat(file_name, ": the loader failed (", e.what(), ")"));
  }
}

}  // namespace visq
