#include "trocar_docking/cpp/markerless_bridge.h"
#include "trocar_docking/cpp/bridge_common.h"

#include <algorithm>
#include <initializer_list>
#include <cmath>
#include <stdexcept>
#include <string>
#include <vector>

#include <opencv2/calib3d.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

namespace trocar_docking {

struct MarkerlessDetectorCpp::Impl {
  bridge::Lens lens;
  int width = 0, height = 0;
  cv::Mat grey8;   // the loaded image, grey
  cv::Mat smooth;  // smoothed, CV_32F
  cv::Mat smooth8; // smoothed, CV_8U (Canny)
  cv::Mat occluded; // CV_8U, non-zero where a known occluder hides the scene; empty = none
  cv::Mat beside;   // the same grown by 3 px: where an edge cut by the occluder ends
  bool loaded = false;

  bool masked(double x, double y) const { return in(occluded, x, y); }

  static bool in(const cv::Mat &m, double x, double y) {
    if (m.empty()) return false;
    const int xi = static_cast<int>(std::lround(x)), yi = static_cast<int>(std::lround(y));
    return xi >= 0 && yi >= 0 && xi < m.cols && yi < m.rows && m.at<uint8_t>(yi, xi) != 0;
  }
};

MarkerlessDetectorCpp::MarkerlessDetectorCpp(std::unique_ptr<Impl> i) : impl(std::move(i)) {}
MarkerlessDetectorCpp::~MarkerlessDetectorCpp() = default;

namespace {

// OpenCV on the calling thread only (as the marker detector: vision_bridge.cpp), set once
// while the process is still single-threaded: cv::setNumThreads rebuilds a process-wide
// pool, and called from a constructor it raced with OpenCV work on other threads (a
// SIGSEGV in the tests, where estimators are built in parallel).
const bool opencv_on_the_calling_thread = [] {
  cv::setNumThreads(1);
  return true;
}();

using bridge::all_finite;
using bridge::require;

// Bilinear sample of a float image at (x, y), pixel centres at integers; false outside.
inline bool bilinear(const cv::Mat &f, double x, double y, double &out) {
  if (!(x >= 0.0 && y >= 0.0 && x < f.cols - 1.0 && y < f.rows - 1.0)) return false;
  const int x0 = static_cast<int>(x), y0 = static_cast<int>(y);
  const double ax = x - x0, ay = y - y0;
  const float *r0 = f.ptr<float>(y0), *r1 = f.ptr<float>(y0 + 1);
  out = (1 - ay) * ((1 - ax) * r0[x0] + ax * r0[x0 + 1]) + ay * ((1 - ax) * r1[x0] + ax * r1[x0 + 1]);
  return true;
}

// Ellipse-frame coordinates of p: (x', y') along the axes of r (a = width / 2 axis).
inline cv::Point2d ellipse_frame(const cv::RotatedRect &r, const cv::Point2f &p) {
  const double t = r.angle * CV_PI / 180.0, c = std::cos(t), s = std::sin(t);
  const double dx = p.x - r.center.x, dy = p.y - r.center.y;
  return {c * dx + s * dy, -s * dx + c * dy};
}

// RMS first-order distance (px) of the points to the ellipse, and how many of 16 sectors
// of the ellipse's parameter they cover (with `d`: or the occluder hides).
void ellipse_fit_quality(const cv::RotatedRect &r, const std::vector<cv::Point2f> &pts, double &rms, int &sectors,
                         const MarkerlessDetectorCpp::Impl *d = nullptr) {
  const double a = 0.5 * r.size.width, b = 0.5 * r.size.height;
  double sum = 0;
  unsigned hit = 0;
  for (const auto &p : pts) {
    const cv::Point2d q = ellipse_frame(r, p);
    const double f = q.x * q.x / (a * a) + q.y * q.y / (b * b) - 1.0;
    const double gx = 2 * q.x / (a * a), gy = 2 * q.y / (b * b);
    const double d = f / std::max(1e-12, std::sqrt(gx * gx + gy * gy));
    sum += d * d;
    const double phi = std::atan2(q.y / b, q.x / a);
    const int k = std::min(15, std::max(0, static_cast<int>((phi + CV_PI) / (2 * CV_PI) * 16)));
    hit |= 1u << k;
  }
  rms = std::sqrt(sum / std::max<size_t>(1, pts.size()));
  if (d != nullptr && !d->occluded.empty()) {
    const double t = r.angle * CV_PI / 180.0, c = std::cos(t), s = std::sin(t);
    for (int k = 0; k < 16; ++k) {
      const double phi = -CV_PI + (k + 0.5) * 2 * CV_PI / 16, x = a * std::cos(phi), y = b * std::sin(phi);
      if (d->masked(r.center.x + c * x - s * y, r.center.y + s * x + c * y)) hit |= 1u << k;
    }
  }
  sectors = __builtin_popcount(hit);
}

// Mean grey on the ellipses scaled by each of `scales` about the centre (32 samples each,
// those the occluder hides left out), NaN unless at least 3 in 4 of the others, and 8, are
// in the image.
double mean_on_ellipse(const MarkerlessDetectorCpp::Impl &d, const cv::RotatedRect &r,
                       std::initializer_list<double> scales) {
  const double t = r.angle * CV_PI / 180.0, c = std::cos(t), s = std::sin(t);
  double sum = 0, v = 0;
  int n = 0, open = 0;
  for (double scale : scales) {
    const double a = 0.5 * r.size.width * scale, b = 0.5 * r.size.height * scale;
    for (int k = 0; k < 32; ++k) {
      const double phi = 2 * CV_PI * k / 32, x = a * std::cos(phi), y = b * std::sin(phi);
      const double px = r.center.x + c * x - s * y, py = r.center.y + s * x + c * y;
      if (d.masked(px, py)) continue;
      ++open;
      if (bilinear(d.smooth, px, py, v)) {
        sum += v;
        ++n;
      }
    }
  }
  return n >= 8 && 4 * n >= 3 * open ? sum / n : std::nan("");
}

}  // namespace

std::unique_ptr<MarkerlessDetectorCpp> new_markerless_detector(rust::Slice<const double> intrinsics,
                                                               rust::Slice<const double> dist, bool fisheye,
                                                               int width, int height) {
  auto impl = std::make_unique<MarkerlessDetectorCpp::Impl>();
  impl->lens = bridge::camera_model(intrinsics, dist, fisheye, width, height);
  impl->width = width;
  impl->height = height;
  return std::make_unique<MarkerlessDetectorCpp>(std::move(impl));
}

void markerless_load(MarkerlessDetectorCpp &det, rust::Slice<const uint8_t> pixels, int width, int height,
                     int channels, double smooth_sigma) {
  auto &d = *det.impl;
  bridge::grey_image(pixels, width, height, channels, d.width, d.height, d.grey8);
  require(std::isfinite(smooth_sigma) && smooth_sigma >= 0.0 && smooth_sigma <= 10.0,
          "smoothing sigma must be in [0, 10] px");
  d.grey8.convertTo(d.smooth, CV_32F);
  if (smooth_sigma > 0.0) cv::GaussianBlur(d.smooth, d.smooth, cv::Size(0, 0), smooth_sigma);
  d.smooth.convertTo(d.smooth8, CV_8U);
  d.loaded = true;
}

rust::Vec<double> markerless_ellipses(MarkerlessDetectorCpp &det, double min_axis_px, double max_axis_px,
                                      int max_count) {
  auto &d = *det.impl;
  require(d.loaded, "no image loaded");
  require(std::isfinite(min_axis_px) && std::isfinite(max_axis_px) && min_axis_px >= 2.0 &&
              max_axis_px >= min_axis_px,
          "semi-axis range must be finite, >= 2 px and ordered");
  require(max_count >= 1 && max_count <= 100, "max_count must be in 1..=100");
  cv::Mat edges;
  cv::Canny(d.smooth8, edges, 20, 50, 3, true);
  std::vector<std::vector<cv::Point>> contours;
  cv::findContours(edges, contours, cv::RETR_LIST, cv::CHAIN_APPROX_NONE);
  if (!d.occluded.empty()) {
    // Leave out what the occluder hides; an opening it cuts across falls apart into arcs that
    // end beside it: each two such arcs are tried together as well (the largest 12 of them).
    // A contour the occluder crosses is split into the runs between its hidden points.
    std::vector<std::vector<cv::Point>> runs;
    for (const auto &c : contours) {
      std::vector<cv::Point> run;
      for (const auto &p : c) {
        if (!d.masked(p.x, p.y)) {
          run.push_back(p);
        } else if (!run.empty()) {
          runs.push_back(std::move(run));
          run.clear();
        }
      }
      if (!run.empty()) runs.push_back(std::move(run));
    }
    contours = std::move(runs);
    std::vector<size_t> cut;
    for (size_t ci = 0; ci < contours.size(); ++ci) {
      const auto &c = contours[ci];
      const bool ends_beside = c.size() >= 8 && std::any_of(c.begin(), c.end(), [&](const cv::Point &p) {
                                 return MarkerlessDetectorCpp::Impl::in(d.beside, p.x, p.y);
                               });
      if (ends_beside) cut.push_back(ci);
    }
    std::sort(cut.begin(), cut.end(), [&](size_t x, size_t y) { return contours[x].size() > contours[y].size(); });
    if (cut.size() > 12) cut.resize(12);
    for (size_t i = 0; i < cut.size(); ++i)
      for (size_t j = i + 1; j < cut.size(); ++j) {
        std::vector<cv::Point> both(contours[cut[i]]);
        both.insert(both.end(), contours[cut[j]].begin(), contours[cut[j]].end());
        contours.push_back(std::move(both));
      }
  }
  struct Cand {
    cv::RotatedRect r;
    double contrast;
    size_t contour;
  };
  std::vector<Cand> cands;
  std::vector<cv::Point2f> pts;
  for (size_t ci = 0; ci < contours.size(); ++ci) {
    const auto &c = contours[ci];
    if (c.size() < 16 || c.size() > 20 * max_axis_px) continue;
    pts.assign(c.begin(), c.end());
    const cv::RotatedRect r = cv::fitEllipseAMS(pts);
    const double a = 0.5 * std::max(r.size.width, r.size.height), b = 0.5 * std::min(r.size.width, r.size.height);
    if (!(std::isfinite(a) && std::isfinite(b)) || a > max_axis_px || a < min_axis_px || b < 0.2 * a || b < 2.0)
      continue;
    double rms = 0;
    int sectors = 0;
    ellipse_fit_quality(r, pts, rms, sectors, &d);
    if (rms > 1.0 || sectors < 13) continue;
    // Inside, where the occluder may cover the middle: rings at 0.3 and 0.7 as well.
    const double inside = d.occluded.empty() ? mean_on_ellipse(d, r, {0.5}) : mean_on_ellipse(d, r, {0.3, 0.5, 0.7});
    const double ring = mean_on_ellipse(d, r, {1.25});
    if (!(ring - inside > 10.0)) continue;
    cands.push_back({r, ring - inside, ci});
  }
  std::sort(cands.begin(), cands.end(), [](const Cand &x, const Cand &y) { return x.contrast > y.contrast; });
  rust::Vec<double> out;
  std::vector<cv::RotatedRect> kept;
  std::vector<cv::Point2f> und;
  for (const auto &c : cands) {
    if (static_cast<int>(kept.size()) >= max_count) break;
    // The two sides of one edge give near-identical ellipses: keep the first.
    bool dup = false;
    for (const auto &k : kept) {
      const double s = std::min(k.size.width, k.size.height);
      dup = dup || (cv::norm(k.center - c.r.center) < 0.2 * s &&
                    std::abs(std::max(k.size.width, k.size.height) - std::max(c.r.size.width, c.r.size.height)) <
                        0.15 * s);
    }
    if (dup) continue;
    kept.push_back(c.r);
    // The same fit in undistorted pixels.
    pts.assign(contours[c.contour].begin(), contours[c.contour].end());
    d.lens.undistort(pts, und, d.lens.K, cv::TermCriteria(cv::TermCriteria::COUNT | cv::TermCriteria::EPS, 20, 1e-10));
    const cv::RotatedRect u = cv::fitEllipseAMS(und);
    double rms = 0;
    int sectors = 0;
    ellipse_fit_quality(u, und, rms, sectors);
    double a = 0.5 * u.size.width, b = 0.5 * u.size.height, ang = u.angle * CV_PI / 180.0;
    if (b > a) {
      std::swap(a, b);
      ang += 0.5 * CV_PI;
    }
    if (!(std::isfinite(a) && std::isfinite(b) && b > 0)) continue;
    for (double v : {static_cast<double>(u.center.x), static_cast<double>(u.center.y), a, b, ang, c.contrast, rms})
      out.push_back(v);
  }
  return out;
}

void markerless_set_occluder(MarkerlessDetectorCpp &det, rust::Slice<const double> points, int section_len,
                             double margin_px) {
  auto &d = *det.impl;
  require(all_finite(points), "occluder points must be finite");
  require(points.size() % 3 == 0, "occluder points must be 3 numbers each (x, y, z)");
  require(std::isfinite(margin_px) && margin_px >= 0.0 && margin_px <= 50.0, "occluder margin must be in [0, 50] px");
  const size_t n = points.size() / 3;
  if (n == 0) {
    d.occluded.release();
    d.beside.release();
    return;
  }
  require(section_len >= 3 && n % static_cast<size_t>(section_len) == 0 && n / section_len >= 2,
          "occluder points must come in two or more sections of at least 3 points");
  std::vector<cv::Point3d> p3(n);
  for (size_t i = 0; i < n; ++i) {
    p3[i] = {points[3 * i], points[3 * i + 1], points[3 * i + 2]};
    require(p3[i].z > 1e-3, "occluder points must lie in front of the camera (z > 1 mm)");
  }
  std::vector<cv::Point2d> px;
  d.lens.project(p3, px);
  cv::Mat mask = cv::Mat::zeros(d.height, d.width, CV_8U);
  const size_t m = static_cast<size_t>(section_len);
  std::vector<cv::Point> two, hull;
  for (size_t s = 0; s + 1 < n / m; ++s) {
    two.clear();
    for (size_t i = s * m; i < (s + 2) * m; ++i) {
      // Far outside the image the projection means nothing: clamp to a frame around it.
      const double x = std::max(-4.0 * d.width, std::min(5.0 * d.width, px[i].x));
      const double y = std::max(-4.0 * d.height, std::min(5.0 * d.height, px[i].y));
      two.emplace_back(static_cast<int>(std::lround(x)), static_cast<int>(std::lround(y)));
    }
    cv::convexHull(two, hull);
    cv::fillConvexPoly(mask, hull, cv::Scalar(255));
  }
  if (margin_px > 0.0) {
    const int r = static_cast<int>(std::ceil(margin_px));
    cv::dilate(mask, mask, cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * r + 1, 2 * r + 1)));
  }
  d.occluded = mask;
  cv::dilate(mask, d.beside, cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(7, 7)));
}

