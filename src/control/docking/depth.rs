//! The tip's depth along the insertion axis: refined where the shaft meets the cannula's
//! seal, and how well it is known, so that DONE is reported only when the depth is.
//!
//! **Why.** The trocar estimate comes through the hand-eye calibration, whose error moves the
//! estimated port, and so the goal, along the axis by up to `hand_eye_error_m` plus
//! `camera_lever_m` times `hand_eye_error_deg` (2 mm + 0.3 m x 1 deg = 7.2 mm as shipped).
//! Across the axis the port itself guides the shaft; along it nothing does, and a DONE judged
//! on the estimate alone can be millimetres short or deep.
//!
//! **The seal's onset** (docs/controller.md, Depth at the seal). A cannula's seal grips the
//! shaft once the tip passes it, at the trocar's seal depth `seal_depth_m` below the port.
//! Until the lip breaks away it sticks to the shaft (a stiff pre-sliding spring: the
//! reset-integrator friction model, Haessig & Friedland 1991), so for that while the tip
//! stays at the seal's depth in the trocar, whatever the trocar does; after it, kinetic
//! friction (1.5 N and more) resists the insertion for as long as the shaft slides. The
//! controller takes as the onset a rise of the axial force resisting the insertion by
//! `onset_force_n` over its level before (following a fall at once, a rise with a 0.2 s
//! low-pass), at least twice the rise of the force across the axis (the seal acts along the
//! axis; the funnel's and the bore's contact before it push across it as much or more), that
//! then holds
//! for `confirm_s` (the bore's contact rises and falls again), dated back by the force
//! estimate's lag (the torques' and the estimate's low-pass time constants: a first-order
//! chain delays a ramp by the sum of its time constants). The stick window, `stick_window_s`
//! after the onset, then measures the estimate's error along the axis at the control rate:
//! at each step within it the tip's depth on the raw trocar pose of that instant,
//! interpolated between the poses captured around it (by capture stamp: the camera's latency
//! and the filter play no part, and any pose rate with a pose on each side of the window
//! serves), less the seal's depth and half the lip's travel `seal_lip_travel_m` (the lip
//! deflects with the shaft from nothing to its breakaway while it sticks). Their mean d moves
//! the goal to `insertion_depth_m` + d on the estimated axis. A d larger than the calibration's
//! bound and the pose source's own error along the axis (`pose_axial_error_m`) is not
//! something they explain (another trocar, a seal at another depth, a force that was not the
//! seal): it is refused and named, and the goal stays.
//!
//! **The uncertainty** (a bound of about two standard deviations), root sum of squares of:
//! - before a refinement: the calibration's bound (above);
//! - after one: the seal's own term `seal_uncertainty_m` (the lip's travel while it sticks,
//!   the onset's dating), the raw poses' noise in the window's mean (2 sigma times the root
//!   of the sum of the squares of each pose's share), and the hand-eye's rotation error times the tip's travel since (the camera moves
//!   with the arm, so the error the refinement removed drifts by that much);
//! - always: the estimate's noise along the axis now, 2 sigma of the filtered estimate: the
//!   poses' sigma from each pose's distance to the line through its neighbours
//!   ([`DepthEstimate::observe_pose`]), times the root of the share V of white noise's
//!   variance the controller's filter keeps ([`AxisFilter::noise_gains`]).
//!
//! DONE needs it, plus the tip's distance from the goal depth on the estimate of that
//! instant, within `tolerance_m`; the gate judges on for `gate_wait_s` from its first
//! failure, then the controller holds, DEPTH_UNCERTAIN, with the figure and its basis.
//! Nothing allocates: the histories are fixed arrays.

use std::fmt;

use nalgebra::{Point3, Vector2, Vector3};
use serde::{Deserialize, Serialize};

use super::geometry::InsertionAxis;
use crate::signal::{exp_smoothing, rc_weight};
use crate::validate;

/// Parameters (`depth:` in `config/controller.yaml`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(remote = "Self", deny_unknown_fields)]
pub struct DepthParams {
    /// The trocar's seal below the port's top face along the axis, m (0: no seal, no
    /// refinement).
    pub seal_depth_m: f64,
    /// How far the seal's lip travels with the shaft before it breaks away, m: while it
    /// sticks the tip is this much deeper than the seal at most, half of it on average.
    pub seal_lip_travel_m: f64,
    /// The rise of the axial force over its level before that marks the seal's onset, N.
    pub onset_force_n: f64,
    /// How long the rise must hold to be the seal's, s.
    pub confirm_s: f64,
    /// The trocar poses captured this long after the onset measure the depth, s (the lip
    /// sticks to the shaft for about that long).
    pub stick_window_s: f64,
    /// The seal's own uncertainty, m (2 sigma).
    pub seal_uncertainty_m: f64,
    /// The hand-eye calibration's translation error bound, m.
    pub hand_eye_error_m: f64,
    /// ... and its rotation error bound, deg.
    pub hand_eye_error_deg: f64,
    /// The camera's distance to the port while docking, m: the lever of the rotation error.
    pub camera_lever_m: f64,
    /// The trocar pose source's own error along the axis, m (2 sigma of one pose, beyond the
    /// hand-eye's): what a seal met off the estimate may owe to the pose itself.
    pub pose_axial_error_m: f64,
    /// DONE only while the depth's uncertainty is within this, m.
    pub tolerance_m: f64,
    /// At the goal with the depth's figure over the tolerance, how long the gate goes on
    /// judging each step before it holds, s (0: hold at once). The figure holds the tip's
    /// distance from the goal on the estimate of that instant, which each new pose moves
    /// (the tip trails a breathing port by up to ~1 mm right after a pose).
    pub gate_wait_s: f64,
}

