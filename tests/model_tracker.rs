//! ViSP's model-based tracker (`vpMbGenericTracker`) on rendered trocar images: it follows a
//! continuous approach, says when it has lost the trocar, and carries the track where the
//! per-frame estimate is not confident, never confidently wrong.

mod common;

use std::path::Path;

use nalgebra::{Isometry3, Point3, Vector3};
use trocar_docking::stats::finite_quantile;
use trocar_docking::vision::markerless::approach::continuous_approach;
use trocar_docking::vision::markerless::render::ToolCylinder;
use trocar_docking::vision::markerless::tracker::{cao, ModelTracker, TrackStep, TrackerParams};
use trocar_docking::vision::markerless::{
    Axis, MarkerlessEstimator, Scene, TrocarModel, TrocarRenderer, HIGH_CONFIDENCE,
};
use trocar_docking::vision::{CameraModel, GreyImage};

fn camera() -> CameraModel {
    common::zedm_camera()
}

fn mount() -> Isometry3<f64> {
    common::camera_mount()
}

/// Port error (mm) and axis error (deg) of `axis` against the true pose.
fn errors(axis: &Axis, truth: &Isometry3<f64>) -> (f64, f64) {
    let t = Axis::of_pose(truth);
    (
        (axis.point - t.point).norm() * 1e3,
        axis.direction.angle(&t.direction).to_degrees(),
    )
}

#[test]
fn the_model_is_the_trocar_yaml_as_polygons_visp_loads() {
    let model = TrocarModel::shipped();
    let text = cao(&model, 24);
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(lines[0], "V1");
    assert_eq!(lines[2], "72", "three rings of 24 corners");
    let corner = |i: usize| -> Vec<f64> { lines[3 + i].split(' ').map(|v| v.parse().unwrap()).collect() };
    // The rim's corners a little outside its radius (the sides' mean distance on it), the
    // opening's likewise, the bottom ring at the head's height.
    let (rim, opening, bottom) = (corner(0), corner(24), corner(48));
    let widen = rim[0] / model.head.radius;
    assert!(widen > 1.004 && widen < 1.008, "{widen}");
    assert!((opening[0] / model.opening.radius - widen).abs() < 1e-6);
    assert!((bottom[2] - model.head.height).abs() < 1e-9);
    // Two faces on the top, 24 on the side; no cylinder, no circle (ViSP 3.5.0's circles).
    assert!(text.contains("# Faces from 3D points\n26\n"));
    assert!(text.ends_with("# 3D cylinders\n0\n# 3D circles\n0\n"));

    let cam = camera();
    assert!(ModelTracker::new(&cam, &model, TrackerParams::default()).is_ok());
    for bad in [
        TrackerParams {
            range_px: 0.0,
            ..TrackerParams::default()
        },
        TrackerParams {
            polygon_sides: 3,
            ..TrackerParams::default()
        },
        TrackerParams {
            max_projection_error_deg: f64::NAN,
            ..TrackerParams::default()
        },
    ] {
        assert!(ModelTracker::new(&cam, &model, bad).is_err(), "{bad:?}");
    }
}

#[test]
fn bad_input_is_an_error_not_a_jump() {
    let cam = camera();
    let model = TrocarModel::shipped();
    let mut t = ModelTracker::new(&cam, &model, TrackerParams::default()).unwrap();
    let img = GreyImage {
        data: vec![128; (cam.width * cam.height) as usize],
        width: cam.width,
        height: cam.height,
    };
    // Tracking before a start.
    assert!(t.track(&img.view()).is_err());
    // A wrong image size.
    let small = GreyImage {
        data: vec![128; 64 * 48],
        width: 64,
        height: 48,
    };
    let axis = Axis {
        point: Vector3::new(0.0, 0.0, 0.3),
        direction: Vector3::z_axis(),
    };
    assert!(t.start(&small.view(), &axis).is_err());
    // A start behind the camera or not finite.
    for point in [Vector3::new(0.0, 0.0, -0.3), Vector3::new(f64::NAN, 0.0, 0.3)] {
        let e = t.start(&img.view(), &Axis { point, ..axis });
        assert!(e.is_err(), "{point:?}");
        assert!(!t.is_tracking());
    }
    // A grey image with nothing in it: started, then lost at once.
    t.start(&img.view(), &axis).unwrap();
    assert!(matches!(t.track(&img.view()).unwrap(), TrackStep::Lost(_)));
    assert!(!t.is_tracking());
}

