//! The simulator: one physics step (free, in contact) and one closed-loop trial:
//! `cargo bench --bench sim`.

use std::hint::black_box;
use std::sync::Arc;

use criterion::{criterion_group, criterion_main, Criterion};
use trocar_docking::bench::sim::world_in_contact;
use trocar_docking::kinematics::lbr::{LbrModel, ToolParams};
use trocar_docking::kinematics::{Kinematics, LbrKinematics};
use trocar_docking::sim::SimWorld;
use trocar_docking::trials::config::SimConfig;
use trocar_docking::trials::run::run_trial;

fn bench(c: &mut Criterion) {
    let cfg = SimConfig::load_default().expect("config");
    let kin: Arc<dyn Kinematics> =
        Arc::new(LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default()).expect("model"));
    let mut free = SimWorld::new(&cfg.sim, kin.clone(), 1).expect("world");
    c.bench_function("sim_physics_step_free", |b| {
        b.iter(|| black_box(free.step_physics().is_ok()))
    });
    let mut contact = world_in_contact(&cfg, kin.clone(), 1).expect("world");
    c.bench_function("sim_physics_step_contact", |b| {
        b.iter(|| black_box(contact.step_physics().is_ok()))
    });
    let mut g = c.benchmark_group("closed_loop");
    g.sample_size(10);
    let controller = trocar_docking::trials::config::load_controller(None).expect("controller config");
    for ff in [false, true] {
        let factory = trocar_docking::trials::policy::factory(&cfg, &controller, ff, kin.limits());
        if factory(1).is_err() {
            continue;
        }
        g.bench_function(if ff { "trial_ff" } else { "trial_no_ff" }, |b| {
            b.iter(|| {
                let mut w = SimWorld::new(&cfg.sim, kin.clone(), 1).expect("world");
                let mut p = factory(1).expect("policy");
                black_box(run_trial(&mut w, p.as_mut(), &cfg.trial, 1).time_s)
            })
        });
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
