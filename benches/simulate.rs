//! Simulator throughput: one paper-like run (30 s at 1 kHz, 4 RK4 sub-steps, events located).

use criterion::{criterion_group, criterion_main, Criterion};
use skelid::model::{EffectKind, RigModel};
use skelid::simulate::{simulate, Drive, SimSettings};

fn bench(c: &mut Criterion) {
    let mut m = RigModel::paper();
    m.effects.set(EffectKind::CoulombFriction, Some(2.5));
    let drive = Drive::Base(skelid::rig::paper_chirp());
    let s = SimSettings::default();
    c.bench_function("simulate paper run 30 s @ 1 kHz", |b| {
        b.iter(|| simulate(&m, &drive, &s))
    });
}

criterion_group!(benches, bench);
criterion_main!(benches);
