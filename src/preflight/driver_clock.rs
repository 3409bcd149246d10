//! `DRIVER_CLOCK`: whether the command stream survives the driver's
//! `joint_trajectory_controller` on the driver's clock (pure).
//!
//! **Which clock stamps what.** The ROS 1 LBR driver calls
//! `controller_manager.update(ros::Time::now(), period)` once per FRI cycle on the driver's
//! PC, and `joint_state_controller` stamps `/lbr/joint_states` with that time: the driver PC's
//! clock, the clock its trajectory controller judges commands on. Its `/lbr/states`
//! (`lbr_msgs/LBRState`) carries the FRI robot state's own timestamp
//! (`lbr_fri_ros/src/lbr_client.h`, `update_lbr`): the KUKA controller's clock, not the driver
//! PC's; it says nothing of when a command is dropped.
//!
//! **The rule** ([`crate::ros::trajectory`], from ros_controllers' `init_joint_trajectory.h`):
//! a message whose point is due at or before the controller's next update is dropped whole.
//! - A **zero stamp** (`command_stamp: next_update`, as shipped) starts the point at the next
//!   update on the driver's own clock: it is due `time_from_start` after it, whatever the two
//!   clocks read. Dropped only when `time_from_start` is 0; no measurement enters.
//! - A **stamped** command (`command_stamp: step`: the time the controller's step starts)
//!   is due `time_from_start` after the step on the controller's clock. It leaves up to a
//!   control period later (the step, then the publisher thread), reaches the driver the
//!   transport's latency after that, by when the driver's clock reads the step time plus its
//!   lead plus both, and the next update comes up to a driver period later. Its least lead
//!   over the next update: `time_from_start - lead - latency - control period - driver
//!   period`; dropped at 0. (Stamped at 100 Hz, the driver 5 ms ahead on one host, wall
//!   clock: this estimate 2.5 ms, the least lead `lbr_med_sim` measured 8.4 ms, none dropped;
//!   30 ms ahead every moving command dropped.)
//!
//! **The measurement.** Each joint state's arrival on the controller's clock minus its
//! stamp is the transport's latency minus the driver clock's lead. The lead is read from the
//! reference delay: on the wall clock the **least** one (no message arrives before it is
//! sent; the least latency taken as 0); under `/use_sim_time` the **median**: there the
//! preflight's clock is the last `/clock` it took in, which lags the simulator's by tens of
//! ms at times on a loaded host, and a lagging clock reads a message as arriving before its
//! stamp, i.e. the driver's clock as ahead. A lag that passes moves a few messages, an offset
//! moves them all; the median follows the offset. The latency's spread is the delays' p99
//! over the reference.
//!
//! **The inputs.** The controller takes a joint state only within its `input_timeout_s`
//! either way of its own clock (`CommandGuard::fresh`): a driver clock off by more, whatever
//! the commands, holds the controller at once (stale or future joint states), so that offset
//! is refused too (the offset, not the latency: a late message the controller holds on
//! itself). The LBRState's offset is reported, never judged here.

use super::{check, not_checked, Check};
use crate::stats::quantile_sorted;

/// What the preflight saw of the driver's clock, and the command stream it must carry.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct DriverClock {
    /// Arrival (controller's clock) minus stamp (driver PC's clock) of each joint state, s.
    pub joint_state_delays_s: Vec<f64>,
    /// The same for each LBRState (the robot controller's clock), s: reported only.
    pub lbr_state_delays_s: Vec<f64>,
    /// Whether the commands carry the step's time as their stamp (`command_stamp: step`);
    /// false: a zero stamp.
    pub stamped_commands: bool,
    /// The command point's `time_from_start`, s.
    pub time_from_start_s: f64,
    /// The driver's period (the LBRState's `sample_time`), s.
    pub driver_period_s: f64,
    /// The controller's period (`dt_s`), s.
    pub control_period_s: f64,
    /// The controller's freshness bound on joint states, s.
    pub input_timeout_s: f64,
}

/// The driver's clock against the controller's, as its stamps show it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ClockOffset {
    /// How far the driver's clock reads ahead of the controller's, s (negative: behind).
    pub ahead_s: f64,
    /// The transport's spread: the delays' p99 over the reference delay, s (>= 0).
    pub spread_s: f64,
    /// The least delay, s.
    pub least_s: f64,
    /// The delays' p99, s.
    pub p99_s: f64,
}

