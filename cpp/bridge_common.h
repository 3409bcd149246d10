// Input checks of the C++ bridges (the markerless one): the camera model and an image of its size.
#pragma once
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <stdexcept>
#include <string>

#include <opencv2/calib3d.hpp>
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

// A camera's lens: K and the distortion coefficients, in OpenCV's rational model (ROS
// `plumb_bob`, `rational_polynomial`: cv::projectPoints, cv::undistortPoints,
// cv::initUndistortRectifyMap) or, `fisheye`, OpenCV's fisheye model (ROS `equidistant`,
// k1 k2 k3 k4 on the ray's angle: the cv::fisheye:: functions, as image_geometry's
// PinholeCameraModel rectifies an equidistant camera).
struct Lens {
  cv::Matx33d K;
  cv::Mat dist;  // 1 x n, CV_64F
  bool fisheye = false;

  // Whether a pixel is not where the pinhole K puts it (an equidistant lens always bends).
  bool distorted() const { return fisheye || (!dist.empty() && cv::countNonZero(dist) > 0); }

  // Distorted pixels to undistorted normalised coordinates (P empty) or to the pixels of P.
  void undistort(cv::InputArray px, cv::OutputArray out, cv::InputArray P = cv::noArray(),
                 cv::TermCriteria criteria = cv::TermCriteria(cv::TermCriteria::COUNT | cv::TermCriteria::EPS, 5,
                                                              0.01)) const {
    if (fisheye)
      cv::fisheye::undistortPoints(px, out, K, dist, cv::noArray(), P,
                                   cv::TermCriteria(cv::TermCriteria::COUNT | cv::TermCriteria::EPS,
                                                    std::max(criteria.maxCount, 10), std::min(criteria.epsilon, 1e-8)));
    else
      cv::undistortPoints(px, out, K, dist, cv::noArray(), P, criteria);
  }

  // Points of the camera frame (moved by rvec, tvec) to distorted pixels.
  void project(cv::InputArray points, cv::OutputArray px, const cv::Vec3d &rvec = cv::Vec3d(0, 0, 0),
               const cv::Vec3d &tvec = cv::Vec3d(0, 0, 0)) const {
    if (fisheye)
      cv::fisheye::projectPoints(points, px, rvec, tvec, K, dist);
    else
      cv::projectPoints(points, rvec, tvec, K, dist, px);
  }

  // The maps that undistort an image of `size` onto the pinhole camera K (cv::remap).
  void undistort_maps(cv::Size size, cv::Mat &map1, cv::Mat &map2) const {
    if (fisheye)
      cv::fisheye::initUndistortRectifyMap(K, dist, cv::Matx33d::eye(), K, size, CV_16SC2, map1, map2);
    else
      cv::initUndistortRectifyMap(K, dist, cv::Mat(), K, size, CV_16SC2, map1, map2);
  }
};

// A lens from fx, fy, cx, cy and the coefficients (`fisheye`: exactly 4, k1 k2 k3 k4; else
// OpenCV's order, 0, 4, 5, 8, 12 or 14), after checking them and the image size.
inline Lens camera_model(rust::Slice<const double> intrinsics, rust::Slice<const double> dist, bool fisheye,
                         int width, int height) {
  require(intrinsics.size() == 4, "intrinsics must be fx, fy, cx, cy");
  require(all_finite(intrinsics) && all_finite(dist), "intrinsics and distortion must be finite");
  require(intrinsics[0] > 1.0 && intrinsics[1] > 1.0, "focal lengths must be > 1 px");
  const size_t nd = dist.size();
  if (fisheye)
    require(nd == 4, "the equidistant (fisheye) model has 4 coefficients (k1 k2 k3 k4), got " + std::to_string(nd));
  else
    require(nd == 0 || nd == 4 || nd == 5 || nd == 8 || nd == 12 || nd == 14,
            "distortion must have 0, 4, 5, 8, 12 or 14 coefficients");
  require(width >= 8 && height >= 8 && width <= 20000 && height <= 20000,
          "image size " + std::to_string(width) + "x" + std::to_string(height) + " out of range (8..=20000 px)");
  Lens lens;
  lens.K = cv::Matx33d(intrinsics[0], 0, intrinsics[2], 0, intrinsics[1], intrinsics[3], 0, 0, 1);
  lens.dist = cv::Mat(1, static_cast<int>(nd), CV_64F);
  for (size_t i = 0; i < nd; ++i) lens.dist.at<double>(0, static_cast<int>(i)) = dist[i];
  lens.fisheye = fisheye;
  return lens;
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
