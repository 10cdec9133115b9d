#include "obscurance/instanced_ray_scene.h"

#include <algorithm>
#include <array>
#include <limits>

#include <embree3/rtcore.h>

#include "raycast/embree_float_mode.h"
#include "raycast/embree_scene.h"

namespace visq::obscurance {

struct InstancedRayScene::Impl {
  RTCDevice device = nullptr;
  RTCScene top = nullptr;  // instances: the static mesh (geom 0), object k (geom k + 1)
  RTCScene static_mesh = nullptr;
  std::vector<RTCScene> object_meshes;    // object k's triangles, pose at Create, frame-relative
  std::vector<RTCScene> object_alone;     // an instance of object k only
  std::vector<RTCScene> object_probe;     // the same, at a pose of its own (SetProbeTransform)
  std::vector<uint32_t> static_triangles;
  std::vector<std::vector<uint32_t>> objects;
  glm::dvec3 origin{0.0};
  double t_min = 0;

  ~Impl() {
    for (RTCScene s : object_probe) rtcReleaseScene(s);
    for (RTCScene s : object_alone) rtcReleaseScene(s);
    for (RTCScene s : object_meshes) rtcReleaseScene(s);
    if (top) rtcReleaseScene(top);
    if (static_mesh) rtcReleaseScene(static_mesh);
    if (device) rtcReleaseDevice(device);
  }

  // What one traced ray found: the scene's triangle, and the object whose
  // instance it belongs to (-1: the static mesh).
  Hit HitOf(const RTCRayHit& rh) const {
    Hit hit;
    if (rh.hit.geomID == RTC_INVALID_GEOMETRY_ID) return hit;
    hit.hit = true;
    hit.t = rh.ray.tfar;
    if (rh.hit.instID[0] != 0) {
      hit.object = static_cast<int32_t>(rh.hit.instID[0]) - 1;
      hit.triangle = objects[hit.object][rh.hit.primID];
    } else {
      hit.triangle = static_triangles[rh.hit.primID];
    }
    return hit;
  }

  // Attaches `triangles` (frame-relative float copies) as geometry 0 of `mesh`.
  void AddTriangles(RTCScene mesh, const Scene& scene, const std::vector<uint32_t>& triangles) const {
    if (!triangles.empty()) {
      RTCGeometry geom = rtcNewGeometry(device, RTC_GEOMETRY_TYPE_TRIANGLE);
      auto* v = static_cast<float*>(rtcSetNewGeometryBuffer(geom, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3,
                                                            3 * sizeof(float), triangles.size() * 3));
      auto* idx = static_cast<uint32_t*>(rtcSetNewGeometryBuffer(geom, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3,
                                                                 3 * sizeof(uint32_t), triangles.size()));
      for (size_t i = 0; i < triangles.size(); ++i)
        for (int c = 0; c < 3; ++c) {
          const glm::dvec3 p = scene.Vertex(triangles[i], c) - origin;
          v[9 * i + 3 * c] = static_cast<float>(p.x);
          v[9 * i + 3 * c + 1] = static_cast<float>(p.y);
          v[9 * i + 3 * c + 2] = static_cast<float>(p.z);
          idx[3 * i + c] = static_cast<uint32_t>(3 * i + c);
        }
      rtcCommitGeometry(geom);
      rtcAttachGeometryByID(mesh, geom, 0);
      rtcReleaseGeometry(geom);
    }
  }
  RTCScene Mesh(const Scene& scene, const std::vector<uint32_t>& triangles) const {
    RTCScene mesh = rtcNewScene(device);
    rtcSetSceneBuildQuality(mesh, RTC_BUILD_QUALITY_HIGH);
    AddTriangles(mesh, scene, triangles);
    rtcCommitScene(mesh);
    return mesh;
  }

