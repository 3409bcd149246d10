#include "trocar_docking/cpp/vision_bridge.h"
#include "trocar_docking/cpp/bridge_common.h"

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <initializer_list>
#include <random>
#include <stdexcept>
#include <string>
#include <vector>

#include <opencv2/aruco.hpp>
#include <opencv2/calib3d.hpp>
#include <opencv2/core.hpp>
#include <opencv2/core/version.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <visp3/core/vpCameraParameters.h>
#include <visp3/core/vpConfig.h>
#include <visp3/core/vpHomogeneousMatrix.h>
#include <visp3/core/vpImage.h>
#include <visp3/core/vpPoint.h>
#include <visp3/detection/vpDetectorAprilTag.h>

extern "C" {
#include <apriltag/apriltag.h>
#include <apriltag/tag16h5.h>
#include <apriltag/tag25h9.h>
#include <apriltag/tag36h10.h>
#include <apriltag/tag36h11.h>
}

#include <omp.h>
#include <visp3/vision/vpHandEyeCalibration.h>
#include <visp3/vision/vpPose.h>

namespace trocar_docking {

rust::String vision_backend_versions() {
  return rust::String("ViSP " + std::to_string(VISP_VERSION_MAJOR) + "." + std::to_string(VISP_VERSION_MINOR) + "." +
                      std::to_string(VISP_VERSION_PATCH) + ", OpenCV " + CV_VERSION + " (threads: " +
                      std::to_string(cv::getNumThreads()) + ")");
}

namespace {

// One thread: OpenCV's pool splits a few-ms detection into tasks that wait for cores busy
// with the control loop, which made the latency tail (p99) several times the median. Set
// once while the process is still single-threaded (a static initialiser): cv::setNumThreads
// rebuilds a process-wide pool and must not race with OpenCV work on other threads.
const bool opencv_on_the_calling_thread = [] {
  cv::setNumThreads(1);
  return true;
}();

// The AprilTag families: detected by ViSP's vpDetectorAprilTag, drawn from the official
// library's codes (libapriltag's family objects), both in the official frame (marker.rs).
struct AprilTagFamily {
  const char *name;
  vpDetectorAprilTag::vpAprilTagFamily visp;
  apriltag_family_t *(*create)();
  void (*destroy)(apriltag_family_t *);
};
const AprilTagFamily kAprilTagFamilies[] = {
    {"tag16h5", vpDetectorAprilTag::TAG_16h5, tag16h5_create, tag16h5_destroy},
    {"tag25h9", vpDetectorAprilTag::TAG_25h9, tag25h9_create, tag25h9_destroy},
    {"tag36h10", vpDetectorAprilTag::TAG_36h10, tag36h10_create, tag36h10_destroy},
    {"tag36h11", vpDetectorAprilTag::TAG_36h11, tag36h11_create, tag36h11_destroy},
};

// The AprilTag family of that official name, or null.
const AprilTagFamily *apriltag_family(const std::string &name) {
  for (const auto &f : kAprilTagFamilies)
    if (name == f.name) return &f;
  return nullptr;
}

// An official tag as libapriltag's apriltag_to_image() draws it: total_width^2 pixels, one a
// cell, row 0 the top of the upright tag, white border included.
struct OfficialTag {
  cv::Mat image;
  int width_at_border = 0;  // the black square's side, cells
  int codes = 0;            // ids in the family
};
OfficialTag official_tag(const AprilTagFamily &f, int id) {
  apriltag_family_t *fam = f.create();
  OfficialTag t;
  t.width_at_border = fam->width_at_border;
  t.codes = static_cast<int>(fam->ncodes);
  if (id < 0 || id >= t.codes) {
    f.destroy(fam);
    throw std::invalid_argument("marker id " + std::to_string(id) + " is not in family " + f.name + " (" +
                                std::to_string(t.codes) + " ids)");
  }
  image_u8_t *im = apriltag_to_image(fam, id);
  t.image = cv::Mat(im->height, im->width, CV_8UC1);
  for (int r = 0; r < im->height; ++r) std::copy_n(im->buf + r * im->stride, im->width, t.image.ptr<uint8_t>(r));
  // image_u8_destroy() (common/image_u8.c: free the pixels, then the struct) is not among
  // the symbols Debian's libapriltag exports: the same two frees.
  free(im->buf);
  free(im);
  f.destroy(fam);
  return t;
}

// OpenCV dictionary by its enum name; throws on an unknown name.
cv::aruco::PREDEFINED_DICTIONARY_NAME dictionary_by_name(const std::string &name) {
  using namespace cv::aruco;
  static const std::pair<const char *, PREDEFINED_DICTIONARY_NAME> table[] = {
      {"DICT_4X4_50", DICT_4X4_50},       {"DICT_4X4_100", DICT_4X4_100},   {"DICT_4X4_250", DICT_4X4_250},
      {"DICT_4X4_1000", DICT_4X4_1000},   {"DICT_5X5_50", DICT_5X5_50},     {"DICT_5X5_100", DICT_5X5_100},
      {"DICT_5X5_250", DICT_5X5_250},     {"DICT_5X5_1000", DICT_5X5_1000}, {"DICT_6X6_50", DICT_6X6_50},
      {"DICT_6X6_100", DICT_6X6_100},     {"DICT_6X6_250", DICT_6X6_250},   {"DICT_6X6_1000", DICT_6X6_1000},
      {"DICT_7X7_50", DICT_7X7_50},       {"DICT_7X7_100", DICT_7X7_100},   {"DICT_7X7_250", DICT_7X7_250},
      {"DICT_7X7_1000", DICT_7X7_1000},   {"DICT_ARUCO_ORIGINAL", DICT_ARUCO_ORIGINAL},
  };
  // OpenCV 4.6 draws its DICT_APRILTAG_* dictionaries turned 180 degrees against the
  // official tags: AprilTags go through the official families only.
  if (name.rfind("DICT_APRILTAG_", 0) == 0)
    throw std::invalid_argument("marker family `" + name + "`: AprilTags are named by their official family (tag" +
                                name.substr(14) + ")");
  for (const auto &e : table) {
    if (name == e.first) return e.second;
  }
  throw std::invalid_argument("unknown marker family `" + name + "`");
}

// Image dimensions every function accepts: 2..=20000 px a side (the bilinear sampling
// below reads a 2 x 2 neighbourhood).
constexpr int kMaxSide = 20000;
void check_size(int width, int height) {
  if (width < 2 || height < 2 || width > kMaxSide || height > kMaxSide)
    throw std::invalid_argument("image size " + std::to_string(width) + "x" + std::to_string(height) +
                                " out of range (2..=" + std::to_string(kMaxSide) + " px a side)");
}

// A pixel buffer of exactly width x height x channels bytes, channels one of `allowed`.
void check_pixels(rust::Slice<const uint8_t> pixels, int width, int height, int channels,
                  std::initializer_list<int> allowed) {
  check_size(width, height);
  if (std::find(allowed.begin(), allowed.end(), channels) == allowed.end())
    throw std::invalid_argument("unsupported channel count " + std::to_string(channels));
  const size_t want = static_cast<size_t>(width) * static_cast<size_t>(height) * static_cast<size_t>(channels);
  if (pixels.size() != want)
    throw std::invalid_argument("pixel buffer has " + std::to_string(pixels.size()) + " bytes, " +
                                std::to_string(width) + "x" + std::to_string(height) + "x" +
                                std::to_string(channels) + " needs " + std::to_string(want));
}

// A grey cv::Mat view (or conversion) of the caller's pixels.
cv::Mat grey_view(rust::Slice<const uint8_t> pixels, int width, int height, int channels) {
  if (channels != 1 && channels != 3 && channels != 4)
    throw std::invalid_argument("channels must be 1 (grey), 3 (RGB8/BGR8) or 4 (BGRA8/RGBA8)");
  check_pixels(pixels, width, height, channels, {1, 3, 4});
  cv::Mat m(height, width, CV_8UC(channels), const_cast<uint8_t *>(pixels.data()));
  if (channels == 1) return m;
  cv::Mat g;
  cv::cvtColor(m, g, channels == 3 ? cv::COLOR_RGB2GRAY : cv::COLOR_RGBA2GRAY);
  return g;
}

// Marker-frame corners, in the order the detectors report them: OpenCV's ArUco corners TL,
// TR, BR, BL with x right, y up, z out of the marker; libapriltag's det->p[0..3] (left-
// bottom, right-bottom, right-top, left-top) with x right, y down, z into the tag, the
// object points of apriltag_pose.c's estimate_tag_pose_orthogonal_iteration. The same
// coordinates in both.
std::vector<cv::Point3d> object_corners(double s) {
  const double h = 0.5 * s;
  return {{-h, h, 0}, {h, h, 0}, {h, -h, 0}, {-h, -h, 0}};
}

// Bilinear sample of a grey image at (x, y) (pixel centres at integers), clamped inside.
inline double sample(const cv::Mat &g, double x, double y) {
  x = std::min(std::max(x, 0.0), g.cols - 1.001);
  y = std::min(std::max(y, 0.0), g.rows - 1.001);
  const int x0 = static_cast<int>(x), y0 = static_cast<int>(y);
  const double fx = x - x0, fy = y - y0;
  const uint8_t *r0 = g.ptr<uint8_t>(y0), *r1 = g.ptr<uint8_t>(y0 + 1);
  return (1 - fy) * ((1 - fx) * r0[x0] + fx * r0[x0 + 1]) + fy * ((1 - fx) * r1[x0] + fx * r1[x0 + 1]);
}

// Sub-pixel corners of a dark square on a light surround: along each edge, the edge offset
// of intensity profiles across it (area method, unbiased under symmetric blur and averaging
// noise), points undistorted, a total-least-squares line per edge, corners at the line
// intersections. `px` (distorted pixels, TL TR BR BL) is refined in place; returns the
// corners in undistorted normalised coordinates, or false when an edge has too few points.
bool refine_corners(const cv::Mat &g, const bridge::Lens &lens, int cells, std::vector<cv::Point2d> &px,
                    std::vector<cv::Point2d> &norm) {
  const cv::Matx33d &K = lens.K;
  for (int pass = 0; pass < 2; ++pass) {
    double perim = 0;
    for (int k = 0; k < 4; ++k) perim += cv::norm(px[(k + 1) % 4] - px[k]);
    const double cell = perim / 4.0 / std::max(cells, 3);
    // Half-width of the profile, px: 3 px spans the blurred edge ramp with flat ends (the
    // area method is biased when the ends sit on the ramp); kept within 0.75 cell so the
    // data cells inside and whatever lies beyond the quiet zone stay out of it.
    const double r = std::min(3.0, std::max(1.0, 0.75 * cell));
    const double step = 0.25;
    const int ns = static_cast<int>(std::round(2 * r / step)) + 1;
    const cv::Point2d centre = 0.25 * (px[0] + px[1] + px[2] + px[3]);
    cv::Vec3d lines[4];
    for (int k = 0; k < 4; ++k) {
      const cv::Point2d a = px[k], b = px[(k + 1) % 4];
      const double len = cv::norm(b - a);
      if (!(len > 4.0)) return false;
      const cv::Point2d d = (b - a) / len;
      cv::Point2d n(-d.y, d.x);
      if ((0.5 * (a + b) - centre).dot(n) < 0) n = -n;  // outward
      const int m = std::min(200, std::max(6, static_cast<int>(len)));
      std::vector<cv::Point2d> pts;
      pts.reserve(m);
      for (int i = 0; i < m; ++i) {
        const double t = 0.12 + 0.76 * (i + 0.5) / m;
        const cv::Point2d p = a + t * len * d;
        double in = 0, out = 0, area = 0;
        const int ends = std::max(1, ns / 6);
        std::vector<double> prof(ns);
        for (int j = 0; j < ns; ++j) {
          const cv::Point2d q = p + (-r + j * step) * n;
          prof[j] = sample(g, q.x, q.y);
        }
        for (int j = 0; j < ends; ++j) {
          in += prof[j];
          out += prof[ns - 1 - j];
        }
        in /= ends;
        out /= ends;
        if (out - in < 15.0) continue;  // no clear dark-to-light edge here
        for (int j = 0; j < ns; ++j) {
          const double w = (j == 0 || j == ns - 1) ? 0.5 : 1.0;  // trapezoid rule
          area += w * std::min(1.0, std::max(0.0, (prof[j] - in) / (out - in)));
        }
        const double e = r - area * step;  // edge offset along n
        pts.push_back(p + e * n);
      }
      if (pts.size() < 4) return false;
      std::vector<cv::Point2d> und;
      lens.undistort(pts, und, K);
      cv::Vec4d line;
      cv::fitLine(und, line, cv::DIST_L2, 0, 1e-6, 1e-6);
      // Line as (nx, ny, c) with nx*x + ny*y + c = 0.
      lines[k] = cv::Vec3d(-line[1], line[0], line[1] * line[2] - line[0] * line[3]);
    }
    std::vector<cv::Point2d> und_c(4);
    for (int k = 0; k < 4; ++k) {
      const cv::Vec3d p = lines[(k + 3) % 4].cross(lines[k]);  // corner k: edges k-1 and k
      if (std::abs(p[2]) < 1e-12) return false;
      und_c[k] = cv::Point2d(p[0] / p[2], p[1] / p[2]);
    }
    // Back to normalised and distorted pixel coordinates.
    norm.resize(4);
    std::vector<cv::Point3d> rays(4);
    for (int k = 0; k < 4; ++k) {
      norm[k] = cv::Point2d((und_c[k].x - K(0, 2)) / K(0, 0), (und_c[k].y - K(1, 2)) / K(1, 1));
      rays[k] = cv::Point3d(norm[k].x, norm[k].y, 1.0);
    }
    lens.project(rays, px);
  }
  return true;
}

}  // namespace

struct MarkerDetectorCpp::Impl {
  bool apriltag = false;
  cv::Ptr<cv::aruco::Dictionary> dict;
  cv::Ptr<cv::aruco::DetectorParameters> params;
  std::unique_ptr<vpDetectorAprilTag> april;
  bridge::Lens lens;
  int width = 0, height = 0;
  std::vector<std::vector<cv::Point2f>> corners, rejected;
  std::vector<int> ids;
  int cells = 6;   // marker side in cells, black border included
  int decimate = 1;
  cv::Mat small;
  vpImage<unsigned char> vimg;
};

MarkerDetectorCpp::MarkerDetectorCpp(std::unique_ptr<Impl> i) : impl(std::move(i)) {}
MarkerDetectorCpp::~MarkerDetectorCpp() = default;

std::unique_ptr<MarkerDetectorCpp> new_marker_detector(rust::Str family, rust::Slice<const double> intrinsics,
                                                       rust::Slice<const double> dist, bool fisheye, int width,
                                                       int height) {
  auto impl = std::make_unique<MarkerDetectorCpp::Impl>();
  impl->lens = bridge::camera_model(intrinsics, dist, fisheye, width, height);
  const std::string fam(family);
  impl->width = width;
  impl->height = height;
  if (const AprilTagFamily *tag = apriltag_family(fam)) {
    impl->apriltag = true;
    impl->april = std::make_unique<vpDetectorAprilTag>(tag->visp);
    // Wide frames are shrunk 2x (area average, halves pixel noise) and quads found at a
    // further 2x decimation: noisy frames stay fast. Corners are refined on the full image.
    impl->april->setAprilTagQuadDecimate(2.0f);
    impl->april->setAprilTagQuadSigma(0.0f);
    impl->april->setAprilTagRefineEdges(true);
    impl->decimate = width >= 960 ? 2 : 1;
    impl->april->setAprilTagNbThreads(1);
    impl->cells = official_tag(*tag, 0).width_at_border;
  } else {
    impl->dict = cv::aruco::getPredefinedDictionary(dictionary_by_name(fam));
    impl->params = cv::aruco::DetectorParameters::create();
    // Corners are refined on the full image by refine_corners; detection runs on a
    // half-size image for wide frames (faster, and averages pixel noise).
    impl->params->cornerRefinementMethod = cv::aruco::CORNER_REFINE_NONE;
    impl->params->adaptiveThreshWinSizeMin = 7;
    impl->params->adaptiveThreshWinSizeMax = 17;
    impl->params->adaptiveThreshWinSizeStep = 10;
    impl->cells = impl->dict->markerSize + 2;
    impl->decimate = width >= 960 ? 2 : 1;
  }
  return std::make_unique<MarkerDetectorCpp>(std::move(impl));
}

namespace {

// Pose of one marker from its 4 corner pixels (TL TR BR BL): undistort to normalised
// coordinates, IPPE-square initialisation (OpenCV), then ViSP virtual visual servoing.
// Appends the 22-number record to `out`.
void pose_from_corners(const MarkerDetectorCpp::Impl &d, const cv::Mat &grey, int id, double size,
                       std::vector<cv::Point2d> px, rust::Vec<double> &out) {
  std::vector<cv::Point2d> norm;
  if (!refine_corners(grey, d.lens, d.cells, px, norm)) d.lens.undistort(px, norm);
  const auto obj = object_corners(size);
  cv::Mat rvec, tvec;
  if (!cv::solvePnP(obj, norm, cv::Matx33d::eye(), cv::noArray(), rvec, tvec, false, cv::SOLVEPNP_IPPE_SQUARE))
    return;
  cv::Matx33d R;
  cv::Rodrigues(rvec, R);
  vpHomogeneousMatrix cMo;
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) cMo[r][c] = R(r, c);
    cMo[r][3] = tvec.at<double>(r);
  }
  vpPose pose;
  for (size_t i = 0; i < 4; ++i) {
    vpPoint P(obj[i].x, obj[i].y, obj[i].z);
    P.set_x(norm[i].x);
    P.set_y(norm[i].y);
    pose.addPoint(P);
  }
  pose.setVvsEpsilon(1e-10);
  pose.setVvsIterMax(50);
  pose.computePose(vpPose::VIRTUAL_VS, cMo);
  // Reprojection error in pixels, distortion included.
  cv::Matx33d Rf;
  cv::Vec3d tf;
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) Rf(r, c) = cMo[r][c];
    tf[r] = cMo[r][3];
  }
  cv::Vec3d rv;
  cv::Rodrigues(Rf, rv);
  std::vector<cv::Point2d> proj;
  d.lens.project(obj, proj, rv, tf);
  double sq = 0;
  for (size_t i = 0; i < 4; ++i) {
    const double du = proj[i].x - px[i].x, dv = proj[i].y - px[i].y;
    sq += du * du + dv * dv;
  }
  out.push_back(id);
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) out.push_back(cMo[r][c]);
  for (int r = 0; r < 3; ++r) out.push_back(cMo[r][3]);
  for (const auto &p : px) {
    out.push_back(p.x);
    out.push_back(p.y);
  }
  out.push_back(std::sqrt(sq / 4.0));
}

}  // namespace

