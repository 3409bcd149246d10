//! The markerless estimator: the opening's ellipse (OpenCV, through the bridge), the two
//! circle poses it admits, each refined on the image's edges (moving edges along the
//! opening, the face's rim and the head's outline; robust Levenberg-Marquardt over the 5
//! DOF), the better explained kept, and a confidence from the fit, the edge support and
//! the ambiguity margin.

use nalgebra::{Isometry3, Matrix5, Unit, Vector2, Vector3, Vector5};

use super::geometry::{
    basis, circle_conic, circle_poses, conic_distance, conic_normal, cylinder_limbs, ellipse_conic, project, Axis,
};
use super::model::TrocarModel;
use super::render::ToolCylinder;
use super::scope_in_view::{stereo_axis, ScopeInView, SCOPE_MAX_OFFSET_M};
use crate::ffi::markerless::{ffi, EDGE_RECORD_LEN, ELLIPSE_RECORD_LEN};
use crate::vision::{CameraModel, ImageView, VisionError};

/// Confidence at or above which an estimate counts as "high confidence".
pub const HIGH_CONFIDENCE: f64 = 0.5;

/// Points sampled on the opening, the rim, and each head limb.
const OPENING_POINTS: usize = 64;
const RIM_POINTS: usize = 96;
const LIMB_POINTS: usize = 10;
const BOTTOM_POINTS: usize = 64;

/// The parts of the model an edge point belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Part {
    Opening,
    Rim,
    Limb(usize),
    /// The visible half of the head's bottom rim (the outline's near side).
    Bottom,
}

/// One model edge sample, normalised image coordinates.
#[derive(Debug, Clone, Copy)]
struct EdgeSample {
    point: Vector2<f64>,
    /// The edge's unit normal.
    normal: Vector2<f64>,
    part: Part,
    /// The gradient searched along the normal: +1 dark to light, -1 light to dark, 0 either.
    polarity: i32,
}

/// What the search along one model edge sample found.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Edge {
    /// No edge within the range.
    None,
    /// The edge, normalised image coordinates.
    At(Vector2<f64>),
    /// The occluder hides the search: neither found nor missed.
    Hidden,
}

impl Edge {
    fn at(self) -> Option<Vector2<f64>> {
        match self {
            Edge::At(p) => Some(p),
            _ => None,
        }
    }
}

/// One estimate of the trocar's axis.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct MarkerlessEstimate {
    /// The axis (port centre and direction into the body), camera frame.
    #[serde(skip)]
    pub axis: Axis,
    /// Confidence in [0, 1]: edge support x fit quality x ambiguity.
    pub confidence: f64,
    /// RMS distance of the opening's edge points to the fitted model, px.
    pub fit_rms_px: f64,
    /// Fraction of the model's edge samples (opening, rim, head outline) found on the image.
    pub edge_support: f64,
    /// Fraction of the opening's samples found.
    pub opening_support: f64,
    /// How much better the chosen circle pose explains the image than the other (score
    /// difference / 0.25, clamped to 0-1), or 1 when the two were within 3 deg of each other.
    pub ambiguity_margin: f64,
}

/// A known cylinder in view that hides the scene behind it: the endoscope's own shaft, rigid
/// to the camera on its mount.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Occluder {
    /// The shaft in the left camera's frame: `start` its tip end, `end` towards the flange
    /// (the part behind the camera is left out).
    pub shaft: ToolCylinder,
    /// The masked image region grows by this much around its outline, px.
    pub margin_px: f64,
}

/// How far past its tip the endoscope is masked, m: its outline across the shaft is found in
/// the image, its tip's place along it is not, and a hand-eye error of 2 mm and 1 deg moves
/// that by up to 2 + 3.8 mm at the 0.22 m from the camera to the tip.
pub const ENDOSCOPE_TIP_MARGIN_M: f64 = 0.006;
/// The masked region's margin around the endoscope's outline, px.
pub const ENDOSCOPE_MARGIN_PX: f64 = 2.0;

impl Occluder {
    /// The endoscope on the flange (a straight shaft along the flange's z axis from the
    /// flange to its tip `length_m` away, `radius_m` thick) seen from the camera at
    /// `flange_t_camera`, masked [`ENDOSCOPE_TIP_MARGIN_M`] past its tip.
    pub fn endoscope(flange_t_camera: &Isometry3<f64>, length_m: f64, radius_m: f64) -> Self {
        Self {
            shaft: ToolCylinder::endoscope(flange_t_camera, length_m + ENDOSCOPE_TIP_MARGIN_M, radius_m),
            margin_px: ENDOSCOPE_MARGIN_PX,
        }
    }

    /// The shaft in the camera at `eye_t_left` (the left camera's points there).
    fn in_eye(&self, eye_t_left: &Isometry3<f64>) -> ToolCylinder {
        self.shaft.transformed(eye_t_left)
    }

    fn validate(&self) -> Result<(), VisionError> {
        self.shaft.validate()?;
        if !(self.margin_px.is_finite() && (0.0..=50.0).contains(&self.margin_px)) {
            return Err(VisionError::InvalidInput(
                "the occluder's margin must be in [0, 50] px".into(),
            ));
        }
        Ok(())
    }
}

/// The ends of `shaft` (camera frame): its tip end and the other.
fn shaft_ends(shaft: &ToolCylinder) -> (Vector3<f64>, Vector3<f64>) {
    (Vector3::from(shaft.start), Vector3::from(shaft.end))
}

/// The rims of the cross-sections along the part of `shaft` (camera frame) in front of the
/// camera (at least 2 cm away): `(points x, y, z, section length)`; `None` when none of it
/// is in front of the camera.
fn shaft_sections(shaft: &ToolCylinder) -> Option<(Vec<f64>, i32)> {
    const SECTIONS: usize = 16;
    const RIM: usize = 16;
    const NEAR_M: f64 = 0.02;
    let (mut a, mut b) = shaft_ends(shaft);
    if a.z < NEAR_M && b.z < NEAR_M {
        return None;
    }
    // Clip the axis to z >= NEAR_M.
    let clip = |p: Vector3<f64>, q: Vector3<f64>| p + (q - p) * ((NEAR_M - p.z) / (q.z - p.z));
    if a.z < NEAR_M {
        a = clip(a, b);
    } else if b.z < NEAR_M {
        b = clip(b, a);
    }
    let axis = Unit::try_new(b - a, 1e-9)?;
    let (u, v) = basis(&axis);
    let mut pts = Vec::with_capacity(3 * SECTIONS * RIM);
    for k in 0..SECTIONS {
        let c = a + (b - a) * (k as f64 / (SECTIONS - 1) as f64);
        for j in 0..RIM {
            let phi = std::f64::consts::TAU * j as f64 / RIM as f64;
            let p = c + shaft.radius * (phi.cos() * u + phi.sin() * v);
            // The rim may dip behind the near plane: keep it just in front.
            pts.extend([p.x, p.y, p.z.max(NEAR_M / 2.0)]);
        }
    }
    Some((pts, RIM as i32))
}

/// One outline line of a shaft in the image (normalised coordinates): the segment it is
/// searched along and the outline's unit normal (the same for both lines).
#[derive(Debug, Clone, Copy)]
struct OutlineLine {
    from: Vector2<f64>,
    to: Vector2<f64>,
    normal: Vector2<f64>,
}

/// Two image lines, each by two points (normalised coordinates).
type LinePair = [[Vector2<f64>; 2]; 2];

/// Samples per outline line.
const OUTLINE_SAMPLES: usize = 32;

impl OutlineLine {
    /// Sample `k` of [`OUTLINE_SAMPLES`] and its place along the segment (0-1).
    fn sample(&self, k: usize) -> (Vector2<f64>, f64) {
        let t = (k as f64 + 0.5) / OUTLINE_SAMPLES as f64;
        (self.from + t * (self.to - self.from), t)
    }
}

/// The two outline lines of `shaft` (camera frame) from 10 to 95 % of the part at least
/// 5 cm in front of the camera, counted from the masked tip (the tip's margin left out).
fn shaft_outline(shaft: &ToolCylinder) -> Option<[OutlineLine; 2]> {
    const NEAR_M: f64 = 0.05;
    let (a, b) = shaft_ends(shaft);
    if a.z < NEAR_M {
        return None;
    }
    let length = if b.z < NEAR_M {
        (b - a).norm() * (a.z - NEAR_M) / (a.z - b.z)
    } else {
        (b - a).norm()
    };
    let axis = Axis {
        point: a,
        direction: Unit::try_new(b - a, 1e-9)?,
    };
    let [l0, l1] = cylinder_limbs(&axis, shaft.radius, 0.1 * length, 0.95 * length)?;
    let (a0, b0) = (project(&l0[0])?, project(&l0[1])?);
    let normal = Vector2::new(a0.y - b0.y, b0.x - a0.x).try_normalize(1e-12)?;
    Some([
        OutlineLine {
            from: a0,
            to: b0,
            normal,
        },
        OutlineLine {
            from: project(&l1[0])?,
            to: project(&l1[1])?,
            normal,
        },
    ])
}

