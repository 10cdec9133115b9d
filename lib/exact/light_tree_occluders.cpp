// Exact tests of one occluder triangle against the whole light from a query
// point, on input doubles only, and the order in which a query subtracts
// occluders.
#include "exact/light_visibility_impl.h"

#include <algorithm>
#include <array>
#include <bit>
#include <cmath>
#include <limits>
#include <mutex>

#include "common/check.h"

namespace visq::exact::detail {

bool LightTree::ShadowMissesLight(const glm::dvec3& p, const glm::dvec3 (&v)[3]) const {
  const Orient3dFan fans[3] = {{p, v[0], v[1]}, {p, v[1], v[2]}, {p, v[2], v[0]}};
  // orient3d(y, p, a, b) = -orient3d(p, a, b, y)
  return ShadowMissesLightBySides(3, [&](size_t e, size_t i) { return -fans[e].Side(light_local[i]); });
}

LightTree::Cover LightTree::CoveredLightVertices(const glm::dvec3& p, const glm::dvec3 (&v)[3]) const {
  Cover cover;
  const Orient3dFan plane(v[0], v[1], v[2]);
  const int p_side = plane.Side(p);
  if (p_side == 0) return cover;
  // A segment crosses the interior when its line has one strict side
  // against the three edge lines.
  const Orient3dFan edges[3] = {{p, v[0], v[1]}, {p, v[1], v[2]}, {p, v[2], v[0]}};
  cover.all = true;
  for (size_t i = 0; i < light_local.size(); ++i) {
    const glm::dvec3& y = light_local[i];
    bool crosses = plane.Side(y) == -p_side;
    if (crosses) {
      const int s0 = edges[0].Side(y);
      crosses = s0 != 0 && edges[1].Side(y) == s0 && edges[2].Side(y) == s0;
    }
    cover.all &= crosses;
    if (crosses && i < 64) cover.mask |= uint64_t{1} << i;
    if (!cover.all && i >= 64) break;
  }
  return cover;
}

LightTree::OccluderTest LightTree::TestOccluder(const glm::dvec3& p, const glm::dvec3 (&v)[3]) const {
  OccluderTest test;
  const size_t n = light_local.size();
  if (n > kSharedSidesVertices) {
    test.misses = ShadowMissesLight(p, v);
    if (!test.misses) test.cover = CoveredLightVertices(p, v);
    return test;
  }
  const Orient3dFan edges[3] = {{p, v[0], v[1]}, {p, v[1], v[2]}, {p, v[2], v[0]}};
  int8_t side[3][kSharedSidesVertices];  // orient3d(p, v_e, v_e+1, y_i)
  for (int e = 0; e < 3; ++e) {
    for (size_t i = 0; i < n; ++i) side[e][i] = static_cast<int8_t>(edges[e].Side(light_local[i]));
  }
  test.misses = ShadowMissesLightBySides(3, [&](size_t e, size_t i) { return -side[e][i]; });
  if (test.misses) return test;
  const Orient3dFan plane(v[0], v[1], v[2]);
  const int p_side = plane.Side(p);
  if (p_side == 0) return test;
  test.cover.all = true;
  for (size_t i = 0; i < n; ++i) {
    const bool crosses = side[0][i] != 0 && side[1][i] == side[0][i] && side[2][i] == side[0][i] &&
                         plane.Side(light_local[i]) == -p_side;
    test.cover.all &= crosses;
    if (crosses) test.cover.mask |= uint64_t{1} << i;
  }
  return test;
}

double LightTree::ApparentSize(const glm::dvec3& p, const glm::dvec3 (&v)[3]) {
  // (n . offset)^2 / |offset|^6: the projected area over the squared
  // distance, squared, and with constant factors left out: no root and one
  // division a candidate (a penumbra point sorts a hundred).
  const glm::dvec3 offset = v[0] + v[1] + v[2] - 3.0 * p;  // three times the centroid's
  const glm::dvec3 normal = glm::cross(v[1] - v[0], v[2] - v[0]);
  const double distance2 = glm::dot(offset, offset);
  const double facing = glm::dot(normal, offset);
  return facing * facing / std::max(distance2 * distance2 * distance2, 1e-300);
}

void LightTree::SortLargestFirst(const glm::dvec3& p, std::vector<uint32_t>* ids) const {
  if (!largest_first) return;
  // One integer a candidate: the size as a float's bits (an order-keeping
  // map for positive floats), complemented so the largest comes first, over
  // the id.
  std::vector<uint64_t> keys;
  keys.reserve(ids->size());
  for (const uint32_t id : *ids) {
    const uint32_t* t = OccluderVertices(id);
    const glm::dvec3 v[3] = {vertices[t[0]], vertices[t[1]], vertices[t[2]]};
    const float size = static_cast<float>(std::min(ApparentSize(p, v), 1e38));
    keys.push_back(uint64_t{~std::bit_cast<uint32_t>(size)} << 32 | id);
  }
  std::sort(keys.begin(), keys.end());
  for (size_t i = 0; i < keys.size(); ++i) (*ids)[i] = static_cast<uint32_t>(keys[i]);
}

}  // namespace visq::exact::detail
