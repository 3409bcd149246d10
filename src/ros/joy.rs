//! A joystick for the lab: `sensor_msgs/Joy` axes and buttons -> the surgeon's
//! [`ScopeCommand`], pure and tested here; the `scope_joy` node ([`crate::ros::joy_node`])
//! publishes it on `/docking/scope_command`.
//!
//! Each of pan, tilt, roll and zoom takes one Joy axis (or none) times a scale; a dead zone
//! about the centre of each axis reads as zero (rescaled, so that the command grows from
//! zero at its edge). Nothing moves unless the dead-man button is held: while it is, a
//! command goes out at every tick; when it is released (or the Joy stream stops, or a Joy
//! is malformed) one zero command stops the scope at once and then the node falls silent,
//! and the controller's own dead-man (`scope.command_timeout_s`) holds the scope still.

use crate::control::ScopeCommand;
use crate::ros::msgs::sensor_msgs;
use crate::validate;

/// A rotation of the scope (pan, tilt, roll) driven by a joystick axis.
#[derive(Debug, Clone, Copy, PartialEq, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AngularAxis {
    /// Index into `Joy.axes` (-1: this motion is not mapped).
    pub axis: i32,
    /// Command at full deflection, rad/s; negative flips the direction.
    pub scale_rad_s: f64,
}

/// A translation of the scope (zoom) driven by a joystick axis.
#[derive(Debug, Clone, Copy, PartialEq, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LinearAxis {
    /// Index into `Joy.axes` (-1: this motion is not mapped).
    pub axis: i32,
    /// Command at full deflection, m/s; negative flips the direction.
    pub scale_m_s: f64,
}

/// Parameters of the `scope_joy` node (its private namespace; `config/scope_joy.yaml`, whose
/// values, built in, are the defaults: [`crate::config::SCOPE_JOY`]).
#[derive(Debug, Clone, PartialEq, serde::Deserialize)]
#[serde(remote = "Self", deny_unknown_fields)]
pub struct JoyParams {
    /// Joy in.
    pub joy_topic: String,
    /// Scope commands out (TwistStamped).
    pub command_topic: String,
    /// Frame of the commands.
    pub frame_id: String,
    /// Commands per second while the dead-man is held, 10..=1000 Hz (well above 1 / the
    /// controller's `scope.command_timeout_s` of 0.2 s, so that a held stick never times out).
    pub rate_hz: f64,
    /// A Joy older than this counts as none (the joystick node stopped), s.
    pub joy_timeout_s: f64,
    /// Pan about the fulcrum (angular.x).
    pub pan: AngularAxis,
    /// Tilt about the fulcrum (angular.y).
    pub tilt: AngularAxis,
    /// Roll about the shaft (angular.z).
    pub roll: AngularAxis,
    /// In and out along the shaft (linear.z).
    pub zoom: LinearAxis,
    /// Dead zone about the centre of every axis, as a fraction of full deflection, [0, 0.9].
    pub dead_zone: f64,
    /// Index into `Joy.buttons` of the dead-man button.
    pub deadman_button: i32,
}

crate::shipped_defaults!(JoyParams, crate::config::SCOPE_JOY, [], deserialize_only);

/// Why a Joy message gives no command.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum JoyError {
    /// The message has fewer axes or buttons than the mapping uses.
    #[error("Joy has {got} {what}, the mapping uses index {index}")]
    Missing {
        /// "axes" or "buttons".
        what: &'static str,
        /// The index the mapping uses.
        index: usize,
        /// How many the message has.
        got: usize,
    },
    /// An axis the mapping uses is NaN or infinite.
    #[error("Joy axis {index} is not finite")]
    NonFinite {
        /// The axis.
        index: usize,
    },
}

impl JoyParams {
    /// Check every range; the error names the key.
    pub fn validate(&self) -> Result<(), validate::RangeError> {
        validate::in_range("rate_hz", self.rate_hz, 10.0, 1000.0)?;
        validate::positive_at_most("joy_timeout_s", self.joy_timeout_s, 10.0)?;
        validate::integer_in_range("deadman_button", i64::from(self.deadman_button), 0, 255)?;
        validate::in_range("dead_zone", self.dead_zone, 0.0, 0.9)?;
        for (name, axis, scale) in [
            ("pan", self.pan.axis, ("scale_rad_s", self.pan.scale_rad_s)),
            ("tilt", self.tilt.axis, ("scale_rad_s", self.tilt.scale_rad_s)),
            ("roll", self.roll.axis, ("scale_rad_s", self.roll.scale_rad_s)),
            ("zoom", self.zoom.axis, ("scale_m_s", self.zoom.scale_m_s)),
        ] {
            validate::integer_in_range(&format!("{name}/axis"), i64::from(axis), -1, 255)?;
            validate::in_range(&format!("{name}/{}", scale.0), scale.1, -10.0, 10.0)?;
        }
        Ok(())
    }