/// The line `offset = a + b t` (along the normal, against the place `t` along the segment)
/// through most of `found` within `tol`, least squares on those: `(a, b, inliers)`.
fn robust_line(found: &[(f64, f64)], tol: f64) -> Option<(f64, f64, usize)> {
    let mut best: Option<(usize, f64, f64)> = None;
    for (i, &(ti, di)) in found.iter().enumerate() {
        for &(tj, dj) in &found[i + 1..] {
            if (tj - ti).abs() < 0.2 {
                continue;
            }
            let b = (dj - di) / (tj - ti);
            let a = di - b * ti;
            let n = found.iter().filter(|(t, d)| (a + b * t - d).abs() <= tol).count();
            if best.is_none_or(|(m, _, _)| n > m) {
                best = Some((n, a, b));
            }
        }
    }
    let (_, a, b) = best?;
    let inl: Vec<(f64, f64)> = found
        .iter()
        .copied()
        .filter(|(t, d)| (a + b * t - d).abs() <= tol)
        .collect();
    let n = inl.len() as f64;
    let (st, sd) = inl.iter().fold((0.0, 0.0), |(x, y), (t, d)| (x + t, y + d));
    let (mt, md) = (st / n, sd / n);
    let (sxx, sxy) = inl.iter().fold((0.0, 0.0), |(x, y), (t, d)| {
        (x + (t - mt).powi(2), y + (t - mt) * (d - md))
    });
    let b = if sxx > 1e-12 { sxy / sxx } else { b };
    Some((md - b * mt, b, inl.len()))
}

/// The shaft's two outline lines `lines` moved onto the edges found, for the axis's plane:
/// each line fitted to its own edges `edges` (either polarity; `in_image`: each line's
/// samples in the image) within what its width may change by of the joint fit `joint`. The
/// width may change by what moving a shaft of `radius` by [`SCOPE_MAX_OFFSET_M`] in depth
/// changes it by (a width `w` at depth `z = 2 radius / w`, normalised units:
/// `w^2 dz / (2 radius)`), plus half a pixel (`tol` is a pixel). Where the two fits' width is
/// within that at both ends of the edges found, each line moves by its own fit (the pair
/// follows the shaft's width). Where it is not, one line's edges are not its outline (a
/// shaded shaft's lit side can be as light as what lies behind it, and then its strongest
/// edge lies a pixel or more inside the outline, scattered): both lines move by the tighter
/// fit (the lower residual), if it holds two thirds of its samples. `None` unless each line
/// holds a third of its samples on its own fit (one line's edges alone can be the other
/// line's, moved by the shaft's width).
fn limbs_fitted(
    lines: &[OutlineLine; 2],
    edges: [[&[(f64, f64)]; 2]; 2],
    joint: (f64, f64),
    in_image: [usize; 2],
    radius: f64,
    tol: f64,
) -> Option<LinePair> {
    let at = |l: &OutlineLine, t: f64| l.from + t * (l.to - l.from);
    let allowed = |t: f64| {
        let w = (at(&lines[1], t) - at(&lines[0], t)).dot(&lines[0].normal);
        w * w * SCOPE_MAX_OFFSET_M / (2.0 * radius) + 0.5 * tol
    };
    // A line's fit of the polarity holding more edges: (a, b, inliers, rms).
    let fit = |e: [&[(f64, f64)]; 2]| {
        e.into_iter()
            .filter_map(|e| {
                let near: Vec<(f64, f64)> = e
                    .iter()
                    .copied()
                    .filter(|(t, d)| (joint.0 + joint.1 * t - d).abs() <= allowed(*t) + tol)
                    .collect();
                let (a, b, n) = robust_line(&near, tol)?;
                // The residual over the edges within `tol` of the fit.
                let (ss, k) = near
                    .iter()
                    .map(|(t, d)| a + b * t - d)
                    .filter(|r| r.abs() <= tol)
                    .fold((0.0, 0usize), |(ss, k), r| (ss + r * r, k + 1));
                Some((a, b, n, (ss / k.max(1) as f64).sqrt()))
            })
            .max_by_key(|f| f.2)
    };
    let (f0, f1) = (fit(edges[0])?, fit(edges[1])?);
    if 3 * f0.2 < in_image[0] || 3 * f1.2 < in_image[1] {
        return None;
    }
    let (lo, hi) = edges
        .iter()
        .flatten()
        .flat_map(|e| e.iter().map(|x| x.0))
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), t| (l.min(t), h.max(t)));
    let width_kept = [lo, hi]
        .into_iter()
        .all(|t| (f1.0 + f1.1 * t - f0.0 - f0.1 * t).abs() <= allowed(t));
    let moved = |l: &OutlineLine, f: (f64, f64, usize, f64)| [l.from + f.0 * l.normal, l.to + (f.0 + f.1) * l.normal];
    if width_kept {
        return Some([moved(&lines[0], f0), moved(&lines[1], f1)]);
    }
    let (carrier, n) = if f0.3 <= f1.3 {
        (f0, in_image[0])
    } else {
        (f1, in_image[1])
    };
    (3 * carrier.2 >= 2 * n).then(|| [moved(&lines[0], carrier), moved(&lines[1], carrier)])
}

/// The unit normals of the two planes through the camera centre and each of the outline
/// lines `lines` (normalised coordinates, each by two points), each pointing away from the
/// other line: a cylinder with that outline has its axis at its radius behind both planes
/// (`n . x = -r`), so in the plane through the centre of normal `n0 - n1`.
fn outline_planes(lines: [[Vector2<f64>; 2]; 2]) -> Option<(Vector3<f64>, Vector3<f64>)> {
    let plane = |l: [Vector2<f64>; 2], other: Vector2<f64>| -> Option<Vector3<f64>> {
        let n = Vector3::new(l[0].x, l[0].y, 1.0)
            .cross(&Vector3::new(l[1].x, l[1].y, 1.0))
            .try_normalize(1e-12)?;
        Some(if n.dot(&Vector3::new(other.x, other.y, 1.0)) > 0.0 {
            -n
        } else {
            n
        })
    };
    Some((plane(lines[0], lines[1][0])?, plane(lines[1], lines[0][0])?))
}

/// The cylinder of radius `shaft.radius` whose outline is the two image lines `lines`
/// (normalised coordinates, each by two points), near `shaft` (camera frame): its axis lies
/// at `radius` from both planes through the camera centre and a line; its tip end is where
/// `shaft`'s tip end appears, moved onto the new outline's middle; `None` when the lines do
/// not make a shaft within 5 deg and 2 cm of `shaft`.
fn shaft_from_outline(shaft: &ToolCylinder, lines: [[Vector2<f64>; 2]; 2]) -> Option<ToolCylinder> {
    let (tip, back) = shaft_ends(shaft);
    let along = Unit::try_new(back - tip, 1e-12)?;
    let (n0, n1) = outline_planes(lines)?;
    let mut d = n0.cross(&n1).try_normalize(1e-9)?;
    if d.dot(&along) < 0.0 {
        d = -d;
    }
    let r = shaft.radius;
    let m = nalgebra::Matrix3::from_rows(&[n0.transpose(), n1.transpose(), d.transpose()]);
    let c = m.try_inverse()? * Vector3::new(-r, -r, 0.0);
    // The tip where its image was, on the new outline's middle line.
    let tip_img = project(&tip)?;
    let (p, q) = (0.5 * (lines[0][0] + lines[1][0]), 0.5 * (lines[0][1] + lines[1][1]));
    let u = (q - p).try_normalize(1e-12)?;
    let on = p + u * (tip_img - p).dot(&u);
    let v = Vector3::new(on.x, on.y, 1.0);
    // The axis point nearest the line of sight through `on`.
    let (b, e, vv, dc) = (d.dot(&v), v.dot(&c), v.dot(&v), d.dot(&c));
    let s = (b * e - vv * dc) / (vv - b * b);
    let new_tip = c + s * d;
    let ok = s.is_finite() && d.angle(&along) <= 5f64.to_radians() && (new_tip - tip).norm() <= 0.02 && new_tip.z > 0.0;
    ok.then(|| ToolCylinder {
        start: new_tip.into(),
        end: (new_tip + d * (back - tip).norm()).into(),
        radius: r,
    })
}

