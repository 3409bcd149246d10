//! `DRIVER_CLOCK`: the driver's clock against the controller's, and whether the command
//! stream survives the driver's `joint_trajectory_controller` with it (pure).
//!
//! The driver stamps its joint states with its own clock (the ROS 1 LBR driver calls
//! `controller_manager.update(ros::Time::now(), period)` once per FRI cycle, and
//! `joint_state_controller` stamps with that time); its LBRState carries the FRI robot
//! state's own timestamp. Each message's arrival (controller's clock) minus its stamp is the
//! transport's latency minus the driver clock's lead; the smallest over the window, the
//! transport's least latency taken as 0, is how far the driver's clock reads **ahead**.
//!
//! Two things fail:
//! - **Stale or future inputs**: the controller takes a joint state or torque only within
//!   `input_timeout_s` of its own clock either way; a stamp off by more than half of it
//!   leaves the other half to the transport and the driver's period.
//! - **Dropped commands** (commands stamped with the step's time only): the trajectory
//!   controller drops a point due at or before its next update
//!   ([`crate::ros::trajectory`]), so the point's `time_from_start` must exceed the driver
//!   clock's lead, the driver's period and the transport's spread (the delays' p99 over
//!   their least). A zero stamp (`command_stamp: next_update`, as shipped) starts each
//!   point at the driver's next update on its own clock: `time_from_start > 0` suffices.

use super::{check, not_checked, Check};

/// What the preflight saw of the driver's clock, and the command stream it must carry.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct DriverClock {
    /// Arrival (controller's clock) minus stamp (driver's clock) of each joint state, s.
    pub joint_state_delays_s: Vec<f64>,
    /// The same for each LBRState, s.
    pub lbr_state_delays_s: Vec<f64>,
    /// Whether the commands carry the step's time as their stamp (`command_stamp: step`);
    /// false: a zero stamp.
    pub stamped_commands: bool,
    /// The command point's `time_from_start`, s.
    pub time_from_start_s: f64,
    /// The driver's period (the LBRState's `sample_time`), s.
    pub driver_period_s: f64,
    /// The controller's freshness bound on joint states and torques, s.
    pub input_timeout_s: f64,
}

/// The smallest and the 99th percentile (nearest rank) of `x`, finite values only.
fn least_and_p99(x: &[f64]) -> Option<(f64, f64)> {
    let mut v: Vec<f64> = x.iter().copied().filter(|d| d.is_finite()).collect();
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let k = ((v.len() as f64 * 0.99).ceil() as usize).clamp(1, v.len()) - 1;
    Some((v[0], v[k]))
}

/// The driver clock's lead over the controller's as its stamps show it, s (None: no stamps).
pub fn driver_clock_ahead_s(delays_s: &[f64]) -> Option<f64> {
    least_and_p99(delays_s).map(|(least, _)| -least)
}

/// The command point's least lead over the driver's next update, s: what the stream has left
/// once the driver clock's lead, its period and the transport's spread are taken.
pub fn command_lead_s(c: &DriverClock) -> Option<f64> {
    if !c.stamped_commands {
        return Some(c.time_from_start_s);
    }
    let (least, p99) = least_and_p99(&c.joint_state_delays_s)?;
    Some(c.time_from_start_s - (-least) - c.driver_period_s - (p99 - least))
}

const FIX: &str = "synchronise the two machines' clocks (chrony: the controller's machine a server of the \
                   driver's, or both of one server; `chronyc tracking` within a millisecond), or leave the \
                   command's stamp 0 (command_stamp: next_update) or raise command_lookahead_periods";