    /// The value of Joy axis `axis`, dead zone applied, times `scale` (0 if unmapped).
    fn axis(&self, joy: &sensor_msgs::Joy, axis: i32, scale: f64) -> Result<f64, JoyError> {
        let Ok(index) = usize::try_from(axis) else {
            return Ok(0.0);
        };
        let v = f64::from(*joy.axes.get(index).ok_or(JoyError::Missing {
            what: "axes",
            index,
            got: joy.axes.len(),
        })?);
        if !v.is_finite() {
            return Err(JoyError::NonFinite { index });
        }
        let v = v.clamp(-1.0, 1.0);
        let beyond = (v.abs() - self.dead_zone).max(0.0) / (1.0 - self.dead_zone);
        Ok(v.signum() * beyond * scale)
    }

    /// Whether the dead-man button is held.
    fn deadman(&self, joy: &sensor_msgs::Joy) -> Result<bool, JoyError> {
        let index = usize::try_from(self.deadman_button).unwrap_or(usize::MAX);
        joy.buttons.get(index).map(|&b| b != 0).ok_or(JoyError::Missing {
            what: "buttons",
            index,
            got: joy.buttons.len(),
        })
    }

    /// The command of `joy`: `None` while the dead-man button is released.
    pub fn command(&self, joy: &sensor_msgs::Joy) -> Result<Option<ScopeCommand>, JoyError> {
        let cmd = ScopeCommand {
            pan: self.axis(joy, self.pan.axis, self.pan.scale_rad_s)?,
            tilt: self.axis(joy, self.tilt.axis, self.tilt.scale_rad_s)?,
            roll: self.axis(joy, self.roll.axis, self.roll.scale_rad_s)?,
            zoom: self.axis(joy, self.zoom.axis, self.zoom.scale_m_s)?,
        };
        Ok(self.deadman(joy)?.then_some(cmd))
    }
}

/// The joystick's state between ticks: whether the last tick sent a command.
#[derive(Debug, Clone, Default)]
pub struct ScopeJoy {
    sending: bool,
}

