// C++ side of the model-based trocar tracker bridge: ViSP's vpMbGenericTracker (moving
// edges) on a model of the trocar given as ViSP .cao text. The image is undistorted here
// (OpenCV) and tracked with the pinhole part of the camera model. Poses cross the bridge as
// 12 numbers, the rotation row by row then the translation (m): the model's frame in the
// camera frame. Every function validates its inputs and turns C++ exceptions into
// rust::Error (cxx); a track the tracker gives up on is a result, not an error.
#pragma once
#include <memory>
#include "rust/cxx.h"

namespace trocar_docking {

// The tracker, the camera model and the undistortion maps.
class ModelTrackerCpp {
 public:
  struct Impl;
  explicit ModelTrackerCpp(std::unique_ptr<Impl> impl);
  ~ModelTrackerCpp();
  std::unique_ptr<Impl> impl;
};

// intrinsics: fx, fy, cx, cy; dist: OpenCV order, 0, 4, 5, 8, 12 or 14 coefficients, or with
// `fisheye` (ROS equidistant) k1 k2 k3 k4.
// cao: the model (ViSP .cao, version 1, metres). moving_edges, 4 numbers: the search range
// along the normal (px); the spacing of the sites along the model's edges (px); ViSP's
// likelihood threshold of an edge (vpMe::setThreshold); how much a site's contrast may
// change from one image to the next (relative: vpMe's mu1 (at most 0.95) and mu2).
std::unique_ptr<ModelTrackerCpp> new_model_tracker(rust::Slice<const double> intrinsics,
                                                   rust::Slice<const double> dist, bool fisheye, int width,
                                                   int height, rust::Str cao, rust::Slice<const double> moving_edges);

// Start tracking on this image (1, 3 or 4 channels, the camera's size) from the pose
// `c_t_o` (12 numbers, as above).
void model_tracker_init(ModelTrackerCpp &t, rust::Slice<const uint8_t> pixels, int width, int height,
                        int channels, rust::Slice<const double> c_t_o);

// Leave out of the edge search where `hidden` (width x height bytes, row by row) is
// non-zero (a known occluder in view); empty: search everywhere.
void model_tracker_set_mask(ModelTrackerCpp &t, rust::Slice<const uint8_t> hidden);

// Track into this image from the last pose. 16 numbers: the pose (12), then whether the
// tracker kept the track (1) or gave up (0: too few edge sites; the pose is the last one),
// the mean angle (deg) between the image's gradient and the model's projected edges at the
// sites (ViSP's projection error), the number of edge sites used, and the fraction of them
// the robust estimator kept (weight over 0.5).
rust::Vec<double> model_tracker_track(ModelTrackerCpp &t, rust::Slice<const uint8_t> pixels, int width,
                                      int height, int channels);

}  // namespace trocar_docking