/// The `DRIVER_CLOCK` check (None: no driver stamps were seen; `JOINT_STATES` says so).
pub fn driver_clock_check(c: Option<&DriverClock>) -> Check {
    let Some(c) = c else {
        return not_checked("DRIVER_CLOCK", "no driver stamps".into());
    };
    let Some((least, p99)) = least_and_p99(&c.joint_state_delays_s) else {
        return not_checked("DRIVER_CLOCK", "no joint-state stamps".into());
    };
    let bound = c.input_timeout_s / 2.0;
    let worst = least.abs().max(p99.abs());
    let lbr = least_and_p99(&c.lbr_state_delays_s);
    let lbr_worst = lbr.map_or(0.0, |(l, p)| l.abs().max(p.abs()));
    let lead = command_lead_s(c).unwrap_or(f64::NAN);
    let ok = worst <= bound && lbr_worst <= bound && lead > 0.0;
    let stamp = if c.stamped_commands {
        "the step's time"
    } else {
        "0 (the driver's next update)"
    };
    let detail = format!(
        "the driver's clock {:+.1} ms ahead (joint states delayed {:.1} to {:.1} ms, LBRState {}; each within \
         +-{:.0} ms); commands stamped {stamp}, due {:.1} ms after the driver's next update at least \
         (time_from_start {:.1} ms, driver period {:.1} ms; > 0 or dropped)",
        -least * 1e3,
        least * 1e3,
        p99 * 1e3,
        lbr.map_or("none".to_string(), |(l, p)| format!(
            "{:.1} to {:.1} ms",
            l * 1e3,
            p * 1e3
        )),
        bound * 1e3,
        lead * 1e3,
        c.time_from_start_s * 1e3,
        c.driver_period_s * 1e3,
    );
    check("DRIVER_CLOCK", ok, detail, FIX)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::preflight::Verdict;

    /// Joint states delayed 0.3-0.8 ms by the transport, the driver's clock `ahead` s ahead.
    fn seen(ahead: f64, stamped: bool, lookahead: f64) -> DriverClock {
        let delays: Vec<f64> = (0..100).map(|k| 3e-4 + 5e-6 * f64::from(k) - ahead).collect();
        DriverClock {
            joint_state_delays_s: delays.clone(),
            lbr_state_delays_s: delays,
            stamped_commands: stamped,
            time_from_start_s: lookahead,
            driver_period_s: 0.002,
            input_timeout_s: 0.1,
        }
    }

    #[test]
    fn the_lead_of_the_drivers_clock_is_read_from_the_least_delay() {
        let a = driver_clock_ahead_s(&seen(0.030, false, 0.02).joint_state_delays_s).unwrap();
        assert!((a - 0.0297).abs() < 1e-9, "{a}");
        assert_eq!(driver_clock_ahead_s(&[f64::NAN]), None);
    }

    #[test]
    fn a_zero_stamp_survives_a_drivers_clock_ahead_that_drops_every_stamped_command() {
        // 100 Hz, two periods of lookahead (20 ms), the driver 30 ms ahead.
        let zero = driver_clock_check(Some(&seen(0.030, false, 0.020)));
        assert_eq!(zero.verdict, Verdict::Pass, "{zero}");
        let stamped = driver_clock_check(Some(&seen(0.030, true, 0.020)));
        assert_eq!(stamped.verdict, Verdict::Fail, "{stamped}");
        assert!(stamped.fix.contains("chrony") && stamped.fix.contains("command_lookahead_periods"));
        // Stamped, 1 kHz (2 ms of lookahead): equal clocks leave 2 - 2 (period) - 0.5 (spread) < 0.
        assert_eq!(driver_clock_check(Some(&seen(0.0, true, 0.002))).verdict, Verdict::Fail);
        // Stamped with clocks in step and 20 ms: 20 - 2 - 0.5 ms left.
        let c = seen(0.0, true, 0.020);
        assert!((command_lead_s(&c).unwrap() - 0.0175).abs() < 1e-9);
        assert_eq!(driver_clock_check(Some(&c)).verdict, Verdict::Pass);
    }

    #[test]
    fn a_clock_off_by_half_the_input_timeout_is_refused_in_either_direction() {
        // 0.1 s timeout: 50 ms either way.
        assert_eq!(
            driver_clock_check(Some(&seen(0.045, false, 0.02))).verdict,
            Verdict::Pass
        );
        assert_eq!(
            driver_clock_check(Some(&seen(0.060, false, 0.02))).verdict,
            Verdict::Fail
        );
        assert_eq!(
            driver_clock_check(Some(&seen(-0.060, false, 0.02))).verdict,
            Verdict::Fail
        );
        // The LBRState on another clock (the robot controller's) counts the same.
        let mut c = seen(0.0, false, 0.02);
        c.lbr_state_delays_s = vec![2.0; 10];
        assert_eq!(driver_clock_check(Some(&c)).verdict, Verdict::Fail);
        assert_eq!(driver_clock_check(None).verdict, Verdict::NotChecked);
    }
}
