// C++ side of the vision bridge: ViSP 3.5 and OpenCV 4.6 aruco.
#pragma once
#include "rust/cxx.h"

namespace trocar_docking {

// "ViSP x.y.z, OpenCV a.b.c": the vision libraries this build links.
rust::String vision_backend_versions();

}  // namespace trocar_docking
