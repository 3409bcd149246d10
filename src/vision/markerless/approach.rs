//! Views along a docking approach: the camera on its mount beside the endoscope (the
//! flange's z axis along the trocar's axis, give or take a misalignment that shrinks as the
//! scope closes in), from far to near. The ground truth of the rendered sequences.

use nalgebra::{Isometry3, Translation3, Unit, UnitQuaternion, Vector3};
use rand::{RngExt, SeedableRng};

use crate::vision::VisionError;

/// Largest angle of the port from the optical axis, rad: nearer than the mount keeps the
/// port in view, the camera is turned towards it (a rotation about the camera centre, which
/// keeps the angle between the line of sight and the trocar's axis).
pub const MAX_OFF_AXIS: f64 = 0.35;

/// `n` port poses in the camera frame, the camera-to-port distance going linearly from
/// `far` to `near` (m), for the mount `flange_t_camera`. Per view, drawn from `seed`: the
/// trocar's axis tilted from the flange's z axis by up to 8 deg and the port off it by up to
/// 15 mm, both scaled by distance / 0.4 m.
pub fn docking_approach(
    flange_t_camera: &Isometry3<f64>,
    far: f64,
    near: f64,
    n: usize,
    seed: u64,
) -> Result<Vec<Isometry3<f64>>, VisionError> {
    let m = flange_t_camera.translation.vector;
    let lateral = (m.x * m.x + m.y * m.y).sqrt();
    crate::validate::in_range("near", near, lateral + 0.03, 2.0)?;
    crate::validate::in_range("far", far, near, 2.0)?;
    crate::validate::integer_in_range("n", n as i64, 1, 100_000)?;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let draw = |rng: &mut rand_chacha::ChaCha8Rng| {
        [
            rng.random_range(0.0..8f64.to_radians()),
            rng.random_range(0.0..std::f64::consts::TAU),
            rng.random_range(0.0..0.015),
            rng.random_range(0.0..std::f64::consts::TAU),
            rng.random_range(-std::f64::consts::PI..std::f64::consts::PI),
        ]
    };
    let mut out = Vec::with_capacity(n);
    for k in 0..n {
        let d = if n == 1 {
            far
        } else {
            far + (near - far) * k as f64 / (n - 1) as f64
        };
        let scale = d / 0.4;
        let [tilt, dir, off, odir, roll] = draw(&mut rng);
        let (tilt, off) = (tilt * scale, off * scale);
        let (ox, oy) = (off * odir.cos(), off * odir.sin());
        let (dx, dy) = (ox - m.x, oy - m.y);
        let s = m.z + (d * d - dx * dx - dy * dy).max(0.0).sqrt();
        let rot = UnitQuaternion::from_axis_angle(&Unit::new_normalize(Vector3::new(dir.cos(), dir.sin(), 0.0)), tilt)
            * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), roll);
        let flange_t_port = Isometry3::from_parts(Translation3::new(ox, oy, s), rot);
        let mut cam_t_port = flange_t_camera.inverse() * flange_t_port;
        let p = cam_t_port.translation.vector;
        let ang = p.normalize().z.clamp(-1.0, 1.0).acos();
        if ang > MAX_OFF_AXIS {
            let axis = Unit::new_normalize(p.cross(&Vector3::z()));
            let turn = UnitQuaternion::from_axis_angle(&axis, ang - MAX_OFF_AXIS);
            cam_t_port = Isometry3::from_parts(Translation3::identity(), turn) * cam_t_port;
        }
        out.push(cam_t_port);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_approach_spans_the_distances_and_keeps_the_port_in_view() {
        let mount = Isometry3::from_parts(
            Translation3::new(0.001, 0.0695, 0.0405),
            UnitQuaternion::from_axis_angle(&Vector3::x_axis(), 15.2f64.to_radians()),
        );
        let poses = docking_approach(&mount, 0.4, 0.1, 31, 5).unwrap();
        assert_eq!(poses.len(), 31);
        let dist: Vec<f64> = poses.iter().map(|p| p.translation.vector.norm()).collect();
        assert!((dist[0] - 0.4).abs() < 1e-9 && (dist[30] - 0.1).abs() < 1e-9);
        for p in &poses {
            let t = p.translation.vector;
            assert!(t.normalize().z.acos() <= MAX_OFF_AXIS + 1e-9);
            // The axis points away from the camera: the camera sees the top face.
            assert!((p.rotation * Vector3::z()).dot(&t) > 0.0);
        }
        assert!(docking_approach(&mount, 0.4, 0.05, 3, 1).is_err());
    }
}