rust::Vec<double> detect_markers(MarkerDetectorCpp &det, rust::Slice<const uint8_t> pixels, int width, int height,
                                 int channels, int id, double size, rust::Slice<const int> roi) {
  if (!det.impl) throw std::invalid_argument("detector is not initialised");
  auto &d = *det.impl;
  if (roi.size() != 0 && roi.size() != 4)
    throw std::invalid_argument("search window must be empty or x, y, w, h; got " + std::to_string(roi.size()) +
                                " numbers");
  if (roi.size() == 4 && (roi[2] < 0 || roi[3] < 0))
    throw std::invalid_argument("search window width and height must be >= 0");
  if (width != d.width || height != d.height)
    throw std::invalid_argument("image is " + std::to_string(width) + "x" + std::to_string(height) +
                                " but the camera model is " + std::to_string(d.width) + "x" + std::to_string(d.height));
  if (!(std::isfinite(size) && size > 0.0)) throw std::invalid_argument("marker size must be > 0");
  cv::Mat grey = grey_view(pixels, width, height, channels);
  rust::Vec<double> out;
  const double f = d.decimate;
  if (d.apriltag) {
    cv::Mat src = grey;
    if (d.decimate > 1) {
      cv::resize(grey, d.small, cv::Size(width / d.decimate, height / d.decimate), 0, 0, cv::INTER_AREA);
      src = d.small;
    }
    d.vimg.resize(static_cast<unsigned>(src.rows), static_cast<unsigned>(src.cols));
    for (int r = 0; r < src.rows; ++r) std::copy_n(src.ptr<uint8_t>(r), src.cols, d.vimg[r]);
    d.april->detect(d.vimg);
    const auto tag_ids = d.april->getTagsId();
    for (size_t i = 0; i < d.april->getNbObjects() && i < tag_ids.size(); ++i) {
      if (id >= 0 && tag_ids[i] != id) continue;
      const auto poly = d.april->getPolygon(i);
      if (poly.size() != 4) continue;
      // ViSP's polygon is libapriltag's det->p[0..3] in order (vpDetectorAprilTag.cpp,
      // Impl::detect): the official corners, kept in their order.
      std::vector<cv::Point2d> px;
      for (const auto &c : poly) px.emplace_back(f * (c.get_u() + 0.5) - 0.5, f * (c.get_v() + 0.5) - 0.5);
      pose_from_corners(d, grey, tag_ids[i], size, px, out);
    }
  } else {
    d.corners.clear();
    d.ids.clear();
    // Search window (x, y, w, h in full-image px), aligned to the decimation; the whole
    // frame when none is given or it is too small to hold a marker.
    const int dec = d.decimate;
    cv::Rect r(0, 0, width, height);
    if (roi.size() == 4) {
      cv::Rect w = cv::Rect(roi[0], roi[1], roi[2], roi[3]) & r;
      w.x -= w.x % dec;
      w.y -= w.y % dec;
      w.width -= w.width % dec;
      w.height -= w.height % dec;
      if (w.width >= 24 * dec && w.height >= 24 * dec) r = w;
    }
    const cv::Mat sub = grey(r);
    if (dec > 1) {
      cv::resize(sub, d.small, cv::Size(r.width / dec, r.height / dec), 0, 0, cv::INTER_AREA);
      cv::aruco::detectMarkers(d.small, d.dict, d.corners, d.ids, d.params, d.rejected);
    } else {
      cv::aruco::detectMarkers(sub, d.dict, d.corners, d.ids, d.params, d.rejected);
    }
    for (size_t i = 0; i < d.ids.size(); ++i) {
      if (id >= 0 && d.ids[i] != id) continue;
      std::vector<cv::Point2d> px;
      for (const auto &c : d.corners[i])
        px.emplace_back(r.x + f * (c.x + 0.5) - 0.5, r.y + f * (c.y + 0.5) - 0.5);
      pose_from_corners(d, grey, d.ids[i], size, px, out);
    }
  }
  return out;
}