crate::shipped_defaults!(DepthParams, crate::config::CONTROLLER, ["depth"]);

impl DepthParams {
    /// Check ranges; the error names the field.
    pub fn validate(&self) -> Result<(), String> {
        validate::non_negative("depth.seal_depth_m", self.seal_depth_m)?;
        validate::non_negative("depth.seal_lip_travel_m", self.seal_lip_travel_m)?;
        validate::positive("depth.onset_force_n", self.onset_force_n)?;
        validate::positive_at_most("depth.stick_window_s", self.stick_window_s, 1.0)?;
        if !(self.confirm_s.is_finite() && self.confirm_s >= self.stick_window_s && self.confirm_s <= 2.0) {
            return Err(format!(
                "depth.confirm_s ({}) must be within depth.stick_window_s ({}) and 2 s",
                self.confirm_s, self.stick_window_s
            ));
        }
        validate::non_negative("depth.seal_uncertainty_m", self.seal_uncertainty_m)?;
        validate::non_negative("depth.hand_eye_error_m", self.hand_eye_error_m)?;
        validate::in_range("depth.hand_eye_error_deg", self.hand_eye_error_deg, 0.0, 45.0)?;
        validate::non_negative("depth.camera_lever_m", self.camera_lever_m)?;
        validate::non_negative("depth.pose_axial_error_m", self.pose_axial_error_m)?;
        validate::positive("depth.tolerance_m", self.tolerance_m)?;
        validate::in_range("depth.gate_wait_s", self.gate_wait_s, 0.0, 5.0)?;
        Ok(())
    }

    /// The calibration's bound on the estimate's error along the axis, m.
    pub fn calibration_bound(&self) -> f64 {
        self.hand_eye_error_m + self.camera_lever_m * self.hand_eye_error_deg.to_radians()
    }

    /// The bound on a seal's distance from where the estimate puts it, m: the calibration's
    /// bound and the pose source's own error along the axis; a seal met farther off is
    /// refused.
    pub fn refusal_bound(&self) -> f64 {
        self.calibration_bound() + self.pose_axial_error_m
    }
}

/// What the depth rests on.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum DepthBasis {
    /// The trocar estimate alone (the seal not met yet, or not felt).
    Estimate,
    /// The trocar estimate alone: the trocar has no seal (`seal_depth_m` 0), nothing along
    /// the axis to refine it.
    NoSeal,
    /// Refined at the seal: the estimate put the tip `correction` m deeper than it was.
    Seal {
        /// The goal's shift along the estimated axis, m.
        correction: f64,
    },
    /// The seal was met `correction` m from where the estimate put it, more than the
    /// calibration's `bound` explains: refused, the estimate alone.
    Refused {
        /// The refused shift, m.
        correction: f64,
        /// The bound ([`DepthParams::refusal_bound`]), m.
        bound: f64,
    },
}

impl DepthBasis {
    /// A stable code for the status and tools: `ESTIMATE`, `NO_SEAL`, `SEAL`, `REFUSED`.
    pub fn code(&self) -> &'static str {
        match self {
            DepthBasis::Estimate => "ESTIMATE",
            DepthBasis::NoSeal => "NO_SEAL",
            DepthBasis::Seal { .. } => "SEAL",
            DepthBasis::Refused { .. } => "REFUSED",
        }
    }
}

impl fmt::Display for DepthBasis {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            DepthBasis::Estimate => write!(f, "the seal was not felt: the depth rests on the trocar estimate"),
            DepthBasis::NoSeal => write!(
                f,
                "the trocar has no seal to feel (depth.seal_depth_m 0): the depth rests on the trocar estimate"
            ),
            DepthBasis::Seal { correction } => write!(f, "refined at the seal by {:+.1} mm", correction * 1e3),
            DepthBasis::Refused { correction, bound } => write!(
                f,
                "the seal was felt {:+.1} mm from where the trocar estimate puts it, more than the hand-eye calibration's and the pose's own error along the axis ({:.1} mm) explain: refused (check the calibration and the trocar's seal depth)",
                correction * 1e3,
                bound * 1e3
            ),
        }
    }
}

/// The time constant of the force's level before the onset as it rises, s: long against the
/// seal's rise (tens of milliseconds), short against the force estimate's drift as the arm
/// moves; it follows a fall at once.
const LEVEL_TIME_CONSTANT_S: f64 = 0.2;

/// The seal's force is along the axis: its rise is at least this many times the rise of the
/// force across it (in the realistic world the force along is 3-6 times the force across at
/// the seal, at most 1.6 times at the funnel's and the bore's contact before it, seeds 11 and
/// 103; a cone's or a cylinder's wall pushes across the axis at least as much as along it,
/// friction at 0.3 of that). Rises, not levels: a scope pressed steadily against the bore
/// (without force feedback) still shows the seal's rise.
const SEAL_AXIAL_RATIO: f64 = 2.0;

/// How many tip positions the history keeps, at least [`TIP_SPACING_S`] apart: 2.56 s at
/// any control rate, more than the onset's `confirm_s` (2 s at most) and the stick window
/// after it, so that every pose of the window still finds the tip at its capture stamp.
const TIP_CAPACITY: usize = 1024;

/// The smallest interval between two positions of the tip history, s.
const TIP_SPACING_S: f64 = 0.0025;

/// How long the tip history spans at the least, s: a confirmed onset waits this long at most
/// for the estimates that span its stick window.
const TIP_HISTORY_S: f64 = TIP_CAPACITY as f64 * TIP_SPACING_S;

