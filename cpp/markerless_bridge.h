// C++ side of the markerless trocar bridge (OpenCV 4): the image-level steps of the
// markerless estimator. The geometry (circle pose, cylinder outline, refinement) is Rust's.
// Points cross the bridge in undistorted normalised camera coordinates (x/z, y/z); the
// distortion is applied and removed here. Every function validates its inputs and turns
// C++ exceptions into rust::Error (cxx).
#pragma once
#include <memory>
#include "rust/cxx.h"

namespace trocar_docking {

// The camera model and the last loaded image (smoothed grey).
class MarkerlessDetectorCpp {
 public:
  struct Impl;
  explicit MarkerlessDetectorCpp(std::unique_ptr<Impl> impl);
  ~MarkerlessDetectorCpp();
  std::unique_ptr<Impl> impl;
};

// intrinsics: fx, fy, cx, cy; dist: OpenCV order, 0, 4, 5, 8, 12 or 14 coefficients, or with
// `fisheye` (ROS equidistant) k1 k2 k3 k4.
std::unique_ptr<MarkerlessDetectorCpp> new_markerless_detector(rust::Slice<const double> intrinsics,
                                                               rust::Slice<const double> dist, bool fisheye,
                                                               int width, int height);

// Load an image (1, 3 or 4 channels, the camera's size): grey, Gaussian-smoothed by
// `smooth_sigma` px (0 = none), kept for the calls below.
void markerless_load(MarkerlessDetectorCpp &det, rust::Slice<const uint8_t> pixels, int width, int height,
                     int channels, double smooth_sigma);

// Dark elliptical blobs with a lighter surround (Canny edges, contours, cv::fitEllipseAMS),
// their semi-axes within [min_axis_px, max_axis_px]; the best `max_count` by contrast.
// 7 numbers each, in undistorted pixel coordinates: centre x, y, semi-axes a >= b, angle of
// a (rad), contrast (grey levels, surround - inside), rms distance of the contour to the
// ellipse (px).
rust::Vec<double> markerless_ellipses(MarkerlessDetectorCpp &det, double min_axis_px, double max_axis_px,
                                      int max_count);

// A known occluder in view (the endoscope's own shaft): `points` are 3-D points in the
// camera frame (x, y, z, m; z > 0), in sections of `section_len` points each (the rims of a
// cylinder's cross-sections along its axis); the image region each two consecutive sections
// cover (the convex hull of their projections through the distortion), grown by `margin_px`,
// is masked for every later image: contour points in it are left out of the ellipses, and
// edge searches that touch it report 2 (masked). Empty `points` clears the mask.
void markerless_set_occluder(MarkerlessDetectorCpp &det, rust::Slice<const double> points, int section_len,
                             double margin_px);

// Moving edges: for each of the n points (4 numbers each: x, y, normal nx, ny; normalised
// coordinates) search the image within +-range_px along the normal for the strongest grey
// gradient of the given polarity (+1: dark to light along the normal, -1: light to dark,
// 0: either) of at least min_strength grey levels per px. 4 numbers each out: found (0/1;
// 2: the search touches the occluder's mask, nothing found), x, y (normalised, sub-pixel),
// strength (grey levels / px, signed along the normal).
// `through_occluder`: search where the occluder's mask is too (to find the occluder's own
// outline).
rust::Vec<double> markerless_search_edges(const MarkerlessDetectorCpp &det, rust::Slice<const double> points,
                                          double range_px, int polarity, double min_strength,
                                          bool through_occluder);

}  // namespace trocar_docking
