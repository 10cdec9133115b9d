// The pinhole camera every viewpoint image shares is the scene vocabulary's
// (scene/pinhole_camera.h); the GPU layer names it as before.
#pragma once

#include "scene/pinhole_camera.h"

namespace visq::gpu {

using ::visq::PinholeCamera;
using ::visq::PinholeClipFromAnchor;
using ::visq::ValidatePinholeCamera;

}  // namespace visq::gpu
