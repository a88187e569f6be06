//! Arguments shared by several subcommands: how archives are read, the report, the wavelet
//! options, the methods and the backend.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::{Args, ValueEnum};
use skelid::ingest::IngestOptions;

/// Options for archives laid out differently from the skelid-campaign/1 format.
#[derive(Args, Clone)]
pub(crate) struct IngestArgs {
    /// Name of the input (drive or force) dataset inside each run group; `NAME[k]` takes
    /// channel k (from 0) of a 2-D dataset, along its shorter axis.
    #[arg(long, default_value = "input", value_name = "NAME")]
    pub(crate) input_name: String,
    /// Name of the output (response) dataset inside each run group; `NAME[k]` takes
    /// channel k (from 0) of a 2-D dataset such as MATLAB's 3×N `Acceleration`.
    #[arg(long, default_value = "output", value_name = "NAME")]
    pub(crate) output_name: String,
    /// Sample rate in Hz for every run, overriding `sample_rate` attributes and `time` datasets.
    #[arg(allow_negative_numbers = true, long, value_name = "HZ")]
    pub(crate) sample_rate: Option<f64>,
    /// Only runs whose group path matches this glob, e.g. '/sine_sweep/level_[1-3]'.
    #[arg(long, value_name = "GLOB")]
    pub(crate) run_glob: Option<String>,
    /// Kind of every run, overriding `kind` attributes: base-motion (input = base
    /// displacement), force (input = force on the mass) or free (decay, no input). With
    /// `skelid gap --self-check`, the kind of model checked: `force` draws one 7.3 Hz mode
    /// of a structure (1 kg modal mass, 0.5 % of critical) under a model of kind = "force",
    /// swept down from 9 to 5.5 Hz by a force at 0.2, 0.4, 0.7 and 1 N and recorded by an
    /// accelerometer with 1 % noise, levels 1 and 3 fitted together and 2 and 4 held out;
    /// friction, a cubic term (softening, then hardening), a sensor delay, the
    /// accelerometer's converter step and microslip in turn, and none.
    #[arg(long, value_name = "KIND", value_parser = parse_kind)]
    pub(crate) kind: Option<skelid::run::RunKind>,
    /// Inertia of every run (kg m² for a rotary rig, kg for a linear one), overriding
    /// `inertia` attributes; gives the absolute stiffness, damping and friction.
    #[arg(allow_negative_numbers = true, long, value_name = "J")]
    pub(crate) inertia: Option<f64>,
    /// What every run's input measures (displacement, velocity, acceleration, force),
    /// overriding `input_quantity` attributes.
    #[arg(long, value_name = "QUANTITY", value_parser = parse_quantity)]
    pub(crate) input_quantity: Option<skelid::run::Quantity>,
    /// What every run's output measures (displacement, velocity, acceleration), overriding
    /// `output_quantity` attributes.
    #[arg(long, value_name = "QUANTITY", value_parser = parse_quantity)]
    pub(crate) output_quantity: Option<skelid::run::Quantity>,
}

pub(crate) fn parse_kind(s: &str) -> Result<skelid::run::RunKind, String> {
    skelid::run::RunKind::parse(s).ok_or_else(|| format!("{s:?}: use base-motion, force or free"))
}

pub(crate) fn parse_quantity(s: &str) -> Result<skelid::run::Quantity, String> {
    skelid::run::Quantity::parse(s)
        .ok_or_else(|| format!("{s:?}: use displacement, velocity, acceleration or force"))
}

impl IngestArgs {
    pub(crate) fn options(&self) -> Result<IngestOptions> {
        let run_glob = match &self.run_glob {
            Some(g) => Some(
                glob::Pattern::new(g)
                    .with_context(|| format!("--run-glob {g}: not a valid glob"))?,
            ),
            None => None,
        };
        if let Some(fs) = self.sample_rate {
            if !(fs.is_finite() && fs > 0.0) {
                bail!("--sample-rate {fs}: must be a positive number of Hz");
            }
        }
        if let Some(j) = self.inertia {
            if !(j.is_finite() && j > 0.0) {
                bail!("--inertia {j}: must be a positive number (kg m² or kg)");
            }
        }
        Ok(IngestOptions {
            input_name: self.input_name.clone(),
            output_name: self.output_name.clone(),
            sample_rate: self.sample_rate,
            run_glob,
            kind: self.kind,
            inertia: self.inertia,
            input_quantity: self.input_quantity,
            output_quantity: self.output_quantity,
        })
    }
}

