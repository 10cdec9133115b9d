// The absorbers' BVHs a resident scene keeps for ray stabbing: one per node
// set whatever the order it is named in, the least recently used out past
// kKept, and their memory counted.
#include "core/absorber_rays_cache.h"

#include <gtest/gtest.h>

#include "scene/sample_scenes.h"

namespace visq::core {
namespace {

TEST(AbsorberRaysCache, KeepsOneBvhANodeSetAndLetsTheLeastRecentlyUsedGo) {
  Scene scene;
  for (int i = 0; i < 6; ++i) AddBox(scene, "box" + std::to_string(i), {3.0 * i, 0, 0}, {3.0 * i + 2, 2, 2}, 0);
  UpdateBounds(scene);
  AbsorberRaysCache cache;
  EXPECT_EQ(cache.MemoryBytes(), 0u);
  auto first = cache.Get(scene, {2, 0}, {});
  ASSERT_TRUE(first.ok()) << first.status();
  auto again = cache.Get(scene, {0, 2, 2}, {});
  ASSERT_TRUE(again.ok());
  EXPECT_EQ(first->get(), again->get()) << "the same set, named in another order, is the same BVH";
  EXPECT_EQ((*first)->node_of_triangle.size(), 24u);  // two boxes of 12 triangles
  EXPECT_GT(cache.MemoryBytes(), 0u);

  // kKept other sets: the first, now the least recently used, goes.
  for (uint32_t n = 1; n <= AbsorberRaysCache::kKept; ++n) ASSERT_TRUE(cache.Get(scene, {n}, {}).ok());
  auto rebuilt = cache.Get(scene, {0, 2}, {});
  ASSERT_TRUE(rebuilt.ok());
  EXPECT_NE(first->get(), rebuilt->get());

  EXPECT_EQ(cache.Get(scene, {99}, {}).status().code(), absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace visq::core
