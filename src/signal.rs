//! Small signal-processing helpers shared by the controller and the simulated sensors.

/// Dead-band: values within ±`band` become 0, others shrink towards 0 by `band`.
pub fn deadband(x: f64, band: f64) -> f64 {
    if x > band {
        x - band
    } else if x < -band {
        x + band
    } else {
        0.0
    }
}
