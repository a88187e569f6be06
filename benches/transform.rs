//! Band-limited transform + DP ridge + skeleton against the plain full-length CWT + argmax
//! ridge, on the same log sweep (`skelid bench --transform` runs the large sizes, HDF5 in).

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use skelid::bench::{bench_signal, BENCH_BAND, BENCH_FS};
use skelid::track::{track_wavelet, WaveletOptions};
use skelid::transform::{log_frequencies, naive, Morlet, Spectrum};

fn transform(c: &mut Criterion) {
    let mut group = c.benchmark_group("transform");
    group.sample_size(10);
    for log2n in [14u32, 17] {
        let x = bench_signal(1 << log2n);
        for scales in [64usize, 256] {
            let id = format!("2^{log2n}x{scales}");
            group.bench_with_input(BenchmarkId::new("skelid", &id), &x, |b, x| {
                let opt = WaveletOptions {
                    fmin: Some(BENCH_BAND.0),
                    fmax: Some(BENCH_BAND.1),
                    scales,
                    ..WaveletOptions::default()
                };
                b.iter(|| track_wavelet(x, BENCH_FS, &opt, None).unwrap())
            });
            group.bench_with_input(BenchmarkId::new("naive", &id), &x, |b, x| {
                let wl = Morlet::default();
                let freqs = log_frequencies(BENCH_BAND.0, BENCH_BAND.1, scales);
                b.iter(|| {
                    let spec = Spectrum::new(x, BENCH_FS, 8600);
                    naive::argmax_ridge(&spec, &wl, &freqs)
                })
            });
        }
    }
    group.finish();
}

criterion_group!(benches, transform);
criterion_main!(benches);
