//! The markerless cases of the vision suite: the trocar's axis from 1280x720 frames rendered
//! along the docking approach (camera_zedm, noise 2; mono, and with the stereo pair's right
//! image, camera_zedm_right), timed per frame on one core, with the
//! accuracy against the truth in `extra`; and the render itself (what the simulated camera
//! spends per frame without the marker, on rayon's threads and on the one thread it runs on).

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

use super::{time_each, LatencyStats, SuiteReport};
use crate::vision::markerless::approach::docking_approach;
use crate::vision::markerless::{MarkerlessEstimator, Scene, TrocarModel, TrocarRenderer};
use crate::vision::{CameraModel, GreyImage, VisionError};

/// The estimates' accuracy for the report: frames, found, and the port's and the axis's
/// median and largest errors (mm, deg).
fn accuracy(
    frames: usize,
    found: usize,
    mut pos: Vec<f64>,
    mut ang: Vec<f64>,
) -> serde_json::Map<String, serde_json::Value> {
    pos.sort_by(f64::total_cmp);
    ang.sort_by(f64::total_cmp);
    let mut extra = serde_json::Map::new();
    extra.insert("frames".into(), frames.into());
    extra.insert("found".into(), found.into());
    if !pos.is_empty() {
        for (key, v, q) in [
            ("port_error_median_mm", &pos, 0.5),
            ("port_error_max_mm", &pos, 1.0),
            ("axis_error_median_deg", &ang, 0.5),
            ("axis_error_max_deg", &ang, 1.0),
        ] {
            extra.insert(key.into(), crate::stats::quantile_sorted(v, q).into());
        }
    }
    extra
}

/// One estimate case: the accuracy of `est` on `frames` (with the stereo pair's `right`
/// frames, if any) against `poses`, and `n` timed estimates (the frames cycle).
fn axis_case(
    name: &str,
    mut est: MarkerlessEstimator,
    frames: &[GreyImage],
    right: Option<&[GreyImage]>,
    poses: &[Isometry3<f64>],
    n: usize,
) -> Result<Option<SuiteReport>, VisionError> {
    let right_view = |i: usize| right.map(|r| r[i].view());
    let (mut pos, mut ang, mut found) = (vec![], vec![], 0usize);
    for (i, (img, p)) in frames.iter().zip(poses).enumerate() {
        if let Some(e) = est.estimate_stereo(&img.view(), right_view(i).as_ref(), None)? {
            found += 1;
            pos.push((e.axis.point - p.translation.vector).norm() * 1e3);
            ang.push(
                e.axis
                    .direction
                    .dot(&(p.rotation * Vector3::z()))
                    .clamp(-1.0, 1.0)
                    .acos()
                    .to_degrees(),
            );
        }
    }
    let idx: Vec<usize> = (0..n.clamp(1, 300)).map(|i| i % frames.len()).collect();
    let t = time_each(&idx, 3, |&i| {
        est.estimate_stereo(&frames[i].view(), right_view(i).as_ref(), None)
            .map(|e| e.is_some())
    });
    Ok(LatencyStats::from_samples(&t).map(|latency| SuiteReport {
        name: name.into(),
        latency,
        extra: accuracy(frames.len(), found, pos, ang),
    }))
}

/// Run the cases: 12 frames from 0.4 to 0.1 m, `n` timed estimates (frames cycle), mono and
/// with the stereo pair's right image; the renders.
pub fn run(n: usize) -> Result<Vec<SuiteReport>, VisionError> {
    let camera = CameraModel::from_yaml_str(include_str!("../../config/camera_zedm.yaml"))?;
    let model = TrocarModel::shipped();
    let renderer = TrocarRenderer::new(&camera)?;
    // The mount of config/lbr_med_sim.yaml.
    let mount = Isometry3::from_parts(
        Translation3::new(0.001, 0.0695, 0.0405),
        UnitQuaternion::from_axis_angle(&Vector3::x_axis(), 15.2f64.to_radians()),
    );
    let poses = docking_approach(&mount, 0.4, 0.1, 12, 17)?;
    let frames: Vec<GreyImage> = poses
        .iter()
        .enumerate()
        .map(|(k, p)| renderer.render(&model, p, &Scene::random(17_000 + k as u64, 2.0)))
        .collect::<Result<_, _>>()?;
    let render_idx: Vec<usize> = (0..n.clamp(1, 24)).map(|i| i % poses.len()).collect();
    // Per pixel (the offline tools), and with the wall every 4 px (the simulated camera),
    // on rayon's threads; and the simulated camera's on one thread, as it runs.
    let one_thread = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .map_err(|e| VisionError::InvalidInput(format!("thread pool: {e}")))?;
    let render_t = [(1, None), (4, None), (4, Some(&one_thread))].map(|(step, pool)| {
        let r = renderer.clone().with_wall_step(step);
        let frame = |i: usize| {
            r.render(&model, &poses[i], &Scene::random(18_000 + i as u64, 2.0))
                .map(|_| true)
        };
        time_each(&render_idx, 1, |&i| match pool {
            Some(p) => p.install(|| frame(i)),
            None => frame(i),
        })
    });
    let right_camera = CameraModel::from_yaml_str(include_str!("../../config/camera_zedm_right.yaml"))?;
    let right_t_left = right_camera.stereo_right_t_left();
    let right_renderer = TrocarRenderer::new(&right_camera)?;
    let right_frames: Vec<GreyImage> = poses
        .iter()
        .enumerate()
        .map(|(k, p)| right_renderer.render(&model, &(right_t_left * p), &Scene::random(17_000 + k as u64, 2.0)))
        .collect::<Result<_, _>>()?;
    let mono = MarkerlessEstimator::new(&camera, &model)?;
    let stereo = MarkerlessEstimator::for_cameras(&camera, Some(&right_camera), &model)?;
    let mut out = vec![];
    for (name, est, right) in [
        ("markerless_axis_zedm_1280x720", mono, None),
        (
            "markerless_axis_stereo_zedm_1280x720",
            stereo,
            Some(right_frames.as_slice()),
        ),
    ] {
        out.extend(axis_case(name, est, &frames, right, &poses, n)?);
    }
    for (t, (name, threads)) in render_t.iter().zip([
        ("markerless_render_zedm_1280x720", rayon::current_num_threads()),
        ("markerless_render_wall4_zedm_1280x720", rayon::current_num_threads()),
        ("markerless_render_wall4_1thread_zedm_1280x720", 1),
    ]) {
        if let Some(latency) = LatencyStats::from_samples(t) {
            let mut extra = serde_json::Map::new();
            extra.insert("threads".into(), threads.into());
            out.push(SuiteReport {
                name: name.into(),
                latency,
                extra,
            });
        }
    }
    Ok(out)
}
