//! `skelid bench --transform`: our band-limited transform + ridge + skeleton against the
//! plain full-length CWT + argmax ridge, HDF5 in, on the same signal, in one run; and
//! `skelid bench ARCHIVE --backend cpu,gpu` ([`backends`]): the two backends side by side.
//!
//! Each measurement runs in its own child process (`skelid __bench-one`) so that its peak
//! resident memory (VmHWM) is its own.

pub mod backends;

use std::f64::consts::PI;
use std::path::Path;
use std::time::Instant;

use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use serde::{Deserialize, Serialize};

use crate::campaign::{write_campaign, Attr, RunData, WriteError};
use crate::ingest::{Archive, IngestError, IngestOptions, Quantity, RunKind};
use crate::track::{track_wavelet, TrackError, WaveletOptions};
use crate::transform::{log_frequencies, naive, Morlet, Spectrum};

/// Sample rate of the benchmark signal (Hz).
pub const BENCH_FS: f64 = 1000.0;
/// Analysis band of the benchmark (Hz), as in the fCWT comparison.
pub const BENCH_BAND: (f64, f64) = (0.5, 50.0);

/// A logarithmic sweep over the benchmark band with 40 dB of white noise.
pub fn bench_signal(n: usize) -> Vec<f64> {
    let t_end = n as f64 / BENCH_FS;
    let (f0, f1) = BENCH_BAND;
    let k = (f1 / f0).ln() / t_end;
    let mut rng = rand::rngs::StdRng::seed_from_u64(1);
    let noise = Normal::new(0.0, 0.01).expect("valid sigma");
    (0..n)
        .map(|i| {
            let t = i as f64 / BENCH_FS;
            let phase = 2.0 * PI * f0 * ((k * t).exp() - 1.0) / k;
            phase.sin() + noise.sample(&mut rng)
        })
        .collect()
}

/// Why a benchmark measurement failed.
#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    /// Writing the benchmark archive.
    #[error(transparent)]
    Write(#[from] WriteError),
    /// Reading it back.
    #[error(transparent)]
    Ingest(#[from] IngestError),
    /// Tracking it.
    #[error(transparent)]
    Track(#[from] TrackError),
}

/// Writes the benchmark signal as a one-run free-decay campaign.
pub fn write_bench_archive(path: &Path, n: usize) -> Result<(), BenchError> {
    let run = RunData {
        path: "/bench/sweep".into(),
        sample_rate: BENCH_FS,
        kind: RunKind::Free,
        input_quantity: None,
        output_quantity: Quantity::Displacement,
        input: None,
        output: bench_signal(n),
        attrs: vec![("excitation".into(), Attr::Text("log sweep".into()))],
    };
    write_campaign(path, &[], &[run], false)?;
    Ok(())
}

/// Which implementation a measurement runs.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, Eq)]
pub enum Variant {
    /// Band-limited transform, DP ridge, corrected skeleton (the pipeline).
    Fast,
    /// Full-length inverse FFT per scale, argmax ridge (the baseline).
    Naive,
}

impl Variant {
    /// The name a child measurement is asked for by (`fast`, `naive`).
    pub fn name(self) -> &'static str {
        match self {
            Variant::Fast => "fast",
            Variant::Naive => "naive",
        }
    }

    /// The variant of that name.
    pub fn from_name(s: &str) -> Option<Variant> {
        [Variant::Fast, Variant::Naive]
            .into_iter()
            .find(|v| v.name() == s)
    }
}

/// One measurement.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Measurement {
    /// Wall time (s), HDF5 read included.
    pub seconds: f64,
    /// Peak resident memory of the process (MiB).
    pub peak_mib: f64,
    /// Fraction of samples marked valid (fast) or 1 (naive).
    pub valid: f64,
}

/// Runs one variant on the archive at `path` with `scales` scales (in this process).
pub fn measure(path: &Path, variant: Variant, scales: usize) -> Result<Measurement, BenchError> {
    let start = Instant::now();
    let archive = Archive::open(path, &IngestOptions::default())?;
    let meta = archive.runs[0].meta.clone()?; // a written archive has its one run
    let run = archive.load(&meta)?;
    let x = run.output;
    let valid = match variant {
        Variant::Fast => {
            let opt = WaveletOptions {
                fmin: Some(BENCH_BAND.0),
                fmax: Some(BENCH_BAND.1),
                scales,
                ..WaveletOptions::default()
            };
            let tr = track_wavelet(&x, meta.sample_rate, &opt, None)?;
            tr.valid_fraction()
        }
        Variant::Naive => {
            let wl = Morlet::default();
            let pad = (wl.support(wl.scale_for(BENCH_BAND.0), 1e-8) * BENCH_FS).ceil() as usize;
            let spec = Spectrum::new(&x, meta.sample_rate, pad);
            let freqs = log_frequencies(BENCH_BAND.0, BENCH_BAND.1, scales);
            let (best, _) = naive::argmax_ridge(&spec, &wl, &freqs);
            std::hint::black_box(&best);
            1.0
        }
    };
    Ok(Measurement {
        seconds: start.elapsed().as_secs_f64(),
        peak_mib: peak_rss_mib(),
        valid,
    })
}

/// Peak resident set size of this process (MiB), from /proc (0 where unavailable).
pub fn peak_rss_mib() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1)?.parse::<f64>().ok())
        })
        .map_or(0.0, |kb| kb / 1024.0)
}
