// Input checks of the C++ bridges (the markerless one): the camera model and an image of its size.
#pragma once
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <stdexcept>
#include <string>

#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include "rust/cxx.h"

namespace trocar_docking {
namespace bridge {

inline void require(bool ok, const std::string &what) {
  if (!ok) throw std::invalid_argument(what);
}

inline bool all_finite(rust::Slice<const double> v) {
  return std::all_of(v.begin(), v.end(), [](double x) { return std::isfinite(x); });
}

// A pinhole camera with OpenCV distortion: K from fx, fy, cx, cy and the coefficients as a
// 1 x n row, after checking them and the image size.
inline void camera_model(rust::Slice<const double> intrinsics, rust::Slice<const double> dist, int width,
                         int height, cv::Matx33d &K, cv::Mat &coefficients) {
  require(intrinsics.size() == 4, "intrinsics must be fx, fy, cx, cy");
  require(all_finite(intrinsics) && all_finite(dist), "intrinsics and distortion must be finite");
  require(intrinsics[0] > 1.0 && intrinsics[1] > 1.0, "focal lengths must be > 1 px");
  const size_t nd = dist.size();
  require(nd == 0 || nd == 4 || nd == 5 || nd == 8 || nd == 12 || nd == 14,
          "distortion must have 0, 4, 5, 8, 12 or 14 coefficients");
  require(width >= 8 && height >= 8 && width <= 20000 && height <= 20000,
          "image size " + std::to_string(width) + "x" + std::to_string(height) + " out of range (8..=20000 px)");
  K = cv::Matx33d(intrinsics[0], 0, intrinsics[2], 0, intrinsics[1], intrinsics[3], 0, 0, 1);
  coefficients = cv::Mat(1, static_cast<int>(nd), CV_64F);
  for (size_t i = 0; i < nd; ++i) coefficients.at<double>(0, static_cast<int>(i)) = dist[i];
}

// The image (1, 3 or 4 channels, RGB order) as grey into `grey`, after checking it is
// `want_width` x `want_height` and the buffer's size.
inline void grey_image(rust::Slice<const uint8_t> pixels, int width, int height, int channels, int want_width,
                       int want_height, cv::Mat &grey) {
  require(width == want_width && height == want_height,
          "image " + std::to_string(width) + "x" + std::to_string(height) + " does not match the camera model (" +
              std::to_string(want_width) + "x" + std::to_string(want_height) + ")");
  require(channels == 1 || channels == 3 || channels == 4, "channels must be 1, 3 or 4");
  require(pixels.size() == static_cast<size_t>(width) * height * channels,
          "pixel buffer has " + std::to_string(pixels.size()) + " bytes, expected " +
              std::to_string(static_cast<size_t>(width) * height * channels));
  cv::Mat m(height, width, CV_8UC(channels), const_cast<uint8_t *>(pixels.data()));
  if (channels == 1)
    m.copyTo(grey);
  else
    cv::cvtColor(m, grey, channels == 3 ? cv::COLOR_RGB2GRAY : cv::COLOR_RGBA2GRAY);
}

}  // namespace bridge
}  // namespace trocar_docking
