//! One control step of the docking controller (criterion): `cargo bench --bench controller`.
//! The `trocar_docking bench --suite controller` command reports percentiles of the same.

use criterion::{criterion_group, criterion_main, Criterion};
use trocar_docking::bench::controller::{run_scenario, Scenario};
use trocar_docking::control::ControllerParams;
use trocar_docking::kinematics::lbr::{LbrModel, ToolParams};
use trocar_docking::kinematics::LbrKinematics;

fn bench(c: &mut Criterion) {
    let kin = LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default()).expect("model");
    let params = ControllerParams::default();
    for scenario in [Scenario::Approach, Scenario::Oscillating] {
        // 100 closed-loop steps per sample; criterion reports the time per 100 steps.
        c.bench_function(&format!("{}_x100", scenario.name()), |b| {
            b.iter(|| run_scenario(&kin, &params, scenario, 100).expect("scenario"))
        });
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);
