//! skelid for Python: a thin layer over the skelid crate. numpy arrays in (float64 read in
//! place by `track`, copied once into a run by `identify` and `gap`; float32 converted),
//! numpy arrays and dicts out; the GIL is released while
//! skelid works; errors are `skelid.SkelidError` with the library's messages, their hints
//! naming this module's keyword arguments. Every function calls the same library code as the
//! command line, so both give the same numbers.

use std::sync::OnceLock;

use numpy::{PyArray1, PyReadonlyArray1, PyUntypedArrayMethods};
use pyo3::exceptions::{PyException, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};

use skelid::backend::{Backend, BackendChoice};
use skelid::hint::Hint;
use skelid::identify::{Identifier, IdentifyOptions};
use skelid::model::{EffectKind, RigModel};
use skelid::run::{Quantity, Run, RunKind, RunMeta};
use skelid::track::{HilbertOptions, Method, Track, WaveletOptions};

pyo3::create_exception!(
    _skelid,
    SkelidError,
    PyException,
    "An error reported by skelid (unreadable archive, impossible option, failed identification)."
);

fn err(e: impl std::fmt::Display) -> PyErr {
    SkelidError::new_err(e.to_string())
}

/// The library's hints, named as this module's keyword arguments.
fn python_names(h: Hint) -> &'static str {
    match h {
        Hint::SampleRate => "sample_rate=",
        Hint::ChannelNames => "input_name= and output_name=",
        Hint::RunGlob => "runs=",
        Hint::Kind => "kind=",
        Hint::Band => "mode_band=",
        Hint::FrequencyRange => "fmin= and fmax=",
        Hint::Bandwidth => "bandwidth=",
        Hint::CpuBackend => "backend=\"cpu\"",
        Hint::GpuBackend => "backend=\"gpu\"",
        other => other.phrase(),
    }
}

/// A channel's samples as f64: a contiguous float64 array is borrowed, anything else
/// (float32, strided, a list) converted once.
enum Samples<'py> {
    Borrowed(PyReadonlyArray1<'py, f64>),
    Owned(Vec<f64>),
}

impl Samples<'_> {
    fn get(&self) -> &[f64] {
        match self {
            Samples::Borrowed(a) => a.as_slice().expect("checked contiguous"),
            Samples::Owned(v) => v,
        }
    }
}

fn samples<'py>(obj: &Bound<'py, PyAny>, name: &str) -> PyResult<Samples<'py>> {
    if let Ok(a) = obj.extract::<PyReadonlyArray1<'py, f64>>() {
        if a.is_contiguous() {
            return Ok(Samples::Borrowed(a));
        }
        return Ok(Samples::Owned(a.as_array().to_vec()));
    }
    if let Ok(a) = obj.extract::<PyReadonlyArray1<'py, f32>>() {
        return Ok(Samples::Owned(
            a.as_array().iter().map(|&v| f64::from(v)).collect(),
        ));
    }
    obj.extract::<Vec<f64>>().map(Samples::Owned).map_err(|_| {
        PyValueError::new_err(format!(
            "{name}: expected a one-dimensional array of float64 or float32 samples"
        ))
    })
}

/// The backend named `name`, opened once per process and shared by every call.
fn backend(name: &str) -> PyResult<&'static Backend> {
    static CPU: OnceLock<Backend> = OnceLock::new();
    static AUTO: OnceLock<Backend> = OnceLock::new();
    static GPU: OnceLock<Backend> = OnceLock::new();
    match name {
        "cpu" => Ok(CPU.get_or_init(Backend::cpu)),
        "auto" => Ok(AUTO
            .get_or_init(|| Backend::open(BackendChoice::Auto).unwrap_or_else(|_| Backend::cpu()))),
        "gpu" => {
            if let Some(b) = GPU.get() {
                return Ok(b);
            }
            let opened = Backend::open(BackendChoice::Gpu).map_err(err)?;
            Ok(GPU.get_or_init(|| opened))
        }
        other => Err(PyValueError::new_err(format!(
            "backend {other:?}: use \"auto\", \"cpu\" or \"gpu\""
        ))),
    }
}

