//! The paper's experiment on the simulated plant ([`crate::sim`]): a policy (the docking
//! controller, [`controller_policy`], or the resolved-rate [`baseline`]) closes the loop
//! around a [`crate::sim::SimWorld`] for one trial ([`run`]); [`batch`] runs many trials
//! per arm (with and without force feedback) in parallel and sums them up; [`plot`] draws
//! the force traces and the M box plot. [`config`] reads `config/sim.yaml`. [`pivot`]: after
//! docking, steering the scope through the port with a script of surgeon's commands.

pub mod baseline;
pub mod batch;
pub mod closed_loop;
pub mod config;
pub mod controller_policy;
pub mod pivot;
pub mod plot;
pub mod policy;
pub mod run;
pub mod soak;