/// Options of report.html.
#[derive(Args)]
pub(crate) struct ReportArgs {
    /// Runs drawn in full in report.html (tracks, backbone, forces: about 100 kB each);
    /// the summary table always lists every run.
    #[arg(long, default_value_t = 100, value_name = "N")]
    pub(crate) report_runs: usize,
    /// Exit with status 1 when any result is `suspect`, or an archive is damaged (its runs
    /// read, but libhdf5 crashed closing it), too, not only when a run failed or a result
    /// is `bad` (for pipelines that must stop on anything doubtful).
    #[arg(long)]
    pub(crate) strict: bool,
}

/// `--figures`: each run's figures as files for test reports.
#[derive(Args, Clone, Copy)]
pub(crate) struct FiguresArgs {
    /// Also write each run's figures as files, in DIR/figures/ARCHIVE/RUN/NN-title.EXT:
    /// `svg` (vector, as drawn on the page), `png` (300 dpi, for word processors) or `pdf`
    /// (vector, one page each, for LaTeX). Every figure has a title, a legend and axis
    /// labels with units; text is set in DejaVu Sans, bundled with skelid. `run`: input and
    /// response envelope and frequency, backbone with the fitted dead zone, restoring and
    /// damping forces (the paper's Figs. 10–13). `gap`: measured, nominal and fitted
    /// envelope, backbone and damping force.
    #[arg(long, value_enum, value_name = "FORMAT")]
    pub(crate) figures: Option<FigureArg>,
}

/// `--figures` values.
#[derive(Clone, Copy, ValueEnum)]
pub(crate) enum FigureArg {
    /// Scalable vector graphics (text as text).
    Svg,
    /// 300 dpi raster image.
    Png,
    /// Vector PDF, one page per figure.
    Pdf,
}

impl FiguresArgs {
    /// The library's format, when figures are asked for.
    pub(crate) fn format(self) -> Option<skelid::report::figure_files::FigureFormat> {
        use skelid::report::figure_files::FigureFormat;
        self.figures.map(|f| match f {
            FigureArg::Svg => FigureFormat::Svg,
            FigureArg::Png => FigureFormat::Png,
            FigureArg::Pdf => FigureFormat::Pdf,
        })
    }

    /// The batch's figure options, writing into `out/figures`.
    pub(crate) fn batch(self, out: &std::path::Path) -> Option<skelid::batch::Figures> {
        self.format().map(|format| skelid::batch::Figures {
            dir: out.join("figures"),
            format,
        })
    }
}

/// `--backbone` values.
#[derive(Clone, Copy, ValueEnum)]
pub(crate) enum BackboneArg {
    Auto,
    Orbit,
    DescribingFunction,
}