/// How many raw trocar poses are kept, at least [`POSE_SPACING_S`] apart: 2.56 s at any
/// pose rate (more at a camera's 15-100 Hz), so that the poses of the stick window are still
/// there when the onset is confirmed `confirm_s` (2 s at most) after it, however fast the
/// poses come (a stream of 1 kHz kept 32 ms of them and lost the window).
const POSE_CAPACITY: usize = 512;

/// The smallest interval between two poses of the history, s (200 Hz: every pose of a
/// camera at up to 100 Hz, with its jitter); every pose still counts in the noise.
const POSE_SPACING_S: f64 = 0.005;

/// How many poses the noise's running mean square weighs (about 2 s at 15 Hz).
const NOISE_WINDOW: u32 = 30;

/// A fixed-capacity ring of samples, oldest first; a push into a full one overwrites the
/// oldest (nothing moves, nothing allocates).
#[derive(Debug, Clone, PartialEq)]
struct History<T: Copy + Default, const N: usize> {
    items: [T; N],
    /// Where the oldest is.
    start: usize,
    len: usize,
}

impl<T: Copy + Default, const N: usize> Default for History<T, N> {
    fn default() -> Self {
        Self {
            items: [T::default(); N],
            start: 0,
            len: 0,
        }
    }
}

impl<T: Copy + Default, const N: usize> History<T, N> {
    fn push(&mut self, x: T) {
        if self.len == N {
            self.items[self.start] = x;
            self.start = (self.start + 1) % N;
        } else {
            self.items[(self.start + self.len) % N] = x;
            self.len += 1;
        }
    }

    /// The `k`-th oldest.
    fn get(&self, k: usize) -> Option<T> {
        (k < self.len).then(|| self.items[(self.start + k) % N])
    }

    fn last(&self) -> Option<T> {
        self.len.checked_sub(1).and_then(|k| self.get(k))
    }

    fn iter(&self) -> impl Iterator<Item = T> + '_ {
        (0..self.len).map(move |k| self.items[(self.start + k) % N])
    }
}

/// A trocar pose: its capture stamp, its raw port, the filtered estimate's unit axis then.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
struct Pose {
    stamp: f64,
    port: Point3<f64>,
    direction: Vector3<f64>,
}

/// A rise of the force that may be the seal's onset.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Candidate {
    /// The onset, dated back by the force estimate's lag, s.
    t_on: f64,
    /// The force's level before it, along and across the axis, N.
    level: Vector2<f64>,
    /// The tip's depth on the estimated axis then, m.
    depth: f64,
    /// Held for `confirm_s`: the seal's, waiting for the estimates that span its stick window.
    confirmed: bool,
}

/// The depth's state over one docking run (`Default`: a new run).
#[derive(Debug, Clone, PartialEq)]
pub struct DepthEstimate {
    tips: History<(f64, Point3<f64>), TIP_CAPACITY>,
    poses: History<Pose, POSE_CAPACITY>,
    /// The force's level along and across the axis (None: not in the seal's depth range), N.
    level: Option<Vector2<f64>>,
    candidate: Option<Candidate>,
    /// The search is over (refined, refused, or past the seal).
    over: bool,
    basis: DepthBasis,
    /// The tip's depth on the estimated axis at the onset (for the drift since), m.
    onset_depth: f64,
    /// 2 sigma of the noise in the stick window's mean of raw poses, m.
    onset_noise: f64,
    /// The raw poses' variance along the axis, m²: a running mean over [`NOISE_WINDOW`]
    /// poses ([`DepthEstimate::observe_pose`]).
    pose_var: f64,
    /// How many poses it holds (its weight grows to a window's worth).
    noise_poses: u32,
    /// Mean interval between the poses, s.
    pose_period: f64,
    /// The newest pose's capture stamp and raw port, s and m (kept in the history or not),
    /// and the one before.
    last_pose: Option<(f64, Point3<f64>)>,
    before_last: Option<(f64, Point3<f64>)>,
}

impl Default for DepthEstimate {
    fn default() -> Self {
        Self {
            tips: History::default(),
            poses: History::default(),
            level: None,
            candidate: None,
            over: false,
            basis: DepthBasis::Estimate,
            onset_depth: f64::NAN,
            onset_noise: 0.0,
            pose_var: 0.0,
            noise_poses: 0,
            pose_period: 0.0,
            last_pose: None,
            before_last: None,
        }
    }
}

/// The controller's filters the depth depends on.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Filters {
    /// The force estimate's lag behind the force, s.
    pub force_lag: f64,
    /// The trocar filter along the axis.
    pub axis: AxisFilter,
}

/// The controller's filter of the trocar estimate along the axis: what share of the poses'
/// white noise the filtered estimate keeps (docs/controller.md, Depth at the seal).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum AxisFilter {
    /// Unfiltered: the estimate is the newest pose.
    None,
    /// The first-order filter of time constant tau s, weight T / (tau + T) per pose T s
    /// after the last ([`crate::signal::rc_weight`]: the controller's trocar filter).
    FirstOrder(f64),
    /// The second-order tracking filter of time constant tau s
    /// ([`crate::signal::TrackingFilter`]).
    Tracking(f64),
}