namespace {

// The upright marker's black square, 480 / cells px a cell (at least 4): an AprilTag from the official family's codes (apriltag_to_image), an ArUco
// marker as OpenCV draws it. Sets `cells`.
cv::Mat draw_marker(const std::string &family, int id, int &cells) {
  cv::Mat marker;
  if (const AprilTagFamily *tag = apriltag_family(family)) {
    const OfficialTag t = official_tag(*tag, id);
    cells = t.width_at_border;
    const int b = (t.image.cols - cells) / 2;
    const int per_cell = std::max(4, 480 / cells);
    cv::resize(t.image(cv::Rect(b, b, cells, cells)), marker, cv::Size(per_cell * cells, per_cell * cells), 0, 0,
               cv::INTER_NEAREST);
    return marker;
  }
  auto dict = cv::aruco::getPredefinedDictionary(dictionary_by_name(family));
  if (id < 0 || id >= dict->bytesList.rows)
    throw std::invalid_argument("marker id " + std::to_string(id) + " is not in family " + family);
  cells = dict->markerSize + 2;
  const int per_cell = std::max(4, 480 / cells);
  dict->drawMarker(id, per_cell * cells, marker, 1);
  return marker;
}

// Texture of the plane: the marker with a white quiet zone, on a random grey pattern.
cv::Mat make_texture(const std::string &family, int id, double size, double plane_size, uint32_t seed, int &marker_px) {
  int cells = 0;
  const cv::Mat marker = draw_marker(family, id, cells);
  marker_px = marker.cols;
  const int per_cell = marker_px / cells;
  const double scale = marker_px / size;  // texture px per metre
  const int plane_px = static_cast<int>(std::lround(plane_size * scale));
  // Smooth random clutter (no marker-like squares): random levels on a coarse grid,
  // interpolated up to the texture size (cheap: no large blur per frame).
  std::mt19937 rng(seed);
  std::uniform_int_distribution<int> u(60, 200);
  const int block = std::max(8, per_cell / 2);
  const int coarse = plane_px / block + 2;
  cv::Mat grid(coarse, coarse, CV_8UC1);
  for (int r = 0; r < coarse; ++r)
    for (int c = 0; c < coarse; ++c) grid.at<uint8_t>(r, c) = static_cast<uint8_t>(u(rng));
  cv::Mat tex;
  cv::resize(grid, tex, cv::Size(plane_px, plane_px), 0, 0, cv::INTER_CUBIC);
  const int quiet = per_cell;  // one cell of white around the marker
  const int off = (plane_px - marker_px) / 2;
  if (off < quiet)
    throw std::invalid_argument("plane too small for the marker and its quiet zone (plane_size >= " +
                                std::to_string(size * (cells + 2.0) / cells) + " m)");
  tex(cv::Rect(off - quiet, off - quiet, marker_px + 2 * quiet, marker_px + 2 * quiet)).setTo(255);
  marker.copyTo(tex(cv::Rect(off, off, marker_px, marker_px)));
  return tex;
}

}  // namespace