/// The estimator for one camera (optionally with the right camera of a stereo pair) and one
/// trocar model.
pub struct MarkerlessEstimator {
    left: Eye,
    right: Option<RightEye>,
    model: TrocarModel,
    occluder: Option<Occluder>,
    /// The hand-eye's error as the endoscope in view tells it (stereo only).
    scope: Option<ScopeInView>,
}

/// One camera's detector (it holds the camera's last image) and model.
struct Eye {
    det: cxx::UniquePtr<ffi::MarkerlessDetectorCpp>,
    camera: CameraModel,
    occluder: Option<EyeOccluder>,
}

/// The occluder as one eye masks it, in this eye's frame: where the hand-eye puts it, where
/// its outline was last found in this eye's images (the shaft is rigid to the camera: it
/// stays there until found elsewhere), where the track puts the port, and the shaft the mask
/// was last built of.
struct EyeOccluder {
    predicted: ToolCylinder,
    margin_px: f64,
    found: Option<ToolCylinder>,
    port: Option<Axis>,
    applied: Option<ToolCylinder>,
    /// The unit normal of the plane through this eye's centre and the shaft's axis, from the
    /// outline found in the image loaded last (`None`: not found there).
    axis_plane: Option<Vector3<f64>>,
    /// Whether `found` came of a fit both outline lines hold.
    found_held: bool,
}

impl EyeOccluder {
    /// The part of the shaft in view: where it was found (else where the hand-eye puts it),
    /// ended [`ENDOSCOPE_TIP_MARGIN_M`] past the port's face where it goes into the port.
    fn in_view(&self) -> ToolCylinder {
        inside_port_hidden(&self.found.unwrap_or(self.predicted), self.port.as_ref())
    }
}

/// `shaft` (camera frame) without its part past the face of the port on `port` (inside the
/// trocar, which hides it), but for [`ENDOSCOPE_TIP_MARGIN_M`]: unchanged unless it runs from
/// before the face's plane to past it.
fn inside_port_hidden(shaft: &ToolCylinder, port: Option<&Axis>) -> ToolCylinder {
    let Some(port) = port else { return *shaft };
    let (tip, back) = shaft_ends(shaft);
    let n = port.direction.into_inner();
    let (dt, db) = ((tip - port.point).dot(&n), (back - port.point).dot(&n));
    if dt <= 0.0 || db >= 0.0 {
        return *shaft;
    }
    let cross = tip + (back - tip) * (dt / (dt - db));
    let Some(along) = (tip - back).try_normalize(1e-12) else {
        return *shaft;
    };
    let cut = cross + along * ENDOSCOPE_TIP_MARGIN_M;
    if (cut - back).norm() >= (tip - back).norm() {
        return *shaft;
    }
    ToolCylinder {
        start: cut.into(),
        ..*shaft
    }
}

/// How far across the shaft its outline is searched for around where the hand-eye puts it, px.
const OCCLUDER_SEARCH_PX: f64 = 25.0;

impl Eye {
    fn new(camera: &CameraModel) -> Result<Self, VisionError> {
        camera.validate()?;
        let det = ffi::new_markerless_detector(
            &camera.intrinsics(),
            &camera.distortion,
            camera.is_equidistant(),
            camera.width as i32,
            camera.height as i32,
        )?;
        Ok(Self {
            det,
            camera: camera.clone(),
            occluder: None,
        })
    }

    /// Mask what `occluder` (the left camera's frame) hides in this eye, which sees the left
    /// camera's points through `eye_t_left`; `None` clears the mask.
    fn set_occluder(&mut self, occluder: Option<&Occluder>, eye_t_left: &Isometry3<f64>) -> Result<(), VisionError> {
        self.occluder = occluder.map(|o| EyeOccluder {
            predicted: o.in_eye(eye_t_left),
            margin_px: o.margin_px,
            found: None,
            port: None,
            applied: None,
            axis_plane: None,
            found_held: false,
        });
        self.apply_occluder()
    }

    /// Where the track puts the port (this eye's frame; `None`: nowhere): the mask ends where
    /// the shaft goes into it. Rebuilt when its tip end moves by 0.2 mm or more.
    fn set_port(&mut self, port: Option<Axis>) -> Result<(), VisionError> {
        let Some(o) = self.occluder.as_mut() else { return Ok(()) };
        o.port = port;
        let moved = o
            .applied
            .is_none_or(|a| (Vector3::from(a.start) - Vector3::from(o.in_view().start)).norm() >= 2e-4);
        if moved {
            self.apply_occluder()?;
        }
        Ok(())
    }

    /// Build the occluder's mask where it was last found, else where the hand-eye puts it
    /// (none without an occluder).
    fn apply_occluder(&mut self) -> Result<(), VisionError> {
        if let Some(o) = self.occluder.as_mut() {
            o.applied = Some(o.in_view());
        }
        let sections = self
            .occluder
            .as_ref()
            .and_then(|o| shaft_sections(&o.in_view()).map(|s| (s, o.margin_px)));
        let ((pts, len), margin) = sections.unwrap_or(((vec![], 3), 0.0));
        ffi::markerless_set_occluder(self.det.pin_mut(), &pts, len, margin)?;
        Ok(())
    }

    /// Find the occluder's outline in the loaded image: its two lines within
    /// [`OCCLUDER_SEARCH_PX`] across the shaft of where the hand-eye puts it (a hand-eye error
    /// of a degree moves it by several pixels), moved together by the straight line of
    /// offsets through most of the edges found on both, and move the mask to the shaft that
    /// has that outline: the best such line that both outline lines hold ([`limbs_fitted`]),
    /// else the best, until one both lines hold has placed the mask. The mask stays where it
    /// was when under half the outline's samples in the image (or 12) lie on that line, or
    /// the shaft it gives is over 5 deg or 2 cm from where the hand-eye puts it. The tip's
    /// place along the shaft is kept where the hand-eye puts it. The axis's plane is taken
    /// only from a line both outline lines hold.
    fn register_occluder(&mut self) -> Result<(), VisionError> {
        self.forget_axis_plane();
        let Some(o) = &self.occluder else { return Ok(()) };
        let Some(lines) = shaft_outline(&inside_port_hidden(&o.predicted, o.port.as_ref())) else {
            return Ok(());
        };
        let cam = &self.camera;
        let in_image = |p: &Vector2<f64>| {
            let (u, v) = (cam.fx * p.x + cam.cx, cam.fy * p.y + cam.cy);
            u >= 0.0 && v >= 0.0 && u < f64::from(cam.width) && v < f64::from(cam.height)
        };
        // The edges found along one line of one polarity: (place along it, offset along the
        // normal in normalised units), and how many of its samples lie in the image.
        let search = |l: &OutlineLine, polarity: i32| -> Result<(Vec<(f64, f64)>, usize), VisionError> {
            let samples: Vec<(Vector2<f64>, f64)> = (0..OUTLINE_SAMPLES)
                .map(|k| l.sample(k))
                .filter(|(p, _)| in_image(p))
                .collect();
            let pts: Vec<f64> = samples
                .iter()
                .flat_map(|(p, _)| [p.x, p.y, l.normal.x, l.normal.y])
                .collect();
            let out = ffi::markerless_search_edges(&self.det, &pts, OCCLUDER_SEARCH_PX, polarity, 4.0, true)?;
            let found = out
                .chunks_exact(EDGE_RECORD_LEN)
                .zip(&samples)
                .filter(|(rec, _)| rec[0] > 0.5 && rec[0] < 1.5)
                .map(|(rec, (p, t))| (*t, (Vector2::new(rec[1], rec[2]) - p).dot(&l.normal)))
                .collect();
            Ok((found, samples.len()))
        };
        let [l0, l1] = &lines;
        let (a, b) = ((search(l0, 1)?, search(l0, -1)?), (search(l1, 1)?, search(l1, -1)?));
        let (searched, in_image) = (a.0 .1 + b.0 .1, [a.0 .1, b.0 .1]);
        // The shaft's image moves as a whole (a hand-eye error of a few mm barely changes its
        // width): one offset `a + b t` along the normal for both lines, fitted to both lines'
        // edges, each of the polarity that fits best (a shaded shaft can be lighter than what
        // is behind it on one side and darker on the other). Of the fits of each pair of
        // polarities, the best that both lines hold
        // ([`limbs_fitted`]), else the best: one line's edges alone can fit it moved by about
        // the shaft's width or turned across it, and a mask moved there leaves the shaft's own
        // edges beside it, which run into the opening's outline (seen near the port: the
        // opening lost for seconds). Only a fit both lines hold gives the axis's plane.
        let tol = 1.0 / cam.fx;
        let edges = [[&a.0 .0[..], &a.1 .0[..]], [&b.0 .0[..], &b.1 .0[..]]];
        let mut held: Option<((f64, f64, usize), LinePair)> = None;
        let mut best: Option<(f64, f64, usize)> = None;
        for first in [&a.0 .0, &a.1 .0] {
            for second in [&b.0 .0, &b.1 .0] {
                let both: Vec<(f64, f64)> = first.iter().chain(second.iter()).copied().collect();
                let Some(f) = robust_line(&both, tol).filter(|f| f.2 >= 12 && 2 * f.2 >= searched) else {
                    continue;
                };
                if best.is_none_or(|b| f.2 > b.2) {
                    best = Some(f);
                }
                if held.is_none_or(|h| f.2 > h.0 .2) {
                    if let Some(l) = limbs_fitted(&lines, edges, (f.0, f.1), in_image, o.predicted.radius, tol) {
                        held = Some((f, l));
                    }
                }
            }
        }
        // Once placed by a fit both lines hold, the shaft (rigid to the camera) stays there
        // until another such fit moves it.
        let Some((a, b, _)) = held.map(|h| h.0).or(best.filter(|_| !o.found_held)) else {
            return Ok(());
        };
        let limbs = held.map(|h| h.1);
        let moved = |l: &OutlineLine| [l.from + a * l.normal, l.to + (a + b) * l.normal];
        let outline = [moved(l0), moved(l1)];
        let found = shaft_from_outline(&o.predicted, outline);
        if found.is_some() {
            if let Some(o) = self.occluder.as_mut() {
                o.found = found;
                o.found_held = limbs.is_some();
                // The axis's plane from each line's own fit ([`limbs_fitted`]): one offset for
                // both lines cannot follow a shaft the hand-eye error moves in depth, nor a
                // line whose edges are not the outline.
                o.axis_plane = limbs
                    .and_then(outline_planes)
                    .and_then(|(n0, n1)| (n0 - n1).try_normalize(1e-12));
            }
            self.apply_occluder()?;
        }
        Ok(())
    }

