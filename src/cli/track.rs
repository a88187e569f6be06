//! `skelid track`: the instantaneous envelope and frequency of one dataset.

use anyhow::{bail, Context, Result};
use clap::Args;
use skelid::ingest::{Archive, IngestOptions};
use skelid::track::WaveletPrep;
use std::path::PathBuf;

use super::args::{report_fallbacks, BackendArg, BackendArgs, IngestArgs, MethodArg, WaveletArgs};

#[derive(Args)]
pub(crate) struct TrackArgs {
    /// Campaign archive (HDF5).
    #[arg(value_name = "ARCHIVE")]
    pub(crate) archive: PathBuf,
    /// Dataset to track, e.g. /runs/run_001/output (a run group alone means its output).
    #[arg(long, value_name = "PATH")]
    pub(crate) dataset: String,
    /// Estimator.
    #[arg(long, value_enum, default_value = "wavelet")]
    pub(crate) method: MethodArg,
    /// Output file: HDF5, or CSV when the name ends in .csv.
    #[arg(long, value_name = "FILE")]
    pub(crate) out: PathBuf,
    #[command(flatten)]
    pub(crate) wavelet: WaveletArgs,
    /// Samples whose ridge is below this multiple of the in-band noise are marked not valid.
    #[arg(
        allow_negative_numbers = true,
        long,
        default_value_t = 10.0,
        value_name = "X"
    )]
    pub(crate) min_snr: f64,
    /// Ridge by per-sample argmax instead of the penalised dynamic programme.
    #[arg(long)]
    pub(crate) argmax: bool,
    /// Do not remove the window's decay/sweep bias (raw |W| and phase derivative).
    #[arg(long)]
    pub(crate) no_correction: bool,
    /// Hilbert only: zero-phase low-pass of A and f, cut-off as a fraction of Nyquist
    /// (the paper uses 0.0005-0.01).
    #[arg(allow_negative_numbers = true, long, value_name = "FRACTION")]
    pub(crate) cutoff: Option<f64>,
    /// Wavelet only: a dataset of the same run whose ridge guides this one (e.g. the input).
    #[arg(long, value_name = "PATH")]
    pub(crate) reference: Option<String>,
    /// Wavelet only: also write the first pass's |W| on its coarse grid (datasets
    /// `scalogram`, scales × steps, with `scalogram_frequency` in Hz and `scalogram_time` in
    /// s) to the HDF5 output; on a GPU this is the only time the scalogram is read back.
    #[arg(long)]
    pub(crate) keep_scalogram: bool,
    #[command(flatten)]
    pub(crate) backend: BackendArgs,
    #[command(flatten)]
    pub(crate) ingest: IngestArgs,
}

/// Reads one dataset of an archive: the run is the dataset's parent group (or the path itself
/// when it names a run, meaning its output).
pub(crate) fn read_dataset(
    archive: &Archive,
    dataset: &str,
    options: &IngestOptions,
) -> Result<(Vec<f64>, f64)> {
    let file = archive.file_name().to_string();
    let dataset = format!("/{}", dataset.trim_start_matches('/'));
    let (run_path, name) = match archive.runs.iter().find(|r| r.path == dataset) {
        Some(_) => (dataset.clone(), options.output_name.clone()),
        None => {
            let (parent, name) = dataset.rsplit_once('/').unwrap_or(("", &dataset));
            let parent = if parent.is_empty() { "/" } else { parent };
            (parent.to_string(), name.to_string())
        }
    };
    let entry = archive
        .runs
        .iter()
        .find(|r| r.path == run_path)
        .with_context(|| {
            format!(
                "{file}: {dataset} is not in a run group; `skelid inspect {file}` lists the runs"
            )
        })?;
    let meta = entry.meta.clone()?;
    let run = archive.load(&meta)?;
    let x = if name == options.output_name {
        run.output
    } else if name == options.input_name {
        run.input
            .with_context(|| format!("{file}: {run_path} is a free decay without an input"))?
    } else {
        bail!(
            "{file}: {dataset}: tracks are taken of a run's `{}` or `{}` dataset",
            options.input_name,
            options.output_name
        );
    };
    Ok((x, meta.sample_rate))
}

/// What `track` has read (and, where it can, prepared) before the backend is needed.
enum Input {
    /// The record, for the Hilbert method.
    Hilbert(Vec<f64>),
    /// The record prepared for the wavelet method (its spectrum and band).
    Prepared(Box<WaveletPrep>),
    /// The record and the reference (its dataset's path and samples) whose wavelet ridge
    /// guides it: the guide's track, and so the record's preparation, needs the backend.
    Guided {
        x: Vec<f64>,
        reference: (String, Vec<f64>),
    },
}

/// Reads the dataset (and the reference) and prepares a wavelet track that has no guide;
/// with the sample rate (Hz).
fn read_input(
    a: &TrackArgs,
    options: &IngestOptions,
    opt: &skelid::track::WaveletOptions,
) -> Result<(Input, f64)> {
    use skelid::profile::span;
    let (x, fs, reference) = span("host.read", || -> Result<_> {
        let archive = Archive::open(&a.archive, options)?;
        let (x, fs) = read_dataset(&archive, &a.dataset, options)?;
        let reference = match &a.reference {
            Some(r) if matches!(a.method, MethodArg::Wavelet) => {
                Some((r.clone(), read_dataset(&archive, r, options)?.0))
            }
            _ => None,
        };
        Ok((x, fs, reference))
    })?;
    let input = match (a.method, reference) {
        (MethodArg::Hilbert, _) => Input::Hilbert(x),
        (MethodArg::Wavelet, Some(reference)) => Input::Guided { x, reference },
        (MethodArg::Wavelet, None) => {
            // Without its padded spectrum where a GPU may compute it (the backend is not
            // open yet): the CPU computes it later if the backend turns out not to.
            let prepare = if skelid::backend::may_compute_spectra(a.backend.backend.into()) {
                WaveletPrep::new_deferred
            } else {
                WaveletPrep::new
            };
            let mut prep = span("host.prepare", || prepare(&x, fs, opt, None))?;
            prep.keep_scalogram = a.keep_scalogram;
            Input::Prepared(Box::new(prep))
        }
    };
    Ok((input, fs))
}

