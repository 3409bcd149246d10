//! Force sensing from the external joint torques: the tare at every start ([`tare`]) with
//! its pose-dependent payload fit ([`payload`]), and the tip force estimate with the
//! admittance law ([`admittance`]); the shaft's whole wrench with its low-pass, the force the
//! fulcrum's adaptation reads ([`wrench`]).

pub mod admittance;
pub mod payload;
pub mod tare;
pub mod wrench;