fn method(name: &str) -> PyResult<Method> {
    match name {
        "wavelet" => Ok(Method::Wavelet),
        "hilbert" => Ok(Method::Hilbert),
        other => Err(PyValueError::new_err(format!(
            "method {other:?}: use \"wavelet\" or \"hilbert\""
        ))),
    }
}

fn kind(name: &str) -> PyResult<RunKind> {
    RunKind::parse(name).ok_or_else(|| {
        PyValueError::new_err(format!(
            "kind {name:?}: use \"base_motion\", \"force\" or \"free\""
        ))
    })
}

fn quantity(name: Option<&str>, what: &str) -> PyResult<Option<Quantity>> {
    name.map(|n| {
        Quantity::parse(n).ok_or_else(|| {
            PyValueError::new_err(format!(
                "{what} {n:?}: use \"displacement\", \"velocity\", \"acceleration\" or \"force\""
            ))
        })
    })
    .transpose()
}

fn array<'py>(py: Python<'py>, v: &[f64]) -> Bound<'py, PyArray1<f64>> {
    PyArray1::from_slice(py, v)
}

fn track_dict<'py>(py: Python<'py>, t: &Track) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    let n = t.amplitude.len();
    let time: Vec<f64> = (0..n).map(|i| i as f64 / t.sample_rate).collect();
    d.set_item("time", array(py, &time))?;
    d.set_item("amplitude", array(py, &t.amplitude))?;
    d.set_item("frequency", array(py, &t.frequency))?;
    d.set_item("phase", array(py, &t.phase))?;
    d.set_item("valid", PyArray1::from_slice(py, &t.valid))?;
    d.set_item("band", t.band)?;
    d.set_item("noise", t.noise)?;
    d.set_item("offset", t.offset)?;
    d.set_item("backend", t.backend.as_str())?;
    d.set_item("method", t.method.as_str())?;
    Ok(d)
}

fn wavelet_options(
    fmin: Option<f64>,
    fmax: Option<f64>,
    scales: Option<usize>,
    bandwidth: Option<f64>,
) -> PyResult<WaveletOptions> {
    let mut o = WaveletOptions {
        fmin,
        fmax,
        ..WaveletOptions::default()
    };
    if let Some(s) = scales {
        o.scales = s;
    }
    if let Some(b) = bandwidth {
        o.wavelet.bandwidth = b;
    }
    o.validate().map_err(PyValueError::new_err)?;
    Ok(o)
}

/// track(x, fs, method="wavelet", fmin=None, fmax=None, scales=None, bandwidth=None,
///       cutoff=0.005, backend="auto") -> dict
/// --
///
/// Instantaneous envelope, frequency and phase of one signal.
///
/// x: samples (1-D float64 array, borrowed without a copy; float32 is converted).
/// fs: sample rate (Hz). method: "wavelet" (complex-Morlet ridge with the bias-corrected
/// skeleton) or "hilbert" (analytic signal by FFT, low-passed at `cutoff` x Nyquist).
/// fmin, fmax: the wavelet's analysis range (Hz), chosen from the spectrum when None.
/// scales: wavelet scales (default 128). bandwidth: the Morlet bandwidth f_b.
/// backend: "auto" (a hardware GPU when one opens, else the CPU), "cpu" or "gpu".
///
/// Returns a dict of numpy arrays, one value per sample: time (s), amplitude (units of x),
/// frequency (Hz), phase (rad), valid (bool: trusted samples); and band (Hz), noise,
/// offset, backend, method. The GIL is released while the track is computed.
#[pyfunction]
#[pyo3(signature = (x, fs, method="wavelet", fmin=None, fmax=None, scales=None, bandwidth=None, cutoff=Some(0.005), backend="auto"))]
#[allow(clippy::too_many_arguments)]
fn track<'py>(
    py: Python<'py>,
    x: &Bound<'py, PyAny>,
    fs: f64,
    method: &str,
    fmin: Option<f64>,
    fmax: Option<f64>,
    scales: Option<usize>,
    bandwidth: Option<f64>,
    cutoff: Option<f64>,
    backend: &str,
) -> PyResult<Bound<'py, PyDict>> {
    let m = self::method(method)?;
    let opt = wavelet_options(fmin, fmax, scales, bandwidth)?;
    let engine = self::backend(backend)?;
    let x = samples(x, "x")?;
    let xs = x.get();
    let t = py
        .detach(|| match m {
            Method::Wavelet => engine.track_wavelet(xs, fs, &opt, None),
            Method::Hilbert => skelid::track::track_hilbert(xs, fs, &HilbertOptions { cutoff }),
        })
        .map_err(err)?;
    track_dict(py, &t)
}