/// How each run is identified (shared by `run` and `gap`), validated once into the
/// library's options.
#[derive(Args, Clone)]
pub(crate) struct IdentifyArgs {
    #[command(flatten)]
    pub(crate) wavelet: WaveletArgs,
    /// Hilbert: zero-phase low-pass cut-off as a fraction of Nyquist (the paper's 0.005).
    #[arg(
        allow_negative_numbers = true,
        long,
        default_value_t = 0.005,
        value_name = "FRACTION"
    )]
    pub(crate) cutoff: f64,
    /// Amplitude bins of the skeleton curves.
    #[arg(long, default_value_t = 40)]
    pub(crate) bins: usize,
    /// Resonance band of the backbone fit for a joint with free play: only samples with
    /// |ω/ω0 − 1| below this are fitted (off resonance, e.g. after a jump-down, the
    /// first-harmonic stiffness of a clearance depends on the forcing). `gap` compares
    /// backbone and damping within it too. [default: 0.1; 0.02 for `gap` with a
    /// `kind = "force"` model and its self-check.] A lightly damped mode of a structure
    /// wants the narrower band: off resonance ForceVib reads a phase error δ of the record
    /// as a damping ratio of about δ·|1 − r²|/2, r = ω/ω0 (on the F-16, whose ratio is
    /// 0.2–1.7 %, the held-out gap shrank by 47 % at 0.02 against 41 % at 0.1).
    #[arg(allow_negative_numbers = true, long, value_name = "FRACTION")]
    pub(crate) resonance: Option<f64>,
    /// Backbone curve fitted to a joint with free play: `orbit` (the exact free periodic
    /// orbit, right for forced runs and lightly damped decays), `describing-function`
    /// (first harmonic of a sinusoid), or `auto` (orbit for forced runs, describing
    /// function for free decays).
    #[arg(long, value_enum, default_value = "auto")]
    pub(crate) backbone: BackboneArg,
    /// Mode isolation: identify the mode whose peak in the record's frequency response
    /// (force-input and free-decay runs; for base-motion runs this turns isolation on) is
    /// nearest HZ. Both channels are band-passed to that mode's band before tracking.
    #[arg(allow_negative_numbers = true, long, value_name = "HZ", conflicts_with_all = ["band", "whole_record"])]
    pub(crate) mode_near: Option<f64>,
    /// Mode isolation: identify what lies in this band, FMIN:FMAX in Hz (e.g. 6:9), in
    /// every run. Without --band or --mode-near, a run is isolated on the band or mode its
    /// `mode_fmin`/`mode_fmax` or `mode_near` attributes name; else a force-input run whose
    /// frequency response shows several modes is isolated on its largest, and every other
    /// run (one mode, base motion, free decay) is identified over the whole record.
    #[arg(long, value_name = "FMIN:FMAX", value_parser = parse_band, conflicts_with = "whole_record")]
    pub(crate) band: Option<(f64, f64)>,
    /// No mode isolation: every run is identified over its whole record, as before
    /// skelid 0.2 (a sweep through several modes then mixes them in one skeleton).
    #[arg(long)]
    pub(crate) whole_record: bool,
}

pub(crate) fn parse_band(s: &str) -> Result<(f64, f64), String> {
    let (a, b) = s
        .split_once(':')
        .ok_or_else(|| format!("{s:?}: give the band as FMIN:FMAX in Hz, e.g. 6:9"))?;
    let num = |t: &str| {
        t.trim()
            .parse::<f64>()
            .map_err(|_| format!("{s:?}: {t:?} is not a number of Hz (FMIN:FMAX, e.g. 6:9)"))
    };
    let (lo, hi) = (num(a)?, num(b)?);
    if !(lo > 0.0 && hi > lo && hi.is_finite()) {
        return Err(format!("{s:?}: need 0 < FMIN < FMAX (Hz), e.g. 6:9"));
    }
    Ok((lo, hi))
}

impl IdentifyArgs {
    /// The identification options these give, with `refine` simulations per half when
    /// asked, checked before any archive is opened (a value no run can use fails here, not
    /// in every run); `command` names the subcommand whose help to see.
    pub(crate) fn options(
        &self,
        command: &str,
        refine: Option<usize>,
    ) -> Result<skelid::identify::IdentifyOptions> {
        let mut options = skelid::identify::IdentifyOptions::default();
        options.wavelet = self.wavelet.apply(options.wavelet);
        options.hilbert_cutoff = Some(self.cutoff);
        options.bins = self.bins;
        options.resonance = self.resonance.unwrap_or(options.resonance);
        options.refine = refine;
        options.backbone = match self.backbone {
            BackboneArg::Auto => None,
            BackboneArg::Orbit => Some(skelid::fit::BackboneModel::PeriodicOrbit),
            BackboneArg::DescribingFunction => Some(skelid::fit::BackboneModel::DescribingFunction),
        };
        options.mode = match (self.whole_record, self.band, self.mode_near) {
            (true, _, _) => skelid::mode::ModeChoice::Whole,
            (_, Some((lo, hi)), _) => skelid::mode::ModeChoice::Band(lo, hi),
            (_, None, Some(f)) => skelid::mode::ModeChoice::Near(f),
            _ => skelid::mode::ModeChoice::ByKind,
        };
        options
            .validate()
            .map_err(|e| anyhow::anyhow!("{e} (see skelid {command} --help; nothing was done)"))?;
        Ok(options)
    }
}

