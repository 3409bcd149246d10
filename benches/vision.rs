//! Marker detection + pose on synthetic 1280x720 frames: `cargo bench --bench vision`.

use criterion::{criterion_group, criterion_main, Criterion};
use std::hint::black_box;
use trocar_docking::vision::{
    facing_pose, render_marker_image, CameraModel, MarkerDetector, MarkerSpec, RenderOptions,
};

fn bench(c: &mut Criterion) {
    let cam = CameraModel::pinhole(1280, 720, 800.0, 800.0, 640.0, 360.0).expect("camera");
    let truth = facing_pose(0.6, 0.03, -0.02, 0.4, 0.3, 0.5);
    for (fam, noise) in [
        ("DICT_4X4_50", 0.0),
        ("DICT_4X4_50", 3.0),
        ("tag36h11", 0.0),
        ("tag36h11", 3.0),
    ] {
        let spec = MarkerSpec {
            family: fam.parse().expect("family"),
            id: Some(3),
            size_m: 0.05,
        };
        let opts = RenderOptions {
            noise_sigma: noise,
            ..Default::default()
        };
        let img = render_marker_image(&spec, &cam, &truth, &opts).expect("render");
        let mut det = MarkerDetector::new(spec, &cam).expect("detector");
        c.bench_function(&format!("detect_pose_{fam}_noise{noise}_1280x720"), |b| {
            b.iter(|| det.detect(black_box(&img.view())).expect("detect"))
        });
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);