    /// Forget what the image loaded last told of the shaft (no image of this frame).
    fn forget_axis_plane(&mut self) {
        if let Some(o) = self.occluder.as_mut() {
            o.axis_plane = None;
        }
    }

    /// Load `image` (the camera's size) into the detector.
    fn load(&mut self, image: &ImageView) -> Result<(), VisionError> {
        image.validate()?;
        if image.width != self.camera.width || image.height != self.camera.height {
            return Err(VisionError::InvalidInput(format!(
                "image {}x{} does not match the camera {} ({}x{})",
                image.width, image.height, self.camera.name, self.camera.width, self.camera.height
            )));
        }
        ffi::markerless_load(
            self.det.pin_mut(),
            image.data,
            image.width as i32,
            image.height as i32,
            image.channels as i32,
            1.0,
        )?;
        Ok(())
    }
}

/// The right camera of a stereo pair: its eye and where it sees the left camera's points.
struct RightEye {
    eye: Eye,
    right_t_left: Isometry3<f64>,
}

impl RightEye {
    /// The right camera's centre in the left camera's frame.
    fn origin_in_left(&self) -> Vector3<f64> {
        self.right_t_left.inverse().translation.vector
    }
}

/// One image a pose is refined on: its eye, and where that eye sees the points of the frame
/// the pose is in (`None`: the pose is in this eye's frame).
#[derive(Clone, Copy)]
struct View<'a> {
    eye: &'a Eye,
    from_pose_frame: Option<&'a Isometry3<f64>>,
}

impl<'a> View<'a> {
    /// The image of `eye`, the pose in its own frame.
    fn of(eye: &'a Eye) -> Self {
        Self {
            eye,
            from_pose_frame: None,
        }
    }

    /// `axis` (the pose's frame) in this eye's frame.
    fn axis(&self, axis: &Axis) -> Axis {
        self.from_pose_frame.map_or(*axis, |t| axis.transformed(t))
    }
}

/// The two circle poses of one ellipse, each refined on the image (those that found the
/// opening), and whether they were within 3 deg of each other from the start (`harmless`).
struct Candidate {
    hyps: Vec<Hypothesis>,
    harmless: bool,
}

/// How far apart (deg) the chosen circle pose and the right camera's nearest one may be for
/// the two views to agree on it.
const STEREO_AGREE_DEG: f64 = 4.0;
/// The stereo margin is the other pose's disagreement minus the chosen one's over this (deg).
const STEREO_MARGIN_DEG: f64 = 5.0;
/// The ambiguity margin of a pose fitted to both images of a stereo pair on which every
/// start settled: between an ellipse's two poses left apart by nothing (0.5) and two within
/// 3 deg from the start (1); a wrong axis can draw every start. Not given to one image
/// alone: at 0.4 m both of an ellipse's poses can settle on one axis 13 deg off.
const ONE_AXIS_MARGIN: f64 = 0.75;

/// One pose hypothesis and how well the image supports it.
#[derive(Debug, Clone, Copy)]
struct Hypothesis {
    axis: Axis,
    score: f64,
    rms_px: f64,
    support: f64,
    opening_support: f64,
}

impl MarkerlessEstimator {
    /// An estimator for `camera` and `model`.
    pub fn new(camera: &CameraModel, model: &TrocarModel) -> Result<Self, VisionError> {
        model.validate()?;
        Ok(Self {
            left: Eye::new(camera)?,
            right: None,
            model: *model,
            occluder: None,
            scope: None,
        })
    }

    /// The same estimator with the right camera of a stereo pair: `right` its model and
    /// `right_t_left` the left camera's points in its frame (a rectified pair: a translation
    /// by minus the baseline along x, [`CameraModel::stereo_right_t_left`]). Its image, when
    /// given ([`MarkerlessEstimator::estimate_stereo`]), decides between the two poses an
    /// ellipse admits: the true pose is one of the right image's two as well, the other is not.
    pub fn with_right_camera(
        mut self,
        right: &CameraModel,
        right_t_left: &Isometry3<f64>,
    ) -> Result<Self, VisionError> {
        let finite = right_t_left.translation.vector.iter().all(|v| v.is_finite())
            && right_t_left.rotation.coords.iter().all(|v| v.is_finite());
        if !finite || right_t_left.translation.vector.norm() > 1.0 {
            return Err(VisionError::InvalidInput(
                "the stereo pair's right_t_left must be finite with a baseline under 1 m".into(),
            ));
        }
        let mut eye = Eye::new(right)?;
        eye.set_occluder(self.occluder.as_ref(), right_t_left)?;
        self.right = Some(RightEye {
            eye,
            right_t_left: *right_t_left,
        });
        Ok(self)
    }

    /// The same estimator with a known occluder in view (the endoscope's own shaft, in the
    /// left camera's frame; `None`: none): the image region it covers, grown by its margin,
    /// is left out in both images (no opening contour, no edge found there), and the model's
    /// edge samples there count neither for nor against an estimate.
    pub fn with_occluder(mut self, occluder: Option<Occluder>) -> Result<Self, VisionError> {
        if let Some(o) = &occluder {
            o.validate()?;
        }
        self.left.set_occluder(occluder.as_ref(), &Isometry3::identity())?;
        if let Some(r) = self.right.as_mut() {
            r.eye.set_occluder(occluder.as_ref(), &r.right_t_left)?;
        }
        self.scope = occluder.as_ref().and_then(|o| ScopeInView::new(&o.shaft));
        self.occluder = occluder;
        Ok(self)
    }

    /// Where the track puts the port (its axis in the left camera's frame; `None`: nowhere
    /// yet): the endoscope's shaft past the port's face is inside the trocar, which hides it,
    /// so its mask ends [`ENDOSCOPE_TIP_MARGIN_M`] past where the shaft crosses the face's
    /// plane (without it, the mask of a scope inside the port reaches over the opening's far
    /// rim). No effect without an occluder.
    pub fn set_port_hint(&mut self, port: Option<&Axis>) -> Result<(), VisionError> {
        self.left.set_port(port.copied())?;
        if let Some(r) = self.right.as_mut() {
            r.eye.set_port(port.map(|a| a.transformed(&r.right_t_left)))?;
        }
        Ok(())
    }

