#include "trocar_docking/cpp/vision_bridge.h"

#include <string>
#include <opencv2/core/version.hpp>
#include <visp3/core/vpConfig.h>

namespace trocar_docking {

rust::String vision_backend_versions() {
  return rust::String("ViSP " + std::to_string(VISP_VERSION_MAJOR) + "." + std::to_string(VISP_VERSION_MINOR) + "." + std::to_string(VISP_VERSION_PATCH) + ", OpenCV " + CV_VERSION);
}

}  // namespace trocar_docking
