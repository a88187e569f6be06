//! `skelid bench ARCHIVE... --backend cpu,gpu --repeat N`: the wavelet tracks of every
//! channel of every run, timed on each backend in one process (a warm-up, then the median
//! of N repetitions), with the agreement of their results.

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;
use std::time::Instant;

use serde::Serialize;

use crate::backend::{Backend, Signal};
use crate::profile::{self, Traffic};
use crate::track::{Track, WaveletOptions};

/// One backend's timings.
#[derive(Debug, Clone, Serialize)]
pub struct BackendTiming {
    /// `cpu` or `gpu`.
    pub backend: String,
    /// GPU adapter name and kind (none for the CPU).
    pub adapter: Option<String>,
    /// The GPU's shader precision, `first pass f64, refinement f64` where the adapter has
    /// SHADER_F64 (none for the CPU).
    pub precision: Option<String>,
    /// Where the GPU backend computes each signal's padded spectrum: `device` (from the
    /// samples, where its first pass is f64) or `host` (none for the CPU).
    pub spectra: Option<String>,
    /// Wall time of each timed repetition (s).
    pub seconds: Vec<f64>,
    /// Their median (s).
    pub median_s: f64,
    /// Runs per second at the median.
    pub runs_per_s: f64,
    /// Samples × scales transformed per second at the median.
    pub samples_scales_per_s: f64,
    /// Tracks whose first pass fell back to the CPU (0 on the CPU backend).
    pub fallbacks: usize,
    /// CPU seconds per stage over the timed repetitions (the first pass and the refinement
    /// in wall seconds of the GPU submissions on a GPU backend): where this backend's track
    /// time goes.
    pub stages: Vec<(String, f64)>,
    /// Host↔device traffic over the timed repetitions (zeros on the CPU).
    pub traffic: Traffic,
    /// Per signal on the GPU: signals per batch, blocking syncs, bytes up, bytes down.
    pub per_signal: Option<PerSignal>,
    /// Minor page faults of the whole process a timed repetition (with `--hold-tracks`,
    /// letting the previous repetition's tracks go included): fresh memory the kernel
    /// mapped and zeroed.
    pub page_faults_per_repetition: f64,
    /// System CPU seconds of the whole process a timed repetition (as the faults), every
    /// thread.
    pub system_s_per_repetition: f64,
}

/// GPU traffic per signal.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct PerSignal {
    /// Signals per GPU batch (one first pass and one refinement for many signals).
    pub signals_per_batch: f64,
    /// Blocking host waits per signal.
    pub syncs: f64,
    /// Bytes host → device per signal.
    pub bytes_up: f64,
    /// Bytes device → host per signal.
    pub bytes_down: f64,
}

impl PerSignal {
    /// From a traffic count; `None` without GPU work.
    pub fn of(t: &Traffic) -> Option<PerSignal> {
        t.per_signal().map(
            |(signals_per_batch, syncs, bytes_up, bytes_down)| PerSignal {
                signals_per_batch,
                syncs,
                bytes_up,
                bytes_down,
            },
        )
    }
}

/// One backend's end-to-end batch (`skelid run`, both methods, into a scratch folder).
#[derive(Debug, Clone, Serialize)]
pub struct EndToEnd {
    /// `cpu` or `gpu`.
    pub backend: String,
    /// Wall time of the whole batch (s), reading and writing included.
    pub seconds: f64,
    /// Runs per second.
    pub runs_per_s: f64,
    /// CPU seconds per stage, summed over every thread (the GPU first pass and refinement in
    /// wall seconds of their submissions).
    pub stages: Vec<(String, f64)>,
    /// Host↔device traffic.
    pub traffic: Traffic,
    /// Per signal on the GPU.
    pub per_signal: Option<PerSignal>,
}

/// How far two backends' tracks of the same signals differ, over samples valid in both.
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct Agreement {
    /// Largest |A₁ − A₂| / A₁.
    pub envelope_rel: f64,
    /// Largest |f₁ − f₂| (Hz).
    pub frequency_hz: f64,
    /// Samples valid in one track only, over all tracks.
    pub mask_samples: usize,
    /// Samples valid in both, over all tracks.
    pub valid_samples: usize,
    /// Tracks compared.
    pub tracks: usize,
}

impl Agreement {
    /// Adds one pair of tracks of the same signal.
    pub fn add(&mut self, a: &Track, b: &Track) {
        self.add_series(Series::of(a), Series::of(b));
    }