/// A run made of arrays and the keyword arguments that describe it.
struct RunArgs {
    kind: RunKind,
    inertia: Option<f64>,
    gravity_stiffness: f64,
    input_quantity: Option<Quantity>,
    output_quantity: Option<Quantity>,
    units: Option<String>,
    mode_band: Option<(f64, f64)>,
    mode_near: Option<f64>,
}

impl RunArgs {
    fn run(&self, input: Option<&[f64]>, output: &[f64], fs: f64) -> PyResult<Run> {
        if self.kind != RunKind::Free && input.is_none() {
            return Err(PyValueError::new_err(format!(
                "a {} run needs its input channel (input=None is for kind=\"free\")",
                self.kind
            )));
        }
        if let Some(i) = input {
            if i.len() != output.len() {
                return Err(PyValueError::new_err(format!(
                    "input has {} samples and output {}: the channels must be the same length",
                    i.len(),
                    output.len()
                )));
            }
        }
        if !(fs > 0.0 && fs.is_finite()) {
            return Err(PyValueError::new_err(format!(
                "fs = {fs}: the sample rate (Hz) must be positive"
            )));
        }
        let default_input = match self.kind {
            RunKind::BaseMotion => Some(Quantity::Displacement),
            RunKind::Force => Some(Quantity::Force),
            RunKind::Free => None,
        };
        Ok(Run {
            meta: RunMeta {
                path: "/python".into(),
                samples: output.len(),
                sample_rate: fs,
                duration: output.len() as f64 / fs,
                kind: self.kind,
                input_quantity: self.input_quantity.or(default_input),
                output_quantity: self.output_quantity.unwrap_or_default(),
                inertia: self.inertia,
                gravity_stiffness: self.gravity_stiffness,
                units: self.units.clone(),
                excitation: None,
                attributes: Default::default(),
                mode_band: self.mode_band,
                mode_near: self.mode_near,
                zero_tolerance: 0.0,
            },
            input: input.map(<[f64]>::to_vec),
            output: output.to_vec(),
        })
    }
}

fn identify_dict<'py>(
    py: Python<'py>,
    id: &skelid::identify::Identification,
    run: &Run,
) -> PyResult<Bound<'py, PyDict>> {
    let units = skelid::units::Units::of(&run.meta);
    let d = PyDict::new(py);
    d.set_item("method", id.method.as_str())?;
    d.set_item("kind", run.meta.kind.as_str())?;
    let params = PyDict::new(py);
    let param_units = PyDict::new(py);
    for (name, value) in skelid::report::parameters(id, run.meta.inertia) {
        params.set_item(name, value)?;
        if let Some(u) = units.parameter(name) {
            param_units.set_item(name, u)?;
        }
    }
    d.set_item("parameters", params)?;
    d.set_item("units", param_units)?;
    let col = |f: fn(&skelid::fit::Bin) -> f64| -> Vec<f64> { id.bins.iter().map(f).collect() };
    let sk = PyDict::new(py);
    sk.set_item("amplitude", array(py, &col(|b| b.amplitude)))?;
    sk.set_item(
        "natural_frequency",
        array(py, &col(|b| b.natural_frequency())),
    )?;
    sk.set_item("stiffness", array(py, &col(|b| b.stiffness)))?;
    sk.set_item("stiffness_spread", array(py, &col(|b| b.stiffness_spread)))?;
    sk.set_item("damping", array(py, &col(|b| b.damping)))?;
    sk.set_item("damping_spread", array(py, &col(|b| b.damping_spread)))?;
    sk.set_item("velocity_amplitude", array(py, &col(|b| b.velocity)))?;
    sk.set_item("restoring_force", array(py, &col(|b| b.restoring_force())))?;
    sk.set_item("damping_force", array(py, &col(|b| b.damping * b.velocity)))?;
    sk.set_item("count", array(py, &col(|b| b.count as f64)))?;
    d.set_item("skeleton", sk)?;
    d.set_item("response", track_dict(py, &id.response)?)?;
    match &id.input {
        Some(t) => d.set_item("input", track_dict(py, t)?)?,
        None => d.set_item("input", py.None())?,
    }
    d.set_item("valid", PyArray1::from_slice(py, &id.used))?;
    d.set_item("mode_band", id.mode.map(|m| (m.fmin, m.fmax)))?;
    d.set_item("warnings", PyList::new(py, &id.warnings)?)?;
    Ok(d)
}

