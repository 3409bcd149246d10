#include "trocar_docking/cpp/model_tracker_bridge.h"
#include "trocar_docking/cpp/bridge_common.h"

#include <cstdio>
#include <cstdlib>
#include <iostream>
#include <mutex>
#include <sstream>
#include <string>
#include <fcntl.h>
#include <unistd.h>

#include <opencv2/calib3d.hpp>

#include <visp3/core/vpCameraParameters.h>
#include <visp3/core/vpException.h>
#include <visp3/core/vpHomogeneousMatrix.h>
#include <visp3/core/vpImage.h>
#include <visp3/core/vpMath.h>
#include <visp3/mbt/vpMbGenericTracker.h>
#include <visp3/me/vpMe.h>

namespace trocar_docking {

struct ModelTrackerCpp::Impl {
  int width = 0, height = 0;
  bool undistort = false;
  cv::Mat map1, map2;  // undistortion maps (when the camera has distortion)
  cv::Mat grey, straight;
  vpImage<unsigned char> image;
  vpImage<bool> mask;  // true where the edges are searched
  vpCameraParameters cam;
  vpMbGenericTracker tracker{1, vpMbGenericTracker::EDGE_TRACKER};
  bool started = false;

  // The image, grey and undistorted, into `image`.
  void load(rust::Slice<const uint8_t> pixels, int w, int h, int channels) {
    bridge::grey_image(pixels, w, h, channels, width, height, grey);
    if (undistort) {
      cv::remap(grey, straight, map1, map2, cv::INTER_LINEAR);
    } else {
      straight = grey;
    }
    image.resize(static_cast<unsigned int>(height), static_cast<unsigned int>(width));
    for (int r = 0; r < height; ++r) {
      const uint8_t *src = straight.ptr<uint8_t>(r);
      std::copy(src, src + width, image[r]);
    }
  }
};

ModelTrackerCpp::ModelTrackerCpp(std::unique_ptr<Impl> i) : impl(std::move(i)) {}
ModelTrackerCpp::~ModelTrackerCpp() = default;

namespace {

using bridge::all_finite;
using bridge::require;

vpHomogeneousMatrix pose_in(rust::Slice<const double> p) {
  require(p.size() == 12, "a pose is 12 numbers (rotation row by row, then translation)");
  require(all_finite(p), "the pose must be finite");
  vpRotationMatrix R;
  for (unsigned int i = 0; i < 3; ++i)
    for (unsigned int j = 0; j < 3; ++j) R[i][j] = p[3 * i + j];
  require(R.isARotationMatrix(1e-6), "the pose's rotation is not a rotation matrix");
  require(p[11] > 0.0, "the model must be in front of the camera (z > 0)");
  return vpHomogeneousMatrix(vpTranslationVector(p[9], p[10], p[11]), R);
}

void pose_out(const vpHomogeneousMatrix &M, rust::Vec<double> &out) {
  for (unsigned int i = 0; i < 3; ++i)
    for (unsigned int j = 0; j < 3; ++j) out.push_back(M[i][j]);
  for (unsigned int i = 0; i < 3; ++i) out.push_back(M[i][3]);
}

// ViSP 3.5 writes to the standard output on its own (the model's parts when loading it,
// through std::cout; "Degenerate case" through printf when a model edge's line passes
// through the camera centre): while one of these lives, both go nowhere, so stdout keeps
// the program's own output (trocar-pose's JSON lines). The standard output is the
// process's: one at a time, and only where the tracker runs (the vision side; the
// control loop never comes here).
class QuietStdout {
 public:
  QuietStdout() : lock_(mutex()), saved_(std::cout.rdbuf(sink_.rdbuf())) {
    std::fflush(stdout);
    saved_fd_ = dup(STDOUT_FILENO);
    const int null_fd = open("/dev/null", O_WRONLY);
    if (saved_fd_ >= 0 && null_fd >= 0) dup2(null_fd, STDOUT_FILENO);
    if (null_fd >= 0) close(null_fd);
  }
  ~QuietStdout() {
    std::fflush(stdout);
    if (saved_fd_ >= 0) {
      dup2(saved_fd_, STDOUT_FILENO);
      close(saved_fd_);
    }
    std::cout.rdbuf(saved_);
  }
  QuietStdout(const QuietStdout &) = delete;
  QuietStdout &operator=(const QuietStdout &) = delete;

