// Trees by scene and light, bounded in bytes, least recently used first out;
// and the light's hash for their keys.
#include "exact/light_visibility.h"

namespace visq::exact {

uint64_t HashLight(const AreaLight& light, const TreeOptions& options) {
  uint64_t h = 1469598103934665603ull;  // FNV-1a over the bit patterns
  auto mix = [&](const void* data, size_t n) {
    const auto* b = static_cast<const unsigned char*>(data);
    for (size_t i = 0; i < n; ++i) h = (h ^ b[i]) * 1099511628211ull;
  };
  for (const auto& v : light.vertices) mix(&v, sizeof(v));
  mix(&light.radiance, sizeof(light.radiance));
  if (options.receiver_bounds) {
    mix(&options.receiver_bounds->min, sizeof(glm::dvec3));
    mix(&options.receiver_bounds->max, sizeof(glm::dvec3));
  }
  for (uint32_t t : options.exclude_triangles) mix(&t, sizeof(t));
  mix(&options.shadow_tolerance, sizeof(options.shadow_tolerance));
  return h;
}

size_t LightVisibilityCache::KeyHash::operator()(const CacheKey& k) const {
  return std::hash<std::string>()(k.scene_id) ^ (k.scene_version * 0x9E3779B97F4A7C15ull) ^
         (k.light_hash * 0xC2B2AE3D27D4EB4Full);
}

LightVisibilityCache::LightVisibilityCache(size_t max_bytes) : max_bytes_(max_bytes) {}

std::shared_ptr<LightVisibilityTree> LightVisibilityCache::Find(const CacheKey& key) {
  std::lock_guard lock(mutex_);
  auto it = index_.find(key);
  if (it == index_.end()) return nullptr;
  lru_.splice(lru_.begin(), lru_, it->second);
  EvictLocked(&key);
  return it->second->second;
}

std::shared_ptr<LightVisibilityTree> LightVisibilityCache::Peek(const CacheKey& key) const {
  std::lock_guard lock(mutex_);
  auto it = index_.find(key);
  return it == index_.end() ? nullptr : it->second->second;
}

StatusOr<std::shared_ptr<LightVisibilityTree>> LightVisibilityCache::GetOrCreate(
    const CacheKey& key, const Factory& make) {
  if (auto hit = Find(key)) return hit;
  // Build outside the lock: creation scans the whole scene.
  VISQ_ASSIGN_OR_RETURN(std::unique_ptr<LightVisibilityTree> made, make());
  std::shared_ptr<LightVisibilityTree> tree(std::move(made));
  std::lock_guard lock(mutex_);
  auto it = index_.find(key);
  if (it != index_.end()) {  // somebody else built it meanwhile; keep theirs
    lru_.splice(lru_.begin(), lru_, it->second);
    return it->second->second;
  }
  lru_.emplace_front(key, tree);
  index_[key] = lru_.begin();
  EvictLocked(&key);
  return tree;
}

void LightVisibilityCache::EvictLocked(const CacheKey* keep) {
  // Trees grow after insertion, so the total is measured afresh.
  size_t total = 0;
  for (const auto& [k, tree] : lru_) total += tree->MemoryBytes();
  while (total > max_bytes_ && !lru_.empty()) {
    auto victim = std::prev(lru_.end());
    if (keep != nullptr && victim->first == *keep) break;  // never the one being returned
    total -= victim->second->MemoryBytes();
    index_.erase(victim->first);
    lru_.erase(victim);
    ++evictions_;
  }
}

void LightVisibilityCache::InvalidateScene(const std::string& scene_id) {
  std::lock_guard lock(mutex_);
  for (auto it = lru_.begin(); it != lru_.end();) {
    if (it->first.scene_id == scene_id) {
      index_.erase(it->first);
      it = lru_.erase(it);
    } else {
      ++it;
    }
  }
}

size_t LightVisibilityCache::bytes() const {
  std::lock_guard lock(mutex_);
  size_t total = 0;
  for (const auto& [k, tree] : lru_) total += tree->MemoryBytes();
  return total;
}

size_t LightVisibilityCache::size() const {
  std::lock_guard lock(mutex_);
  return lru_.size();
}

uint64_t LightVisibilityCache::evictions() const {
  std::lock_guard lock(mutex_);
  return evictions_;
}

}  // namespace visq::exact