/// identify(input, output, fs, kind="base_motion", method="wavelet", inertia=None,
///          gravity_stiffness=0.0, input_quantity=None, output_quantity=None, units=None,
///          mode_band=None, mode_near=None, fmin=None, fmax=None, scales=None,
///          bandwidth=None, bins=40, resonance=0.1, cutoff=0.005, backend="auto") -> dict
/// --
///
/// Identifies the joint of one run: tracks, ForceVib, skeleton, dead-zone and damping fits,
/// exactly as `skelid run` does for one run of an archive.
///
/// input, output: the channels (1-D arrays of equal length; input=None for kind="free").
/// fs: sample rate (Hz). kind: "base_motion" (input = base displacement), "force" (input =
/// force on the mass) or "free" (free decay). inertia: J (kg m^2) or m (kg) when known
/// (estimated for force runs otherwise). gravity_stiffness: C = mgL/J (1/s^2).
/// input_quantity, output_quantity: "displacement", "velocity", "acceleration" or "force"
/// (integrated to displacement before tracking). units: the archive-style units text
/// ("rad", or "input N, output m/s^2"). mode_band=(fmin, fmax) or mode_near=Hz: the mode to
/// isolate. The rest as `skelid run`'s options of the same names.
///
/// Returns a dict: parameters (every FORMATS.md section 3 name, each estimate with its
/// `_stderr`, NaN where not fitted), units (per parameter), skeleton (numpy arrays per bin:
/// amplitude, natural_frequency, stiffness, damping, their spreads, velocity_amplitude,
/// restoring_force, damping_force, count), response and input (track dicts as `track`
/// returns), valid (samples used), mode_band, warnings, method, kind. Raises SkelidError
/// with the library's message when the run cannot be identified.
#[pyfunction]
#[pyo3(signature = (input, output, fs, kind="base_motion", method="wavelet", inertia=None, gravity_stiffness=0.0, input_quantity=None, output_quantity=None, units=None, mode_band=None, mode_near=None, fmin=None, fmax=None, scales=None, bandwidth=None, bins=40, resonance=0.1, cutoff=Some(0.005), backend="auto"))]
#[allow(clippy::too_many_arguments)]
fn identify<'py>(
    py: Python<'py>,
    input: Option<&Bound<'py, PyAny>>,
    output: &Bound<'py, PyAny>,
    fs: f64,
    kind: &str,
    method: &str,
    inertia: Option<f64>,
    gravity_stiffness: f64,
    input_quantity: Option<&str>,
    output_quantity: Option<&str>,
    units: Option<String>,
    mode_band: Option<(f64, f64)>,
    mode_near: Option<f64>,
    fmin: Option<f64>,
    fmax: Option<f64>,
    scales: Option<usize>,
    bandwidth: Option<f64>,
    bins: usize,
    resonance: f64,
    cutoff: Option<f64>,
    backend: &str,
) -> PyResult<Bound<'py, PyDict>> {
    let args = RunArgs {
        kind: self::kind(kind)?,
        inertia,
        gravity_stiffness,
        input_quantity: quantity(input_quantity, "input_quantity")?,
        output_quantity: quantity(output_quantity, "output_quantity")?,
        units,
        mode_band,
        mode_near,
    };
    let m = self::method(method)?;
    let options = IdentifyOptions {
        wavelet: wavelet_options(fmin, fmax, scales, bandwidth)?,
        hilbert_cutoff: cutoff,
        bins,
        resonance,
        ..IdentifyOptions::default()
    };
    options.validate().map_err(PyValueError::new_err)?;
    let engine = self::backend(backend)?;
    let input = input.map(|i| samples(i, "input")).transpose()?;
    let output = samples(output, "output")?;
    let run = args.run(input.as_ref().map(Samples::get), output.get(), fs)?;
    let id = py
        .detach(|| skelid::identify::identify(&run, m, &options, engine))
        .map_err(err)?;
    identify_dict(py, &id, &run)
}

