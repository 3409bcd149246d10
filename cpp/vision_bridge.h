// C++ side of the vision bridge: ViSP 3.5 and OpenCV 4.6 aruco.
// Every function validates its inputs and turns C++ exceptions into rust::Error (cxx).
#pragma once
#include <memory>
#include "rust/cxx.h"

namespace trocar_docking {

// "ViSP x.y.z, OpenCV a.b.c": the vision libraries this build links.
rust::String vision_backend_versions();

// A configured marker detector (ArUco dictionary through OpenCV, or an official AprilTag
// family through ViSP) with the camera intrinsics; pose by IPPE initialisation + ViSP VVS.
class MarkerDetectorCpp {
 public:
  struct Impl;
  explicit MarkerDetectorCpp(std::unique_ptr<Impl> impl);
  ~MarkerDetectorCpp();
  std::unique_ptr<Impl> impl;
};

// family: OpenCV ArUco dictionary name (DICT_4X4_50, ...) or official AprilTag family
// (tag16h5, tag25h9, tag36h10, tag36h11); OpenCV's DICT_APRILTAG_* names are refused.
// intrinsics: fx, fy, cx, cy; dist: OpenCV order (k1 k2 p1 p2 [k3 [k4 k5 k6 ...]]), 0,4,5,8,12 or 14,
// or with `fisheye` (ROS equidistant) k1 k2 k3 k4.
std::unique_ptr<MarkerDetectorCpp> new_marker_detector(rust::Str family, rust::Slice<const double> intrinsics,
                                                       rust::Slice<const double> dist, bool fisheye, int width,
                                                       int height);

// Detect markers of `id` (-1: any) of side `size` metres. Output, 22 numbers per marker:
// id, R row-major (9), t (3), corners (8: u0 v0 u1 v1 ...), RMS reprojection error px.
// Corners and frame: ArUco TL TR BR BL, x right, y up, z out of the marker (OpenCV's);
// AprilTag libapriltag's det->p order (left-bottom, right-bottom, right-top, left-top),
// x right, y down, z into the tag (the official frame).
rust::Vec<double> detect_markers(MarkerDetectorCpp &det, rust::Slice<const uint8_t> pixels, int width, int height,
                                 int channels, int id, double size, rust::Slice<const int> roi);

// Render a marker (family, id, side `size` m) centred on a textured square plane of side
// `plane_size` m, seen from camera pose cMo (R row-major 9 + t 3), into a grey image.
rust::Vec<uint8_t> render_marker(rust::Str family, int id, double size, double plane_size,
                                 rust::Slice<const double> cmo, rust::Slice<const double> intrinsics,
                                 rust::Slice<const double> dist, bool fisheye, int width, int height,
                                 double blur_sigma, uint32_t texture_seed);

// The official tag `id` of an AprilTag family as libapriltag's apriltag_to_image() draws it
// (one byte a cell, row 0 at the top of the upright tag, white border included); `dims`
// gets total_width, width_at_border (the black square, cells) and the family's id count.
rust::Vec<uint8_t> official_apriltag(rust::Str family, int id, rust::Slice<int32_t> dims);

// Read an image file as grey (channels = 1) or RGB (3); returns width, height in `dims`.
rust::Vec<uint8_t> read_image(rust::Str path, int channels, rust::Slice<int32_t> dims);
// Write a grey or RGB image (PNG, PGM, JPEG... by extension).
void write_image(rust::Str path, rust::Slice<const uint8_t> pixels, int width, int height, int channels);

// ViSP hand-eye calibration: cMo and rMe as n x 12 (R row-major + t); returns eMc (12).
rust::Vec<double> hand_eye_calibrate(rust::Slice<const double> cmo, rust::Slice<const double> rme);

}  // namespace trocar_docking