impl AxisFilter {
    /// For white noise on poses every `period` s, in the steady state: the weight g of the
    /// newest pose in the filtered estimate and the share V of the noise's variance the
    /// filtered estimate keeps. A linear filter fed z_k = x + n_k leaves the estimate's
    /// error a sum of w_j n_(k-j): V = sum w_j^2, g = w_0.
    /// - First order, a = T / (tau + T): w_j = a (1 - a)^j, V = a / (2 - a).
    /// - Tracking (the critically damped g-h filter, theta = exp(-T / tau), g = 1 - theta^2,
    ///   h = (1 - theta)^2): the steady state of the filter's error covariance (the
    ///   discrete Lyapunov equation of its error recursion) gives
    ///   V = (2g^2 + 2h - 3gh) / (g (4 - 2g - h)) = (1 - theta)(1 + 4 theta + 5 theta^2) / (1 + theta)^3
    ///   (0.36 at 15 Hz and tau 0.2 s, where T / (2 tau) is 0.17).
    /// - None: g = V = 1.
    pub fn noise_gains(self, period: f64) -> (f64, f64) {
        match self {
            AxisFilter::FirstOrder(tau) if tau > 0.0 && period > 0.0 => {
                let a = rc_weight(period, tau);
                (a, a / (2.0 - a))
            }
            AxisFilter::Tracking(tau) if tau > 0.0 && period > 0.0 => {
                let th = (-period / tau).exp();
                let v = (1.0 - th) * (1.0 + 4.0 * th + 5.0 * th * th) / (1.0 + th).powi(3);
                (1.0 - th * th, v)
            }
            _ => (1.0, 1.0),
        }
    }
}

/// The depth's report: what the status carries.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DepthReport {
    /// The goal's shift along the estimated axis, m (0 unless refined).
    pub correction: f64,
    /// The depth's uncertainty, m (about 2 sigma); in the report at the goal, plus the tip's
    /// distance from the goal depth on the estimate (the DONE gate's figure).
    pub uncertainty: f64,
    /// What it rests on.
    pub basis: DepthBasis,
}

impl DepthEstimate {
    /// The goal's shift along the estimated axis, m (0 unless refined at the seal).
    pub fn correction(&self) -> f64 {
        match self.basis {
            DepthBasis::Seal { correction } => correction,
            _ => 0.0,
        }
    }

    /// What the depth rests on.
    pub fn basis(&self) -> DepthBasis {
        self.basis
    }

    /// A new trocar pose captured at `stamp`: its raw port `raw`, and the unit axis
    /// `direction` of the filtered estimate after it. A pose no newer than the last is
    /// ignored; one less than [`POSE_SPACING_S`] after the last kept one counts in the noise
    /// only.
    ///
    /// The noise: each pose's distance along the axis from the line through its two
    /// neighbours, r = z1 - ((1 - w) z0 + w z2), w = (t1 - t0) / (t2 - t0), holds
    /// (1 + w^2 + (1 - w)^2) sigma^2 of white noise (3/2 at a steady rate), and of the
    /// port's own motion only its curvature: a 4 mm breathing at 0.3 Hz, poses at 15 Hz,
    /// 0.03 mm. (The distance from the filtered estimate holds the filter's lag behind the
    /// breathing too: up to ~0.5 mm with the tracking filter's tau of 0.2 s.)
    pub fn observe_pose(&mut self, raw: &Point3<f64>, direction: &Vector3<f64>, stamp: f64) {
        let last = self.last_pose;
        let finite = stamp.is_finite() && raw.iter().chain(direction.iter()).all(|x| x.is_finite());
        if last.is_some_and(|(t, _)| stamp <= t) || !finite {
            return;
        }
        if let (Some((t0, z0)), Some((t1, z1))) = (self.before_last, last) {
            let w = (t1 - t0) / (stamp - t0);
            let r = (z1 - (z0 + (raw - z0) * w)).dot(direction);
            let var = r * r / (1.0 + w * w + (1.0 - w) * (1.0 - w));
            self.noise_poses = (self.noise_poses + 1).min(NOISE_WINDOW);
            self.pose_var += (var - self.pose_var) / f64::from(self.noise_poses);
        }
        if let Some((t, _)) = last {
            let gap = stamp - t;
            self.pose_period = if self.pose_period > 0.0 {
                self.pose_period + (gap - self.pose_period) / f64::from(NOISE_WINDOW)
            } else {
                gap
            };
        }
        self.before_last = last;
        self.last_pose = Some((stamp, *raw));
        if self.poses.last().is_none_or(|p| stamp >= p.stamp + POSE_SPACING_S) {
            self.poses.push(Pose {
                stamp,
                port: *raw,
                direction: *direction,
            });
        }
    }

    /// 2 sigma of the estimate along the axis through `filter`, m: V of the poses' variance
    /// ([`AxisFilter::noise_gains`]).
    pub fn noise(&self, filter: AxisFilter) -> f64 {
        let (_, v) = filter.noise_gains(self.pose_period);
        2.0 * (self.pose_var * v).sqrt()
    }