/// A rig model from a path, TOML text, or a dict (via JSON).
fn rig_model(py: Python<'_>, model: &Bound<'_, PyAny>) -> PyResult<RigModel> {
    if let Ok(text) = model.extract::<String>() {
        let path = std::path::Path::new(&text);
        if !text.contains('\n') && path.is_file() {
            return RigModel::load(path).map_err(err);
        }
        return RigModel::from_toml_str(&text, "the model text").map_err(err);
    }
    if let Ok(path) = model.extract::<std::path::PathBuf>() {
        return RigModel::load(&path).map_err(err);
    }
    if let Ok(dict) = model.cast::<PyDict>() {
        let json: String = py
            .import("json")?
            .call_method1("dumps", (dict,))?
            .extract()?;
        let value: serde_json::Value = serde_json::from_str(&json).map_err(err)?;
        let text = toml::to_string(&value).map_err(err)?;
        return RigModel::from_toml_str(&text, "the model dict").map_err(err);
    }
    Err(PyValueError::new_err(
        "model: give a path to a rig TOML file, its text, or a dict of its keys",
    ))
}

/// gap(model, input, output, fs, kind="base_motion", inertia=None, gravity_stiffness=0.0,
///     units=None, holdout_block=1.0, baseline_evaluations=150, candidate_evaluations=45,
///     pairs=True, fit_inertia=False, effects=None, backend="cpu", waveform=True,
///     zero_tolerance=None, refit_effects=False) -> dict
/// --
///
/// Why a rig model's simulation does not match one measured base-motion run: the gap and
/// where it lies, the baseline refit, each unmodelled effect tried, and the verdict, scored
/// on held-out time blocks, as `skelid gap` does.
///
/// model: a rig TOML file's path, its text, or a dict of its keys (FORMATS.md section 2).
/// input, output: base and link angle (rad). effects: the effect names to try (all seven
/// by default). waveform: score the waveform within a cycle (the third harmonic at
/// resonance; the default, as `skelid gap`; False as `skelid gap --no-waveform`). zero_tolerance: how far apart the two encoders'
/// zeros may be (rad), as `skelid gap --zero-tolerance`; None is 0 (arrays carry no run
/// attribute to fall back on). refit_effects: refit the effects the model already has in
/// the baseline, as `skelid gap --refit-effects`. The rest as `skelid gap`'s options of the same
/// names.
///
/// Returns the gap.json document as a dict, as `skelid gap` writes it: format, settings,
/// runs (one entry: run "/python", nominal_gap, baseline_gap, regions, candidates best
/// first, verdict, ...) and failed.
#[pyfunction]
#[pyo3(signature = (model, input, output, fs, kind="base_motion", inertia=None, gravity_stiffness=0.0, units=None, holdout_block=1.0, baseline_evaluations=150, candidate_evaluations=45, pairs=true, fit_inertia=false, effects=None, backend="cpu", waveform=true, zero_tolerance=None, refit_effects=false))]
#[allow(clippy::too_many_arguments)]
fn gap<'py>(
    py: Python<'py>,
    model: &Bound<'py, PyAny>,
    input: &Bound<'py, PyAny>,
    output: &Bound<'py, PyAny>,
    fs: f64,
    kind: &str,
    inertia: Option<f64>,
    gravity_stiffness: f64,
    units: Option<String>,
    holdout_block: f64,
    baseline_evaluations: usize,
    candidate_evaluations: usize,
    pairs: bool,
    fit_inertia: bool,
    effects: Option<Vec<String>>,
    backend: &str,
    waveform: bool,
    zero_tolerance: Option<f64>,
    refit_effects: bool,
) -> PyResult<Bound<'py, PyAny>> {
    let model = rig_model(py, model)?;
    if zero_tolerance.is_some_and(|t| !(t >= 0.0 && t.is_finite())) {
        return Err(PyValueError::new_err(
            "zero_tolerance: how far apart the encoders' zeros may be, in rad: 0 or more",
        ));
    }
    let effects = match effects {
        None => EffectKind::ALL.to_vec(),
        Some(names) => names
            .iter()
            .map(|n| {
                EffectKind::parse(n).ok_or_else(|| {
                    let all: Vec<&str> = EffectKind::ALL.iter().map(|k| k.name()).collect();
                    PyValueError::new_err(format!("unknown effect `{n}`: use {}", all.join(", ")))
                })
            })
            .collect::<PyResult<_>>()?,
    };
    let opt = skelid::gap::SearchOptions {
        blocks: skelid::gap::Blocks {
            seconds: holdout_block,
        },
        baseline_evaluations,
        candidate_evaluations,
        pairs,
        fit_inertia,
        refit_effects,
        effects,
        waveform,
        zero_tolerance,
        ..Default::default()
    };
    let args = RunArgs {
        kind: self::kind(kind)?,
        inertia,
        gravity_stiffness,
        input_quantity: None,
        output_quantity: None,
        units,
        mode_band: None,
        mode_near: None,
    };
    if args.kind != RunKind::BaseMotion {
        return Err(PyValueError::new_err(
            "gap: only base-motion runs can be diagnosed (kind=\"base_motion\")",
        ));
    }
    let input = samples(input, "input")?;
    let output = samples(output, "output")?;
    let run = args.run(Some(input.get()), output.get(), fs)?;
    let engine = self::backend(backend)?;
    let options = IdentifyOptions::default();
    let json = py
        .detach(|| -> Result<String, String> {
            let identifier = Identifier {
                options: &options,
                backend: engine,
            };
            let reference = skelid::gap::search::Reference::new(&run, opt.blocks, identifier)
                .map_err(|e| e.to_string())?
                .scored_as(&opt);
            let d = skelid::gap::search::diagnose(&reference, &model, &opt)
                .map_err(|e| e.to_string())?;
            let r = skelid::gap::GapRun::new(&reference, d).map_err(|e| e.to_string())?;
            let settings = serde_json::json!({
                "holdout": format!(
                    "alternate {holdout_block} s blocks: fits on the even ones (from t = 0), \
                     gaps scored on the odd ones"
                ),
                "baseline_evaluations": opt.baseline_evaluations,
                "candidate_evaluations": opt.candidate_evaluations,
                "refine": opt.refine,
                "pairs": opt.pairs,
                "backend": if engine.is_gpu() { "gpu" } else { "cpu" },
                "fit_inertia": opt.fit_inertia,
                "refit_effects": opt.refit_effects,
                "waveform": opt.waveform,
                "zero_tolerance": opt.zero_tolerance,
                "min_shrink": skelid::gap::search::MIN_SHRINK,
                "min_drop": skelid::gap::search::MIN_DROP,
            });
            Ok(skelid::gap::export::gap_document(&[&r], &[], settings).to_string())
        })
        .map_err(err)?;
    py.import("json")?.call_method1("loads", (json,))
}

