//! Markerless trocar pose: the trocar's axis (5 DOF: the port centre and the axis
//! direction; roll does not matter) from one image, from the shape in
//! `config/trocar_model.yaml` alone. See docs/markerless.md.

pub mod approach;
pub mod estimator;
pub mod geometry;
pub mod measurement;
pub mod model;
pub mod render;
pub mod scope_in_view;

pub use estimator::{MarkerlessEstimate, MarkerlessEstimator, Occluder, HIGH_CONFIDENCE};
pub use geometry::Axis;
pub use measurement::{EstimatorMethod, MarkerlessParams};
pub use model::TrocarModel;
pub use render::{Scene, TrocarRenderer};