/// The driver clock's lead from arrival-minus-stamp `delays_s` (see the module doc;
/// `sim_time`: the controller's clock is `/clock`). None without a finite delay.
pub fn clock_offset(delays_s: &[f64], sim_time: bool) -> Option<ClockOffset> {
    let mut v: Vec<f64> = delays_s.iter().copied().filter(|d| d.is_finite()).collect();
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let reference = if sim_time { quantile_sorted(&v, 0.5) } else { v[0] };
    let p99 = quantile_sorted(&v, 0.99);
    Some(ClockOffset {
        ahead_s: -reference,
        spread_s: (p99 - reference).max(0.0),
        least_s: v[0],
        p99_s: p99,
    })
}

/// The command point's least lead over the driver's next update, s (see the module doc):
/// `time_from_start` for a zero stamp; for a stamped command what is left of it once the
/// driver clock's lead, the transport's spread, the controller's and the driver's periods are
/// taken.
pub fn command_lead_s(c: &DriverClock, offset: &ClockOffset) -> f64 {
    if c.stamped_commands {
        c.time_from_start_s - offset.ahead_s - offset.spread_s - c.control_period_s - c.driver_period_s
    } else {
        c.time_from_start_s
    }
}

const FIX: &str =
    "leave the command's stamp 0 (command_stamp: next_update, as shipped: the driver starts each point at \
                   its own next update), or raise command_lookahead_periods, or synchronise the two machines' clocks \
                   (chrony: the controller's machine a server of the driver's, or both of one server; `chronyc \
                   tracking` within a millisecond)";