    /// Adds one pair of tracks of the same signal, as their series.
    fn add_series(&mut self, a: Series, b: Series) {
        self.tracks += 1;
        for i in 0..a.valid.len().min(b.valid.len()) {
            match (a.valid[i], b.valid[i]) {
                (true, true) => {
                    self.valid_samples += 1;
                    let e = (a.amplitude[i] - b.amplitude[i]).abs() / a.amplitude[i];
                    self.envelope_rel = self.envelope_rel.max(e);
                    self.frequency_hz = self
                        .frequency_hz
                        .max((a.frequency[i] - b.frequency[i]).abs());
                }
                (false, false) => {}
                _ => self.mask_samples += 1,
            }
        }
    }
}

/// What [`Agreement`] compares of a track: its envelope, frequency (Hz) and validity.
#[derive(Clone, Copy)]
struct Series<'a> {
    amplitude: &'a [f64],
    frequency: &'a [f64],
    valid: &'a [bool],
}

impl<'a> Series<'a> {
    fn of(t: &'a Track) -> Series<'a> {
        Series {
            amplitude: &t.amplitude,
            frequency: &t.frequency,
            valid: &t.valid,
        }
    }
}

/// How far two `run`s' wavelet results differ (results.h5 of the same archives, one per
/// backend): every run's `wavelet/response_amplitude`, `response_frequency` and `valid`,
/// matched by the run's path. These are the tracks as `run` makes them, a forced
/// response's ridge guided by its input's, which [`compare`]'s unguided tracks are not.
pub fn results_agreement(
    a: &std::path::Path,
    b: &std::path::Path,
) -> Result<Agreement, hdf5::Error> {
    fn wavelet_groups(g: &hdf5::Group, path: &str, out: &mut Vec<String>) -> hdf5::Result<()> {
        for name in g.member_names()? {
            let Ok(child) = g.group(&name) else { continue };
            let here = format!("{path}/{name}");
            if name == "wavelet" && child.link_exists("valid") {
                out.push(path.to_string());
            } else {
                wavelet_groups(&child, &here, out)?;
            }
        }
        Ok(())
    }
    // A run's wavelet group as owned series: envelope, frequency (Hz), validity.
    let read = |g: &hdf5::Group| -> hdf5::Result<(Vec<f64>, Vec<f64>, Vec<bool>)> {
        let valid = g.dataset("valid")?.read_raw::<u8>()?;
        Ok((
            g.dataset("response_amplitude")?.read_raw::<f64>()?,
            g.dataset("response_frequency")?.read_raw::<f64>()?,
            valid.into_iter().map(|v| v != 0).collect(),
        ))
    };
    fn series(t: &(Vec<f64>, Vec<f64>, Vec<bool>)) -> Series<'_> {
        Series {
            amplitude: &t.0,
            frequency: &t.1,
            valid: &t.2,
        }
    }
    let (fa, fb) = (hdf5::File::open(a)?, hdf5::File::open(b)?);
    let mut runs = Vec::new();
    wavelet_groups(&fa, "", &mut runs)?;
    let mut agreement = Agreement::default();
    // A run that one backend has no wavelet result for is not compared: `tracks` says how
    // many were.
    for run in runs {
        let Ok(gb) = fb.group(&format!("{run}/wavelet")) else {
            continue;
        };
        let ga = fa.group(&format!("{run}/wavelet"))?;
        let (x, y) = (read(&ga)?, read(&gb)?);
        agreement.add_series(series(&x), series(&y));
    }
    Ok(agreement)
}

/// The whole comparison, as printed and written to JSON (`skelid-bench/1`).
#[derive(Debug, Clone, Serialize)]
pub struct BackendBench {
    /// `skelid-bench/1`.
    pub format: String,
    /// Archives read.
    pub archives: Vec<String>,
    /// Runs read.
    pub runs: usize,
    /// Signals tracked per repetition (every run's input and output channels).
    pub signals: usize,
    /// Samples over all signals.
    pub samples: usize,
    /// Scales per signal.
    pub scales: usize,
    /// Timed repetitions per backend.
    pub repeat: usize,
    /// Whether every track of a repetition was held until it ended (`--hold-tracks`), rather
    /// than let go as it was complete.
    pub held_tracks: bool,
    /// Per backend, in the order asked.
    pub backends: Vec<BackendTiming>,
    /// Median CPU time over median GPU time, when both ran.
    pub gpu_speedup: Option<f64>,
    /// CPU against GPU tracks, when both ran.
    pub agreement: Option<Agreement>,
    /// Per backend, the whole batch end to end with its stages (empty with
    /// `--no-end-to-end`).
    pub end_to_end: Vec<EndToEnd>,
    /// CPU against GPU results of the end-to-end runs ([`results_agreement`]: the tracks
    /// as `run` guides them), when both ran end to end.
    pub end_to_end_agreement: Option<Agreement>,
    /// The CPU backend's end-to-end wall time over the GPU backend's, when both ran end to
    /// end (an added key of `skelid-bench/1`).
    pub end_to_end_gpu_speedup: Option<f64>,
}