/// The wavelet method's analysis band and mother wavelet (shared by `track` and `run`).
#[derive(Args, Clone)]
pub(crate) struct WaveletArgs {
    /// Wavelet: lowest analysis frequency, Hz (default: from the spectrum and the record length).
    #[arg(allow_negative_numbers = true, long, value_name = "HZ")]
    pub(crate) fmin: Option<f64>,
    /// Wavelet: highest analysis frequency, Hz (default: from the spectrum).
    #[arg(allow_negative_numbers = true, long, value_name = "HZ")]
    pub(crate) fmax: Option<f64>,
    /// Wavelet: number of log-spaced scales between --fmin and --fmax.
    #[arg(long, default_value_t = 64)]
    pub(crate) scales: usize,
    /// Wavelet: Morlet bandwidth f_b; larger is longer in time and finer in frequency.
    #[arg(
        allow_negative_numbers = true,
        long,
        default_value_t = 1.0,
        value_name = "FB"
    )]
    pub(crate) bandwidth: f64,
    /// Wavelet: Morlet centre frequency f_c.
    #[arg(
        allow_negative_numbers = true,
        long,
        default_value_t = 1.0,
        value_name = "FC"
    )]
    pub(crate) centre: f64,
}

impl WaveletArgs {
    /// These settings on top of `base`.
    pub(crate) fn apply(
        &self,
        base: skelid::track::WaveletOptions,
    ) -> skelid::track::WaveletOptions {
        skelid::track::WaveletOptions {
            wavelet: skelid::transform::Morlet {
                bandwidth: self.bandwidth,
                centre: self.centre,
            },
            fmin: self.fmin,
            fmax: self.fmax,
            scales: self.scales,
            ..base
        }
    }
}

#[derive(Clone, Copy, ValueEnum)]
pub(crate) enum RunMethod {
    /// Complex-Morlet ridge and bias-corrected skeleton.
    Wavelet,
    /// Analytic signal by FFT, low-passed with --cutoff.
    Hilbert,
    /// Both, side by side.
    Both,
}

impl RunMethod {
    pub(crate) fn methods(self) -> Vec<skelid::track::Method> {
        use skelid::track::Method;
        match self {
            RunMethod::Wavelet => vec![Method::Wavelet],
            RunMethod::Hilbert => vec![Method::Hilbert],
            RunMethod::Both => vec![Method::Wavelet, Method::Hilbert],
        }
    }
}

#[derive(Clone, Copy, ValueEnum)]
pub(crate) enum MethodArg {
    /// Complex-Morlet ridge and bias-corrected skeleton.
    Wavelet,
    /// Analytic signal by FFT (optionally low-passed with --cutoff).
    Hilbert,
}

#[derive(Args, Clone, Copy)]
pub(crate) struct BackendArgs {
    /// Where the wavelet transform's first pass (the band-limited Morlet transform at every
    /// scale and the ridge search) runs. `auto`: a hardware GPU when wgpu opens one, else
    /// the CPU (a software adapter such as lavapipe is passed over: it is slower than the
    /// CPU backend). `gpu`: any adapter, lavapipe included, or an error when none opens.
    /// `cpu`: rustfft and rayon only. A signal the GPU cannot take (beyond the adapter's
    /// limits, or a device lost mid-batch) is done on the CPU with a warning; results.h5
    /// records per run which backend did the work.
    #[arg(long, value_enum, default_value = "auto", value_name = "BACKEND")]
    pub(crate) backend: BackendArg,
}

/// `--backend` values (the library's [`skelid::backend::BackendChoice`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub(crate) enum BackendArg {
    /// A hardware GPU when one opens, else the CPU. A software adapter (lavapipe) is
    /// slower than the CPU backend on the same cores, so `auto` passes it over.
    Auto,
    /// The CPU (rustfft + rayon).
    Cpu,
    /// The GPU, or an error when none opens.
    Gpu,
}