    /// An estimator for `camera` and `model`, with `right` the right camera of a rectified
    /// stereo pair ([`MarkerlessEstimator::with_right_camera`] at its baseline), if any.
    pub fn for_cameras(
        camera: &CameraModel,
        right: Option<&CameraModel>,
        model: &TrocarModel,
    ) -> Result<Self, VisionError> {
        let e = Self::new(camera, model)?;
        match right {
            Some(r) => e.with_right_camera(r, &r.stereo_right_t_left()),
            None => Ok(e),
        }
    }

    /// The hand-eye's error as the endoscope in view tells it: the points of the camera frame
    /// the occluder was given in (the believed camera) in the frame the images are seen in
    /// (the true camera), [`ScopeInView::camera_t_believed`]; the identity without an
    /// occluder or a stereo pair, or until both eyes have found the shaft in
    /// [`super::scope_in_view::SCOPE_MIN_FRAMES`] frames. The camera's pose is the believed one times
    /// its inverse.
    pub fn camera_t_believed(&self) -> Isometry3<f64> {
        self.scope
            .as_ref()
            .map_or(Isometry3::identity(), ScopeInView::camera_t_believed)
    }

    /// Frames in the correction's window (0 without an occluder or a stereo pair).
    pub fn scope_frames(&self) -> usize {
        self.scope
            .as_ref()
            .filter(|_| self.right.is_some())
            .map_or(0, ScopeInView::frames)
    }

    /// The shaft's axis where both eyes found it in the images loaded last (left frame):
    /// added to the correction.
    fn see_scope(&mut self) {
        let (Some(scope), Some(r)) = (self.scope.as_mut(), self.right.as_ref()) else {
            return;
        };
        let left = self.left.occluder.as_ref().and_then(|o| o.axis_plane);
        let right = r.eye.occluder.as_ref().and_then(|o| o.axis_plane);
        let (Some(left), Some(right), Some(o)) = (left, right, self.occluder.as_ref()) else {
            return;
        };
        let left_t_right = r.right_t_left.inverse();
        let right = left_t_right.rotation * right;
        let near = Vector3::from(o.shaft.start);
        if let Some((p, d)) = stereo_axis(&left, &right, &left_t_right.translation.vector, &near) {
            scope.add(&p, &d);
        }
    }

    /// The camera it was built for (the left one of a stereo pair).
    pub fn camera(&self) -> &CameraModel {
        &self.left.camera
    }

    /// The right camera of a stereo pair, if it has one.
    pub fn right_camera(&self) -> Option<&CameraModel> {
        self.right.as_ref().map(|r| &r.eye.camera)
    }

    /// The axis of the trocar in `image`, or `None` when no opening is found well enough.
    /// `prior`: an axis direction the estimate should be near (resolves the ambiguity).
    pub fn estimate(
        &mut self,
        image: &ImageView,
        prior: Option<&Unit<Vector3<f64>>>,
    ) -> Result<Option<MarkerlessEstimate>, VisionError> {
        self.estimate_stereo(image, None, prior)
    }

    /// [`MarkerlessEstimate`] of the left `image` with the right camera's image `right`
    /// captured with it (ignored without a right camera): where the left image admits two
    /// poses, the one the right image admits too is kept, whatever the prior and the outline
    /// say, and the port centre is where the two eyes' lines of sight to it cross
    /// ([`triangulate`]); where the right image finds no opening there, the left image's
    /// estimate stands; where it sees the same opening but none of its poses is within
    /// 4 deg of either, the left image does not decide: one axis is refined on both images
    /// at once from each eye's poses. Where the left image gives no
    /// confident estimate, the right image's own confident one of an opening the left image
    /// found too stands (carried into the left frame).
    pub fn estimate_stereo(
        &mut self,
        image: &ImageView,
        right: Option<&ImageView>,
        prior: Option<&Unit<Vector3<f64>>>,
    ) -> Result<Option<MarkerlessEstimate>, VisionError> {
        self.left.load(image)?;
        self.left.register_occluder()?;
        if let Some(r) = self.right.as_mut() {
            r.eye.forget_axis_plane();
        }
        let recs = ellipses(&mut self.left, &self.model)?;
        let cands = self.candidates(&self.left, &recs)?;
        let right = right.filter(|_| self.right.is_some());
        // The right image's candidates and poses (left frame), read once some ellipse gave a
        // pose.
        let mut seen_right: Option<(Vec<Candidate>, Vec<Axis>)> = None;
        let mut best: Option<MarkerlessEstimate> = None;
        for c in &cands {
            let stereo = match (right, self.right.as_ref().map(RightEye::origin_in_left)) {
                (Some(img), Some(origin)) if !c.hyps.is_empty() => {
                    if seen_right.is_none() {
                        seen_right = Some(self.right_candidates(img)?);
                    }
                    let r = seen_right.as_ref().map_or(&[][..], |r| &r.1);
                    let choice = stereo_choice(&c.hyps, r, &origin);
                    // The right image sees this opening but none of its poses agrees with
                    // either of the left image's: one eye is off, and the left alone does not
                    // decide; one axis fitted to both images does.
                    if choice.is_none() && same_opening(&c.hyps[0].axis.point, r) {
                        if let Some(e) = self.joint(&c.hyps, r)? {
                            if best.as_ref().is_none_or(|b| e.edge_support > b.edge_support) {
                                best = Some(e);
                            }
                        }
                        continue;
                    }
                    choice
                }
                _ => None,
            };
            let Some(e) = self.decide(&c.hyps, prior, c.harmless, stereo) else {
                continue;
            };
            if best.as_ref().is_none_or(|b| e.edge_support > b.edge_support) {
                best = Some(e);
            }
        }
        // Where the left image gives no confident estimate (its refinements may both have
        // settled on one wrong axis), the right image's own, carried into the left frame,
        // stands if it is confident and its port is one the left image found too (the pair's
        // calibration checked by the two images, not trusted).
        let left_ports: Vec<Axis> = cands.iter().flat_map(|c| c.hyps.iter().map(|h| h.axis)).collect();
        let seen_left = |p: &Vector3<f64>| same_opening(p, &left_ports);
        let unsure = best.as_ref().is_none_or(|b| b.confidence < HIGH_CONFIDENCE);
        if let Some(img) = right.filter(|_| unsure && !left_ports.is_empty()) {
            if seen_right.is_none() {
                seen_right = Some(self.right_candidates(img)?);
            }
            for c in seen_right.as_ref().map_or(&[][..], |r| &r.0) {
                if let Some(e) = self.decide(&c.hyps, prior, c.harmless, None) {
                    let better = best.as_ref().is_none_or(|b| e.confidence > b.confidence);
                    if e.confidence >= HIGH_CONFIDENCE && better && seen_left(&e.axis.point) {
                        best = Some(e);
                    }
                }
            }
        }
        self.see_scope();
        Ok(best)
    }

    /// Where the two eyes' poses of one opening disagree: one axis refined on both images at
    /// once (the right image loaded), from each of the left image's poses `hyps` and each of
    /// the right image's poses `right` (left frame) of the same opening; the best supported
    /// is graded against the best that settled more than 3 deg from it (margin 1 when every
    /// start settled on one axis, 0.5 when only one found the opening in both images).
    fn joint(&self, hyps: &[Hypothesis], right: &[Axis]) -> Result<Option<MarkerlessEstimate>, VisionError> {
        let (Some(r), Some(first)) = (self.right.as_ref(), hyps.first()) else {
            return Ok(None);
        };
        let views = [
            View::of(&self.left),
            View {
                eye: &r.eye,
                from_pose_frame: Some(&r.right_t_left),
            },
        ];
        let same = right.iter().filter(|a| same_port(&a.point, &first.axis.point));
        let mut found = vec![];
        for start in hyps.iter().map(|h| h.axis).chain(same.copied()) {
            if let Some(h) = self.refine(&views, start)? {
                found.push(h);
            }
        }
        found.sort_by(|a, b| b.score.total_cmp(&a.score));
        let Some(best) = found.first() else { return Ok(None) };
        let other = found.iter().find(|h| h.axis.angle_to(&best.axis) > 3f64.to_radians());
        Ok(Some(match other {
            Some(o) => graded(best, ((best.score - o.score) / 0.25).clamp(0.0, 1.0)),
            // Every start settled on one axis: no other pose explains the two images, but a
            // wrong axis can draw every start (seen at 0.34 m with the axis 11 deg from the
            // line of sight, where the opening's ellipses barely tell the tilt).
            None if found.len() > 1 => graded(best, ONE_AXIS_MARGIN),
            None => graded(best, 0.5),
        }))
    }

