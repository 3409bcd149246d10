//! Safety: the command guard ([`guard`]) and the guard as a decorator around any command
//! source ([`guarded`]), the typed hold reasons ([`hold`]), and the tip's speed,
//! acceleration and jerk bounded in every phase ([`motion`]), and the audit of a published
//! command stream against the guard's limits ([`audit`]).

pub mod audit;
pub mod guard;
pub mod guarded;
pub mod hold;
pub mod motion;
