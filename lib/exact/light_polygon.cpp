// The light's checks (ValidateAreaLight) and its exact triangulation.
#include "exact/light_visibility_impl.h"

#include <algorithm>
#include <array>
#include <bit>
#include <cmath>
#include <limits>
#include <mutex>

#include "common/coordinates.h"

namespace visq::exact::detail {

namespace {

// Ear clipping in the projection that drops the dominant normal axis; exact
// 2D orientation tests. Returns triangles as vertex index triples in the
// polygon's winding, or an error for non-simple polygons.
StatusOr<std::vector<std::array<uint32_t, 3>>> Triangulate(const std::vector<glm::dvec3>& v,
                                                           const glm::dvec3& newell) {
  int k = 0;
  for (int i = 1; i < 3; ++i) {
    if (std::fabs(newell[i]) > std::fabs(newell[k])) k = i;
  }
  int i2 = (k + 1) % 3, j2 = (k + 2) % 3;
  if (newell[k] < 0) std::swap(i2, j2);  // make the polygon counter-clockwise
  // Simple: no two non-adjacent edges meet (exact segment tests).
  const size_t n = v.size();
  auto meet = [&](const glm::dvec3& a, const glm::dvec3& b, const glm::dvec3& c, const glm::dvec3& d) {
    const int o1 = Orient2d(a, b, c, i2, j2), o2 = Orient2d(a, b, d, i2, j2);
    const int o3 = Orient2d(c, d, a, i2, j2), o4 = Orient2d(c, d, b, i2, j2);
    if (o1 * o2 < 0 && o3 * o4 < 0) return true;
    auto on = [&](const glm::dvec3& p, const glm::dvec3& q, const glm::dvec3& x, int o) {
      return o == 0 && std::min(p[i2], q[i2]) <= x[i2] && x[i2] <= std::max(p[i2], q[i2]) &&
             std::min(p[j2], q[j2]) <= x[j2] && x[j2] <= std::max(p[j2], q[j2]);
    };
    return on(a, b, c, o1) || on(a, b, d, o2) || on(c, d, a, o3) || on(c, d, b, o4);
  };
  for (size_t e = 0; e < n; ++e) {
    for (size_t f = e + 2; f < n; ++f) {
      if (e == 0 && f == n - 1) continue;  // adjacent through vertex 0
      if (meet(v[e], v[(e + 1) % n], v[f], v[(f + 1) % n])) {
        return absl::InvalidArgumentError(absl::StrCat(
            "light: not a simple polygon (edges ", e, " and ", f, " meet)"));
      }
    }
  }
  std::vector<uint32_t> ring(v.size());
  for (uint32_t i = 0; i < ring.size(); ++i) ring[i] = i;
  std::vector<std::array<uint32_t, 3>> out;
  // Drop exactly collinear (straight) vertices first; they would give
  // zero-area ears.
  auto drop_straight = [&]() {
    bool changed = true;
    while (changed && ring.size() > 3) {
      changed = false;
      for (size_t i = 0; i < ring.size(); ++i) {
        const size_t a = (i + ring.size() - 1) % ring.size(), c = (i + 1) % ring.size();
        if (Orient2d(v[ring[a]], v[ring[i]], v[ring[c]], i2, j2) == 0) {
          ring.erase(ring.begin() + static_cast<long>(i));
          changed = true;
          break;
        }
      }
    }
  };
  drop_straight();
  while (ring.size() > 3) {
    bool found = false;
    for (size_t i = 0; i < ring.size() && !found; ++i) {
      const size_t a = (i + ring.size() - 1) % ring.size(), c = (i + 1) % ring.size();
      const glm::dvec3 &pa = v[ring[a]], &pb = v[ring[i]], &pc = v[ring[c]];
      if (Orient2d(pa, pb, pc, i2, j2) <= 0) continue;  // reflex
      bool empty = true;
      for (size_t m = 0; m < ring.size() && empty; ++m) {
        if (m == a || m == i || m == c) continue;
        const glm::dvec3& x = v[ring[m]];
        if (Orient2d(pa, pb, x, i2, j2) >= 0 && Orient2d(pb, pc, x, i2, j2) >= 0 &&
            Orient2d(pc, pa, x, i2, j2) >= 0) {
          empty = false;
        }
      }
      if (!empty) continue;
      out.push_back({ring[a], ring[i], ring[c]});
      ring.erase(ring.begin() + static_cast<long>(i));
      drop_straight();
      found = true;
    }
    if (!found) return absl::InvalidArgumentError("light: not a simple polygon");
  }
  if (ring.size() == 3) {
    if (Orient2d(v[ring[0]], v[ring[1]], v[ring[2]], i2, j2) <= 0) {
      return absl::InvalidArgumentError("light: not a simple polygon");
    }
    out.push_back({ring[0], ring[1], ring[2]});
  }
  return out;
}

}  // namespace

StatusOr<PreparedLight> PrepareLight(const AreaLight& light) {
  const auto& lv = light.vertices;
  if (lv.size() < 3) {
    return absl::InvalidArgumentError(
        absl::StrCat("light.vertices: need at least 3, got ", lv.size()));
  }
  for (size_t i = 0; i < lv.size(); ++i) {
    for (int c = 0; c < 3; ++c) {
      if (std::isnan(lv[i][c])) {
        return absl::InvalidArgumentError(absl::StrCat("light.vertices[", i, "]: NaN coordinate"));
      }
      if (!InCoordinateRange(lv[i][c])) {
        return absl::InvalidArgumentError(
            absl::StrCat("light.vertices[", i, "]: infinite coordinate or beyond ±", kMaxCoordinate));
      }
    }
    if (lv[i] == lv[(i + 1) % lv.size()]) {
      return absl::InvalidArgumentError(absl::StrCat("light.vertices[", (i + 1) % lv.size(),
                                                     "]: repeats light.vertices[", i, "]"));
    }
  }
  if (!std::isfinite(light.radiance) || light.radiance < 0.0) {
    return absl::InvalidArgumentError(
        absl::StrCat("light.radiance: must be finite and >= 0, got ", light.radiance));
  }
  glm::dvec3 centroid(0.0);
  for (const auto& p : lv) centroid += p;
  centroid /= static_cast<double>(lv.size());
  PreparedLight out;
  out.origin = centroid;
  for (const auto& p : lv) out.local.push_back(p - centroid);
  const auto& ll = out.local;
  glm::dvec3 newell(0.0);
  double diameter = 0.0;
  for (size_t i = 0; i < ll.size(); ++i) {
    newell += glm::cross(ll[i], ll[(i + 1) % ll.size()]);
    for (size_t j = 0; j < i; ++j) diameter = std::max(diameter, glm::length(ll[i] - ll[j]));
  }
  const double newell_len = glm::length(newell);
  if (!(newell_len > 1e-12 * diameter * diameter)) {
    return absl::InvalidArgumentError("light: zero area");
  }
  const glm::dvec3 unit_normal = newell / newell_len;
  for (size_t i = 0; i < ll.size(); ++i) {
    const double off = std::fabs(glm::dot(unit_normal, ll[i]));
    if (off > 1e-6 * diameter) {
      return absl::InvalidArgumentError(absl::StrCat(
          "light: not planar (light.vertices[", i, "] is ", off, " off the plane)"));
    }
  }
  out.unit_normal = unit_normal;
  out.diameter = diameter;
  VISQ_ASSIGN_OR_RETURN(out.triangles, Triangulate(ll, newell));
  return out;
}

}  // namespace visq::exact::detail

namespace visq::exact {

Status ValidateAreaLight(const AreaLight& light) { return detail::PrepareLight(light).status(); }

}  // namespace visq::exact
