#include "obscurance/obscurance_export.h"

#include <algorithm>
#include <cmath>

#include <stb_image_write.h>

#include "scene/gltf_writer.h"

namespace visq::obscurance {

std::vector<float> AtlasUvs(const std::vector<glm::vec2>& corner_uv, uint32_t width, uint32_t height) {
  std::vector<float> uvs;
  uvs.reserve(corner_uv.size() * 2);
  for (const glm::vec2& uv : corner_uv) {
    uvs.push_back(uv.x / static_cast<float>(width));
    uvs.push_back(uv.y / static_cast<float>(height));
  }
  return uvs;
}

StatusOr<std::string> BakedSceneGlb(const Scene& placed_scene, const std::vector<glm::vec2>& corner_uv, uint32_t width,
                                    uint32_t height, const std::vector<glm::vec3>& w, BakedSceneOptions options) {
  const Scene& scene = placed_scene.Flattened();
  const size_t triangles = scene.triangles.size();
  if (corner_uv.size() != 3 * triangles || w.size() != size_t(width) * height || width == 0 || height == 0 ||
      (!options.vertex_w.empty() && options.vertex_w.size() != scene.positions.size()) ||
      (options.atlas_is_lightmap_uvs && scene.lightmap_uvs.size() != scene.positions.size()))
    return absl::InternalError("the obscurance solution does not match its scene");
  GltfExtras extras;
  // An atlas on the artist's own lightmap UVs is read through them: they
  // are the atlas UVs, to a rounding of the texel scale.
  if (!options.atlas_is_lightmap_uvs) {
    extras.occlusion_uv.reserve(3 * triangles);
    const std::vector<float> uvs = AtlasUvs(corner_uv, width, height);
    for (size_t i = 0; i < 3 * triangles; ++i) extras.occlusion_uv.emplace_back(uvs[2 * i], uvs[2 * i + 1]);
  }
  extras.vertex_colors = std::move(options.vertex_w);

  std::vector<unsigned char> pixels(w.size() * 3);
  for (size_t i = 0; i < w.size(); ++i)
    for (int c = 0; c < 3; ++c)
      pixels[3 * i + c] = static_cast<unsigned char>(std::lround(std::clamp(w[i][c], 0.0f, 1.0f) * 255.0f));
  auto append = [](void* context, void* data, int size) {
    static_cast<std::string*>(context)->append(static_cast<const char*>(data), static_cast<size_t>(size));
  };
  if (stbi_write_png_to_func(append, &extras.occlusion_png, static_cast<int>(width), static_cast<int>(height), 3,
                             pixels.data(), static_cast<int>(width) * 3) == 0)
    return absl::InternalError("encoding the W atlas as PNG failed");
  return WriteGlb(scene, extras);
}

}  // namespace visq::obscurance