    /// One INSERT step at time `now` (the clock of the poses' stamps): the estimated `axis`,
    /// the measured `tip`, the force estimate on the tip `f` (N, base frame).
    pub fn update(
        &mut self,
        p: &DepthParams,
        axis: &InsertionAxis,
        tip: &Point3<f64>,
        f: &Vector3<f64>,
        now: f64,
        filters: Filters,
    ) {
        if self.tips.last().is_none_or(|(t, _)| now >= t + TIP_SPACING_S) {
            self.tips.push((now, *tip));
        }
        // The force resisting the insertion, and the force across the axis.
        let force = Vector2::new(-f.dot(&axis.direction), axis.across(f).norm());
        if p.seal_depth_m <= 0.0 {
            self.basis = DepthBasis::NoSeal;
            self.over = true;
        }
        if let Some(c) = self.candidate.filter(|c| c.confirmed) {
            self.measure(p, &c, now);
            return;
        }
        if self.over || !force.iter().all(|x| x.is_finite()) || !axis.is_finite() {
            return;
        }
        // Whether a rise over `level` is the seal's: along the axis, where a funnel's or a
        // bore's contact pushes across it as much or more.
        let rise = |level: Vector2<f64>| {
            let r = force - level;
            r.x >= p.onset_force_n && r.x >= SEAL_AXIAL_RATIO * r.y.max(0.0)
        };
        let depth = axis.depth_of(tip);
        // Twice the bound: a seal met farther off than the bound is still seen, and refused
        // by name.
        let reach = 2.0 * p.refusal_bound() + p.seal_uncertainty_m;
        if let Some(c) = self.candidate {
            if !rise(c.level) {
                // It fell back, or grew across the axis: not the seal (the bore's contact); the
                // level goes on from before.
                self.candidate = None;
                self.level = Some(c.level);
            } else if now - c.t_on >= p.confirm_s {
                let c = Candidate { confirmed: true, ..c };
                self.candidate = Some(c);
                self.measure(p, &c, now);
            }
            return;
        }
        if depth > p.seal_depth_m + reach {
            // Past every depth the seal could be at: no refinement.
            self.over = true;
            return;
        }
        if depth < p.seal_depth_m - reach {
            self.level = None;
            return;
        }
        match self.level {
            Some(level) if rise(level) => {
                self.candidate = Some(Candidate {
                    t_on: now - filters.force_lag,
                    level,
                    depth,
                    confirmed: false,
                });
            }
            Some(level) => {
                // Down at once, up slowly: a contact before the seal that lets go leaves the
                // level where the force fell to.
                let dt = self
                    .tips
                    .len
                    .checked_sub(2)
                    .and_then(|k| self.tips.get(k))
                    .map_or(0.0, |(t, _)| now - t);
                let up = level + (force - level) * exp_smoothing(dt, LEVEL_TIME_CONSTANT_S);
                self.level = Some(up.inf(&force));
            }
            None => self.level = Some(force),
        }
    }

    /// The seal's onset `c` confirmed: measured once the estimates span its stick window
    /// ([`DepthEstimate::refine`]), while the tip history still holds it. An onset refused
    /// as felt shallower than the seal could be is a contact on the way in (the funnel or the
    /// bore, pressed along the axis): the search goes on deeper, where the seal still is, and
    /// the basis stays refused until a seal within the bound replaces it.
    fn measure(&mut self, p: &DepthParams, c: &Candidate, now: f64) {
        if self.refine(p, c) {
            self.candidate = None;
            if matches!(self.basis, DepthBasis::Refused { correction, .. } if correction < 0.0) {
                self.level = None;
            } else {
                self.over = true;
            }
        } else if now - c.t_on >= TIP_HISTORY_S {
            self.over = true;
            self.candidate = None;
        }
    }

    /// The poses captured around `t`: their places in the history and `t`'s weight between
    /// them (None outside the history; at a pose's own stamp that one twice).
    fn poses_around(&self, t: f64) -> Option<(usize, usize, f64)> {
        let h = &self.poses;
        let kb = h.iter().position(|q| q.stamp >= t)?;
        let tb = h.get(kb)?.stamp;
        if tb == t {
            return Some((kb, kb, 0.0));
        }
        let ka = kb.checked_sub(1)?;
        let ta = h.get(ka)?.stamp;
        Some((ka, kb, (t - ta) / (tb - ta)))
    }

    /// The basis from the seal's stick window after the onset `c`: at every control step
    /// within it the tip's depth on the trocar pose of that instant, interpolated between
    /// the raw poses captured around it (the camera's latency plays no part, the filter's
    /// lag neither, and the pose rate only needs a pose on each side of the window; the
    /// port's motion between two poses at 15 Hz, a 4 mm breathing at 0.3 Hz, bends away from
    /// the line by 0.01 mm); their mean less `seal_depth_m` and half the lip's travel is the
    /// estimate's error d along the axis. False while the newest pose is older than the
    /// window's end (the camera's latency): then it waits.
    fn refine(&mut self, p: &DepthParams, c: &Candidate) -> bool {
        let end = c.t_on + p.stick_window_s;
        if self.poses.last().is_none_or(|q| q.stamp < end) {
            return false;
        }
        // Each pose's share of the mean (the mean's noise: sigma^2 times their sum of squares).
        let mut share = [0.0; POSE_CAPACITY];
        let (mut sum, mut n) = (0.0, 0u32);
        for (t, tip) in self.tips.iter() {
            if t < c.t_on || t > end {
                continue;
            }
            let Some((ka, kb, w)) = self.poses_around(t) else {
                continue;
            };
            let (Some(a), Some(b)) = (self.poses.get(ka), self.poses.get(kb)) else {
                continue;
            };
            let port = a.port + (b.port - a.port) * w;
            let direction = a.direction.lerp(&b.direction, w).normalize();
            sum += (tip - port).dot(&direction);
            n += 1;
            share[ka] += 1.0 - w;
            share[kb] += w;
        }
        if n == 0 {
            return true;
        }
        let n = f64::from(n);
        let correction = sum / n - p.seal_depth_m - 0.5 * p.seal_lip_travel_m;
        let bound = p.refusal_bound();
        self.basis = if correction.abs() <= bound {
            DepthBasis::Seal { correction }
        } else {
            DepthBasis::Refused { correction, bound }
        };
        self.onset_depth = c.depth;
        let squares: f64 = share.iter().map(|c| (c / n) * (c / n)).sum();
        self.onset_noise = 2.0 * (self.pose_var * squares).sqrt();
        true
    }

