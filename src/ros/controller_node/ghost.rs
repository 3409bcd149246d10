//! The dry run's ghost arm: the arm the controller steers when its commands go to
//! `~preview` instead of the driver.
//!
//! In a dry run the real arm stands still, so its measured joints would soon lag the
//! commands by more than the command guard allows (`ARM_NOT_FOLLOWING`), and the docking
//! law would plan from a pose the arm never left. The ghost stands in for the arm as the
//! FRI position mode moves it: at the command it was given, one period later. It starts
//! where the real arm is (its first measured joints) and goes back there on a reset, so a
//! dry run begins from the real pose every time.
//!
//! Everything else stays real: the measurement's stamp (a driver that stops still makes the
//! joints stale and the controller hold), the external torques (the real arm at rest: no
//! contact) and the trocar pose (from the real camera through the real arm's pose).

use crate::control::ControlInput;
use crate::kinematics::JointVector;

/// The commanded arm of a dry run; `None` until the first measured joints.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Ghost {
    q: Option<JointVector>,
}

impl Ghost {
    /// The ghost's joints, once it has any.
    #[cfg(test)]
    pub fn joints(&self) -> Option<JointVector> {
        self.q
    }

    /// Put the ghost's joints in place of the measured ones, keeping the measurement's
    /// stamp. The first measurement places the ghost; no measurement leaves the input
    /// without joints, as it came.
    pub fn substitute(&mut self, input: &mut ControlInput) {
        if let Some(measured) = input.joints.as_mut() {
            match self.q {
                Some(q) => measured.value = q,
                None => self.q = Some(measured.value),
            }
        }
    }

    /// The step's command moves the ghost there (no command: it stays).
    pub fn follow(&mut self, command: Option<&JointVector>) {
        if let Some(c) = command {
            self.q = Some(*c);
        }
    }

    /// Back to the real arm at the next measurement (on a reset).
    pub fn clear(&mut self) {
        self.q = None;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::control::Stamped;

    fn input(q: Option<JointVector>, stamp: f64) -> ControlInput {
        ControlInput {
            now: stamp,
            joints: q.map(|value| Stamped { stamp, value }),
            tau_ext: None,
            torque_samples: Default::default(),
            trocar: None,
            scope: None,
        }
    }

    #[test]
    fn the_ghost_starts_at_the_arm_then_follows_its_commands_not_the_arm() {
        let real = JointVector::from_element(0.3);
        let mut g = Ghost::default();
        let mut i = input(Some(real), 1.0);
        g.substitute(&mut i);
        assert_eq!(
            i.joints.map(|j| j.value),
            Some(real),
            "the first step sees the real arm"
        );
        let command = JointVector::from_element(0.31);
        g.follow(Some(&command));
        let mut i = input(Some(real), 1.01);
        g.substitute(&mut i);
        let j = i.joints.expect("joints");
        assert_eq!(
            (j.value, j.stamp),
            (command, 1.01),
            "the ghost's joints, the measurement's stamp"
        );
        g.follow(None);
        assert_eq!(g.joints(), Some(command), "no command: the ghost stays");
    }

    #[test]
    fn no_measurement_stays_none_and_a_reset_returns_to_the_arm() {
        let mut g = Ghost::default();
        let mut i = input(None, 1.0);
        g.substitute(&mut i);
        assert!(i.joints.is_none() && g.joints().is_none());
        g.substitute(&mut input(Some(JointVector::zeros()), 1.0));
        g.follow(Some(&JointVector::from_element(0.5)));
        let mut stale = input(None, 2.0);
        g.substitute(&mut stale);
        assert!(
            stale.joints.is_none(),
            "a missing measurement is not made up by the ghost"
        );
        g.clear();
        let real = JointVector::from_element(-0.2);
        let mut i = input(Some(real), 3.0);
        g.substitute(&mut i);
        assert_eq!(i.joints.map(|j| j.value), Some(real));
    }
}