/// Tracks the continuous approach of `seed` from the true pose of its first image, 151
/// images from 0.4 to 0.1 m; the port and axis errors of every image (`None`: lost).
fn track_approach(seed: u64) -> Vec<Option<(f64, f64, f64)>> {
    let cam = camera();
    let model = TrocarModel::shipped();
    let r = TrocarRenderer::new(&cam).unwrap();
    let poses = continuous_approach(&mount(), 0.4, 0.1, 151, seed).unwrap();
    let scene = Scene::random(seed, 2.0);
    let mut t = ModelTracker::new(&cam, &model, TrackerParams::default()).unwrap();
    let mut out = vec![];
    for (k, p) in poses.iter().enumerate() {
        let img = r.render(&model, p, &scene).unwrap();
        if k == 0 {
            t.start(&img.view(), &Axis::of_pose(p)).unwrap();
        }
        out.push(match t.track(&img.view()).unwrap() {
            TrackStep::Tracked(tp) => {
                let (dp, da) = errors(&tp.axis, p);
                Some((dp, da, tp.confidence))
            }
            TrackStep::Lost(_) => break,
        });
    }
    out
}

/// The tracker left alone on one recorded approach (seed 2): it holds every image, the
/// port's error shrinking with the distance. Not every approach goes so: on seed 4's it
/// settles on the other pose the face's circles admit at 0.4 m (26 deg off) and keeps it
/// with a good fit, which is why the estimator lets it carry the track only briefly.
#[test]
fn the_tracker_follows_a_continuous_approach() {
    let seed = 2u64;
    let e = track_approach(seed);
    assert_eq!(e.len(), 151, "seed {seed}: lost after {} images", e.len());
    let port: Vec<f64> = e.iter().flatten().map(|x| x.0).collect();
    let axis: Vec<f64> = e.iter().flatten().map(|x| x.1).collect();
    let near: Vec<f64> = port[100..].to_vec();
    let (pm, am, nm) = (
        finite_quantile(&port, 0.5),
        finite_quantile(&axis, 0.5),
        finite_quantile(&near, 0.5),
    );
    eprintln!("seed {seed}: port median {pm:.2} mm (under 0.2 m: {nm:.2} mm), axis median {am:.2} deg");
    assert!(pm <= TRACKED_PORT_MEDIAN_MM, "seed {seed}: port median {pm:.2} mm");
    assert!(
        nm <= TRACKED_NEAR_PORT_MEDIAN_MM,
        "seed {seed}: near port median {nm:.2} mm"
    );
    assert!(am <= TRACKED_AXIS_MEDIAN_DEG, "seed {seed}: axis median {am:.2} deg");
}

/// Bounds just above the measured figures of the tracker left alone (docs/markerless.md).
const TRACKED_PORT_MEDIAN_MM: f64 = 4.0;
const TRACKED_NEAR_PORT_MEDIAN_MM: f64 = 2.0;
const TRACKED_AXIS_MEDIAN_DEG: f64 = 1.0;

#[test]
fn the_tracker_loses_a_trocar_that_leaves_the_view() {
    let cam = camera();
    let model = TrocarModel::shipped();
    let r = TrocarRenderer::new(&cam).unwrap();
    let poses = continuous_approach(&mount(), 0.25, 0.24, 6, 5).unwrap();
    let mut scene = Scene::random(5, 2.0);
    let mut t = ModelTracker::new(&cam, &model, TrackerParams::default()).unwrap();
    let img = r.render(&model, &poses[0], &scene).unwrap();
    t.start(&img.view(), &Axis::of_pose(&poses[0])).unwrap();
    for p in &poses[1..5] {
        let img = r.render(&model, p, &scene).unwrap();
        let step = t.track(&img.view()).unwrap();
        assert!(matches!(step, TrackStep::Tracked(_)), "{step:?}");
    }
    scene.show_trocar = false;
    let img = r.render(&model, &poses[5], &scene).unwrap();
    let step = t.track(&img.view()).unwrap();
    assert!(matches!(step, TrackStep::Lost(_)), "{step:?}");
    assert!(!t.is_tracking());
}