/// The `DRIVER_CLOCK` check (None: no driver stamps were seen; `JOINT_STATES` says so);
/// `sim_time`: the controller's clock is `/clock`.
pub fn driver_clock_check(c: Option<&DriverClock>, sim_time: bool) -> Check {
    let Some(c) = c else {
        return not_checked("DRIVER_CLOCK", "no driver stamps".into());
    };
    let Some(o) = clock_offset(&c.joint_state_delays_s, sim_time) else {
        return not_checked("DRIVER_CLOCK", "no joint-state stamps".into());
    };
    let lead = command_lead_s(c, &o);
    // CommandGuard::fresh: a joint state's age on the controller's clock, -ahead plus its
    // latency, within the timeout either way. The offset is judged, not the latency: the
    // controller holds on a late message itself, and under load the preflight's own
    // subscriber lags (p99 234 ms once in a camera run under /use_sim_time).
    let fresh = o.ahead_s.abs() <= c.input_timeout_s;
    let ok = lead > 0.0 && fresh;
    let lbr = clock_offset(&c.lbr_state_delays_s, sim_time)
        .map_or("none".to_string(), |l| format!("{:+.1} ms", l.ahead_s * 1e3));
    let (stamp, basis) = if c.stamped_commands {
        (
            "the step's time",
            "time_from_start - lead - spread - control period - driver period",
        )
    } else {
        ("0", "time_from_start after the driver's next update, on its own clock")
    };
    let detail = format!(
        "the driver PC's clock {:+.1} ms ahead ({} delay of its joint states; least {:.1}, p99 {:.1} ms; \
         within +-{:.0} ms or the controller holds); commands stamped {stamp}: due {:.1} ms after the \
         driver's next update at least ({basis}: time_from_start {:.1} ms, spread {:.1} ms, control period \
         {:.1} ms, driver period {:.1} ms; > 0 or dropped); LBRState (robot controller's clock) {lbr}",
        o.ahead_s * 1e3,
        if sim_time { "median" } else { "least" },
        o.least_s * 1e3,
        o.p99_s * 1e3,
        c.input_timeout_s * 1e3,
        lead * 1e3,
        c.time_from_start_s * 1e3,
        o.spread_s * 1e3,
        c.control_period_s * 1e3,
        c.driver_period_s * 1e3,
    );
    check("DRIVER_CLOCK", ok, detail, FIX)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::preflight::Verdict;

    /// Joint states delayed 0.3-0.8 ms by the transport, the driver's clock `ahead` s ahead;
    /// `time_from_start` two control periods.
    fn seen(ahead: f64, stamped: bool, time_from_start: f64) -> DriverClock {
        let delays: Vec<f64> = (0..101).map(|k| 3e-4 + 5e-6 * f64::from(k) - ahead).collect();
        DriverClock {
            joint_state_delays_s: delays.clone(),
            lbr_state_delays_s: delays,
            stamped_commands: stamped,
            time_from_start_s: time_from_start,
            driver_period_s: 0.002,
            control_period_s: time_from_start / 2.0,
            input_timeout_s: 0.1,
        }
    }

    fn verdict(c: &DriverClock, sim_time: bool) -> Verdict {
        driver_clock_check(Some(c), sim_time).verdict
    }

    #[test]
    fn the_lead_is_read_from_the_least_delay_on_the_wall_clock_and_the_median_on_sim_time() {
        let c = seen(0.030, false, 0.02);
        let wall = clock_offset(&c.joint_state_delays_s, false).unwrap();
        assert!((wall.ahead_s - 0.0297).abs() < 1e-9, "{wall:?}");
        assert!((wall.spread_s - 0.000495).abs() < 1e-9, "{wall:?}");
        let sim = clock_offset(&c.joint_state_delays_s, true).unwrap();
        assert!((sim.ahead_s - 0.02945).abs() < 1e-9, "{sim:?}");
        assert_eq!(clock_offset(&[f64::NAN], false), None);
    }

    #[test]
    fn a_lagging_sim_clock_on_a_few_messages_is_not_read_as_the_drivers_lead() {
        // Clocks in step; a tenth of the joint states timed on a /clock 60 ms behind.
        let mut c = seen(0.0, true, 0.020);
        for d in c.joint_state_delays_s.iter_mut().step_by(10) {
            *d -= 0.060;
        }
        let sim = clock_offset(&c.joint_state_delays_s, true).unwrap();
        assert!(sim.ahead_s.abs() < 1e-3, "{sim:?}");
        assert_eq!(verdict(&c, true), Verdict::Pass);
        // On the wall clock no message arrives before it is sent: the least delay is the lead.
        assert_eq!(verdict(&c, false), Verdict::Fail);
    }

    #[test]
    fn a_zero_stamp_survives_a_drivers_clock_ahead_that_drops_every_stamped_command() {
        for sim_time in [false, true] {
            // 100 Hz, two periods of lookahead (20 ms), the driver 30 ms ahead.
            let zero = driver_clock_check(Some(&seen(0.030, false, 0.020)), sim_time);
            assert_eq!(zero.verdict, Verdict::Pass, "{zero}");
            let stamped = driver_clock_check(Some(&seen(0.030, true, 0.020)), sim_time);
            assert_eq!(stamped.verdict, Verdict::Fail, "{stamped}");
            assert!(stamped.fix.contains("chrony") && stamped.fix.contains("command_lookahead_periods"));
            assert!(stamped.fix.contains("command_stamp: next_update"));
            // Stamped, 5 ms ahead: 20 - 5 - 0.5 - 10 - 2 ms left; 10 ms ahead: none.
            assert_eq!(verdict(&seen(0.005, true, 0.020), sim_time), Verdict::Pass);
            assert_eq!(verdict(&seen(0.010, true, 0.020), sim_time), Verdict::Fail);
            // Stamped at 1 kHz (2 ms of lookahead): equal clocks leave 2 - 0.5 - 1 - 2 ms < 0.
            assert_eq!(verdict(&seen(0.0, true, 0.002), sim_time), Verdict::Fail);
            // A zero stamp at 1 kHz, 30 ms ahead: due 2 ms after the driver's next update.
            assert_eq!(verdict(&seen(0.030, false, 0.002), sim_time), Verdict::Pass);
            // A zero stamp with time_from_start 0 is due at the next update: dropped.
            assert_eq!(verdict(&seen(0.0, false, 0.0), sim_time), Verdict::Fail);
        }
        let c = seen(0.0, true, 0.020);
        let o = clock_offset(&c.joint_state_delays_s, false).unwrap();
        assert!((command_lead_s(&c, &o) - (0.020 - (-0.0003) - 0.000495 - 0.010 - 0.002)).abs() < 1e-9);
    }

    #[test]
    fn a_clock_off_by_more_than_the_input_timeout_is_refused_in_either_direction() {
        // 0.1 s timeout, zero stamps: commands survive any offset; the joint states do not.
        assert_eq!(verdict(&seen(0.080, false, 0.02), false), Verdict::Pass);
        assert_eq!(verdict(&seen(0.120, false, 0.02), false), Verdict::Fail);
        assert_eq!(verdict(&seen(-0.080, false, 0.02), false), Verdict::Pass);
        assert_eq!(verdict(&seen(-0.120, false, 0.02), false), Verdict::Fail);
        // The LBRState on another clock (the robot controller's) is reported, not judged.
        // A slow subscriber (the p99 delay past the timeout) is latency, not an offset.
        let mut c = seen(0.0, false, 0.02);
        c.joint_state_delays_s.extend([0.25; 3]);
        assert_eq!(verdict(&c, true), Verdict::Pass);
        c.lbr_state_delays_s = vec![2.0; 10];
        let r = driver_clock_check(Some(&c), false);
        assert_eq!(r.verdict, Verdict::Pass);
        assert!(
            r.detail.contains("LBRState (robot controller's clock) -2000.0 ms"),
            "{r}"
        );
        assert_eq!(driver_clock_check(None, false).verdict, Verdict::NotChecked);
    }
}
