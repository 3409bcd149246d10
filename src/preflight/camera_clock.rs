//! The camera's clock against the controller's (`CAMERA_CLOCK`): on two machines (the camera
//! and the estimator on a GPU machine, the controller on the robot's real-time PC) the
//! images are stamped by the camera's machine, the joint states by the robot's. The estimator
//! pairs each image with the arm's pose at the image's stamp, and the controller ages the
//! trocar pose (stamped with the image's stamp) on its own clock; an offset between the two
//! clocks takes the pose at the wrong arm configuration (behind), drops frames as newer than
//! every joint state (ahead), or holds on stale poses, none of which names the clock.
//!
//! **The measurement.** Each image's age on arrival at the controller's machine, its clock
//! at arrival minus the image's stamp, is the camera's own latency (capture to arrival, never
//! negative) minus the offset of the camera's clock. One-way times cannot tell a slow camera
//! from a clock behind, so the lower quartile of the ages over the window (the faster
//! quarter of the frames) bounds the offset: below 0 the camera's clock is ahead by at least
//! as much (no frame arrives before it is taken); above `limits.camera_latency_max_s` (the
//! latency a camera may have, which the estimator tolerates: it pairs by the stamp, not by
//! the arrival) it is behind by at least the excess. Within that band the offset is taken as
//! none. The quartile, not the least age: under `/use_sim_time` the controller's clock is the
//! last `/clock` it took in, and on a starved host it lags the simulator's by tens of ms at
//! times (one image 68 ms "before" its stamp at load average 30, the others after it): a
//! lag that passes moves a few frames, an offset moves them all.
//!
//! **The bound**, from the parameters the offset defeats: the estimator answers a stamp up to
//! `max_joint_extrapolation_s` past the newest joint state with that state (the arm taken as
//! still for so long), so the joint-history pairing tolerates that much error in a stamp;
//! and a pose must stay younger than the staleness checks' timeout (the controller's
//! `guard.trocar_timeout_s`, the estimator's `estimator.stale_after_s`, the smaller) until the
//! next frame, after the camera's latency: `timeout - latency_max - frame period`. The
//! allowed offset is the smaller of the two (as shipped 20 ms, the pairing's).

use super::{check, not_checked, Check, Limits};

/// What the camera's clock is held to: the parameters of the checks an offset defeats.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraClockTolerance {
    /// The estimator's `max_joint_extrapolation_s`: the error in a stamp its joint-history
    /// pairing tolerates, s.
    pub pairing_s: f64,
    /// The staleness timeout of a trocar pose: the smaller of the controller's
    /// `guard.trocar_timeout_s` and the estimator's `estimator.stale_after_s`, s.
    pub pose_timeout_s: f64,
}

impl CameraClockTolerance {
    /// The largest offset of the camera's clock allowed, s, for a camera of `frame_period_s`
    /// whose latency is at most `latency_max_s` (see the module doc).
    pub fn max_offset_s(&self, latency_max_s: f64, frame_period_s: f64) -> f64 {
        let staleness = self.pose_timeout_s - latency_max_s - frame_period_s.max(0.0);
        self.pairing_s.min(staleness).max(0.0)
    }
}

/// The images' stamps against the controller's clock.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraClock {
    /// Each image's age on arrival: the controller's clock at its arrival minus its stamp, s.
    pub ages_s: Vec<f64>,
    /// The node publishing the images and the machine it runs on (its URI's host).
    pub camera: String,
    /// The machine of the controller's clock (the host the images were timed on).
    pub controller_host: String,
    /// The tolerances of the pairing and the staleness checks.
    pub tolerance: CameraClockTolerance,
}

impl CameraClock {
    /// The offset of the camera's clock the ages prove, s (positive: ahead of the
    /// controller's, negative: behind; 0 within what a latency of up to `latency_max_s`
    /// explains), the least age and the lower quartile it is read from; None without an
    /// image.
    pub fn offset_s(&self, latency_max_s: f64) -> Option<(f64, f64, f64)> {
        let mut ages: Vec<f64> = self.ages_s.iter().copied().filter(|a| a.is_finite()).collect();
        ages.sort_by(f64::total_cmp);
        let least = *ages.first()?;
        let fast = crate::stats::quantile_sorted(&ages, 0.25);
        let offset = if fast < 0.0 {
            -fast
        } else {
            -(fast - latency_max_s).max(0.0)
        };
        Some((offset, least, fast))
    }
}