rust::Vec<double> markerless_search_edges(const MarkerlessDetectorCpp &det, rust::Slice<const double> points,
                                          double range_px, int polarity, double min_strength,
                                          bool through_occluder) {
  const auto &d = *det.impl;
  require(d.loaded, "no image loaded");
  require(points.size() % 4 == 0, "points must be 4 numbers each (x, y, nx, ny)");
  require(points.size() <= 4 * 100000, "at most 100000 points");
  require(all_finite(points), "points must be finite");
  require(std::isfinite(range_px) && range_px >= 0.5 && range_px <= 50.0, "search range must be in [0.5, 50] px");
  require(polarity >= -1 && polarity <= 1, "polarity must be -1, 0 or +1");
  require(std::isfinite(min_strength) && min_strength >= 0.0, "minimum strength must be finite and >= 0");
  const size_t n = points.size() / 4;
  rust::Vec<double> out;
  if (n == 0) return out;
  // Each point and a step of about one pixel along its normal, through the distortion.
  const double eps = 1.0 / d.lens.K(0, 0);
  std::vector<cv::Point3d> rays(2 * n);
  for (size_t i = 0; i < n; ++i) {
    const double x = points[4 * i], y = points[4 * i + 1], nx = points[4 * i + 2], ny = points[4 * i + 3];
    const double nn = std::max(1e-12, std::hypot(nx, ny));
    rays[2 * i] = {x, y, 1.0};
    rays[2 * i + 1] = {x + eps * nx / nn, y + eps * ny / nn, 1.0};
  }
  std::vector<cv::Point2d> px;
  d.lens.project(rays, px);
  const double step = 0.5;
  const int half = static_cast<int>(std::ceil(range_px / step)) + 1;
  std::vector<double> g(2 * half + 1);
  std::vector<cv::Point2d> found_px;
  std::vector<size_t> found_idx;
  std::vector<double> found_strength;
  std::vector<size_t> masked_idx;
  for (size_t i = 0; i < n; ++i) {
    const cv::Point2d p = px[2 * i];
    cv::Point2d u = px[2 * i + 1] - p;
    const double len = cv::norm(u);
    if (!(len > 1e-9)) continue;
    u /= len;
    if (!d.occluded.empty() && !through_occluder) {
      bool hidden = false;
      for (int j = -half; j <= half && !hidden; ++j) hidden = d.masked(p.x + j * step * u.x, p.y + j * step * u.y);
      if (hidden) {
        masked_idx.push_back(i);
        continue;
      }
    }
    bool inside = true;
    for (int j = -half; j <= half && inside; ++j) {
      const double s = j * step;
      double lo = 0, hi = 0;
      inside = bilinear(d.smooth, p.x + (s - 0.5) * u.x, p.y + (s - 0.5) * u.y, lo) &&
               bilinear(d.smooth, p.x + (s + 0.5) * u.x, p.y + (s + 0.5) * u.y, hi);
      g[j + half] = hi - lo;
    }
    if (!inside) continue;
    int best = -1;
    double best_v = min_strength;
    for (int j = 1; j < 2 * half; ++j) {
      const double v = polarity == 0 ? std::abs(g[j]) : polarity * g[j];
      if (v > best_v) {
        best_v = v;
        best = j;
      }
    }
    if (best < 0) continue;
    const double gm = polarity == 0 ? std::abs(g[best - 1]) : polarity * g[best - 1];
    const double g0 = best_v;
    const double gp = polarity == 0 ? std::abs(g[best + 1]) : polarity * g[best + 1];
    const double den = gm - 2 * g0 + gp;
    const double delta = den < 0 ? std::max(-0.5, std::min(0.5, 0.5 * (gm - gp) / den)) : 0.0;
    const double s = (best - half + delta) * step;
    if (std::abs(s) > range_px) continue;
    found_px.push_back(p + s * u);
    found_idx.push_back(i);
    found_strength.push_back(g[best]);
  }
  std::vector<cv::Point2d> norm;
  if (!found_px.empty())
    d.lens.undistort(found_px, norm, cv::noArray(),
                     cv::TermCriteria(cv::TermCriteria::COUNT | cv::TermCriteria::EPS, 20, 1e-12));
  out.reserve(4 * n);
  for (size_t i = 0; i < 4 * n; ++i) out.push_back(0.0);
  for (size_t i : masked_idx) out[4 * i] = 2.0;
  for (size_t k = 0; k < found_idx.size(); ++k) {
    const size_t i = found_idx[k];
    out[4 * i] = 1.0;
    out[4 * i + 1] = norm[k].x;
    out[4 * i + 2] = norm[k].y;
    out[4 * i + 3] = found_strength[k];
  }
  return out;
}

}  // namespace trocar_docking
