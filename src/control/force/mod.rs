//! Force sensing from the external joint torques: the tare at every start ([`tare`]) with
//! its pose-dependent payload fit ([`payload`]), and the tip force estimate with the
//! admittance law ([`admittance`]).

pub mod admittance;
pub mod payload;
pub mod tare;