/// The `CAMERA_CLOCK` line (`frame_period_s`: the images' median interval).
pub fn camera_clock(clock: Option<&CameraClock>, lim: &Limits, frame_period_s: f64) -> Check {
    let fix = "synchronise the camera's machine (named above) with the robot's PC: chrony on both, the robot PC \
               its server (`chronyc tracking` on the camera's machine: offset well under 1 ms, `chronyc sources`: the \
               robot PC selected '*'), then restart the camera driver; docs/two-machines.md";
    let Some(c) = clock else {
        return not_checked(
            "CAMERA_CLOCK",
            "no camera: the simulator publishes the trocar pose directly".into(),
        );
    };
    let Some((offset, least, fast)) = c.offset_s(lim.camera_latency_max_s) else {
        return check("CAMERA_CLOCK", false, format!("no image from {} timed", c.camera), fix);
    };
    let period = if frame_period_s.is_finite() {
        frame_period_s
    } else {
        0.0
    };
    let allowed = c.tolerance.max_offset_s(lim.camera_latency_max_s, period);
    let ms = |s: f64| s * 1e3;
    let seen = match offset {
        o if o > 0.0 => format!("its clock is at least {:.0} ms AHEAD", ms(o)),
        o if o < 0.0 => format!("its clock is at least {:.0} ms BEHIND", ms(-o)),
        _ => "no offset beyond a camera's latency".into(),
    };
    check(
        "CAMERA_CLOCK",
        offset.abs() <= allowed,
        format!(
            "{} images arrive {:.0} ms or more after their stamps at {}, a quarter of them within {:.0} ms (a \
             camera's latency is 0 to {:.0} ms): {seen} (<= {:.0} ms: the estimator's joint-history pairing {:.0} ms, \
             the pose timeout {:.0} ms)",
            c.camera,
            ms(least),
            c.controller_host,
            ms(fast),
            ms(lim.camera_latency_max_s),
            ms(allowed),
            ms(c.tolerance.pairing_s),
            ms(c.tolerance.pose_timeout_s)
        ),
        fix,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::preflight::Verdict;

    fn clock(offset_s: f64, latency: &[f64]) -> CameraClock {
        CameraClock {
            ages_s: latency.iter().map(|l| l - offset_s).collect(),
            camera: "/lbr_med_sim on 10.200.0.1".into(),
            controller_host: "10.200.0.1".into(),
            tolerance: CameraClockTolerance {
                pairing_s: 0.02,
                pose_timeout_s: 0.5,
            },
        }
    }

    /// The simulated camera's latency over a window: 35-55 ms a frame, one slow frame.
    const LATENCY: [f64; 6] = [0.041, 0.036, 0.052, 0.047, 0.12, 0.038];

    #[test]
    fn the_bound_is_the_pairings_unless_the_staleness_leaves_less() {
        let t = clock(0.0, &LATENCY).tolerance;
        assert_eq!(t.max_offset_s(0.12, 1.0 / 15.0), 0.02);
        // A 0.15 s pose timeout at 5 Hz leaves 0.15 - 0.1 - 0.2 < 0: no offset at all.
        let tight = CameraClockTolerance {
            pose_timeout_s: 0.15,
            ..t
        };
        assert_eq!(tight.max_offset_s(0.1, 0.2), 0.0);
        let loose = CameraClockTolerance { pairing_s: 0.2, ..t };
        assert_eq!(loose.max_offset_s(0.1, 0.1), 0.2);
        assert!((loose.max_offset_s(0.3, 0.1) - 0.1).abs() < 1e-12);
    }

    #[test]
    fn an_offset_within_a_cameras_latency_passes_and_beyond_the_pairing_fails_naming_it() {
        let lim = Limits::default();
        assert_eq!(lim.camera_latency_max_s, 0.12);
        let period = 1.0 / 15.0;
        for (offset, pass, says) in [
            (0.0, true, "no offset"),
            (-0.02, true, "no offset"),
            (0.02, true, "no offset"),
            (-0.2, false, "at least 119 ms BEHIND"),
            (0.2, false, "at least 161 ms AHEAD"),
            (0.07, false, "at least 31 ms AHEAD"),
        ] {
            let c = camera_clock(Some(&clock(offset, &LATENCY)), &lim, period);
            let want = if pass { Verdict::Pass } else { Verdict::Fail };
            assert_eq!(c.verdict, want, "{offset}: {c}");
            assert!(c.detail.contains(says), "{offset}: {c}");
            assert!(c.detail.contains("/lbr_med_sim on 10.200.0.1"), "{c}");
            if !pass {
                assert!(c.to_string().contains("chrony"), "{c}");
            }
        }
        // The faster quarter's age: one slow frame does not move it, nor one early frame (a
        // simulated clock that lagged for a moment), whatever the offset.
        let (_, least, fast) = clock(-0.2, &LATENCY).offset_s(0.12).unwrap();
        assert!(
            (least - 0.236).abs() < 1e-9 && (fast - 0.23875).abs() < 1e-9,
            "{least} {fast}"
        );
        let mut lagged = clock(0.0, &LATENCY);
        lagged.ages_s[2] = -0.068;
        let c = camera_clock(Some(&lagged), &lim, period);
        assert_eq!(c.verdict, Verdict::Pass, "{c}");
        assert!(c.detail.contains("-68 ms or more"), "{c}");
        // Every frame early: the camera's clock is ahead.
        let early = clock(0.0, &[-0.05, -0.04, -0.06, -0.045]);
        assert_eq!(camera_clock(Some(&early), &lim, period).verdict, Verdict::Fail);
    }

    #[test]
    fn no_image_fails_and_no_camera_is_not_checked() {
        let lim = Limits::default();
        let none = clock(0.0, &[f64::NAN]);
        assert_eq!(camera_clock(Some(&none), &lim, 0.1).verdict, Verdict::Fail);
        assert_eq!(camera_clock(None, &lim, 0.1).verdict, Verdict::NotChecked);
    }
}