impl BackendBench {
    /// `backend`'s median repetition (s), when it was timed.
    pub fn median_s(&self, backend: &str) -> Option<f64> {
        let t = self.backends.iter().find(|t| t.backend == backend)?;
        Some(t.median_s)
    }

    /// `backend`'s end-to-end wall time (s), when it ran end to end.
    pub fn end_to_end_s(&self, backend: &str) -> Option<f64> {
        let e = self.end_to_end.iter().find(|e| e.backend == backend)?;
        Some(e.seconds)
    }

    /// The CPU backend's end-to-end wall time over the GPU backend's, when both ran.
    pub fn end_to_end_speedup(&self) -> Option<f64> {
        Some(self.end_to_end_s("cpu")? / self.end_to_end_s("gpu")?)
    }
}

/// Signals tracked at a time by both backends for [`compare`]'s agreement: 128 tracks of
/// 30 000 samples are about 220 MB a backend.
const AGREEMENT_GROUP: usize = 128;

/// Times `backends` (name, backend) on `signals` (samples, sample rate), `runs` runs' worth.
/// Each track is let go the moment it is complete, as a batch lets each go once it is used,
/// unless `hold` (every track of a repetition held until it ends, as `bench` did before
/// 2026-12-03). The agreement is measured after the timings, on both backends again, a
/// few signals at a time, so that memory stays bounded.
pub fn compare(
    signals: &[(Vec<f64>, f64)],
    runs: usize,
    opt: &WaveletOptions,
    backends: &[(&str, &Backend)],
    repeat: usize,
    hold: bool,
    mut progress: impl FnMut(&str),
) -> BackendBench {
    let repeat = repeat.max(1);
    let refs: Vec<Signal> = signals
        .iter()
        .map(|(x, fs)| Signal {
            samples: x,
            sample_rate: *fs,
            guide: None,
        })
        .collect();
    let samples: usize = signals.iter().map(|s| s.0.len()).sum();
    let mut timings = Vec::new();
    for &(name, backend) in backends {
        // Tracks of a GPU backend whose first pass was done on the CPU, counted in the last
        // timed repetition only (the warm-up is `usize::MAX`).
        let fallen = AtomicUsize::new(0);
        let count_in = repeat - 1;
        // With `hold`, the tracks of the repetition under way; let go before the next starts.
        let held = Mutex::new(Vec::new());
        let repetition = |r: usize| {
            held.lock().expect("never poisoned").clear();
            let t0 = Instant::now();
            backend.track_each(&refs, opt, |_, t| {
                let Ok(t) = t else { return };
                if r == count_in && backend.is_gpu() && t.backend != crate::track::Device::Gpu {
                    fallen.fetch_add(1, Ordering::Relaxed);
                }
                if hold {
                    held.lock().expect("never poisoned").push(t);
                }
            });
            t0.elapsed().as_secs_f64()
        };
        progress(&format!("{name}: warm-up"));
        // Warm-up: one whole repetition, untimed. It plans the FFTs, compiles the pipelines
        // and fills the GPU's buffer pool at the batch sizes the timed repetitions use: a
        // warm-up of 8 signals left the first timed repetition allocating hundreds of MB
        // (1.11 s against 0.57 s for the third on an H100). A campaign pays that once.
        repetition(usize::MAX);
        profile::print_spans(&format!("{name}, warm-up"));
        profile::reset();
        let kernel0 = profile::kernel_share();
        let seconds: Vec<f64> = (0..repeat)
            .map(|r| {
                progress(&format!("{name}: repetition {}/{repeat}", r + 1));
                repetition(r)
            })
            .collect();
        let kernel1 = profile::kernel_share();
        drop(held);
        profile::print_spans(&format!("{name}, {repeat} repetition(s)"));
        let mut sorted = seconds.clone();
        sorted.sort_by(f64::total_cmp);
        let median = sorted[sorted.len() / 2];
        let prof = profile::snapshot();
        timings.push(BackendTiming {
            backend: name.to_string(),
            adapter: backend.adapter().map(str::to_string),
            precision: backend.gpu_precision(),
            spectra: backend.spectra_where().map(str::to_string),
            seconds,
            median_s: median,
            runs_per_s: runs as f64 / median,
            samples_scales_per_s: (samples * opt.scales) as f64 / median,
            fallbacks: fallen.into_inner(),
            stages: prof
                .stages
                .into_iter()
                .filter(|s| s.0 == "first_pass" || s.0 == "refine")
                .collect(),
            per_signal: PerSignal::of(&prof.gpu),
            traffic: prof.gpu,
            page_faults_per_repetition: kernel1.0.saturating_sub(kernel0.0) as f64 / repeat as f64,
            system_s_per_repetition: (kernel1.1 - kernel0.1) / repeat as f64,
        });
    }
    let find = |n: &str| timings.iter().position(|t| t.backend == n);
    let (gpu_speedup, agreement) = match (find("cpu"), find("gpu")) {
        (Some(c), Some(g)) => {
            progress(&format!(
                "agreement: both backends again, {AGREEMENT_GROUP} signals at a time (untimed)"
            ));
            let mut a = Agreement::default();
            for group in refs.chunks(AGREEMENT_GROUP) {
                let x = backends[c].1.track_many(group, opt);
                let y = backends[g].1.track_many(group, opt);
                for (x, y) in x.iter().zip(&y) {
                    if let (Ok(x), Ok(y)) = (x, y) {
                        a.add(x, y);
                    }
                }
            }
            (Some(timings[c].median_s / timings[g].median_s), Some(a))
        }
        _ => (None, None),
    };
    BackendBench {
        format: "skelid-bench/1".into(),
        archives: Vec::new(),
        runs,
        signals: signals.len(),
        samples,
        scales: opt.scales,
        repeat,
        held_tracks: hold,
        backends: timings,
        gpu_speedup,
        agreement,
        end_to_end: Vec::new(),
        end_to_end_agreement: None,
        end_to_end_gpu_speedup: None,
    }
}