/// read_campaign(path, sample_rate=None, input_name="input", output_name="output",
///               runs=None, kind=None, errors="raise") -> list
/// --
///
/// The runs of campaign archives (HDF5, or MATLAB v7.3) as a list of dicts, read by the
/// same reader as the command line: `path` is a file, a folder (searched for archives) or a
/// glob, as `skelid run` takes them.
///
/// sample_rate: Hz, for archives that state none. input_name, output_name: the channels'
/// dataset names. runs: a glob on run paths ("/runs/run_0*"). kind: the kind of every run.
/// errors: "raise" (SkelidError at the first run that cannot be read, with the command
/// line's message) or "keep" (such a run is a dict with `path` and `error`).
///
/// Each run: path, source, kind, sample_rate, duration, input (numpy array, None for a free
/// decay), output, input_quantity, output_quantity, inertia, gravity_stiffness, units,
/// mode_band, mode_near, attributes.
#[pyfunction]
#[pyo3(signature = (path, sample_rate=None, input_name="input", output_name="output", runs=None, kind=None, errors="raise"))]
#[allow(clippy::too_many_arguments)]
fn read_campaign<'py>(
    py: Python<'py>,
    path: std::path::PathBuf,
    sample_rate: Option<f64>,
    input_name: &str,
    output_name: &str,
    runs: Option<&str>,
    kind: Option<&str>,
    errors: &str,
) -> PyResult<Bound<'py, PyList>> {
    let keep = match errors {
        "raise" => false,
        "keep" => true,
        other => {
            return Err(PyValueError::new_err(format!(
                "errors={other:?}: use \"raise\" or \"keep\""
            )))
        }
    };
    let options = skelid::ingest::IngestOptions {
        input_name: input_name.into(),
        output_name: output_name.into(),
        sample_rate,
        run_glob: runs
            .map(|g| {
                glob::Pattern::new(g).map_err(|e| PyValueError::new_err(format!("runs={g:?}: {e}")))
            })
            .transpose()?,
        kind: kind.map(self::kind).transpose()?,
        ..Default::default()
    };
    let arg = path.to_string_lossy().into_owned();
    let archives = py
        .detach(|| -> Result<_, String> {
            let files = skelid::ingest::find_archives(std::slice::from_ref(&arg))
                .map_err(|e| e.to_string())?
                .archives;
            files
                .iter()
                .map(|file| {
                    let archive =
                        skelid::ingest::Archive::open(file, &options).map_err(|e| e.to_string())?;
                    let runs: Vec<(String, Result<Run, String>)> = archive
                        .load_all()
                        .into_iter()
                        .map(|(p, r)| (p, r.map_err(|e| e.to_string())))
                        .collect();
                    Ok((file.display().to_string(), runs))
                })
                .collect::<Result<Vec<_>, String>>()
        })
        .map_err(err)?;
    let out = PyList::empty(py);
    for (source, runs) in archives {
        for (run_path, run) in runs {
            let d = PyDict::new(py);
            d.set_item("path", &run_path)?;
            d.set_item("source", &source)?;
            match run {
                Err(e) if keep => d.set_item("error", e)?,
                Err(e) => return Err(SkelidError::new_err(format!("{run_path}: {e}"))),
                Ok(r) => {
                    let m = &r.meta;
                    d.set_item("kind", m.kind.as_str())?;
                    d.set_item("sample_rate", m.sample_rate)?;
                    d.set_item("duration", m.duration)?;
                    match &r.input {
                        Some(x) => d.set_item("input", array(py, x))?,
                        None => d.set_item("input", py.None())?,
                    }
                    d.set_item("output", array(py, &r.output))?;
                    d.set_item("input_quantity", m.input_quantity.map(Quantity::as_str))?;
                    d.set_item("output_quantity", m.output_quantity.as_str())?;
                    d.set_item("inertia", m.inertia)?;
                    d.set_item("gravity_stiffness", m.gravity_stiffness)?;
                    d.set_item("units", m.units.as_deref())?;
                    d.set_item("mode_band", m.mode_band)?;
                    d.set_item("mode_near", m.mode_near)?;
                    let attrs = PyDict::new(py);
                    for (k, v) in &m.attributes {
                        attrs.set_item(k, v)?;
                    }
                    d.set_item("attributes", attrs)?;
                }
            }
            out.append(d)?;
        }
    }
    Ok(out)
}

/// The compiled half of the `skelid` package.
#[pymodule]
fn _skelid(m: &Bound<'_, PyModule>) -> PyResult<()> {
    skelid::hint::set_namer(python_names);
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add("SkelidError", m.py().get_type::<SkelidError>())?;
    m.add_function(wrap_pyfunction!(track, m)?)?;
    m.add_function(wrap_pyfunction!(identify, m)?)?;
    m.add_function(wrap_pyfunction!(gap, m)?)?;
    m.add_function(wrap_pyfunction!(read_campaign, m)?)?;
    Ok(())
}