impl From<BackendArg> for skelid::backend::BackendChoice {
    fn from(a: BackendArg) -> Self {
        match a {
            BackendArg::Auto => Self::Auto,
            BackendArg::Cpu => Self::Cpu,
            BackendArg::Gpu => Self::Gpu,
        }
    }
}

impl BackendArgs {
    /// Opens the backend, saying on stderr what `auto` chose and why.
    pub(crate) fn open(self) -> Result<skelid::backend::Backend> {
        let b = skelid::backend::Backend::open(self.backend.into()).with_context(|| {
            "--backend gpu: no GPU could be opened (use --backend auto to fall back to the CPU)"
        })?;
        for w in b.notes().iter().chain(&b.warnings()) {
            eprintln!("note: {w}");
        }
        if let (Some(a), Some(p), Some(w)) = (b.adapter(), b.gpu_precision(), b.spectra_where()) {
            eprintln!("GPU backend: {a}; shaders in {p}; padded spectra on the {w}");
        }
        Ok(b)
    }
}

/// Prints the backend's fallback warnings gathered during the work, and how the GPU's work
/// was batched.
pub(crate) fn report_fallbacks(b: &skelid::backend::Backend) {
    if let Some((signals, batches)) = b.gpu_work() {
        eprintln!(
            "GPU backend: {signals} signal(s) in {batches} batch(es) ({:.1} per batch; two \
             submissions each: first pass, refinement)",
            signals as f64 / batches.max(1) as f64
        );
        skelid::profile::print_spans("the whole command");
    }
    for w in b.warnings() {
        eprintln!("warning: {w}");
    }
}

pub(crate) fn self_exe() -> Result<PathBuf> {
    std::env::current_exe().context("cannot locate the skelid executable to isolate HDF5 reads")
}

/// The archives the command's inputs name, saying on stderr which files a folder search
/// passed over as skelid's own results.
pub(crate) fn archives(args: &[String]) -> Result<Vec<PathBuf>> {
    let inputs = skelid::ingest::find_archives(args)?;
    if let Some(note) = skelid::ingest::passed_over_note(&inputs.passed_over) {
        eprintln!("note: {note}");
    }
    Ok(inputs.archives)
}

/// Whether writing `out` would replace `input`, however either is spelt (`./x.h5`, an
/// absolute path, folders through links). A file output is written beside and renamed onto
/// its path, so a link named as the output is replaced, not followed: only its folder is
/// resolved. A folder output (`is_folder`) is written into, so it is resolved whole.
pub(crate) fn lands_on(out: &Path, is_folder: bool, input: &Path) -> bool {
    let landing = if is_folder {
        std::fs::canonicalize(out).ok()
    } else {
        let folder = match out.parent() {
            Some(p) if !p.as_os_str().is_empty() => p,
            _ => Path::new("."),
        };
        std::fs::canonicalize(folder)
            .ok()
            .zip(out.file_name())
            .map(|(f, n)| f.join(n))
    };
    match (landing, std::fs::canonicalize(input)) {
        (Some(o), Ok(i)) => o == i,
        _ => false,
    }
}

/// Refuses an output `out` (named by `flag`) that would replace the input `input` (`what`
/// it is to the command; see [`lands_on`]): a campaign is not written over.
pub(crate) fn refuse_overwriting(
    flag: &str,
    out: &Path,
    is_folder: bool,
    what: &str,
    input: &Path,
) -> Result<()> {
    if lands_on(out, is_folder, input) {
        bail!(
            "{flag} {} is {what} ({}): writing there would replace it; name another path \
             (nothing was written)",
            out.display(),
            input.display()
        );
    }
    Ok(())
}

/// Refuses an output folder `out` (named by `flag`) that is an existing file, before any
/// work: the OS's words for it ("File exists", "Not a directory" of `out/runs`) did not
/// say which argument was wrong.
pub(crate) fn refuse_file_as_folder(flag: &str, out: &Path) -> Result<()> {
    if out.exists() && !out.is_dir() {
        bail!(
            "{flag} {} is a file, not a folder: name a folder (new or existing) for the outputs \
             (nothing was done)",
            out.display()
        );
    }
    Ok(())
}
