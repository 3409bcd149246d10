//! FK + Jacobian through the KDL bridge: `cargo bench --bench kinematics`.

use criterion::{criterion_group, criterion_main, Criterion};
use std::hint::black_box;
use trocar_docking::kinematics::lbr::{LbrModel, ToolParams};
use trocar_docking::kinematics::{JointVector, Kinematics, LbrKinematics};

fn bench(c: &mut Criterion) {
    let kin = LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default()).expect("model");
    let q = JointVector::from_column_slice(&[0.3, 0.6, -0.2, -1.2, 0.4, 0.8, 0.1]);
    c.bench_function("fk_jacobian_med7", |b| {
        b.iter(|| kin.fk_jacobian(black_box(&q)).unwrap())
    });
    c.bench_function("fk_med7", |b| b.iter(|| kin.fk(black_box(&q)).unwrap()));
}

criterion_group!(benches, bench);
criterion_main!(benches);
