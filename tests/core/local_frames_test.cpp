// Local frames (core/local_frames.h): the region around a query holds its
// triangles and only those near it, nearby queries share it, and the cache
// keeps at most kMaxFrames.
#include <gtest/gtest.h>

#include "core/local_frames.h"
#include "scene/sample_scenes.h"

namespace visq::core {
namespace {

// One small triangle at each of `corners`.
Scene TrianglesAt(const std::vector<glm::dvec3>& corners) {
  std::vector<std::array<glm::dvec3, 3>> triangles;
  for (const glm::dvec3& c : corners) triangles.push_back({c, c + glm::dvec3(0.25, 0, 0), c + glm::dvec3(0, 0, 0.25)});
  return SceneOfTriangles(triangles);
}

Bounds Box(const glm::dvec3& lo, const glm::dvec3& hi) {
  Bounds b;
  b.Extend(lo);
  b.Extend(hi);
  return b;
}

TEST(LocalFrames, ARegionHoldsTheTrianglesNearTheQueryRebasedToItsCentre) {
  const glm::dvec3 far(1e6, 0, 1e6);
  const Scene scene = TrianglesAt({glm::dvec3(0), far, far + glm::dvec3(1, 0, 0), far + glm::dvec3(100, 0, 0)});
  auto index = exact::SceneTriangleIndex::Build(std::make_shared<const Scene>(scene));
  ASSERT_TRUE(index.ok()) << index.status();
  LocalFrames frames;
  // A query 1.5 across: its region is a cube of side 4 on the grid of step 2.
  const std::shared_ptr<LocalFrame> frame =
      frames.For(scene, **index, Box(far - glm::dvec3(0.25), far + glm::dvec3(1.25)));
  EXPECT_EQ(frame->side, 4.0);
  EXPECT_EQ(frame->scene->TriangleCount(), 2u) << "the two triangles within the region, not the origin's or 100 away";
  EXPECT_EQ(frame->origin(), frame->lo + glm::dvec3(2.0));
  EXPECT_LE(glm::length(frame->origin() - far), 4.0);
  // Positions stay world-space doubles: the float32 copies rebase them.
  EXPECT_EQ(frame->scene->positions[0], far);

  // A query nearby, on the same grid cell, shares the frame.
  EXPECT_EQ(frames.For(scene, **index, Box(far - glm::dvec3(0.5), far + glm::dvec3(0.5))), frame);
  EXPECT_EQ(frames.size(), 1u);
  for (int k = 1; k <= int(LocalFrames::kMaxFrames) + 3; ++k)
    (void)frames.For(scene, **index, Box(far + glm::dvec3(10.0 * k), far + glm::dvec3(10.0 * k + 1)));
  EXPECT_EQ(frames.size(), LocalFrames::kMaxFrames);
}

}  // namespace
}  // namespace visq::core