/// A tool shaft (10 mm across) lying over the port, between it and the camera: 2 cm above
/// the face, across the axis.
fn tool_over(port: &Isometry3<f64>) -> ToolCylinder {
    let at = |x: f64| -> [f64; 3] { (port * Point3::new(x, 0.0, -0.02)).coords.into() };
    ToolCylinder {
        start: at(-0.08),
        end: at(0.08),
        radius: 0.005,
    }
}

/// The hidden images of an approach (0.3 -> 0.15 m, seed 6) with a tool over the port for
/// images 20-29, through the estimator with a tracker that may carry `max_frames`: how many
/// it carried, and their largest port error (mm).
fn carried_through_the_tool(max_frames: usize) -> (usize, f64) {
    let cam = camera();
    let model = TrocarModel::shipped();
    let r = TrocarRenderer::new(&cam).unwrap();
    let poses = continuous_approach(&mount(), 0.3, 0.15, 61, 6).unwrap();
    let scene = Scene::random(6, 2.0);
    let hidden = 20..30;
    let mut est = MarkerlessEstimator::new(&cam, &model).unwrap().with_tracker(Some((
        ModelTracker::new(&cam, &model, TrackerParams::default()).unwrap(),
        max_frames,
    )));
    let (mut carried, mut worst) = (0, 0.0f64);
    for (k, p) in poses.iter().enumerate() {
        let mut s = scene.clone();
        if hidden.contains(&k) {
            s.tool = Some(tool_over(p));
        }
        let img = r.render(&model, p, &s).unwrap();
        let Some(e) = est.estimate(&img.view(), None).unwrap() else {
            continue;
        };
        let (dp, da) = errors(&e.axis, p);
        assert!(
            e.confidence < HIGH_CONFIDENCE || (dp <= 10.0 && da <= 5.0),
            "image {k}: confident and wrong, {dp:.1} mm {da:.1} deg (tracked {}, {:.2})",
            e.tracked.is_some(),
            e.confidence
        );
        if hidden.contains(&k) && e.tracked.is_some() {
            carried += 1;
            worst = worst.max(dp);
            assert!(da <= 2.0, "image {k}: carried {da:.2} deg off");
        }
        if !hidden.contains(&k) && k > 0 {
            assert!(
                e.tracked.is_none(),
                "image {k}: the per-frame estimate answers where it can"
            );
        }
    }
    (carried, worst)
}

#[test]
fn the_tracker_carries_the_track_where_the_opening_is_hidden() {
    let (carried, worst) = carried_through_the_tool(15);
    eprintln!("hidden images: {carried} carried by the tracker, port error at most {worst:.1} mm");
    assert!(carried >= 8, "the tracker carried {carried} of the 10 hidden images");
    assert!(worst <= 10.0, "carried {worst:.1} mm off");
    // At most `max_frames` in a row.
    assert_eq!(carried_through_the_tool(3).0, 3);
}

#[test]
fn trocar_pose_tracks_a_continuous_sequence_and_says_the_source() {
    let exe = env!("CARGO_BIN_EXE_trocar_docking");
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let dir = std::env::temp_dir().join(format!("tracker_seq_{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let run = |args: &[&str]| {
        let out = std::process::Command::new(exe)
            .current_dir(root)
            .args(args)
            .arg(&dir)
            .output()
            .unwrap();
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        out
    };
    let cam = "config/camera_zedm.yaml";
    run(&[
        "render-trocar",
        "--camera",
        cam,
        "--sequence",
        "8",
        "--continuous",
        "--range",
        "0.2,0.19",
        "--seed",
        "3",
        "--out",
    ]);
    let truth: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("truth.json")).unwrap()).unwrap();
    let frames = truth["frames"].as_array().unwrap();
    // One scene for the whole video.
    assert!(frames.iter().all(|f| f["scene"] == frames[0]["scene"]));
    let out = run(&["trocar-pose", "--json", "--tracker", "--camera", cam, "--images"]);
    let lines: Vec<serde_json::Value> = String::from_utf8_lossy(&out.stdout)
        .lines()
        .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("not a JSON line ({e}): {l}")))
        .collect();
    assert_eq!(lines.len(), frames.len());
    for (e, t) in lines.iter().zip(frames) {
        assert_eq!(e["image"], t["image"]);
        assert!(e["source"] == "detector" || e["source"] == "tracker", "{e}");
        assert!(
            e["confidence"].as_f64().is_some_and(|c| (0.0..=1.0).contains(&c)),
            "{e}"
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}