pub(crate) fn cmd_track(a: TrackArgs) -> Result<()> {
    use skelid::track::{track_hilbert, HilbertOptions, RidgeSearch, WaveletOptions};
    match a.method {
        MethodArg::Wavelet if a.cutoff.is_some() => {
            bail!(
                "--cutoff low-passes the Hilbert method's tracks; add --method hilbert or drop it"
            )
        }
        MethodArg::Hilbert if a.reference.is_some() => {
            bail!("--reference guides a wavelet ridge; the Hilbert method has none (use --method wavelet)")
        }
        MethodArg::Hilbert if a.keep_scalogram => {
            bail!("--keep-scalogram keeps the wavelet transform; add --method wavelet")
        }
        _ if a.keep_scalogram
            && a.out
                .extension()
                .is_some_and(|e| e.eq_ignore_ascii_case("csv")) =>
        {
            bail!("--keep-scalogram needs an HDF5 output (a 2-D dataset); name --out FILE.h5")
        }
        _ => {}
    }
    super::args::refuse_overwriting(
        "--out",
        &a.out,
        false,
        "the archive being tracked",
        &a.archive,
    )?;
    let options = a.ingest.options()?;
    let opt = a.wavelet.apply(WaveletOptions {
        ridge: if a.argmax {
            RidgeSearch::Argmax
        } else {
            RidgeSearch::Dynamic
        },
        min_snr: a.min_snr,
        correct: !a.no_correction,
        ..WaveletOptions::default()
    });
    // The backend opens (on a GPU: the device and its pipelines, tenths of a second) on a
    // thread of its own while the record is read and prepared, which need no backend; its
    // error, if any, is still the one reported first, as when it opened before the read.
    // The Hilbert track is the CPU's on every backend: no device is opened for it.
    let backend_args = match a.method {
        MethodArg::Hilbert => {
            if a.backend.backend == BackendArg::Gpu {
                eprintln!(
                    "note: the Hilbert method runs on the CPU; --backend gpu applies to the \
                     wavelet transform (--method wavelet)"
                );
            }
            BackendArgs {
                backend: BackendArg::Cpu,
            }
        }
        MethodArg::Wavelet => a.backend,
    };
    let (opened, input) = std::thread::scope(|s| {
        let opening = s.spawn(move || backend_args.open());
        let input = read_input(&a, &options, &opt);
        let opened = opening
            .join()
            .unwrap_or_else(|panic| std::panic::resume_unwind(panic));
        (opened, input)
    });
    let backend = opened?;
    let (input, fs) = input?;
    let track = match input {
        Input::Hilbert(x) => track_hilbert(&x, fs, &HilbertOptions { cutoff: a.cutoff })?,
        Input::Prepared(prep) => backend.track_prepared_alone(*prep),
        Input::Guided {
            x,
            reference: (r, reference),
        } => {
            // One track after the other, each alone on the device: neither waits for the
            // other to share its batch.
            let gt = backend
                .track_wavelet_alone(&reference, fs, &opt, None, false)
                .with_context(|| format!("tracking the reference {r}"))?;
            backend.track_wavelet_alone(&x, fs, &opt, Some(&gt.frequency), a.keep_scalogram)?
        }
    };
    report_fallbacks(&backend);
    skelid::report::write_track(
        &a.out,
        &track,
        &format!("{}:{}", a.archive.display(), a.dataset),
    )?;
    let n = track.len();
    let valid: Vec<usize> = (0..n).filter(|&i| track.valid[i]).collect();
    let (fmin_v, fmax_v, amin, amax) = valid.iter().fold(
        (f64::INFINITY, 0f64, f64::INFINITY, 0f64),
        |(a0, a1, b0, b1), &i| {
            (
                a0.min(track.frequency[i]),
                a1.max(track.frequency[i]),
                b0.min(track.amplitude[i]),
                b1.max(track.amplitude[i]),
            )
        },
    );
    println!(
        "{} {}: {n} samples at {fs} Hz, method {}, band {:.3}-{:.3} Hz, backend {}",
        a.archive.display(),
        a.dataset,
        track.method.as_str(),
        track.band.0,
        track.band.1,
        track.backend.as_str()
    );
    if valid.is_empty() {
        // The ranges over no sample would read inf-0.
        let (causes, remedy) = if track.method == skelid::track::Method::Wavelet {
            (
                ", a band that misses the mode, a mode between too few scales, or a record \
                 too short for the wavelet's edges",
                "more --scales, or --fmin/--fmax around the mode",
            )
        } else {
            ("", "--method wavelet")
        };
        println!(
            "valid 0.0 % of samples: none passed the {} checks (a signal below the noise \
             floor{causes}); try {remedy}",
            track.method.as_str(),
        );
    } else {
        println!(
            "valid {:.1} % of samples; over them frequency {:.4}-{:.4} Hz, amplitude {:.4e}-{:.4e}",
            100.0 * track.valid_fraction(),
            fmin_v,
            fmax_v,
            amin,
            amax
        );
    }
    println!(
        "offset removed {:.4e}, white-noise estimate {:.3e} per sample; wrote {}",
        track.offset,
        track.noise,
        a.out.display()
    );
    Ok(())
}
