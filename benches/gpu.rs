//! The backends side by side on a batch of paper-like runs: the wavelet tracks of 16 chirps
//! of 30 000 samples with 128 scales, first pass on the CPU or on the GPU (whatever adapter
//! wgpu opens: lavapipe here, a real GPU elsewhere; without one only the CPU is measured).
//! `skelid bench ARCHIVE` measures the same on a campaign's own runs.

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use skelid::backend::{Backend, BackendChoice};
use skelid::track::WaveletOptions;

fn chirps(count: usize) -> Vec<Vec<f64>> {
    (0..count)
        .map(|k| {
            (0..30_000)
                .map(|i| {
                    let t = i as f64 / 1000.0;
                    let f0 = 0.5 + 0.05 * k as f64;
                    (2.0 * std::f64::consts::PI * (f0 * t + 0.2 * t * t)).sin()
                })
                .collect()
        })
        .collect()
}

fn backends(c: &mut Criterion) {
    let signals = chirps(16);
    let refs: Vec<skelid::backend::Signal> = signals
        .iter()
        .map(|x| skelid::backend::Signal {
            samples: x,
            sample_rate: 1000.0,
            guide: None,
        })
        .collect();
    let opt = WaveletOptions {
        scales: 128,
        ..WaveletOptions::default()
    };
    let mut group = c.benchmark_group("backend");
    group.sample_size(10);
    let mut all = vec![("cpu".to_string(), Backend::cpu())];
    match Backend::open(BackendChoice::Gpu) {
        Ok(g) => all.push((format!("gpu {}", g.adapter().unwrap_or("?")), g)),
        Err(e) => eprintln!("GPU not measured: {e}"),
    }
    for (name, backend) in &all {
        group.bench_with_input(BenchmarkId::new(name, "16x30000x128"), &refs, |b, refs| {
            b.iter(|| backend.track_many(refs, &opt))
        });
    }
    group.finish();
}

criterion_group!(benches, backends);
criterion_main!(benches);
