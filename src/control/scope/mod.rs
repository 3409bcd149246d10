//! After docking: the port held as a remote centre of motion while the surgeon steers the
//! scope through it (config key `scope:`, topic `scope_command`). [`command`]: the
//! surgeon's commands, the limits, the parameters and the report; [`pivot`]: the law about
//! the port, and the retract; [`fulcrum`]: the fulcrum adapted from the contact;
//! [`port_follow`]: the port's breathing along the docking axis.

pub mod command;
pub mod fulcrum;
pub mod pivot;
pub mod port_follow;