/// Runs `run` over `files` (both methods) on `backend` into `dir` and measures it: wall
/// time, stages and traffic. Its results.h5 is moved to `keep_results` when given.
pub fn end_to_end(
    name: &str,
    files: &[std::path::PathBuf],
    ingest: &crate::ingest::IngestOptions,
    batch: &crate::batch::BatchOptions<'_>,
    dir: &std::path::Path,
    keep_results: Option<&std::path::Path>,
) -> Result<EndToEnd, crate::batch::BatchError> {
    let _ = std::fs::remove_dir_all(dir);
    profile::reset();
    let t0 = Instant::now();
    let summary = crate::batch::run_campaigns(files, ingest, batch, dir, &|_| {})?;
    let seconds = t0.elapsed().as_secs_f64();
    let prof = profile::snapshot();
    if let Some(to) = keep_results {
        // Moved out before the folder goes, so that the next backend's run does not write
        // beside this one's files, only beside its results.
        let _ = std::fs::rename(dir.join("results.h5"), to);
    }
    let _ = std::fs::remove_dir_all(dir);
    Ok(EndToEnd {
        backend: name.to_string(),
        seconds,
        runs_per_s: summary.runs as f64 / seconds,
        stages: prof.stages,
        per_signal: PerSignal::of(&prof.gpu),
        traffic: prof.gpu,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_agreement_covers_every_signal_in_groups_whether_tracks_are_held_or_not() {
        // Two CPU backends under the two names: their tracks are the same, so the agreement
        // is exact, and it must count every signal, across more than one AGREEMENT_GROUP.
        let signals: Vec<(Vec<f64>, f64)> = (0..AGREEMENT_GROUP + 5)
            .map(|k| {
                let f = 6.0 + (k % 7) as f64;
                let x = (0..1200)
                    .map(|i| {
                        let t = i as f64 / 400.0;
                        (-0.2 * t).exp() * (2.0 * std::f64::consts::PI * f * t).sin()
                    })
                    .collect();
                (x, 400.0)
            })
            .collect();
        let opt = WaveletOptions {
            scales: 24,
            ..Default::default()
        };
        let (a, b) = (Backend::cpu(), Backend::cpu());
        for hold in [false, true] {
            let r = compare(
                &signals,
                7,
                &opt,
                &[("cpu", &a), ("gpu", &b)],
                1,
                hold,
                |_| {},
            );
            assert_eq!(r.held_tracks, hold);
            let g = r.agreement.expect("both names ran");
            assert_eq!(g.tracks, signals.len(), "held: {hold}");
            assert!(g.valid_samples > signals.len() * 600, "{g:?}");
            assert_eq!(
                (g.envelope_rel, g.frequency_hz, g.mask_samples),
                (0.0, 0.0, 0)
            );
            assert_eq!(r.backends.len(), 2);
            assert!(r
                .backends
                .iter()
                .all(|t| t.fallbacks == 0 && t.median_s > 0.0));
        }
    }
}