namespace {

// Pixel box [u0, u1] x [v0, v1] of an image.
struct PixelBox {
  int u0, v0, u1, v1;
};

// The region to render: the bounding box of the plane's border (half side h, plane to
// camera H = [r1 r2 t]) projected with distortion, 3 px wider; the whole image when part
// of the plane is behind the camera.
PixelBox render_region(const cv::Matx33d &H, double h, const bridge::Lens &lens, int width, int height) {
  PixelBox box{0, 0, width - 1, height - 1};
  std::vector<cv::Point3d> border;
  const int per_side = 32;
  for (int i = 0; i < per_side; ++i) {
    const double a = -h + 2 * h * i / per_side;
    for (const auto &q : {cv::Point3d(a, h, 0), cv::Point3d(h, -a, 0), cv::Point3d(-a, -h, 0), cv::Point3d(-h, a, 0)})
      border.push_back(q);
  }
  std::vector<cv::Point3d> cam_pts;
  for (const auto &q : border) {
    const cv::Vec3d c = H * cv::Vec3d(q.x, q.y, 1.0);
    if (c[2] <= 1e-6) return box;
    cam_pts.emplace_back(c[0], c[1], c[2]);
  }
  std::vector<cv::Point2d> img_pts;
  lens.project(cam_pts, img_pts);
  double umin = 1e18, umax = -1e18, vmin = 1e18, vmax = -1e18;
  for (const auto &p : img_pts) {
    umin = std::min(umin, p.x);
    umax = std::max(umax, p.x);
    vmin = std::min(vmin, p.y);
    vmax = std::max(vmax, p.y);
  }
  if (std::isfinite(umin) && std::isfinite(umax) && std::isfinite(vmin) && std::isfinite(vmax)) {
    box.u0 = static_cast<int>(std::max(0.0, std::floor(umin) - 3));
    box.v0 = static_cast<int>(std::max(0.0, std::floor(vmin) - 3));
    box.u1 = static_cast<int>(std::min(width - 1.0, std::ceil(umax) + 3));
    box.v1 = static_cast<int>(std::min(height - 1.0, std::ceil(vmax) + 3));
  }
  return box;
}

// Grey level of pixel (xn, yn) (undistorted normalised coordinates of its centre): 3 x 3
// supersampling (box filter) of the texture, bilinear at texel centres, `bg` off the plane.
// The texture's rows run along -y of the marker frame (`y_down` false: OpenCV's ArUco
// frame, y up) or along +y (`y_down`: the official AprilTag frame, y down).
double shade_pixel(const cv::Mat &tex, const cv::Matx33d &Hi, double h, double xn, double yn, double fx, double fy,
                   double bg, bool y_down) {
  const int ss = 3;
  double acc = 0;
  for (int i = 0; i < ss; ++i)
    for (int j = 0; j < ss; ++j) {
      const double x = xn + ((j + 0.5) / ss - 0.5) / fx, y = yn + ((i + 0.5) / ss - 0.5) / fy;
      const cv::Vec3d P = Hi * cv::Vec3d(x, y, 1.0);
      if (P[2] <= 0) {  // ray hits the plane behind the camera
        acc += bg;
        continue;
      }
      const double X = P[0] / P[2], Y = P[1] / P[2];
      const double tu = (X / (2 * h) + 0.5) * tex.cols - 0.5;
      const double tv = (0.5 + (y_down ? Y : -Y) / (2 * h)) * tex.rows - 0.5;
      if (tu < -0.5 || tv < -0.5 || tu > tex.cols - 0.5 || tv > tex.rows - 0.5) {
        acc += bg;
      } else {
        acc += sample(tex, tu, tv);
      }
    }
  return acc / (ss * ss);
}

void check_render_inputs(rust::Slice<const double> cmo, double size, double plane_size, double blur_sigma) {
  if (cmo.size() != 12) throw std::invalid_argument("camera pose must have 12 numbers");
  for (double v : cmo)
    if (!std::isfinite(v)) throw std::invalid_argument("camera pose must be finite");
  if (!(std::isfinite(size) && size > 0.0 && size < 10.0)) throw std::invalid_argument("marker size out of range");
  if (!(std::isfinite(plane_size) && plane_size >= size * 1.25 && plane_size < 100.0))
    throw std::invalid_argument("plane must be at least 1.25 x the marker size");
  if (!(std::isfinite(blur_sigma) && blur_sigma >= 0.0 && blur_sigma <= 50.0))
    throw std::invalid_argument("blur sigma out of range");
}

}  // namespace