impl ScopeJoy {
    /// One tick of the node, given the newest Joy and its age (s), if any: the command to
    /// send, if one is due, and why the Joy gave none, if it was malformed. A released
    /// dead-man, a stale or missing Joy, or a malformed one send one zero command (if
    /// commands were going out), then nothing.
    pub fn tick(
        &mut self,
        p: &JoyParams,
        joy: Option<(&sensor_msgs::Joy, f64)>,
    ) -> (Option<ScopeCommand>, Option<JoyError>) {
        let fresh = joy.filter(|(_, age)| *age <= p.joy_timeout_s);
        let (cmd, err) = match fresh.map(|(j, _)| p.command(j)) {
            Some(Ok(c)) => (c, None),
            Some(Err(e)) => (None, Some(e)),
            None => (None, None),
        };
        let out = match cmd {
            Some(c) => Some(c),
            None if self.sending => Some(ScopeCommand::default()),
            None => None,
        };
        self.sending = cmd.is_some();
        (out, err)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn joy(axes: &[f32], deadman: bool) -> sensor_msgs::Joy {
        let mut buttons = vec![0; 8];
        buttons[4] = i32::from(deadman);
        sensor_msgs::Joy {
            axes: axes.to_vec(),
            buttons,
            ..Default::default()
        }
    }

    #[test]
    fn axes_map_with_their_scales_and_the_dead_zone() {
        let p = JoyParams::default();
        let c = p
            .command(&joy(&[1.0, -1.0, 0.0, 0.5, -0.05, 0.0], true))
            .unwrap()
            .unwrap();
        assert!((c.pan - 0.17).abs() < 1e-12, "full deflection: the scale");
        assert!((c.tilt + 0.17).abs() < 1e-12);
        // 0.5 with a 0.1 dead zone: (0.5 - 0.1) / 0.9 of full scale.
        assert!((c.roll - 0.3 * 0.4 / 0.9).abs() < 1e-7, "{}", c.roll);
        assert_eq!(c.zoom, 0.0, "inside the dead zone");
        // Just past the dead zone the command starts from zero, no jump.
        let c = p.command(&joy(&[0.1001, 0.0, 0.0, 0.0, 0.0], true)).unwrap().unwrap();
        assert!(c.pan > 0.0 && c.pan < 1e-4, "{}", c.pan);
        // Beyond full deflection (a badly calibrated stick) is full deflection.
        let c = p.command(&joy(&[0.0, 0.0, 0.0, 0.0, 1.5], true)).unwrap().unwrap();
        assert!((c.zoom - 0.01).abs() < 1e-12);
        // A negative scale flips, an unmapped motion is zero.
        let q = JoyParams {
            pan: AngularAxis {
                axis: 2,
                scale_rad_s: -0.1,
            },
            roll: AngularAxis {
                axis: -1,
                scale_rad_s: 1.0,
            },
            ..p
        };
        let c = q.command(&joy(&[0.0, 0.0, 1.0, 1.0, 0.0], true)).unwrap().unwrap();
        assert!((c.pan + 0.1).abs() < 1e-12 && c.roll == 0.0);
    }

    #[test]
    fn nothing_without_the_deadman_and_bad_joys_are_named() {
        let p = JoyParams::default();
        assert_eq!(p.command(&joy(&[1.0, 1.0, 0.0, 1.0, 1.0], false)).unwrap(), None);
        assert_eq!(
            p.command(&joy(&[1.0, 1.0], true)).unwrap_err(),
            JoyError::Missing {
                what: "axes",
                index: 3,
                got: 2
            }
        );
        let mut j = joy(&[0.0, f32::NAN, 0.0, 0.0, 0.0], true);
        assert_eq!(p.command(&j).unwrap_err(), JoyError::NonFinite { index: 1 });
        j.axes[1] = 0.0;
        j.buttons.truncate(3);
        assert!(matches!(
            p.command(&j).unwrap_err(),
            JoyError::Missing {
                what: "buttons",
                index: 4,
                ..
            }
        ));
    }

    #[test]
    fn a_release_a_stale_or_a_bad_joy_sends_one_stop_then_silence() {
        let p = JoyParams::default();
        let mut s = ScopeJoy::default();
        let held = joy(&[1.0, 0.0, 0.0, 0.0, 0.0], true);
        let released = joy(&[1.0, 0.0, 0.0, 0.0, 0.0], false);
        let stop = Some(ScopeCommand::default());
        assert_eq!(s.tick(&p, None), (None, None), "no joystick: nothing");
        assert_eq!(s.tick(&p, Some((&released, 0.0))).0, None);
        let (c, _) = s.tick(&p, Some((&held, 0.0)));
        assert!((c.unwrap().pan - 0.17).abs() < 1e-12);
        assert!(s.tick(&p, Some((&held, 0.1))).0.is_some(), "held: sent at every tick");
        assert_eq!(s.tick(&p, Some((&released, 0.0))).0, stop, "released: one stop");
        assert_eq!(s.tick(&p, Some((&released, 0.05))).0, None, "then silence");
        // The Joy stream stops while held.
        assert!(s.tick(&p, Some((&held, 0.0))).0.is_some());
        assert_eq!(s.tick(&p, Some((&held, p.joy_timeout_s + 0.01))).0, stop);
        assert_eq!(s.tick(&p, Some((&held, p.joy_timeout_s + 0.05))).0, None);
        // A malformed Joy while held: a stop and the reason.
        assert!(s.tick(&p, Some((&held, 0.0))).0.is_some());
        let bad = joy(&[f32::NAN, 0.0, 0.0, 0.0, 0.0], true);
        let (c, e) = s.tick(&p, Some((&bad, 0.0)));
        assert_eq!(c, stop);
        assert_eq!(e, Some(JoyError::NonFinite { index: 0 }));
        assert_eq!(s.tick(&p, Some((&bad, 0.0))).0, None);
    }

    #[test]
    fn the_shipped_yaml_is_valid_and_bad_values_are_named() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("config/scope_joy.yaml");
        let p: JoyParams = crate::ros::params::from_yaml_file(&path).unwrap();
        p.validate().unwrap();
        assert_eq!(p, JoyParams::default(), "the built-in file is the defaults");
        assert_eq!((p.rate_hz, p.zoom.scale_m_s, p.deadman_button), (30.0, 0.01, 4));
        let partial: JoyParams =
            crate::config::from_yaml_str("t", "rate_hz: 20\nzoom: {axis: 5, scale_m_s: 0.02}\n").unwrap();
        let expected = JoyParams {
            rate_hz: 20.0,
            zoom: LinearAxis {
                axis: 5,
                scale_m_s: 0.02,
            },
            ..p.clone()
        };
        assert_eq!(partial, expected, "a partial file takes the rest from the built-in one");
        let e = crate::config::from_yaml_str::<JoyParams>("t", "rate: 20\n").unwrap_err();
        assert!(e.message.contains("`rate`: unknown key"), "{e}");
        for (text, message) in [
            ("joy_timeout: 1\n", "`joy_timeout`: the key is now `joy_timeout_s`"),
            (
                "pan: {axis: 0, scale: 0.1}\n",
                "`pan.scale`: the key is now `pan.scale_rad_s`",
            ),
        ] {
            let e = crate::config::from_yaml_str::<JoyParams>("t", text).unwrap_err();
            assert!(e.message.contains(message), "{e}");
        }
        let bad = [
            (
                "rate_hz",
                JoyParams {
                    rate_hz: 4.0,
                    ..p.clone()
                },
            ),
            (
                "dead_zone",
                JoyParams {
                    dead_zone: 1.0,
                    ..p.clone()
                },
            ),
            (
                "deadman_button",
                JoyParams {
                    deadman_button: -1,
                    ..p.clone()
                },
            ),
            (
                "zoom/scale_m_s",
                JoyParams {
                    zoom: LinearAxis {
                        axis: 4,
                        scale_m_s: f64::NAN,
                    },
                    ..p.clone()
                },
            ),
            (
                "tilt/axis",
                JoyParams {
                    tilt: AngularAxis {
                        axis: -2,
                        scale_rad_s: 0.1,
                    },
                    ..p.clone()
                },
            ),
        ];
        for (key, b) in bad {
            assert_eq!(b.validate().unwrap_err().key, key);
        }
    }
}
