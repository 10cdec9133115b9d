#include "raycast/flat_bvh.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <memory>

#include <embree3/rtcore.h>

#include "common/check.h"
#include "raycast/embree_scene.h"

namespace visq::raycast {

namespace {

// The builder's nodes live in Embree's thread-local allocator until the
// tree is flattened; both kinds start with the tag.
struct BuildNode {
  bool leaf = false;
};
struct BuildInner : BuildNode {
  BuildNode* children[2] = {nullptr, nullptr};
  RTCBounds bounds[2] = {};
};
struct BuildLeaf : BuildNode {
  uint32_t count = 0;
  uint32_t triangles[1];  // `count` of them, allocated past the struct
};

void* CreateInner(RTCThreadLocalAllocator allocator, unsigned int child_count, void*) {
  VISQ_CHECK_LE(child_count, 2u);
  void* memory = rtcThreadLocalAlloc(allocator, sizeof(BuildInner), 16);
  return new (memory) BuildInner();
}

void SetChildren(void* node, void** children, unsigned int child_count, void*) {
  auto* inner = static_cast<BuildInner*>(node);
  for (unsigned i = 0; i < child_count; ++i) inner->children[i] = static_cast<BuildNode*>(children[i]);
}

void SetBounds(void* node, const RTCBounds** bounds, unsigned int child_count, void*) {
  auto* inner = static_cast<BuildInner*>(node);
  for (unsigned i = 0; i < child_count; ++i) inner->bounds[i] = *bounds[i];
}

void* CreateLeaf(RTCThreadLocalAllocator allocator, const RTCBuildPrimitive* primitives, size_t count, void*) {
  void* memory = rtcThreadLocalAlloc(allocator, sizeof(BuildLeaf) + count * sizeof(uint32_t), 16);
  auto* leaf = new (memory) BuildLeaf();
  leaf->leaf = true;
  leaf->count = static_cast<uint32_t>(count);
  for (size_t i = 0; i < count; ++i) leaf->triangles[i] = primitives[i].primID;
  return leaf;
}

bool Progress(void* user, double) { return !static_cast<const StopToken*>(user)->Stopped(); }

// A box grown by a few float ulps of its magnitude: the traversal's slab
// test rounds too, and a segment that grazes a box must still reach the
// triangles inside (the triangle test alone decides).
void Widen(glm::vec3& lower, glm::vec3& upper) {
  for (int a = 0; a < 3; ++a) {
    const float magnitude = std::max(std::abs(lower[a]), std::abs(upper[a]));
    const float pad = magnitude * 0x1p-20f + std::numeric_limits<float>::min();
    lower[a] -= pad;
    upper[a] += pad;
  }
}

struct Flattener {
  const std::vector<glm::vec3>& scene_corners;  // three per scene triangle
  FlatBvh& out;