rust::Vec<uint8_t> render_marker(rust::Str family, int id, double size, double plane_size,
                                 rust::Slice<const double> cmo, rust::Slice<const double> intrinsics,
                                 rust::Slice<const double> dist, bool fisheye, int width, int height,
                                 double blur_sigma, uint32_t texture_seed) {
  const bridge::Lens lens = bridge::camera_model(intrinsics, dist, fisheye, width, height);
  check_render_inputs(cmo, size, plane_size, blur_sigma);
  int marker_px = 0;
  const std::string fam(family);
  cv::Mat tex = make_texture(fam, id, size, plane_size, texture_seed, marker_px);
  const bool y_down = apriltag_family(fam) != nullptr;
  const double h = 0.5 * tex.cols * size / marker_px;  // plane half side, m
  // Plane (X, Y, 1) -> normalised image point: H = [r1 r2 t]; we need its inverse.
  const cv::Matx33d H(cmo[0], cmo[1], cmo[9], cmo[3], cmo[4], cmo[10], cmo[6], cmo[7], cmo[11]);
  if (cmo[11] <= 0) throw std::invalid_argument("the marker must be in front of the camera (z > 0)");
  if (std::abs(cv::determinant(H)) < 1e-12) throw std::invalid_argument("the plane is seen edge-on");
  const cv::Matx33d Hi = H.inv();
  const double fx = intrinsics[0], fy = intrinsics[1], cx = intrinsics[2], cy = intrinsics[3];
  const bool distorted = lens.distorted();
  const PixelBox r = render_region(H, h, lens, width, height);
  // Undistorted normalised coordinates of the pixel centres in the region.
  std::vector<cv::Point2d> normc;
  if (distorted && r.u1 >= r.u0 && r.v1 >= r.v0) {
    std::vector<cv::Point2d> grid;
    grid.reserve(static_cast<size_t>(r.u1 - r.u0 + 1) * (r.v1 - r.v0 + 1));
    for (int v = r.v0; v <= r.v1; ++v)
      for (int u = r.u0; u <= r.u1; ++u) grid.emplace_back(u, v);
    lens.undistort(grid, normc);
  }
  const double bg = 96.0;
  cv::Mat img(height, width, CV_8UC1, cv::Scalar(bg));
  for (int v = r.v0; v <= r.v1; ++v) {
    uint8_t *row = img.ptr<uint8_t>(v);
    for (int u = r.u0; u <= r.u1; ++u) {
      double xn = (u - cx) / fx, yn = (v - cy) / fy;
      if (distorted) {
        const auto &p = normc[static_cast<size_t>(v - r.v0) * (r.u1 - r.u0 + 1) + (u - r.u0)];
        xn = p.x;
        yn = p.y;
      }
      row[u] = cv::saturate_cast<uint8_t>(shade_pixel(tex, Hi, h, xn, yn, fx, fy, bg, y_down));
    }
  }
  if (blur_sigma > 0.0) cv::GaussianBlur(img, img, cv::Size(0, 0), blur_sigma);
  rust::Vec<uint8_t> out;
  out.reserve(static_cast<size_t>(width) * height);
  for (int v = 0; v < height; ++v)
    for (int u = 0; u < width; ++u) out.push_back(img.at<uint8_t>(v, u));
  return out;
}