    /// The right camera's image `img`: its candidates (each circle pose refined on it) and
    /// all their poses, in the left camera's frame.
    fn right_candidates(&mut self, img: &ImageView) -> Result<(Vec<Candidate>, Vec<Axis>), VisionError> {
        let Some(mut r) = self.right.take() else {
            return Ok((vec![], vec![]));
        };
        let out = r.eye.load(img).and_then(|()| {
            r.eye.register_occluder()?;
            let recs = ellipses(&mut r.eye, &self.model)?;
            let left_t_right = r.right_t_left.inverse();
            let mut cands = self.candidates(&r.eye, &recs)?;
            for h in cands.iter_mut().flat_map(|c| c.hyps.iter_mut()) {
                h.axis = h.axis.transformed(&left_t_right);
            }
            let poses = cands.iter().flat_map(|c| c.hyps.iter().map(|h| h.axis)).collect();
            Ok((cands, poses))
        });
        self.right = Some(r);
        out
    }

    /// The refined circle poses of the ellipses `recs` found in the image `eye` holds.
    fn candidates(&self, eye: &Eye, recs: &[f64]) -> Result<Vec<Candidate>, VisionError> {
        let cam = &eye.camera;
        let r = self.model.opening.radius;
        let mut out = vec![];
        for rec in recs.chunks_exact(ELLIPSE_RECORD_LEN) {
            let conic = ellipse_conic([rec[0], rec[1]], rec[2], rec[3], rec[4], cam.intrinsics());
            let Some(sols) = circle_poses(&conic, r) else { continue };
            // Solutions within 3 deg of each other from the start: the ambiguity is harmless.
            let harmless = sols[0].angle_to(&sols[1]) < 3f64.to_radians();
            let mut hyps: Vec<Hypothesis> = vec![];
            for s in sols {
                if let Some(h) = self.refine(&[View::of(eye)], s)? {
                    hyps.push(h);
                }
            }
            out.push(Candidate { hyps, harmless });
        }
        Ok(out)
    }

    /// Pick the better hypothesis and grade it: by the head's outline (the score) alone, or,
    /// with a `prior`, the one nearer the prior, unless the outline picks the other one with
    /// high confidence on its own: the image overrides the prior it contradicts, so that a
    /// wrong prior (a wrong earlier estimate) can neither hold the estimate on the wrong pose
    /// nor keep every frame below the confidence gate, where the estimator's outlier gate
    /// would never see them and the track could never be re-initialised.
    /// `harmless`: the two circle poses were within 3 deg of each other before refinement.
    /// `stereo`: the hypothesis the right camera's image agrees with, the margin it gives and
    /// the triangulated port centre ([`stereo_choice`]); it decides, before the prior and the
    /// outline.
    fn decide(
        &self,
        hyps: &[Hypothesis],
        prior: Option<&Unit<Vector3<f64>>>,
        harmless: bool,
        stereo: Option<StereoChoice>,
    ) -> Option<MarkerlessEstimate> {
        if let Some(StereoChoice { index, margin, point }) = stereo {
            let h = hyps.get(index)?;
            let other = hyps.iter().enumerate().find(|(k, _)| *k != index).map(|(_, o)| o);
            // With one pose left after refinement the right image confirms it: margin as given.
            let mut e = grade(h, other.or(Some(h)), harmless, |_, _| margin);
            e.axis.point = point;
            return Some(e);
        }
        let mut by_score: Vec<Hypothesis> = hyps.to_vec();
        by_score.sort_by(|a, b| b.score.total_cmp(&a.score));
        let outline = grade(by_score.first()?, by_score.get(1), harmless, |h, o| {
            ((h.score - o.score) / 0.25).clamp(0.0, 1.0)
        });
        let Some(p) = prior else { return Some(outline) };
        let mut by_prior = by_score.clone();
        by_prior.sort_by(|a, b| a.axis.direction.dot(p).total_cmp(&b.axis.direction.dot(p)).reverse());
        let with_prior = grade(by_prior.first()?, by_prior.get(1), harmless, |h, o| {
            let (ab, ao) = (h.axis.direction.angle(p), o.axis.direction.angle(p));
            ((ao - ab) / 10f64.to_radians()).clamp(0.0, 1.0)
        });
        let disagree = outline.axis.direction.angle(&with_prior.axis.direction) > 3f64.to_radians();
        Some(if disagree && outline.confidence >= HIGH_CONFIDENCE {
            outline
        } else {
            with_prior
        })
    }

    /// Model edge samples of `axis`.
    fn samples(&self, axis: &Axis) -> Vec<EdgeSample> {
        let mut out = Vec::with_capacity(OPENING_POINTS + RIM_POINTS + 2 * LIMB_POINTS);
        let (u, v) = basis(&axis.direction);
        for (part, radius, n, pol) in [
            (Part::Opening, self.model.opening.radius, OPENING_POINTS, 1),
            (Part::Rim, self.model.head.radius, RIM_POINTS, 0),
        ] {
            let Some(c) = circle_conic(&axis.point, &axis.direction, radius) else {
                continue;
            };
            for k in 0..n {
                let phi = std::f64::consts::TAU * k as f64 / n as f64;
                if let Some(p) = project(&(axis.point + radius * (phi.cos() * u + phi.sin() * v))) {
                    out.push(EdgeSample {
                        point: p,
                        normal: conic_normal(&c, &p),
                        part,
                        polarity: pol,
                    });
                }
            }
        }
        let h = self.model.head.height;
        let rh = self.model.head.radius;
        let bottom_centre = axis.at(h);
        if let Some(c) = circle_conic(&bottom_centre, &axis.direction, rh) {
            for k in 0..BOTTOM_POINTS {
                let phi = std::f64::consts::TAU * k as f64 / BOTTOM_POINTS as f64;
                let w = phi.cos() * u + phi.sin() * v;
                let q = bottom_centre + rh * w;
                // Visible where the side faces the camera, away from the tangent points.
                if w.dot(&(-q)) > 0.2 * q.norm() * (1.0 - axis.direction.dot(&q.normalize()).powi(2)).sqrt() {
                    if let Some(p) = project(&q) {
                        out.push(EdgeSample {
                            point: p,
                            normal: conic_normal(&c, &p),
                            part: Part::Bottom,
                            polarity: 0,
                        });
                    }
                }
            }
        }
        if let Some(limbs) = cylinder_limbs(axis, rh, 0.15 * h, 0.85 * h) {
            for (i, [a, b]) in limbs.iter().enumerate() {
                let (Some(pa), Some(pb)) = (project(a), project(b)) else {
                    continue;
                };
                let dir = pb - pa;
                if dir.norm() < 1e-9 {
                    continue;
                }
                let n = Vector2::new(-dir.y, dir.x).normalize();
                for k in 0..LIMB_POINTS {
                    let t = (k as f64 + 0.5) / LIMB_POINTS as f64;
                    out.push(EdgeSample {
                        point: pa + t * dir,
                        normal: n,
                        part: Part::Limb(i),
                        polarity: 0,
                    });
                }
            }
        }
        out
    }

    /// Search the image for the edges of `samples` (within `range_px`): per sample the edge
    /// found, nothing, or [`Edge::Hidden`] where the occluder hides the search.
    fn search(eye: &Eye, samples: &[EdgeSample], range_px: f64) -> Result<Vec<Edge>, VisionError> {
        let mut found = vec![Edge::None; samples.len()];
        for pol in [-1, 0, 1] {
            let idx: Vec<usize> = (0..samples.len()).filter(|&i| samples[i].polarity == pol).collect();
            if idx.is_empty() {
                continue;
            }
            let pts: Vec<f64> = idx
                .iter()
                .flat_map(|&i| {
                    let EdgeSample {
                        point: p, normal: n, ..
                    } = samples[i];
                    [p.x, p.y, n.x, n.y]
                })
                .collect();
            let out = ffi::markerless_search_edges(&eye.det, &pts, range_px, pol, 4.0, false)?;
            for (k, rec) in out.chunks_exact(EDGE_RECORD_LEN).enumerate() {
                found[idx[k]] = if rec[0] > 1.5 {
                    Edge::Hidden
                } else if rec[0] > 0.5 {
                    Edge::At(Vector2::new(rec[1], rec[2]))
                } else {
                    Edge::None
                };
            }
        }
        Ok(found)
    }