 private:
  static std::mutex &mutex() {
    static std::mutex m;
    return m;
  }
  std::lock_guard<std::mutex> lock_;
  std::ostringstream sink_;
  std::streambuf *saved_;
  int saved_fd_ = -1;
};

// ViSP reads a model from a file named *.cao only: write the text to a private temporary one.
void load_model(vpMbGenericTracker &tracker, rust::Str cao) {
  char path[] = "/tmp/trocar_model_XXXXXX.cao";
  const int fd = mkstemps(path, 4);
  require(fd >= 0, "cannot create a temporary file for the tracker's model");
  const std::string text(cao.data(), cao.size());
  const ssize_t written = write(fd, text.data(), text.size());
  close(fd);
  try {
    require(written == static_cast<ssize_t>(text.size()), "cannot write the tracker's model");
    const QuietStdout quiet;
    tracker.loadModel(path);
  } catch (...) {
    std::remove(path);
    throw;
  }
  std::remove(path);
}

}  // namespace

std::unique_ptr<ModelTrackerCpp> new_model_tracker(rust::Slice<const double> intrinsics,
                                                   rust::Slice<const double> dist, bool fisheye, int width,
                                                   int height, rust::Str cao, rust::Slice<const double> moving_edges) {
  auto impl = std::make_unique<ModelTrackerCpp::Impl>();
  const bridge::Lens lens = bridge::camera_model(intrinsics, dist, fisheye, width, height);
  require(moving_edges.size() == 4, "moving edges: range, sample step, threshold, contrast tolerance");
  const double range_px = moving_edges[0], sample_step_px = moving_edges[1];
  const double edge_threshold = moving_edges[2], contrast_tolerance = moving_edges[3];
  require(std::isfinite(range_px) && range_px >= 1.0 && range_px <= 50.0, "the search range must be 1-50 px");
  require(std::isfinite(sample_step_px) && sample_step_px >= 1.0 && sample_step_px <= 50.0,
          "the sample step must be 1-50 px");
  require(std::isfinite(edge_threshold) && edge_threshold > 0.0, "the edge threshold must be > 0");
  require(std::isfinite(contrast_tolerance) && contrast_tolerance > 0.0 && contrast_tolerance <= 10.0,
          "the contrast tolerance must be in (0, 10]");
  impl->width = width;
  impl->height = height;
  impl->undistort = lens.distorted();
  if (impl->undistort) lens.undistort_maps(cv::Size(width, height), impl->map1, impl->map2);
  impl->cam.initPersProjWithoutDistortion(intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]);

  auto &t = impl->tracker;
  vpMe me;
  me.setMaskSize(5);
  me.setMaskNumber(180);
  me.setRange(static_cast<unsigned int>(std::lround(range_px)));
  me.setThreshold(edge_threshold);
  // A site keeps its edge while the contrast stays within (1 - mu1) to (1 + mu2) times the
  // last one.
  me.setMu1(std::min(contrast_tolerance, 0.95));
  me.setMu2(contrast_tolerance);
  me.setSampleStep(sample_step_px);
  t.setMovingEdge(me);
  t.setCameraParameters(impl->cam);
  t.setAngleAppear(vpMath::rad(80));
  t.setAngleDisappear(vpMath::rad(85));
  t.setNearClippingDistance(0.01);
  t.setFarClippingDistance(2.0);
  t.setClipping(vpPolygon3D::NEAR_CLIPPING | vpPolygon3D::FAR_CLIPPING);
  t.setProjectionErrorComputation(true);
  t.setDisplayFeatures(false);
  try {
    load_model(t, cao);
  } catch (const vpException &e) {
    throw std::invalid_argument(std::string("the tracker's model: ") + e.getMessage());
  }
  return std::make_unique<ModelTrackerCpp>(std::move(impl));
}

void model_tracker_init(ModelTrackerCpp &tracker, rust::Slice<const uint8_t> pixels, int width, int height,
                        int channels, rust::Slice<const double> c_t_o) {
  auto &d = *tracker.impl;
  const vpHomogeneousMatrix cMo = pose_in(c_t_o);
  d.load(pixels, width, height, channels);
  try {
    const QuietStdout quiet;
    d.tracker.initFromPose(d.image, cMo);
  } catch (const vpException &e) {
    d.started = false;
    throw std::runtime_error(std::string("the tracker could not start: ") + e.getMessage());
  }
  d.started = true;
}

void model_tracker_set_mask(ModelTrackerCpp &tracker, rust::Slice<const uint8_t> hidden) {
  auto &d = *tracker.impl;
  if (hidden.empty()) {
    d.mask.resize(static_cast<unsigned int>(d.height), static_cast<unsigned int>(d.width), true);
  } else {
    require(hidden.size() == static_cast<size_t>(d.width) * d.height,
            "the mask must be the camera's size (" + std::to_string(d.width) + "x" + std::to_string(d.height) + ")");
    d.mask.resize(static_cast<unsigned int>(d.height), static_cast<unsigned int>(d.width));
    for (int r = 0; r < d.height; ++r)
      for (int c = 0; c < d.width; ++c) d.mask[r][c] = hidden[static_cast<size_t>(r) * d.width + c] == 0;
  }
  d.tracker.setMask(d.mask);
}

rust::Vec<double> model_tracker_track(ModelTrackerCpp &tracker, rust::Slice<const uint8_t> pixels, int width,
                                      int height, int channels) {
  auto &d = *tracker.impl;
  require(d.started, "the tracker has not been started from a pose");
  d.load(pixels, width, height, channels);
  double kept = 1.0;
  try {
    const QuietStdout quiet;
    d.tracker.track(d.image);
  } catch (const vpException &) {
    // vpTrackingException: too few edge sites left to estimate the pose.
    kept = 0.0;
  }
  vpHomogeneousMatrix cMo;
  d.tracker.getPose(cMo);
  rust::Vec<double> out;
  out.reserve(16);
  pose_out(cMo, out);
  const vpColVector w = d.tracker.getRobustWeights();
  unsigned int good = 0;
  for (unsigned int i = 0; i < w.size(); ++i) good += w[i] > 0.5 ? 1 : 0;
  out.push_back(kept);
  out.push_back(d.tracker.getProjectionError());
  out.push_back(static_cast<double>(d.tracker.getNbFeaturesEdge()));
  out.push_back(w.size() > 0 ? static_cast<double>(good) / w.size() : 0.0);
  if (kept == 0.0) d.started = false;
  return out;
}

}  // namespace trocar_docking