    /// The depth's uncertainty now, m, with the tip at `depth` on the estimated axis and the
    /// trocar `filter` along the axis.
    pub fn report(&self, p: &DepthParams, depth: f64, filter: AxisFilter) -> DepthReport {
        let now = self.noise(filter);
        let rss = |a: f64, b: f64, c: f64, d: f64| (a * a + b * b + c * c + d * d).sqrt();
        let uncertainty = match self.basis {
            DepthBasis::Seal { .. } => {
                let drift = p.hand_eye_error_deg.to_radians() * (depth - self.onset_depth).abs();
                rss(p.seal_uncertainty_m, self.onset_noise, drift, now)
            }
            DepthBasis::Estimate | DepthBasis::NoSeal | DepthBasis::Refused { .. } => rss(
                p.hand_eye_error_m,
                p.camera_lever_m * p.hand_eye_error_deg.to_radians(),
                now,
                0.0,
            ),
        };
        DepthReport {
            correction: self.correction(),
            uncertainty: if uncertainty.is_finite() {
                uncertainty
            } else {
                f64::INFINITY
            },
            basis: self.basis,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::signal::TrackingFilter;
    use nalgebra::{Isometry3, Translation3, UnitQuaternion};
    use rand::{RngExt, SeedableRng};
    use rand_distr::StandardNormal;

    /// The estimated axis: the port at `e` along +z (the estimate `e` deeper than the truth,
    /// whose port is at the origin).
    fn axis(e: f64) -> InsertionAxis {
        InsertionAxis::from_pose(&Isometry3::from_parts(
            Translation3::new(0.0, 0.0, e),
            UnitQuaternion::identity(),
        ))
    }

    /// What touches the shaft before the seal.
    #[derive(Debug, Clone, Copy, PartialEq)]
    enum Bump {
        None,
        /// The funnel, 6 to 9 mm deep: 1.5 N along the axis and 1.2 N across (not the seal's
        /// signature).
        Funnel,
        /// A contact pressed along the axis alone, 2 to 10 mm deep (2 N, a seal's signature,
        /// 13 mm shallower than the seal).
        Axial,
    }

    const FILTERS: Filters = Filters {
        force_lag: 0.013,
        axis: AxisFilter::Tracking(0.2),
    };

    /// A docking along z at 30 mm/s from 5 mm before the port, 100 Hz, with trocar poses at
    /// 15 Hz (captured 40 ms before they arrive, `e` too deep, with white noise of sigma
    /// `noise` along the axis, filtered by the controller's tracking filter): the tip sticks
    /// in the seal for 0.1 s (2 N along the axis), then slides against 1.5 N; `bump` touches
    /// it on the way in. Returns the estimate when the tip is 30 mm past the estimated port
    /// (and 25 mm past the true one).
    fn dock(p: &DepthParams, e: f64, noise: f64, seal: bool, bump: Bump) -> DepthEstimate {
        dock_at(p, e, (noise, 5), (seal, bump), (15.0, 0.04))
    }

    /// [`dock`] with the poses at `hz`, each arriving `latency` s after its capture, the
    /// noise drawn from `seed`.
    fn dock_at(
        p: &DepthParams,
        e: f64,
        (noise, seed): (f64, u64),
        (seal, bump): (bool, Bump),
        (hz, latency): (f64, f64),
    ) -> DepthEstimate {
        let mut d = DepthEstimate::default();
        let (dt, v) = (0.01, 0.03);
        let (mut z, mut stuck_until, mut frame) = (-0.005, None::<f64>, 0u32);
        let mut captured: Vec<(f64, f64)> = vec![];
        let a = axis(e);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        for k in 0..3000 {
            let t = k as f64 * dt;
            // The seal grips at its depth (plus half the lip's travel while it sticks).
            if seal && stuck_until.is_none() && z >= p.seal_depth_m {
                stuck_until = Some(t + 0.1);
            }
            let sticking = stuck_until.is_some_and(|u| t < u);
            if !sticking {
                z += v * dt;
            }
            let tip = Point3::new(
                0.0,
                0.0,
                if sticking {
                    p.seal_depth_m + 0.5 * p.seal_lip_travel_m
                } else {
                    z
                },
            );
            // Poses: captured every 1 / hz s (within the step), delivered `latency` s later.
            while f64::from(frame) / hz < t + dt - 1e-9 {
                let stamp = f64::from(frame) / hz;
                captured.push((stamp, noise * rng.sample::<f64, _>(StandardNormal)));
                frame += 1;
            }
            while let Some(&(stamp, n)) = captured.first().filter(|(s, _)| *s + latency <= t + 1e-9) {
                captured.remove(0);
                d.observe_pose(&Point3::new(0.0, 0.0, e + n), &Vector3::z(), stamp);
            }
            let f = match (seal && stuck_until.is_some(), sticking) {
                (true, true) => Vector3::new(0.0, 0.0, -2.0),
                (true, false) => Vector3::new(0.0, 0.0, -1.5),
                _ if bump == Bump::Funnel && (0.006..0.009).contains(&z) => Vector3::new(1.2, 0.0, -1.5),
                _ if bump == Bump::Axial && (0.002..0.010).contains(&z) => Vector3::new(0.0, 0.0, -2.0),
                _ => Vector3::new(0.05, 0.0, -0.05),
            };
            d.update(p, &a, &tip, &f, t, FILTERS);
            if a.depth_of(&tip) >= 0.03 + d.correction() && z >= 0.025 {
                break;
            }
        }
        d
    }

    #[test]
    fn the_seal_measures_the_estimate_s_error_along_the_axis() {
        let p = DepthParams::default();
        for e in [-0.004, -0.0015, 0.0, 0.002, 0.005] {
            let d = dock(&p, e, 0.0, true, Bump::Funnel);
            match d.basis() {
                // The estimate `e` too deep puts the tip `e` shallower: the goal moves by -e.
                DepthBasis::Seal { correction } => assert!((correction + e).abs() < 2e-4, "{e}: {correction}"),
                b => panic!("{e}: {b:?}"),
            }
            let r = d.report(&p, 0.03, FILTERS.axis);
            assert!(
                r.uncertainty < p.tolerance_m && r.uncertainty >= p.seal_uncertainty_m,
                "{r:?}"
            );
        }
        // Pose noise of sigma 0.5 mm, ten draws: the uncertainty counts it (about 1.4 mm
        // against 1.04 mm without), and the refined depth is within it.
        let quiet = dock(&p, 0.002, 0.0, true, Bump::None)
            .report(&p, 0.03, FILTERS.axis)
            .uncertainty;
        let mut over = 0;
        for seed in 1..=10 {
            let d = dock_at(&p, 0.002, (0.0005, seed), (true, Bump::None), (15.0, 0.04));
            let noisy = d.report(&p, 0.03, FILTERS.axis).uncertainty;
            let err = (d.correction() + 0.002).abs();
            assert!(err < noisy, "seed {seed}: {err} {noisy}");
            over += usize::from(noisy > quiet + 2e-4);
        }
        assert!(over >= 8, "{over} of 10");
    }

    #[test]
    fn no_seal_leaves_the_calibration_s_uncertainty_and_a_far_seal_is_refused() {
        let p = DepthParams::default();
        // No seal, the funnel's bump only (across the axis: not a seal).
        let d = dock(&p, 0.002, 0.0, false, Bump::Funnel);
        assert_eq!(d.basis(), DepthBasis::Estimate);
        let r = d.report(&p, 0.03, FILTERS.axis);
        let cal = p
            .hand_eye_error_m
            .hypot(p.camera_lever_m * p.hand_eye_error_deg.to_radians());
        assert!(
            (r.uncertainty - cal).abs() < 1e-9 && r.uncertainty > p.tolerance_m,
            "{r:?}"
        );
        assert_eq!(r.correction, 0.0);
        // A seal 13 mm from where the estimate puts it: more than the 7.2 mm of the shipped
        // calibration (2 mm + 1 deg x 0.3 m; the pose's own error 0 as shipped).
        assert!((p.refusal_bound() - 0.0072).abs() < 1e-4, "{}", p.refusal_bound());
        let d = dock(&p, -0.013, 0.0, true, Bump::None);
        match d.basis() {
            DepthBasis::Refused { correction, bound } => {
                assert!((correction - 0.013).abs() < 2e-4 && (bound - p.refusal_bound()).abs() < 1e-12);
                assert!(d.basis().to_string().contains("refused"));
            }
            b => panic!("{b:?}"),
        }
        assert_eq!(d.correction(), 0.0, "a refused correction moves nothing");
        assert!(d.report(&p, 0.03, FILTERS.axis).uncertainty > p.tolerance_m);
        // A trocar declared without a seal (`seal_depth_m` 0): nothing refines the depth, the
        // calibration's uncertainty stays, and the basis says why.
        let off = DepthParams {
            seal_depth_m: 0.0,
            ..p.clone()
        };
        let d = dock(&off, 0.002, 0.0, true, Bump::None);
        assert_eq!(d.basis(), DepthBasis::NoSeal);
        assert!(d.basis().to_string().contains("no seal"), "{}", d.basis());
        let r = d.report(&off, 0.03, FILTERS.axis);
        assert!((r.uncertainty - cal).abs() < 1e-9 && r.correction == 0.0, "{r:?}");
        // Without a hand-eye error the estimate's noise alone is the uncertainty.
        let exact = DepthParams {
            hand_eye_error_m: 0.0,
            hand_eye_error_deg: 0.0,
            ..p
        };
        let r = dock(&exact, 0.0, 0.0003, false, Bump::None).report(&exact, 0.03, FILTERS.axis);
        assert!(r.uncertainty > 0.0 && r.uncertainty < 0.5e-3, "{r:?}");
    }

    /// A contact pressed along the axis 13 mm before the seal (a seal's signature, shallower
    /// than the seal could be): refused, and the search goes on to the seal itself, which
    /// refines the depth as without the contact. With a calibration off by more than the
    /// bound the seal itself is felt too shallow and stays refused.
    #[test]
    fn an_onset_felt_too_shallow_is_refused_and_the_seal_is_looked_for_deeper() {
        let p = DepthParams::default();
        for e in [-0.002, 0.0, 0.003] {
            let d = dock(&p, e, 0.0, true, Bump::Axial);
            match d.basis() {
                DepthBasis::Seal { correction } => assert!((correction + e).abs() < 2e-4, "{e}: {correction}"),
                b => panic!("{e}: {b:?}"),
            }
            assert!(d.report(&p, 0.03, FILTERS.axis).uncertainty < p.tolerance_m);
        }
        // The contact alone, no seal: refused, never a DONE's basis.
        let d = dock(&p, 0.0, 0.0, false, Bump::Axial);
        assert!(
            matches!(d.basis(), DepthBasis::Refused { correction, .. } if correction < -0.01),
            "{:?}",
            d.basis()
        );
        assert!(d.report(&p, 0.03, FILTERS.axis).uncertainty > p.tolerance_m);
        // The estimate 10 mm too deep: the seal is felt 10 mm shallow, refused, and nothing
        // deeper replaces it.
        let d = dock(&p, 0.010, 0.0, true, Bump::None);
        assert!(
            matches!(d.basis(), DepthBasis::Refused { correction, .. } if (correction + 0.010).abs() < 2e-4),
            "{:?}",
            d.basis()
        );
    }

    /// Poses at any rate: at 1 kHz (a flood of poses, 32 of them in 32 ms) the poses of the
    /// stick window are still there when the onset is confirmed `confirm_s` later, and the
    /// depth is refined as at a camera's 15 or 100 Hz; the uncertainty stays within the
    /// tolerance.
    #[test]
    fn the_seal_is_felt_whatever_the_pose_rate() {
        let p = DepthParams::default();
        // 10 and 5 Hz: a pose every 100 and 200 ms, none within the 70 ms stick window.
        for (hz, latency) in [
            (15.0, 0.04),
            (10.0, 0.04),
            (5.0, 0.1),
            (100.0, 0.02),
            (1000.0, 0.0),
            (1000.0, 0.04),
        ] {
            let d = dock_at(&p, 0.003, (0.0, 5), (true, Bump::None), (hz, latency));
            match d.basis() {
                DepthBasis::Seal { correction } => assert!((correction + 0.003).abs() < 2e-4, "{hz} Hz: {correction}"),
                b => panic!("{hz} Hz, {latency} s: {b:?}"),
            }
            let r = d.report(&p, 0.03, FILTERS.axis);
            assert!(r.uncertainty <= p.tolerance_m, "{hz} Hz: {r:?}");
        }
    }

    /// The noise term against a simulation of the filters: white noise of sigma 1 mm at 15
    /// and 100 Hz through the tracking filter and the first-order one: the filtered estimate
    /// keeps V of the noise's variance ([`AxisFilter::noise_gains`]), and the term is
    /// 2 sigma sqrt(V) (T / (2 tau), the first-order rule, read 0.17 at 15 Hz where the
    /// tracking filter keeps 0.36); on a port breathing 4 mm at 0.3 Hz too (the noise is
    /// judged apart from the port's motion).
    #[test]
    fn the_noise_term_is_the_filter_s_noise_gain() {
        let sigma = 0.001;
        for (hz, breathing) in [(15.0, 0.0), (100.0, 0.0), (15.0, 0.004)] {
            let period = 1.0 / hz;
            for filter in [AxisFilter::Tracking(0.2), AxisFilter::FirstOrder(0.1)] {
                let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
                let mut track = TrackingFilter::<1>::new(0.2, 0.5);
                let mut first: Option<f64> = None;
                let mut d = DepthEstimate::default();
                let (mut kept, mut term, mut n) = (0.0, 0.0, 0.0);
                for k in 0..40_000 {
                    let t = f64::from(k) * period;
                    let noise = sigma * rng.sample::<f64, _>(StandardNormal);
                    let y = match filter {
                        AxisFilter::Tracking(_) => track.update(t, &nalgebra::Vector1::new(noise)).x,
                        _ => *first.insert(first.map_or(noise, |y| y + (noise - y) * rc_weight(period, 0.1))),
                    };
                    let port = breathing * (2.0 * std::f64::consts::PI * 0.3 * t).sin();
                    d.observe_pose(&Point3::new(0.0, 0.0, port + noise), &Vector3::z(), t);
                    if k >= 200 {
                        kept += y * y;
                        term += (0.5 * d.noise(filter)).powi(2);
                        n += 1.0;
                    }
                }
                let (_, v) = filter.noise_gains(period);
                let kept = kept / n / (sigma * sigma);
                assert!((kept / v - 1.0).abs() < 0.05, "{hz} Hz {filter:?}: kept {kept}, V {v}");
                let term = term / n / (sigma * sigma);
                assert!(
                    (term / v - 1.0).abs() < 0.05,
                    "{hz} Hz {breathing} {filter:?}: term {term}, V {v}"
                );
            }
        }
        let (_, v) = AxisFilter::Tracking(0.2).noise_gains(1.0 / 15.0);
        assert!((v - 0.36).abs() < 0.005, "{v}");
        assert_eq!(AxisFilter::None.noise_gains(1.0 / 15.0), (1.0, 1.0));
    }

    #[test]
    fn a_rise_that_falls_back_is_not_the_seal() {
        let p = DepthParams::default();
        let a = axis(0.0);
        let mut d = DepthEstimate::default();
        // 1 N along the axis for 0.1 s at the seal's depth (shorter than confirm_s), then
        // nothing: no onset; the tip passes every depth the seal could be at.
        for k in 0..400 {
            let t = k as f64 * 0.01;
            let tip = Point3::new(0.0, 0.0, 0.005 + 0.0001 * k as f64);
            d.observe_pose(&a.port, &Vector3::z(), t);
            let f = if (1.0..1.1).contains(&t) { -1.0 } else { 0.0 };
            d.update(&p, &a, &tip, &Vector3::new(0.0, 0.0, f), t, FILTERS);
        }
        assert_eq!(d.basis(), DepthBasis::Estimate);
    }

    #[test]
    fn the_history_keeps_the_newest_in_order() {
        let mut h = History::<u32, 4>::default();
        assert_eq!((h.last(), h.get(0)), (None, None));
        for k in 0..6 {
            h.push(k);
        }
        assert_eq!(h.iter().collect::<Vec<_>>(), vec![2, 3, 4, 5]);
        assert_eq!((h.get(0), h.last(), h.get(4)), (Some(2), Some(5), None));
    }

    #[test]
    fn bad_parameters_are_named() {
        assert!(DepthParams::default().validate().is_ok());
        let bad = DepthParams {
            confirm_s: 0.01,
            ..Default::default()
        };
        assert!(bad.validate().unwrap_err().contains("confirm_s"));
        let bad = DepthParams {
            tolerance_m: f64::NAN,
            ..Default::default()
        };
        assert!(bad.validate().unwrap_err().contains("tolerance_m"));
    }
}