rust::Vec<uint8_t> official_apriltag(rust::Str family, int id, rust::Slice<int32_t> dims) {
  if (dims.size() != 3) throw std::invalid_argument("dims must have 3 slots");
  const AprilTagFamily *tag = apriltag_family(std::string(family));
  if (!tag) throw std::invalid_argument("unknown AprilTag family `" + std::string(family) + "`");
  const OfficialTag t = official_tag(*tag, id);
  dims[0] = t.image.cols;
  dims[1] = t.width_at_border;
  dims[2] = t.codes;
  rust::Vec<uint8_t> out;
  out.reserve(t.image.total());
  for (int r = 0; r < t.image.rows; ++r)
    for (int c = 0; c < t.image.cols; ++c) out.push_back(t.image.at<uint8_t>(r, c));
  return out;
}

rust::Vec<uint8_t> read_image(rust::Str path, int channels, rust::Slice<int32_t> dims) {
  if (channels != 1 && channels != 3) throw std::invalid_argument("channels must be 1 or 3");
  if (dims.size() != 2) throw std::invalid_argument("dims must have 2 slots");
  const std::string p(path);
  cv::Mat m = cv::imread(p, channels == 1 ? cv::IMREAD_GRAYSCALE : cv::IMREAD_COLOR);
  if (m.empty()) throw std::runtime_error("cannot read image `" + p + "`");
  if (channels == 3) cv::cvtColor(m, m, cv::COLOR_BGR2RGB);
  if (!m.isContinuous()) m = m.clone();
  dims[0] = m.cols;
  dims[1] = m.rows;
  rust::Vec<uint8_t> out;
  const size_t n = m.total() * m.elemSize();
  out.reserve(n);
  for (size_t i = 0; i < n; ++i) out.push_back(m.data[i]);
  return out;
}