  // Appends `node` and its subtree, depth first; returns its index.
  uint32_t Add(const BuildNode* node, const glm::vec3& lower, const glm::vec3& upper, uint32_t depth) {
    out.depth = std::max(out.depth, depth);
    const uint32_t index = static_cast<uint32_t>(out.nodes.size());
    FlatBvhNode flat;
    flat.lower = lower;
    flat.upper = upper;
    Widen(flat.lower, flat.upper);
    out.nodes.push_back(flat);
    if (node->leaf) {
      const auto* leaf = static_cast<const BuildLeaf*>(node);
      out.nodes[index].right_or_first = static_cast<uint32_t>(out.corners.size() / 3);
      out.nodes[index].count = leaf->count;
      for (uint32_t i = 0; i < leaf->count; ++i) {
        const uint32_t t = leaf->triangles[i];
        out.corners.push_back({scene_corners[3 * size_t(t)], t});
        out.corners.push_back({scene_corners[3 * size_t(t) + 1], 0});
        out.corners.push_back({scene_corners[3 * size_t(t) + 2], 0});
      }
      return index;
    }
    const auto* inner = static_cast<const BuildInner*>(node);
    auto box = [](const RTCBounds& b, glm::vec3& lo, glm::vec3& hi) {
      lo = {b.lower_x, b.lower_y, b.lower_z};
      hi = {b.upper_x, b.upper_y, b.upper_z};
    };
    glm::vec3 lo, hi;
    box(inner->bounds[0], lo, hi);
    Add(inner->children[0], lo, hi, depth + 1);
    if (inner->children[1] != nullptr) {
      box(inner->bounds[1], lo, hi);
      out.nodes[index].right_or_first = Add(inner->children[1], lo, hi, depth + 1);
    } else {
      out.nodes[index].right_or_first = index + 1;  // a lone child: visited twice at worst, never missed
    }
    return index;
  }
};

}  // namespace

StatusOr<FlatBvh> BuildFlatBvh(const Scene& scene, const FlatBvhOptions& options) {
  FlatBvh out;
  const Bounds bounds = PositionBounds(scene);
  const glm::dvec3 extent = bounds.Empty() ? glm::dvec3(0.0) : bounds.Extent();
  out.origin = options.origin.value_or(bounds.Empty() ? glm::dvec3(0.0) : bounds.Center());
  out.extent = std::max({extent.x, extent.y, extent.z});
  const size_t triangles = scene.TriangleCount();
  if (triangles == 0) return out;
  if (triangles >= std::numeric_limits<uint32_t>::max() / 4)
    return absl::ResourceExhaustedError(absl::StrCat("the GPU ray method holds up to ", std::numeric_limits<uint32_t>::max() / 4,
                                                     " triangles; the scene has ", triangles));

  // Corners in the frame, rounded once from world doubles (as Embree's
  // flattened upload), and each triangle's box for the builder.
  std::vector<glm::vec3> corners(3 * triangles);
  std::vector<RTCBuildPrimitive> primitives;
  primitives.reserve(triangles);
  for (size_t t = 0; t < triangles; ++t) {
    if (t % 65536 == 0) VISQ_RETURN_IF_ERROR(options.stop.Check("building the GPU ray BVH"));
    glm::vec3 lower(std::numeric_limits<float>::max()), upper(-std::numeric_limits<float>::max());
    for (int c = 0; c < 3; ++c) {
      const glm::vec3 corner(scene.Vertex(t, c) - out.origin);
      corners[3 * t + c] = corner;
      lower = glm::min(lower, corner);
      upper = glm::max(upper, corner);
    }
    RTCBuildPrimitive primitive;
    primitive.lower_x = lower.x;
    primitive.lower_y = lower.y;
    primitive.lower_z = lower.z;
    primitive.upper_x = upper.x;
    primitive.upper_y = upper.y;
    primitive.upper_z = upper.z;
    primitive.geomID = 0;
    primitive.primID = static_cast<unsigned>(t);
    primitives.push_back(primitive);
  }

  struct DeviceOwner {
    RTCDevice device = nullptr;
    RTCBVH bvh = nullptr;
    ~DeviceOwner() {
      if (bvh) rtcReleaseBVH(bvh);
      if (device) rtcReleaseDevice(device);
    }
  } owner;
  owner.device = rtcNewDevice(EmbreeDeviceConfig().c_str());
  if (owner.device == nullptr) return absl::InternalError("rtcNewDevice failed for the GPU ray BVH");
  owner.bvh = rtcNewBVH(owner.device);
  StopToken stop = options.stop;
  RTCBuildArguments arguments = rtcDefaultBuildArguments();
  arguments.buildQuality = RTC_BUILD_QUALITY_MEDIUM;
  arguments.maxBranchingFactor = 2;
  arguments.maxDepth = kMaxFlatBvhDepth;
  arguments.sahBlockSize = 1;
  arguments.minLeafSize = 1;
  arguments.maxLeafSize = 8;
  // A box test against a triangle test, as a GPU thread pays them.
  arguments.traversalCost = 1.0f;
  arguments.intersectionCost = 2.0f;
  arguments.bvh = owner.bvh;
  arguments.primitives = primitives.data();
  arguments.primitiveCount = primitives.size();
  arguments.primitiveArrayCapacity = primitives.size();
  arguments.createNode = CreateInner;
  arguments.setNodeChildren = SetChildren;
  arguments.setNodeBounds = SetBounds;
  arguments.createLeaf = CreateLeaf;
  arguments.splitPrimitive = nullptr;
  arguments.buildProgress = Progress;
  arguments.userPtr = &stop;
  const auto* root = static_cast<const BuildNode*>(rtcBuildBVH(&arguments));
  VISQ_RETURN_IF_ERROR(options.stop.Check("building the GPU ray BVH"));
  if (root == nullptr || rtcGetDeviceError(owner.device) != RTC_ERROR_NONE)
    return absl::InternalError("rtcBuildBVH failed for the GPU ray BVH");

  glm::vec3 lower(std::numeric_limits<float>::max()), upper(-std::numeric_limits<float>::max());
  for (const RTCBuildPrimitive& p : primitives) {
    lower = glm::min(lower, glm::vec3(p.lower_x, p.lower_y, p.lower_z));
    upper = glm::max(upper, glm::vec3(p.upper_x, p.upper_y, p.upper_z));
  }
  primitives = {};
  out.nodes.reserve(triangles / 2 + 1);
  out.corners.reserve(3 * triangles);
  Flattener{corners, out}.Add(root, lower, upper, 0);
  VISQ_CHECK_EQ(out.corners.size(), 3 * triangles);
  if (out.depth > kMaxFlatBvhDepth)
    return absl::ResourceExhaustedError(absl::StrCat("the GPU ray BVH is ", out.depth, " levels deep; its traversal holds ",
                                                     kMaxFlatBvhDepth));
  return out;
}

}  // namespace visq::raycast