    /// Refine one circle pose on the image's edges; `None` when the opening is not there.
    /// `views`: the images it is refined on (one, or the two of a stereo pair), the axis in the
    /// first one's frame; each must show the opening.
    fn refine(&self, views: &[View<'_>], start: Axis) -> Result<Option<Hypothesis>, VisionError> {
        let mut axis = start;
        let mut matched: Vec<(usize, Vector2<f64>, Part)> = vec![];
        for range in [3.0, 2.0, 1.5] {
            matched.clear();
            for (i, view) in views.iter().enumerate() {
                let samples = self.samples(&view.axis(&axis));
                let found = Self::search(view.eye, &samples, range)?;
                let before = matched.len();
                matched.extend(
                    samples
                        .iter()
                        .zip(&found)
                        .filter_map(|(s, f)| f.at().map(|p| (i, p, s.part)))
                        // The outline's edges decide between the hypotheses; near the rim's
                        // tangent points they lie within a few pixels of the face's edge, so
                        // the fit leaves them out.
                        .filter(|(_, _, part)| matches!(part, Part::Opening | Part::Rim)),
                );
                let n_open = matched[before..].iter().filter(|m| m.2 == Part::Opening).count();
                if n_open < OPENING_POINTS / 3 {
                    return Ok(None);
                }
            }
            axis = self.fit(views, axis, &matched);
        }
        // Grade: the samples of the final pose, found within 1 px of the model.
        let mut counts = [0usize; 4];
        let mut totals = [0usize; 4];
        let mut sq = 0.0;
        let mut n_open = 0;
        for view in views {
            let (at, f) = (view.axis(&axis), view.eye.camera.fx);
            let samples = self.samples(&at);
            let found = Self::search(view.eye, &samples, 1.0)?;
            for (s, p) in samples.iter().zip(&found) {
                if *p == Edge::Hidden {
                    continue;
                }
                let k = match s.part {
                    Part::Opening => 0,
                    Part::Rim => 1,
                    Part::Limb(_) => 2,
                    Part::Bottom => 3,
                };
                totals[k] += 1;
                if let Edge::At(p) = p {
                    let res = self.residual(&at, p, s.part).unwrap_or(f64::INFINITY) * f;
                    if res.abs() <= 1.0 {
                        counts[k] += 1;
                    }
                    if k == 0 && res.is_finite() {
                        sq += res * res;
                        n_open += 1;
                    }
                }
            }
        }
        let frac = |k: usize| counts[k] as f64 / totals[k].max(1) as f64;
        let support = 0.4 * frac(0) + 0.2 * frac(1) + 0.2 * frac(2) + 0.2 * frac(3);
        let rms = if n_open > 0 {
            (sq / n_open as f64).sqrt()
        } else {
            f64::INFINITY
        };
        let z = axis.point.z;
        if !(0.03..=2.0).contains(&z) {
            return Ok(None);
        }
        Ok(Some(Hypothesis {
            axis,
            score: support,
            rms_px: rms,
            support,
            opening_support: frac(0),
        }))
    }

    /// Distance (normalised units) of an edge point to its model part at `axis`.
    fn residual(&self, axis: &Axis, p: &Vector2<f64>, part: Part) -> Option<f64> {
        match part {
            Part::Opening | Part::Rim => {
                let r = if part == Part::Opening {
                    self.model.opening.radius
                } else {
                    self.model.head.radius
                };
                Some(conic_distance(&circle_conic(&axis.point, &axis.direction, r)?, p))
            }
            Part::Bottom => Some(conic_distance(
                &circle_conic(
                    &axis.at(self.model.head.height),
                    &axis.direction,
                    self.model.head.radius,
                )?,
                p,
            )),
            Part::Limb(i) => {
                let h = self.model.head.height;
                let limbs = cylinder_limbs(axis, self.model.head.radius, 0.0, h)?;
                let [a, b] = limbs[i];
                let (pa, pb) = (project(&a)?, project(&b)?);
                let l = Vector3::new(pa.x, pa.y, 1.0).cross(&Vector3::new(pb.x, pb.y, 1.0));
                let norm = (l.x * l.x + l.y * l.y).sqrt();
                (norm > 1e-15).then(|| l.dot(&Vector3::new(p.x, p.y, 1.0)) / norm)
            }
        }
    }

    /// The axis moved by the 5 parameters: centre offset (3) and a tilt of the direction (2).
    fn perturb(axis: &Axis, d: &Vector5<f64>) -> Axis {
        let (u, v) = basis(&axis.direction);
        Axis {
            point: axis.point + Vector3::new(d[0], d[1], d[2]),
            direction: Unit::new_normalize(axis.direction.into_inner() + d[3] * u + d[4] * v),
        }
    }

    /// Robust Levenberg-Marquardt (Cauchy weights, 1 px scale) of the axis (the first view's
    /// frame) on the matched edge points: (view, point, part).
    fn fit(&self, views: &[View<'_>], start: Axis, matched: &[(usize, Vector2<f64>, Part)]) -> Axis {
        let residuals = |a: &Axis| -> Vec<f64> {
            let at: Vec<(Axis, f64)> = views.iter().map(|v| (v.axis(a), v.eye.camera.fx)).collect();
            matched
                .iter()
                .map(|(i, p, part)| self.residual(&at[*i].0, p, *part).map_or(0.0, |r| r * at[*i].1))
                .collect()
        };
        let cost = |r: &[f64]| r.iter().map(|x| (1.0 + x * x).ln()).sum::<f64>();
        let mut axis = start;
        let mut r = residuals(&axis);
        let mut c = cost(&r);
        let mut lambda = 1e-3;
        let steps = [1e-6, 1e-6, 1e-6, 1e-6, 1e-6];
        for _ in 0..10 {
            let cols: Vec<Vec<f64>> = (0..5)
                .map(|j| {
                    let mut d = Vector5::zeros();
                    d[j] = steps[j];
                    let rj = residuals(&Self::perturb(&axis, &d));
                    rj.iter().zip(&r).map(|(a, b)| (a - b) / steps[j]).collect()
                })
                .collect();
            let mut jtj = Matrix5::zeros();
            let mut jtr = Vector5::zeros();
            for (i, ri) in r.iter().enumerate() {
                let w = 1.0 / (1.0 + ri * ri);
                let row = Vector5::from_fn(|j, _| cols[j][i]);
                jtj += w * row * row.transpose();
                jtr += w * *ri * row;
            }
            let mut improved = false;
            for _ in 0..6 {
                let mut a = jtj;
                for j in 0..5 {
                    a[(j, j)] *= 1.0 + lambda;
                    a[(j, j)] += 1e-12;
                }
                let Some(delta) = a.lu().solve(&(-jtr)) else { break };
                let cand = Self::perturb(&axis, &delta);
                let rc = residuals(&cand);
                let cc = cost(&rc);
                if cc < c {
                    axis = cand;
                    r = rc;
                    c = cc;
                    lambda = (lambda * 0.3).max(1e-9);
                    improved = true;
                    break;
                }
                lambda *= 10.0;
            }
            if !improved {
                break;
            }
        }
        axis
    }
}

/// The opening-like ellipses of the image `eye` holds (records of `markerless_ellipses`): a
/// semi-axis of an opening between 0.05 and 1.5 m away, the best six by contrast.
fn ellipses(eye: &mut Eye, model: &TrocarModel) -> Result<Vec<f64>, VisionError> {
    let cam = &eye.camera;
    let f = cam.fx.max(cam.fy);
    let r = model.opening.radius;
    let (lo, hi) = ((cam.fx.min(cam.fy) * r / 1.5).max(3.0), f * r / 0.05);
    Ok(ffi::markerless_ellipses(eye.det.pin_mut(), lo, hi.max(lo), 6)?)
}

/// Which of the left image's hypotheses `hyps` the right image's poses `right` (left frame)
/// agree with, and the margin: for each hypothesis the smallest angle to a right pose of the
/// same opening (its port within 10 mm + 5 % of the distance); the hypothesis within
/// [`STEREO_AGREE_DEG`] of one, by how much more the other disagrees over
/// [`STEREO_MARGIN_DEG`] (1 when the other has no right pose near it). `None`: the right
/// image cannot tell (no right pose of this opening, or none agrees).
/// `right_origin`: the right camera's centre in the left frame. With the choice comes the
/// port centre triangulated from the two eyes ([`triangulate`]).
fn stereo_choice(hyps: &[Hypothesis], right: &[Axis], right_origin: &Vector3<f64>) -> Option<StereoChoice> {
    let disagreement = |h: &Hypothesis| {
        right
            .iter()
            .filter(|r| same_port(&r.point, &h.axis.point))
            .map(|r| (r.direction.angle(&h.axis.direction).to_degrees(), r.point))
            .min_by(|a, b| a.0.total_cmp(&b.0))
    };
    let d: Vec<Option<(f64, Vector3<f64>)>> = hyps.iter().map(disagreement).collect();
    let (best, db, right_point) = d
        .iter()
        .enumerate()
        .filter_map(|(i, x)| x.map(|(a, p)| (i, a, p)))
        .min_by(|a, b| a.1.total_cmp(&b.1))?;
    if db > STEREO_AGREE_DEG {
        return None;
    }
    let other = d
        .iter()
        .enumerate()
        .filter(|(i, _)| *i != best)
        .map(|(_, x)| x.map_or(f64::INFINITY, |x| x.0))
        .fold(f64::INFINITY, f64::min);
    let left_point = hyps[best].axis.point;
    Some(StereoChoice {
        index: best,
        margin: ((other - db) / STEREO_MARGIN_DEG).clamp(0.0, 1.0),
        point: triangulate(&left_point, right_origin, &right_point).unwrap_or(left_point),
    })
}

/// Whether the port estimate `p` is the port `q` (camera frame) as the other image or the
/// other pose sees it: within 10 mm + 5 % of the distance.
fn same_port(p: &Vector3<f64>, q: &Vector3<f64>) -> bool {
    (p - q).norm() <= 0.01 + 0.05 * q.norm()
}

/// Whether some pose of `poses` has its port at `point` ([`same_port`]): the same opening
/// seen in the other image.
fn same_opening(point: &Vector3<f64>, poses: &[Axis]) -> bool {
    poses.iter().any(|a| same_port(&a.point, point))
}

/// The hypothesis the right image agrees with ([`stereo_choice`]).
#[derive(Debug, Clone, Copy)]
struct StereoChoice {
    /// Its index among the left image's hypotheses.
    index: usize,
    /// How much more the other hypothesis disagrees with the right image (0-1).
    margin: f64,
    /// The port centre triangulated from the two eyes (left frame).
    point: Vector3<f64>,
}

/// The port centre seen from the two eyes: the midpoint of the shortest segment between the
/// left camera's ray through its estimate `left` (left frame, from the origin) and the right
/// camera's ray from `right_origin` through its estimate `right` (left frame). Each eye's
/// circle pose puts the centre on its line of sight well (the ellipse's position) but its
/// distance along it from the ellipse's size, where a fraction of a pixel is millimetres;
/// the two lines of sight cross at the centre whatever each distance. `None`: the rays are
/// (near) parallel, or the crossing is not in front of both cameras, or it lies more than
/// 10 mm + 5 % of the distance from `left` (the rays do not meet near the estimates).
pub fn triangulate(left: &Vector3<f64>, right_origin: &Vector3<f64>, right: &Vector3<f64>) -> Option<Vector3<f64>> {
    let (d1, d2) = (left.try_normalize(1e-12)?, (right - right_origin).try_normalize(1e-12)?);
    let w0 = -right_origin;
    let (b, d, e) = (d1.dot(&d2), d1.dot(&w0), d2.dot(&w0));
    let denom = 1.0 - b * b;
    if denom < 1e-6 {
        return None;
    }
    let (t1, t2) = ((b * e - d) / denom, (e - b * d) / denom);
    if t1 <= 0.0 || t2 <= 0.0 {
        return None;
    }
    let p = 0.5 * (t1 * d1 + right_origin + t2 * d2);
    (same_port(&p, left) && p.iter().all(|v| v.is_finite())).then_some(p)
}

/// Grade hypothesis `h` against the other one `o` (if any): edge support x fit x ambiguity
/// margin, the margin by `margin(h, o)` (1 when the two poses were within 3 deg of each other
/// from the start, `harmless`; 0.5 when the other found no opening on refinement: nothing to
/// tell them apart by).
fn grade(
    h: &Hypothesis,
    o: Option<&Hypothesis>,
    harmless: bool,
    margin: impl Fn(&Hypothesis, &Hypothesis) -> f64,
) -> MarkerlessEstimate {
    let margin = match o {
        _ if harmless => 1.0,
        Some(o) => margin(h, o),
        None => 0.5,
    };
    graded(h, margin)
}

/// The estimate of hypothesis `h` with the ambiguity margin `margin`: confidence = edge
/// support x fit x margin.
fn graded(h: &Hypothesis, margin: f64) -> MarkerlessEstimate {
    let fit = 1.0 / (1.0 + (h.rms_px / 0.6).powi(2));
    MarkerlessEstimate {
        axis: h.axis,
        confidence: (h.support * fit * margin).clamp(0.0, 1.0),
        fit_rms_px: h.rms_px,
        edge_support: h.support,
        opening_support: h.opening_support,
        ambiguity_margin: margin,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn two_lines_of_sight_meet_at_the_port_whatever_each_eyes_distance_error() {
        let port = Vector3::new(0.02, -0.01, 0.3);
        let right_origin = Vector3::new(0.063, 0.0, 0.0);
        // Each eye's estimate on its own line of sight, 1 % too deep and 1 % too near (3 mm).
        let left = 1.01 * port;
        let right = right_origin + 0.99 * (port - right_origin);
        let p = triangulate(&left, &right_origin, &right).unwrap();
        assert!((p - port).norm() < 1e-9, "{:?}", p - port);
        // Lines of sight 0.1 mm apart at the port (an image error): the midpoint, within it.
        let skew = right + Vector3::new(0.0, 1e-4, 0.0);
        assert!((triangulate(&left, &right_origin, &skew).unwrap() - port).norm() < 1e-4);
        // Parallel lines of sight, a crossing behind the cameras, or one far from the
        // estimates: none.
        assert!(triangulate(&left, &right_origin, &(right_origin + left)).is_none());
        assert!(triangulate(&left, &right_origin, &(right_origin - 0.5 * (port - right_origin))).is_none());
        let far = right_origin + 0.9 * (Vector3::new(0.05, -0.01, 0.3) - right_origin);
        assert!(triangulate(&left, &right_origin, &far).is_none());
        assert!(triangulate(&Vector3::zeros(), &right_origin, &right).is_none());
    }

    #[test]
    fn both_outline_lines_move_by_their_own_edges_unless_one_is_not_the_outline() {
        // A shaft 17 px wide at its tip end, 38 px at the other (fx 700, radius 2.5 mm): the
        // width may change by ~1 px at the tip end, ~3 px at the other.
        let px = 1.0 / 700.0;
        let line = |x: f64, spread: f64| OutlineLine {
            from: Vector2::new(x, 0.1),
            to: Vector2::new(x * spread, -0.4),
            normal: Vector2::new(1.0, 0.0),
        };
        let lines = [line(-8.5 * px, 19.0 / 8.5), line(8.5 * px, 19.0 / 8.5)];
        // 16 samples' edges at `d(t, k)` px along the normal.
        let edges = |d: &dyn Fn(f64, usize) -> f64| -> Vec<(f64, f64)> {
            (0..16)
                .map(|k| {
                    let t = (k as f64 + 0.5) / 32.0;
                    (t, d(t, k) * px)
                })
                .collect()
        };
        let none: Vec<(f64, f64)> = vec![];
        let fit = |e0: &[(f64, f64)], e1: &[(f64, f64)], joint: (f64, f64)| {
            limbs_fitted(
                &lines,
                [[e0, &none], [&none, e1]],
                (joint.0 * px, joint.1 * px),
                [16, 16],
                0.0025,
                px,
            )
        };
        let offset = |l: &[Vector2<f64>; 2], k: usize| (l[0].x - lines[k].from.x) / px;
        // The shaft moved by 2 px and 0.4 px wider (in depth): each line by its own edges.
        let (e0, e1) = (edges(&|_, _| 1.8), edges(&|_, _| 2.2));
        let m = fit(&e0, &e1, (2.0, 0.0)).unwrap();
        assert!((offset(&m[0], 0) - 1.8).abs() < 1e-6 && (offset(&m[1], 1) - 2.2).abs() < 1e-6);
        // One line's edges 2 px inside it and scattered (a lit side as light as the
        // background): both lines move by the other, tight one.
        let scattered = edges(&|_, k| 1.2 + 0.15 * (k % 5) as f64 + 0.1 * (k % 3) as f64);
        let tight = edges(&|_, k| 0.05 * (k % 2) as f64);
        let m = fit(&tight, &scattered, (0.5, 0.0)).unwrap();
        assert!(offset(&m[0], 0).abs() < 0.1 && offset(&m[1], 1).abs() < 0.1, "{m:?}");
        // A line with edges at under a third of its samples: nothing, whatever the other.
        let few: Vec<(f64, f64)> = tight[..4].to_vec();
        assert!(fit(&few, &tight, (0.0, 0.0)).is_none());
        assert!(fit(&tight, &few, (0.0, 0.0)).is_none());
        // Edges far from the joint fit are not the line's.
        assert!(fit(&edges(&|_, _| 9.0), &tight, (0.0, 0.0)).is_none());
    }
}