void write_image(rust::Str path, rust::Slice<const uint8_t> pixels, int width, int height, int channels) {
  if (channels != 1 && channels != 3) throw std::invalid_argument("channels must be 1 or 3");
  check_pixels(pixels, width, height, channels, {1, 3});
  cv::Mat m(height, width, channels == 1 ? CV_8UC1 : CV_8UC3, const_cast<uint8_t *>(pixels.data()));
  cv::Mat w = m;
  if (channels == 3) cv::cvtColor(m, w, cv::COLOR_RGB2BGR);
  const std::string p(path);
  if (!cv::imwrite(p, w)) throw std::runtime_error("cannot write image `" + p + "`");
}

rust::Vec<double> hand_eye_calibrate(rust::Slice<const double> cmo, rust::Slice<const double> rme) {
  if (cmo.size() != rme.size() || cmo.size() % 12 != 0) throw std::invalid_argument("pose arrays must be n x 12");
  const size_t n = cmo.size() / 12;
  if (n < 3) throw std::invalid_argument("hand-eye calibration needs at least 3 pose pairs");
  for (size_t i = 0; i < cmo.size(); ++i)
    if (!std::isfinite(cmo[i]) || !std::isfinite(rme[i])) throw std::invalid_argument("poses must be finite");
  auto to_h = [](rust::Slice<const double> s, size_t k) {
    vpRotationMatrix R;
    vpTranslationVector t;
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 3; ++c) R[r][c] = s[12 * k + 3 * r + c];
      t[r] = s[12 * k + 9 + r];
    }
    return vpHomogeneousMatrix(t, R);
  };
  std::vector<vpHomogeneousMatrix> c, r;
  for (size_t k = 0; k < n; ++k) {
    c.push_back(to_h(cmo, k));
    r.push_back(to_h(rme, k));
  }
  vpHomogeneousMatrix eMc;
  if (vpHandEyeCalibration::calibrate(c, r, eMc) != 0)
    throw std::runtime_error("hand-eye calibration failed (degenerate motions: rotate about at least 2 axes)");
  rust::Vec<double> out;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) out.push_back(eMc[i][j]);
  for (int i = 0; i < 3; ++i) out.push_back(eMc[i][3]);
  return out;
}

}  // namespace trocar_docking