  static void AttachInstance(RTCDevice device, RTCScene parent, RTCScene child, unsigned id) {
    RTCGeometry inst = rtcNewGeometry(device, RTC_GEOMETRY_TYPE_INSTANCE);
    rtcSetGeometryInstancedScene(inst, child);
    const float identity[12] = {1, 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0};
    rtcSetGeometryTransform(inst, 0, RTC_FORMAT_FLOAT3X4_COLUMN_MAJOR, identity);
    rtcCommitGeometry(inst);
    rtcAttachGeometryByID(parent, inst, id);
    rtcReleaseGeometry(inst);
  }
};

InstancedRayScene::InstancedRayScene(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
InstancedRayScene::~InstancedRayScene() = default;
size_t InstancedRayScene::object_count() const { return impl_->objects.size(); }

StatusOr<std::unique_ptr<InstancedRayScene>> InstancedRayScene::Create(
    const Scene& scene, const std::vector<std::vector<uint32_t>>& objects) {
  auto impl = std::make_unique<Impl>();
  impl->device = rtcNewDevice(raycast::EmbreeDeviceConfig().c_str());
  if (impl->device == nullptr) return absl::InternalError("rtcNewDevice failed");
  impl->origin = scene.bounds.Empty() ? glm::dvec3(0.0) : scene.bounds.Center();
  impl->t_min = 1e-6 * std::max(1e-30, glm::length(scene.bounds.Extent()));
  impl->objects = objects;
  std::vector<uint8_t> dynamic(scene.TriangleCount(), 0);
  for (const auto& o : objects)
    for (uint32_t t : o) {
      if (t >= scene.TriangleCount() || dynamic[t])
        return absl::InvalidArgumentError(absl::StrCat("objects: triangle ", t, " out of range or in two objects"));
      dynamic[t] = 1;
    }
  for (uint32_t t = 0; t < scene.TriangleCount(); ++t)
    if (!dynamic[t]) impl->static_triangles.push_back(t);

  impl->top = rtcNewScene(impl->device);
  // The static mesh is an instance too (geometry 0): the top scene then holds
  // only a few instances, and re-committing it after a move rebuilds a BVH
  // over those few boxes instead of over the static triangles.
  impl->static_mesh = impl->Mesh(scene, impl->static_triangles);
  Impl::AttachInstance(impl->device, impl->top, impl->static_mesh, 0);
  for (size_t k = 0; k < objects.size(); ++k) {
    RTCScene mesh = impl->Mesh(scene, objects[k]);
    impl->object_meshes.push_back(mesh);
    Impl::AttachInstance(impl->device, impl->top, mesh, static_cast<unsigned>(k + 1));
    for (std::vector<RTCScene>* list : {&impl->object_alone, &impl->object_probe}) {
      RTCScene alone = rtcNewScene(impl->device);
      Impl::AttachInstance(impl->device, alone, mesh, 0);
      rtcCommitScene(alone);
      list->push_back(alone);
    }
  }
  rtcCommitScene(impl->top);
  if (rtcGetDeviceError(impl->device) != RTC_ERROR_NONE) return absl::InternalError("Embree scene build failed");
  return std::unique_ptr<InstancedRayScene>(new InstancedRayScene(std::move(impl)));
}

namespace {

// `delta` as Embree's float matrix in the frame: p' = L (p + o) + t - o =
// L p + (L o + t - o).
std::array<float, 12> FrameTransform(const glm::dmat4& delta, const glm::dvec3& origin) {
  const glm::dmat3 lin(delta);
  const glm::dvec3 trans = lin * origin + glm::dvec3(delta[3]) - origin;
  std::array<float, 12> xfm;
  for (int c = 0; c < 3; ++c)
    for (int r = 0; r < 3; ++r) xfm[3 * c + r] = static_cast<float>(lin[c][r]);
  for (int r = 0; r < 3; ++r) xfm[9 + r] = static_cast<float>(trans[r]);
  return xfm;
}

void SetInstanceTransform(RTCScene parent, unsigned id, const std::array<float, 12>& xfm) {
  RTCGeometry inst = rtcGetGeometry(parent, id);
  rtcSetGeometryTransform(inst, 0, RTC_FORMAT_FLOAT3X4_COLUMN_MAJOR, xfm.data());
  rtcCommitGeometry(inst);
}

}  // namespace

void InstancedRayScene::SetTransform(size_t object, const glm::dmat4& delta) {
  const std::array<float, 12> xfm = FrameTransform(delta, impl_->origin);
  SetInstanceTransform(impl_->top, static_cast<unsigned>(object + 1), xfm);
  SetInstanceTransform(impl_->object_alone[object], 0, xfm);
  rtcCommitScene(impl_->object_alone[object]);
}

void InstancedRayScene::SetProbeTransform(size_t object, const glm::dmat4& delta) {
  // The same float matrix as SetTransform makes for `delta`, so that the
  // probe meets a ray exactly when the object moved there would.
  SetInstanceTransform(impl_->object_probe[object], 0, FrameTransform(delta, impl_->origin));
  rtcCommitScene(impl_->object_probe[object]);
}

void InstancedRayScene::Commit() { rtcCommitScene(impl_->top); }

namespace {
RTCRayHit MakeRay(const glm::dvec3& origin, const glm::dvec3& frame, const glm::dvec3& d, double t_min, double tmax) {
  RTCRayHit rh{};
  const glm::dvec3 o = origin - frame;
  rh.ray.org_x = static_cast<float>(o.x);
  rh.ray.org_y = static_cast<float>(o.y);
  rh.ray.org_z = static_cast<float>(o.z);
  rh.ray.dir_x = static_cast<float>(d.x);
  rh.ray.dir_y = static_cast<float>(d.y);
  rh.ray.dir_z = static_cast<float>(d.z);
  rh.ray.tnear = static_cast<float>(t_min);
  rh.ray.tfar = static_cast<float>(tmax);
  rh.ray.mask = 0xFFFFFFFFu;
  rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
  rh.hit.instID[0] = RTC_INVALID_GEOMETRY_ID;
  return rh;
}
}  // namespace

namespace {
// Rays per stream call: enough for Embree to fill its packets, few enough
// to stay on a thread's stack.
constexpr size_t kStream = 64;
}  // namespace

void InstancedRayScene::ClosestStream(std::span<const PatchRay> rays, double tmax, std::span<Hit> hits) const {
  RTCRayHit stream[kStream];
  for (size_t base = 0; base < rays.size(); base += kStream) {
    const size_t n = std::min(kStream, rays.size() - base);
    for (size_t i = 0; i < n; ++i)
      stream[i] = MakeRay(rays[base + i].origin, impl_->origin, rays[base + i].direction, impl_->t_min, tmax);
    RTCIntersectContext context;
    rtcInitIntersectContext(&context);
    {
      const raycast::EmbreeFloatMode float_mode;
      rtcIntersect1M(impl_->top, &context, stream, static_cast<unsigned>(n), sizeof(RTCRayHit));
    }
    for (size_t i = 0; i < n; ++i) hits[base + i] = impl_->HitOf(stream[i]);
  }
}

InstancedRayScene::Hit InstancedRayScene::Closest(const glm::dvec3& origin, const glm::dvec3& direction,
                                                  double tmax) const {
  RTCRayHit rh = MakeRay(origin, impl_->origin, direction, impl_->t_min, tmax);
  RTCIntersectContext context;
  rtcInitIntersectContext(&context);
  {
    const raycast::EmbreeFloatMode float_mode;
    rtcIntersect1(impl_->top, &context, &rh);
  }
  return impl_->HitOf(rh);
}

namespace {

// Whether anything in `scene` meets the ray in (t_min, tmax].
bool Occludes(RTCScene scene, const glm::dvec3& frame_origin, double t_min, const glm::dvec3& origin,
              const glm::dvec3& direction, double tmax) {
  RTCRayHit rh = MakeRay(origin, frame_origin, direction, t_min, tmax);
  RTCIntersectContext context;
  rtcInitIntersectContext(&context);
  {
    const raycast::EmbreeFloatMode float_mode;
    rtcOccluded1(scene, &context, &rh.ray);
  }
  return rh.ray.tfar < 0;  // Embree sets tfar = -inf on a hit
}

}  // namespace

bool InstancedRayScene::HitsObject(size_t object, const glm::dvec3& origin, const glm::dvec3& direction,
                                   double tmax) const {
  return Occludes(impl_->object_alone[object], impl_->origin, impl_->t_min, origin, direction, tmax);
}

bool InstancedRayScene::HitsProbe(size_t object, const glm::dvec3& origin, const glm::dvec3& direction,
                                  double tmax) const {
  return Occludes(impl_->object_probe[object], impl_->origin, impl_->t_min, origin, direction, tmax);
}

}  // namespace visq::obscurance
