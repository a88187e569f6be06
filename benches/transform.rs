//! Band-limited transform + DP ridge + skeleton against the plain full-length CWT + argmax
//! ridge, on the same log sweep (`skelid bench --transform` runs the large sizes, HDF5 in).

use std::hint::black_box;
use std::time::{Duration, Instant};

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

/// The CPU's own share of a GPU track, which no device hides: preparing a signal (band,
/// spectrum, plans) and completing its track from the skeleton (noise floor, validity,
/// smoothing, every sample), for one 30 000-sample record of the throughput campaign's size,
/// on one core of a pool, as skelid runs it.
fn host_share(c: &mut Criterion) {
    use skelid::track::{Device, WaveletPrep};
    // As skelid runs: malloc keeps freed blocks, so a track's arrays are reused memory,
    // not pages the kernel must fault in and zero.
    skelid::backend::keep_freed_memory();
    // Timed inside a pool of one thread, as a worker tracks a campaign signal: its loops
    // over the signal's points stay one task. Called from outside a pool, each loop handed
    // its task to a pool thread and slept until it was done, and a quarter of the time
    // measured was the kernel's wake-ups.
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .expect("a pool of one thread");
    let on_one_core = |iters: u64, f: &(dyn Fn() -> Duration + Sync)| {
        pool.install(|| (0..iters).map(|_| f()).sum::<Duration>())
    };
    let mut group = c.benchmark_group("host_share");
    group.sample_size(20);
    let x = bench_signal(30_000);
    let opt = WaveletOptions {
        scales: 128,
        ..WaveletOptions::default()
    };
    let timed = |f: &dyn Fn()| {
        let start = Instant::now();
        f();
        start.elapsed()
    };
    group.bench_function("prepare", |b| {
        b.iter_custom(|iters| {
            on_one_core(iters, &|| {
                timed(&|| {
                    drop(black_box(
                        WaveletPrep::new(&x, BENCH_FS, &opt, None).unwrap(),
                    ))
                })
            })
        })
    });
    // What the GPU backend's workers do before the device takes a signal, for the log sweep
    // and for a campaign-like chirp (`chirp_signal`).
    let chirp = chirp_signal(30_000);
    for (name, x) in [("prepare_deferred", &x), ("prepare_deferred_chirp", &chirp)] {
        group.bench_function(name, |b| {
            b.iter_custom(|iters| {
                on_one_core(iters, &|| {
                    timed(&|| {
                        drop(black_box(
                            WaveletPrep::new_deferred(x, BENCH_FS, &opt, None).unwrap(),
                        ))
                    })
                })
            })
        });
    }
    // As `bench` and `run` prepare them: many records, each once, so that their samples come
    // from memory rather than the cache (400 chirps, 96 MB; a 2000-signal `bench`
    // repetition's are 480 MB). One record prepared over and over, as above, hides what
    // reading cold samples costs: a third of a group's deferred preparations by `perf`
    // before the fortieth session read short records once (README, *Since … fortieth
    // session*). Each iteration is the 400 preparations.
    let many: Vec<Vec<f64>> = (0..400)
        .map(|seed| chirp_signal_seeded(30_000, seed))
        .collect();
    group.bench_function("prepare_deferred_400_chirps", |b| {
        b.iter_custom(|iters| {
            on_one_core(iters, &|| {
                timed(&|| {
                    for x in &many {
                        drop(black_box(
                            WaveletPrep::new_deferred(x, BENCH_FS, &opt, None).unwrap(),
                        ))
                    }
                })
            })
        })
    });
    // The log sweep's grid is dense (about 5 000 points, segments of about 6 samples); a
    // throughput campaign signal's is sparser (the chirp to 12 Hz: about 2 300 points,
    // segments of about 13 samples), so the per-sample work weighs more there: both timed.
    for (name, x) in [("complete", &x), ("complete_chirp", &chirp)] {
        let prep = WaveletPrep::new(x, BENCH_FS, &opt, None).unwrap();
        let ridge = prep.coarse_ridge();
        let grid = prep.grid(&ridge.path);
        let est = prep.estimate_grid(&grid);
        group.bench_function(name, |b| {
            b.iter_custom(|iters| {
                on_one_core(iters, &|| {
                    let (p, r) = (prep.clone(), ridge.clone());
                    let start = Instant::now();
                    let track = black_box(p.complete(r, &grid, &est, Device::Gpu));
                    let took = start.elapsed();
                    drop(track);
                    took
                })
            })
        });
    }
    group.finish();
}

/// A throughput campaign's kind of record at [`BENCH_FS`]: a linear chirp from 0.2 to 12 Hz
/// over the record, with 1 % noise (an amplitude that falls with the frequency brings in the
/// low-SNR smoothing, which the campaign's records barely need: under 0.3 % of its CPU time
/// by `perf`).
fn chirp_signal(n: usize) -> Vec<f64> {
    chirp_signal_seeded(n, 7)
}

/// [`chirp_signal`] with the noise of `seed`.
fn chirp_signal_seeded(n: usize, seed: u64) -> Vec<f64> {
    use rand::{Rng, SeedableRng};
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let t_end = n as f64 / BENCH_FS;
    let (f0, f1) = (0.2, 12.0);
    (0..n)
        .map(|i| {
            let t = i as f64 / BENCH_FS;
            let phase = 2.0 * std::f64::consts::PI * (f0 * t + (f1 - f0) * t * t / (2.0 * t_end));
            phase.sin() + 0.01 * rng.random_range(-1.7..1.7)
        })
        .collect()
}

/// A long record's spectrum, realfft's serial plan against the four-step on every core
/// (`transform::parallel`), at the two lengths a 2^20-sample record's preparation takes:
/// its band's (2^20) and its padded spectrum's (1.6 M points for the log sweep below).
fn long_spectrum(c: &mut Criterion) {
    skelid::backend::keep_freed_memory();
    let mut group = c.benchmark_group("long_spectrum");
    group.sample_size(20);
    let x = bench_signal(1 << 20);
    for len in [1usize << 20, 1_600_000] {
        group.bench_with_input(BenchmarkId::new("realfft", len), &len, |b, &len| {
            b.iter(|| skelid::transform::serial_spectrum(&x, 0.0, len))
        });
        group.bench_with_input(BenchmarkId::new("four_step", len), &len, |b, &len| {
            b.iter(|| skelid::transform::parallel::real_spectrum(&x, 0.0, len))
        });
    }
    group.finish();
}

criterion_group!(benches, transform, host_share, long_spectrum);
criterion_main!(benches);
