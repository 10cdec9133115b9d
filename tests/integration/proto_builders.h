// Filling request messages in the integration tests.
#pragma once

#include <vector>

#include <glm/glm.hpp>

#include "visq/v1/visq.pb.h"

namespace visq::testing {

inline void Set(v1::Vec3* v, double x, double y, double z) {
  v->set_x(x);
  v->set_y(y);
  v->set_z(z);
}

// origin + s * u + t * v, the proto's Patch.
inline void SetPatch(v1::Patch* p, glm::dvec3 o, glm::dvec3 u, glm::dvec3 v) {
  Set(p->mutable_origin(), o.x, o.y, o.z);
  Set(p->mutable_edge_u(), u.x, u.y, u.z);
  Set(p->mutable_edge_v(), v.x, v.y, v.z);
}

// A translation as SetNodeTransformRequest.world_matrix wants it: 16
// numbers, column-major like glTF.
inline std::vector<double> Translation(double x, double y, double z) {
  return {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, x, y, z, 1};
}

}  // namespace visq::testing
