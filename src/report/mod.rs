//! Output files for people and other programs: tracks (FORMATS.md §4), identification
//! results and summaries (FORMATS.md §3).

pub mod encoded;
pub mod gap;
pub mod html;

use std::borrow::Cow;
use std::io::Write;
use std::path::{Path, PathBuf};

use crate::campaign::{tmp_path, write_signal};
use crate::fit::{Bin, Estimate};
use crate::h5util::{write_f64_attr, write_str_attr, AttrMaker};
use crate::identify::Identification;
use crate::track::{Method, Track};
use crate::units::Units;
use encoded::{Elem, EncodedRun, Item, Scalar, Storage};

/// Why an output file could not be written.
#[derive(Debug, thiserror::Error)]
#[error("{file}: cannot write: {detail}")]
pub struct ReportError {
    /// Output path.
    pub file: String,
    /// What went wrong.
    pub detail: String,
}

/// Writes a track as HDF5 datasets, or as CSV columns when the name ends in `.csv`:
/// `time` (s), `amplitude`, `frequency` (Hz), `valid` (0/1) — the contract — then `phase`
/// (rad), `d_amplitude` (1/s), `d2_amplitude` (1/s²), `d_frequency` (Hz/s).
/// The file appears complete or not at all (written aside, then renamed).
pub fn write_track(path: &Path, track: &Track, source: &str) -> Result<(), ReportError> {
    let err = |detail: String| ReportError {
        file: path.display().to_string(),
        detail,
    };
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).map_err(|e| err(e.to_string()))?;
    }
    let tmp = tmp_path(path);
    let is_csv = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("csv"));
    let result = if is_csv {
        write_csv(&tmp, track).map_err(|e| e.to_string())
    } else {
        write_hdf5(&tmp, track, source).map_err(|e| e.to_string())
    };
    if let Err(e) = result {
        let _ = std::fs::remove_file(&tmp);
        return Err(err(e));
    }
    std::fs::rename(&tmp, path).map_err(|e| err(e.to_string()))
}

fn columns(track: &Track) -> Vec<(&'static str, Cow<'_, [f64]>)> {
    vec![
        ("time", Cow::Owned(track.time())),
        ("amplitude", Cow::Borrowed(&track.amplitude)),
        ("frequency", Cow::Borrowed(&track.frequency)),
        (
            "valid",
            Cow::Owned(
                track
                    .valid
                    .iter()
                    .map(|&v| f64::from(u8::from(v)))
                    .collect(),
            ),
        ),
        ("phase", Cow::Borrowed(&track.phase)),
        ("d_amplitude", Cow::Borrowed(&track.d_amplitude)),
        ("d2_amplitude", Cow::Borrowed(&track.d2_amplitude)),
        ("d_frequency", Cow::Borrowed(&track.d_frequency)),
    ]
}

fn write_csv(path: &Path, track: &Track) -> std::io::Result<()> {
    let mut w = std::io::BufWriter::new(std::fs::File::create(path)?);
    let cols = columns(track);
    let names: Vec<&str> = cols.iter().map(|c| c.0).collect();
    writeln!(w, "{}", names.join(","))?;
    for i in 0..track.len() {
        let row: Vec<String> = cols
            .iter()
            .map(|(name, v)| {
                if *name == "valid" {
                    format!("{}", v[i] as u8)
                } else {
                    format!("{:.10e}", v[i])
                }
            })
            .collect();
        writeln!(w, "{}", row.join(","))?;
    }
    w.flush()
}

fn write_hdf5(path: &Path, track: &Track, source: &str) -> hdf5::Result<()> {
    let file = hdf5::File::create(path)?;
    write_str_attr(&file, "format", "skelid-track/1")?;
    write_str_attr(&file, "method", track.method.as_str())?;
    write_str_attr(&file, "source", source)?;
    write_f64_attr(&file, "sample_rate", track.sample_rate)?;
    write_f64_attr(&file, "offset", track.offset)?;
    write_f64_attr(&file, "noise", track.noise)?;
    write_f64_attr(&file, "fmin", track.band.0)?;
    write_f64_attr(&file, "fmax", track.band.1)?;
    for (name, v) in columns(track) {
        if name == "valid" {
            let bytes: Vec<u8> = track.valid.iter().map(|&b| u8::from(b)).collect();
            file.new_dataset_builder().with_data(&bytes).create(name)?;
        } else {
            write_signal(&file, name, &v, false)?;
        }
    }
    if let Some(sc) = &track.scalogram {
        file.new_dataset::<f32>()
            .shape((sc.frequency.len(), sc.time.len()))
            .create("scalogram")?
            .write_raw(&sc.magnitude)?;
        write_signal(&file, "scalogram_frequency", &sc.frequency, false)?;
        write_signal(&file, "scalogram_time", &sc.time, false)?;
    }
    file.flush()
}

/// What `run` did with one run of an archive: per method the identification or its error.
#[derive(Debug)]
pub struct RunOutcome {
    /// Run path in the archive.
    pub path: String,
    /// Archive file name.
    pub source: String,
    /// Sample rate (Hz), when the run could be read.
    pub sample_rate: Option<f64>,
    /// Samples, when the run could be read.
    pub samples: usize,
    /// Inertia attribute (J or m), when given.
    pub inertia: Option<f64>,
    /// The units of the run's results (from its `units`, `kind` and quantities).
    pub units: crate::units::Units,
    /// The simulation-refined estimates, when asked for (`--refine`), or why there are none.
    pub refined: Option<Result<crate::refine::Refined, String>>,
    /// Why the run could not be read at all.
    pub error: Option<String>,
    /// Per method: the result (or its error) and the seconds it took.
    pub methods: Vec<(Method, Result<Identification, String>, f64)>,
}

impl RunOutcome {
    /// The verdict on each method's result, in `methods` order (`None` where it failed),
    /// and the method whose estimate to read ([`crate::quality`]).
    pub fn qualities(&self) -> (Vec<Option<crate::quality::Quality>>, Option<Method>) {
        let results: Vec<(Method, Option<&Identification>)> = self
            .methods
            .iter()
            .map(|(m, r, _)| (*m, r.as_ref().ok()))
            .collect();
        let judged = crate::quality::judge(&results, &self.units.displacement);
        let pairs: Vec<(Method, Option<crate::quality::Quality>)> = self
            .methods
            .iter()
            .map(|m| m.0)
            .zip(judged.iter().cloned())
            .collect();
        (judged, crate::quality::recommend(&pairs))
    }

    /// `gpu` when the GPU did the transform's first pass of every wavelet track of this
    /// run, else `cpu` (the Hilbert method, the CPU backend, or a fallback).
    pub fn backend(&self) -> &'static str {
        let mut tracks = self
            .methods
            .iter()
            .filter_map(|(m, r, _)| (*m == Method::Wavelet).then_some(r.as_ref().ok()?))
            .flat_map(|id| id.input.iter().chain(std::iter::once(&id.response)))
            .peekable();
        if tracks.peek().is_some() && tracks.all(|t| t.backend == "gpu") {
            "gpu"
        } else {
            "cpu"
        }
    }

    /// A run not yet read: no data, no error, no method results.
    pub fn new(path: String, source: String) -> RunOutcome {
        RunOutcome {
            path,
            source,
            sample_rate: None,
            samples: 0,
            inertia: None,
            units: Default::default(),
            refined: None,
            error: None,
            methods: Vec::new(),
        }
    }

    /// `ok` when at least one method identified the run.
    pub fn status(&self) -> &'static str {
        if self.error.is_none() && self.methods.iter().any(|m| m.1.is_ok()) {
            "ok"
        } else {
            "failed"
        }
    }

    /// The run's error text: the read error, or every method's error.
    pub fn error_text(&self) -> Option<String> {
        if let Some(e) = &self.error {
            return Some(e.clone());
        }
        let errs: Vec<String> = self
            .methods
            .iter()
            .filter_map(|(m, r, _)| r.as_ref().err().map(|e| format!("{}: {e}", m.as_str())))
            .collect();
        (!errs.is_empty()).then(|| errs.join("; "))
    }
}

/// A results file being written (`results.h5`, or one run's journal file): written as
/// `<path>.tmp` and renamed into place by [`finish`](Self::finish), so a crash never leaves
/// a half-written one visible.
pub struct ResultsWriter {
    file: hdf5::File,
    path: PathBuf,
    tmp: PathBuf,
    attrs: AttrMaker,
    layouts: Layouts,
}

impl ResultsWriter {
    /// Starts `<dir>/results.h5`.
    pub fn create(dir: &Path) -> Result<ResultsWriter, ReportError> {
        Self::create_at(&dir.join("results.h5"))
    }

    /// Starts a results file at `path` (written as `path.tmp` until [`finish`](Self::finish)).
    pub fn create_at(path: &Path) -> Result<ResultsWriter, ReportError> {
        let path = path.to_path_buf();
        let err = |detail: String| ReportError {
            file: path.display().to_string(),
            detail,
        };
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir).map_err(|e| err(e.to_string()))?;
        }
        let tmp = tmp_path(&path);
        let file = hdf5::File::create(&tmp).map_err(|e| err(e.to_string()))?;
        write_str_attr(&file, "format", "skelid-results/1").map_err(|e| err(e.to_string()))?;
        write_str_attr(&file, "skelid_version", env!("CARGO_PKG_VERSION"))
            .map_err(|e| err(e.to_string()))?;
        let attrs = AttrMaker::new().map_err(|e| err(e.to_string()))?;
        let layouts = Layouts::new().map_err(|e| err(e.to_string()))?;
        Ok(ResultsWriter {
            file,
            path,
            tmp,
            attrs,
            layouts,
        })
    }

    /// Sets a string attribute on the file's root.
    pub fn set_root_attr(&self, name: &str, value: &str) -> Result<(), ReportError> {
        write_str_attr(&self.file, name, value).map_err(|e| ReportError {
            file: self.path.display().to_string(),
            detail: e.to_string(),
        })
    }

    /// Stores a batch's settings on the file's root: `settings` (the fingerprint) and
    /// `settings_json` (everything, [`crate::journal::settings_record`]).
    pub fn write_settings(&self, record: &serde_json::Value) -> Result<(), ReportError> {
        if let Some(f) = record.get("fingerprint").and_then(|f| f.as_str()) {
            self.set_root_attr("settings", f)?;
        }
        self.set_root_attr("settings_json", &record.to_string())
    }

    /// Copies the group `src_path` of the results file `src` to `dst_path` here, whole
    /// (datasets, attributes, sub-groups), with libhdf5's object copy.
    pub fn copy_run_from(
        &self,
        src: &Path,
        src_path: &str,
        dst_path: &str,
    ) -> Result<(), ReportError> {
        let err = |detail: String| ReportError {
            file: self.path.display().to_string(),
            detail: format!("copying {src_path} from {}: {detail}", src.display()),
        };
        let source = hdf5::File::open(src).map_err(|e| err(e.to_string()))?;
        let (parent, src_name, dst_name) = self.raw_target(src_path, dst_path).map_err(err)?;
        // The hdf5 crate serialises every libhdf5 call behind one lock; a raw call must
        // take the same lock.
        let status = hdf5::sync::sync(|| unsafe {
            hdf5_sys::h5o::H5Ocopy(
                source.id(),
                src_name.as_ptr(),
                parent.id(),
                dst_name.as_ptr(),
                hdf5_sys::h5p::H5P_DEFAULT,
                hdf5_sys::h5p::H5P_DEFAULT,
            )
        });
        if status < 0 {
            return Err(err("H5Ocopy failed".into()));
        }
        Ok(())
    }

    /// Adds one run (failed runs included, with their error) encoded by [`encode_run`]
    /// (possibly on another thread): groups and attributes through the hdf5 crate,
    /// compressed chunks straight into the file.
    pub fn write_encoded(&self, run: &EncodedRun) -> Result<(), ReportError> {
        self.write_encoded_as(run, &run.path)
    }

    /// [`write_encoded`](Self::write_encoded) under the group path `dst` instead of the
    /// run's own.
    pub fn write_encoded_as(&self, run: &EncodedRun, dst: &str) -> Result<(), ReportError> {
        self.write_encoded_inner(run, dst).map_err(|e| ReportError {
            file: self.path.display().to_string(),
            detail: format!("run {}: {e}", run.path),
        })
    }

    /// Moves the run at group path `from` to `to` (a link move: no data is copied),
    /// creating `to`'s parent groups.
    pub fn move_run(&self, from: &str, to: &str) -> Result<(), ReportError> {
        let err = |detail: String| ReportError {
            file: self.path.display().to_string(),
            detail: format!("moving {from} to {to}: {detail}"),
        };
        let (parent, src, dst) = self.raw_target(from, to).map_err(err)?;
        // A raw call takes the hdf5 crate's lock like every other libhdf5 call.
        let status = hdf5::sync::sync(|| unsafe {
            hdf5_sys::h5l::H5Lmove(
                self.file.id(),
                src.as_ptr(),
                parent.id(),
                dst.as_ptr(),
                hdf5_sys::h5p::H5P_DEFAULT,
                hdf5_sys::h5p::H5P_DEFAULT,
            )
        });
        if status < 0 {
            return Err(err("H5Lmove failed".into()));
        }
        Ok(())
    }

    /// For a raw libhdf5 call that puts `src` at the group path `dst`: `dst`'s parent group
    /// (created if need be), and `src` and `dst`'s last component as C strings.
    fn raw_target(
        &self,
        src: &str,
        dst: &str,
    ) -> Result<(hdf5::Group, std::ffi::CString, std::ffi::CString), String> {
        let (parent, name) = match dst.trim_end_matches('/').rsplit_once('/') {
            Some((p, n)) if !n.is_empty() => (p, n),
            _ => return Err("a run path must name a group below the root".into()),
        };
        let parent = group_path(&self.file, parent).map_err(|e| e.to_string())?;
        let c = |s: &str| std::ffi::CString::new(s).map_err(|e| e.to_string());
        Ok((parent, c(src)?, c(name)?))
    }

    /// Removes the object at `path` (a group and everything under it).
    pub fn remove(&self, path: &str) -> Result<(), ReportError> {
        self.file.unlink(path).map_err(|e| ReportError {
            file: self.path.display().to_string(),
            detail: format!("removing {path}: {e}"),
        })
    }

    fn write_encoded_inner(&self, run: &EncodedRun, dst: &str) -> hdf5::Result<()> {
        // Groups by relative path, opened once: a run has about a hundred items.
        let mut groups = std::collections::HashMap::new();
        groups.insert(String::new(), group_path(&self.file, dst)?);
        let at = |groups: &mut std::collections::HashMap<String, hdf5::Group>,
                  rel: &str|
         -> hdf5::Result<hdf5::Group> {
            if let Some(g) = groups.get(rel) {
                return Ok(g.clone());
            }
            let g = groups[""].group(rel)?;
            groups.insert(rel.to_string(), g.clone());
            Ok(g)
        };
        // A dataset's `units` follows it: the handle is kept, not reopened by name
        // (H5Dopen2 was an eighth of the writer's time).
        let mut last: Option<(&str, &str, hdf5::Dataset)> = None;
        for item in &run.items {
            match item {
                Item::Group(rel) => {
                    let (parent, name) = rel.rsplit_once('/').unwrap_or(("", rel));
                    let g = at(&mut groups, parent)?.create_group(name)?;
                    groups.insert(rel.clone(), g);
                }
                // The run's groups are new and an encoded run names each attribute once:
                // created without looking for an old one.
                Item::Attr { group, name, value } => {
                    let g = at(&mut groups, group)?;
                    match value {
                        Scalar::F64(x) => self.attrs.number(&g, name, *x)?,
                        Scalar::Str(s) => self.attrs.text(&g, name, s)?,
                    }
                }
                Item::Dataset(d) => {
                    let ds = write_dataset(&at(&mut groups, &d.group)?, d, &self.layouts)?;
                    last = Some((d.group.as_str(), d.name.as_str(), ds));
                }
                Item::DatasetAttr {
                    group,
                    dataset,
                    name,
                    value,
                } => match &last {
                    Some((g, n, ds)) if g == group && n == dataset => {
                        self.attrs.text(ds, name, value)?
                    }
                    _ => {
                        let ds = at(&mut groups, group)?.dataset(dataset)?;
                        self.attrs.text(&ds, name, value)?
                    }
                },
            }
        }
        // No flush here: `finish` flushes once, and a file not finished is discarded.
        Ok(())
    }

    /// Closes the file and renames it into place.
    pub fn finish(self) -> Result<PathBuf, ReportError> {
        let ResultsWriter {
            file, path, tmp, ..
        } = self;
        let err = |detail: String| ReportError {
            file: path.display().to_string(),
            detail,
        };
        let flushed = file.flush();
        drop(file);
        let done = flushed
            .map_err(|e| err(e.to_string()))
            .and_then(|()| std::fs::rename(&tmp, &path).map_err(|e| err(e.to_string())));
        if done.is_err() {
            let _ = std::fs::remove_file(&tmp);
        }
        done.map(|()| path)
    }

    /// Closes and deletes the unfinished file: a batch that stops on an error leaves no
    /// `.tmp` behind (its runs are in the journal).
    pub fn abandon(self) {
        let ResultsWriter { file, tmp, .. } = self;
        drop(file);
        let _ = std::fs::remove_file(&tmp);
    }
}

/// Opens or creates the group at an absolute path, creating its parents.
fn group_path(file: &hdf5::File, path: &str) -> hdf5::Result<hdf5::Group> {
    let mut g = file.group("/")?;
    for part in path.split('/').filter(|p| !p.is_empty()) {
        g = match g.group(part) {
            Ok(x) => x,
            Err(_) => g.create_group(part)?,
        };
    }
    Ok(g)
}

/// One column of a skeleton, read off a bin.
type BinColumn = fn(&Bin) -> f64;

/// A run's results laid out for [`ResultsWriter::write_encoded`]: pure CPU work (the
/// compression included), so the batch's workers do it in parallel, outside libhdf5's lock.
pub fn encode_run(run: &RunOutcome) -> EncodedRun {
    let mut e = EncodedRun::new(&run.path);
    e.str_attr("", "status", run.status());
    // `error` goes with `failed` only (FORMATS.md §3): a run that one method identified is
    // `ok`, and names its failed methods instead (each method's group holds its error).
    if run.status() == "failed" {
        if let Some(err) = run.error_text() {
            e.str_attr("", "error", &err);
        }
    } else {
        let failed: Vec<&str> = run
            .methods
            .iter()
            .filter(|m| m.1.is_err())
            .map(|m| m.0.as_str())
            .collect();
        if !failed.is_empty() {
            e.str_attr("", "failed_methods", &failed.join(","));
        }
    }
    e.str_attr("", "backend", run.backend());
    e.str_attr("", "source", &run.source);
    let (qualities, recommended) = run.qualities();
    if let Some(m) = recommended {
        e.str_attr("", "recommended", m.as_str());
    }
    match &run.refined {
        Some(Ok(r)) => {
            for (name, value) in crate::refine::NAMES.into_iter().zip(r.values()) {
                e.f64_attr("", name, value);
                if let Some(u) = run.units.parameter(name) {
                    e.str_attr("", &format!("{name}_units"), &u);
                }
            }
        }
        Some(Err(err)) => e.str_attr("", "refined_error", err),
        None => {}
    }
    if let Some(fs) = run.sample_rate {
        e.f64_attr("", "sample_rate", fs);
        let t: Vec<f64> = (0..run.samples).map(|i| i as f64 / fs).collect();
        e.signal("", "time", &t, true);
        e.dataset_attr("", "time", "units", "s");
    }
    for ((method, result, seconds), quality) in run.methods.iter().zip(&qualities) {
        let m = method.as_str();
        e.group(m);
        e.f64_attr(m, "seconds", *seconds);
        if let Some(q) = quality {
            e.str_attr(m, "quality", q.verdict.as_str());
            e.str_attr(m, "quality_reasons", &q.reasons.join("; "));
        }
        match result {
            Err(err) => {
                e.str_attr(m, "status", "failed");
                e.str_attr(m, "error", err);
            }
            Ok(id) => {
                e.str_attr(m, "status", "ok");
                encode_identification(&mut e, m, id, run.inertia, &run.units);
            }
        }
    }
    e
}

/// One skeleton's columns (FORMATS.md §3 names plus stiffness, spreads and counts).
fn encode_bins(e: &mut EncodedRun, g: &str, bins: &[Bin], units: &Units) {
    let columns: [(&str, BinColumn); 9] = [
        ("amplitude", |b| b.amplitude),
        ("natural_frequency", |b| b.natural_frequency()),
        ("stiffness", |b| b.stiffness),
        ("stiffness_spread", |b| b.stiffness_spread),
        ("restoring_force", |b| b.restoring_force()),
        ("velocity_amplitude", |b| b.velocity),
        ("damping_force", |b| b.damping_force()),
        ("damping_spread", |b| b.damping_spread),
        ("count", |b| b.count as f64),
    ];
    e.group(g);
    for (name, f) in columns {
        let v: Vec<f64> = bins.iter().map(f).collect();
        e.signal(g, name, &v, false);
        unit(e, g, name, units.dataset(name));
    }
}

/// Sets the `units` attribute of a dataset just written.
fn unit(e: &mut EncodedRun, group: &str, name: &str, unit: Option<String>) {
    if let Some(u) = unit {
        e.dataset_attr(group, name, "units", &u);
    }
}

fn encode_identification(
    e: &mut EncodedRun,
    m: &str,
    id: &Identification,
    inertia: Option<f64>,
    units: &Units,
) {
    let signal = |e: &mut EncodedRun, name: &str, v: &[f64]| {
        e.signal(m, name, v, true);
        unit(e, m, name, units.dataset(name));
    };
    if let Some(inp) = &id.input {
        signal(e, "input_amplitude", &inp.amplitude);
        signal(e, "input_frequency", &inp.frequency);
    }
    signal(e, "response_amplitude", &id.response.amplitude);
    signal(e, "response_frequency", &id.response.frequency);
    signal(e, "stiffness", &id.modal.stiffness);
    signal(e, "damping", &id.modal.damping);
    let valid: Vec<u8> = id.used.iter().map(|&b| u8::from(b)).collect();
    e.bytes(m, "valid", &valid, 4);
    unit(e, m, "valid", units.dataset("valid"));
    encode_bins(e, &format!("{m}/skeleton"), &id.bins, units);
    // The bins the backbone was fitted on, when not the whole skeleton.
    if id.fitted_at_resonance {
        encode_bins(
            e,
            &format!("{m}/skeleton_resonant"),
            &id.resonant_bins,
            units,
        );
    }
    if let Some(dz) = &id.dead_zone {
        e.str_attr(m, "backbone_model", dz.model.name());
    }
    e.str_attr(
        m,
        "mode_choice",
        id.mode.map_or("whole_record", |b| b.chosen.as_str()),
    );
    e.str_attr(
        m,
        "backbone_bins",
        if id.fitted_at_resonance {
            "resonant"
        } else {
            "all"
        },
    );
    // An attribute cannot carry attributes: each parameter's unit is `<name>_units`.
    for (name, value) in parameters(id, inertia) {
        e.f64_attr(m, name, value);
        if let Some(u) = units.parameter(name) {
            e.str_attr(m, &format!("{name}_units"), &u);
        }
    }
    e.str_attr(m, "warnings", &id.warnings.join("\n"));
}

/// The datasets' layouts written so far, each
/// with the datatype, dataspace and creation list of its first dataset, so that the next
/// ones are created with one libhdf5 call: a run has two dozen chunked datasets of three
/// or four layouts and as many small contiguous ones (skeleton columns) of a few lengths,
/// and building those lists anew for each was a fifth of what creating a dataset cost the
/// writer.
struct Layouts {
    /// Link creation as the binding's dataset builder sets it.
    lcpl: hdf5::plist::LinkCreate,
    /// The memory type of float data.
    native_f64: hdf5::Datatype,
    seen: std::sync::Mutex<std::collections::HashMap<LayoutKey, Layout>>,
}

/// What makes two datasets alike for [`Layouts`].
#[derive(Clone, Copy, PartialEq, Eq, Hash)]
enum LayoutKey {
    /// Contiguous float64 values of this length.
    Plain(usize),
    /// Chunked: element, length, deflate level.
    Chunked(Elem, usize, u8),
}

/// Datatype, dataspace and creation list of one layout.
type Layout = (hdf5::Datatype, hdf5::Dataspace, hdf5::plist::DatasetCreate);

impl Layouts {
    fn new() -> hdf5::Result<Layouts> {
        Ok(Layouts {
            lcpl: hdf5::plist::LinkCreate::build()
                .create_intermediate_group(true)
                .finish()?,
            native_f64: hdf5::Datatype::from_type::<f64>()?,
            seen: std::sync::Mutex::new(std::collections::HashMap::new()),
        })
    }

    /// Creates the dataset `name` in `g` like the first of its layout, if one was made.
    fn create_like(
        &self,
        g: &hdf5::Group,
        name: &str,
        key: LayoutKey,
    ) -> hdf5::Result<Option<hdf5::Dataset>> {
        let seen = self.seen.lock().unwrap_or_else(|p| p.into_inner());
        let Some((dtype, space, dcpl)) = seen.get(&key) else {
            return Ok(None);
        };
        let cname = std::ffi::CString::new(name)
            .map_err(|e| hdf5::Error::from(format!("dataset name {name:?}: {e}")))?;
        // The binding serialises every libhdf5 call behind one lock; a raw call takes it too.
        let id = hdf5::sync::sync(|| unsafe {
            hdf5_sys::h5d::H5Dcreate2(
                g.id(),
                cname.as_ptr(),
                dtype.id(),
                space.id(),
                self.lcpl.id(),
                dcpl.id(),
                hdf5_sys::h5p::H5P_DEFAULT,
            )
        });
        if id < 0 {
            return Err(hdf5::Error::from(format!("cannot create dataset {name}")));
        }
        // SAFETY: a fresh identifier from H5Dcreate2, owned by the handle from here on.
        unsafe { hdf5::from_id::<hdf5::Dataset>(id) }.map(Some)
    }

    /// Writes all of `v` into the float dataset `ds`.
    fn write_all(&self, ds: &hdf5::Dataset, v: &[f64]) -> hdf5::Result<()> {
        use hdf5_sys::h5s::H5S_ALL;
        let status = hdf5::sync::sync(|| unsafe {
            hdf5_sys::h5d::H5Dwrite(
                ds.id(),
                self.native_f64.id(),
                H5S_ALL,
                H5S_ALL,
                hdf5_sys::h5p::H5P_DEFAULT,
                v.as_ptr().cast(),
            )
        });
        if status < 0 {
            return Err(hdf5::Error::from(format!("cannot write {}", ds.name())));
        }
        Ok(())
    }

    /// Remembers the layout of `ds`, the first dataset of `key`.
    fn remember(&self, key: LayoutKey, ds: &hdf5::Dataset) -> hdf5::Result<()> {
        let layout = (ds.dtype()?, ds.space()?, ds.create_plist()?);
        self.seen
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .insert(key, layout);
        Ok(())
    }
}

/// Creates one encoded dataset in `g`: contiguous values written as usual, or the dataset
/// created with the same chunking and filters the chunks were encoded for, then each chunk
/// handed to libhdf5 as it is (`H5Dwrite_chunk`, no filtering under the lock).
fn write_dataset(
    g: &hdf5::Group,
    d: &encoded::Dataset,
    layouts: &Layouts,
) -> hdf5::Result<hdf5::Dataset> {
    let (level, chunks) = match &d.storage {
        Storage::Plain(v) => {
            let key = LayoutKey::Plain(v.len());
            if let Some(ds) = layouts.create_like(g, &d.name, key)? {
                layouts.write_all(&ds, v)?;
                return Ok(ds);
            }
            let ds = g
                .new_dataset_builder()
                .with_data(v)
                .create(d.name.as_str())?;
            layouts.remember(key, &ds)?;
            return Ok(ds);
        }
        Storage::Chunked { level, chunks } => (*level, chunks),
    };
    let key = LayoutKey::Chunked(d.elem, d.len, level);
    let ds = match layouts.create_like(g, &d.name, key)? {
        Some(ds) => ds,
        None => {
            let b = match d.elem {
                Elem::F64 => g.new_dataset::<f64>(),
                Elem::U8 => g.new_dataset::<u8>(),
            }
            .shape(d.len)
            .chunk(encoded::chunk_len(d.len));
            // The chunks were shuffled exactly when the element is wider than a byte.
            let b = if d.elem == Elem::U8 { b } else { b.shuffle() };
            let ds = b.deflate(level).create(d.name.as_str())?;
            layouts.remember(key, &ds)?;
            ds
        }
    };
    let step = encoded::chunk_len(d.len) as u64;
    for (i, c) in chunks.iter().enumerate() {
        let offset = [i as u64 * step];
        // The hdf5 crate serialises every libhdf5 call behind one lock; a raw call must
        // take the same lock.
        let status = hdf5::sync::sync(|| unsafe {
            hdf5_sys::h5d::H5Dwrite_chunk(
                ds.id(),
                hdf5_sys::h5p::H5P_DEFAULT,
                0,
                offset.as_ptr(),
                c.len(),
                c.as_ptr().cast(),
            )
        });
        if status < 0 {
            return Err(hdf5::Error::from(format!(
                "H5Dwrite_chunk failed for {} chunk {i}",
                d.name
            )));
        }
    }
    Ok(ds)
}

/// The fitted parameters under their FORMATS.md §3 names (NaN where not fitted), then the
/// extras: amplitude range, mass used, contact stiffness in physical units.
pub fn parameters(id: &Identification, inertia: Option<f64>) -> Vec<(&'static str, f64)> {
    let nan = f64::NAN;
    let split = |e: Option<Estimate>| e.map_or([nan, nan], |e| [e.value, e.stderr]);
    let [c, c_se] = split(id.clearance());
    let [ce, ce_se] = split(id.clearance_extrapolated());
    let [k, k_se] = split(id.dead_zone.map(|d| d.stiffness));
    let [v, v_se] = split(id.damping.map(|d| d.0));
    let [f, f_se] = split(id.damping.map(|d| d.1));
    let (a_lo, a_hi) = id.amplitude_range().unwrap_or((nan, nan));
    let mass = id.mass.map(|m| m.0).or(inertia);
    let at_max = id
        .bins
        .iter()
        .max_by(|a, b| a.amplitude.total_cmp(&b.amplitude))
        .map_or(nan, |b| b.natural_frequency());
    // In the order of PARAMETER_NAMES, which names them once for every output.
    let values = [
        c,
        c_se,
        ce,
        ce_se,
        k,
        k_se,
        v,
        v_se,
        f,
        f_se,
        a_lo,
        a_hi,
        mass.unwrap_or(nan),
        mass.map_or(nan, |m| m * k),
        id.mass.map_or(0.0, |m| f64::from(u8::from(m.1))),
        at_max,
    ];
    // The absolute values: the per-inertia ones times the inertia (given or estimated).
    let abs = |x: f64| mass.map_or(nan, |m| m * x);
    let absolute = [abs(k_se), abs(v), abs(v_se), abs(f), abs(f_se)];
    let largest = id
        .bins
        .iter()
        .max_by(|a, b| a.amplitude.total_cmp(&b.amplitude));
    // ζ = h0/ω0, with the bin's damping 2 h0.
    let zeta = largest
        .filter(|b| b.stiffness > 0.0)
        .map_or(nan, |b| 0.5 * b.damping / b.stiffness.sqrt());
    let mode = [
        id.mode.map_or(nan, |m| m.peak),
        id.mode.map_or(nan, |m| m.fmin),
        id.mode.map_or(nan, |m| m.fmax),
        zeta,
    ];
    PARAMETER_NAMES
        .into_iter()
        .zip(values)
        .chain(ABSOLUTE_NAMES.into_iter().zip(absolute))
        .chain(MODE_NAMES.into_iter().zip(mode))
        .collect()
}

/// One row of `summary.json` / `summary.csv`: a run × method.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct SummaryRow {
    /// Run path.
    pub run: String,
    /// Archive file name.
    pub source: String,
    /// Method (empty when the run could not be read).
    pub method: String,
    /// `ok` or `failed`.
    pub status: String,
    /// Error text when failed.
    pub error: String,
    /// Fitted parameters and extras, FORMATS.md §3 names (null where not fitted).
    #[serde(flatten)]
    pub parameters: std::collections::BTreeMap<String, Option<f64>>,
    /// Warnings, joined by "; ".
    pub warnings: String,
    /// Seconds spent on this method.
    pub seconds: f64,
    /// `good`, `suspect` or `bad` ([`crate::quality`]); empty when the method failed.
    #[serde(default)]
    pub quality: String,
    /// Why, joined by "; ".
    #[serde(default)]
    pub quality_reasons: String,
    /// Whether this row is the run's recommended estimate (the first good result,
    /// wavelet first, else the first suspect one).
    #[serde(default)]
    pub recommended: bool,
    /// Unit of each parameter in `parameters` ([`crate::units`]).
    #[serde(default)]
    pub units: std::collections::BTreeMap<String, String>,
    /// Displacement, force and inertia units of the run, the three that every parameter's
    /// unit is made of (`summary.csv` has them as its last columns).
    #[serde(default)]
    pub base_units: Option<crate::units::Units>,
}

/// The summary rows of one run.
pub fn summary_rows(run: &RunOutcome) -> Vec<SummaryRow> {
    let base = |method: &str, status: &str, error: String, seconds: f64| SummaryRow {
        run: run.path.clone(),
        source: run.source.clone(),
        method: method.into(),
        status: status.into(),
        error,
        parameters: Default::default(),
        warnings: String::new(),
        seconds,
        quality: String::new(),
        quality_reasons: String::new(),
        recommended: false,
        units: Default::default(),
        base_units: Some(run.units.clone()),
    };
    if let Some(e) = &run.error {
        return vec![base("", "failed", e.clone(), 0.0)];
    }
    let (qualities, recommended) = run.qualities();
    run.methods
        .iter()
        .zip(qualities)
        .map(|((m, r, secs), quality)| match r {
            Err(e) => base(m.as_str(), "failed", e.clone(), *secs),
            Ok(id) => {
                let mut row = base(m.as_str(), "ok", String::new(), *secs);
                row.parameters = parameters(id, run.inertia)
                    .into_iter()
                    .map(|(k, v)| (k.to_string(), v.is_finite().then_some(v)))
                    .collect();
                if let Some(Ok(r)) = &run.refined {
                    for (name, v) in crate::refine::NAMES.into_iter().zip(r.values()) {
                        row.parameters
                            .insert(name.to_string(), v.is_finite().then_some(v));
                    }
                }
                row.units = row
                    .parameters
                    .keys()
                    .filter_map(|k| Some((k.clone(), run.units.parameter(k)?)))
                    .collect();
                row.warnings = id.warnings.join("; ");
                if let Some(q) = quality {
                    row.quality = q.verdict.as_str().into();
                    row.quality_reasons = q.reasons.join("; ");
                }
                row.recommended = recommended == Some(*m);
                row
            }
        })
        .collect()
}

/// Writes `<dir>/summary.json` and `<dir>/summary.csv` (each atomically).
pub fn write_summary(dir: &Path, rows: &[SummaryRow]) -> Result<(), ReportError> {
    let json = serde_json::json!({
        "format": "skelid-summary/1",
        "units": campaign_units(rows),
        "rows": rows,
    });
    let text = serde_json::to_string_pretty(&json).map_err(|e| ReportError {
        file: "summary.json".into(),
        detail: e.to_string(),
    })?;
    write_atomic(&dir.join("summary.json"), text.as_bytes())?;
    let names = PARAMETER_NAMES;
    let mut csv = String::from("run,source,method,status,");
    csv.push_str(&names.join(","));
    csv.push_str(",seconds,warnings,error,quality,quality_reasons,recommended,");
    // Added after the columns other programs already read, never between them.
    csv.push_str(&ABSOLUTE_NAMES.join(","));
    csv.push_str(",displacement_unit,force_unit,inertia_unit,");
    csv.push_str(&crate::refine::NAMES.join(","));
    csv.push(',');
    csv.push_str(&MODE_NAMES.join(","));
    csv.push('\n');
    let quote = |s: &str| format!("\"{}\"", s.replace('"', "\"\""));
    let value = |r: &SummaryRow, n: &str| match r.parameters.get(n) {
        Some(Some(v)) => format!("{v:.6e}"),
        _ => String::new(),
    };
    for r in rows {
        csv.push_str(&format!(
            "{},{},{},{},",
            quote(&r.run),
            quote(&r.source),
            r.method,
            r.status
        ));
        for n in names {
            csv.push_str(&value(r, n));
            csv.push(',');
        }
        csv.push_str(&format!(
            "{:.3},{},{},{},{},{},",
            r.seconds,
            quote(&r.warnings),
            quote(&r.error),
            r.quality,
            quote(&r.quality_reasons),
            u8::from(r.recommended)
        ));
        for n in ABSOLUTE_NAMES {
            csv.push_str(&value(r, n));
            csv.push(',');
        }
        let u = r.base_units.clone().unwrap_or_default();
        csv.push_str(&format!(
            "{},{},{}",
            quote(&u.displacement),
            quote(&u.force),
            quote(&u.inertia)
        ));
        for n in crate::refine::NAMES.into_iter().chain(MODE_NAMES) {
            csv.push(',');
            csv.push_str(&value(r, n));
        }
        csv.push('\n');
    }
    write_atomic(&dir.join("summary.csv"), csv.as_bytes())
}

/// summary.json's campaign-wide `units`: each parameter's unit where every row that has it
/// agrees, else its unit in symbols: "F s/D (D, F, J: each row's base_units)".
fn campaign_units(rows: &[SummaryRow]) -> std::collections::BTreeMap<String, String> {
    let symbols = Units {
        displacement: "D".into(),
        input: "I".into(),
        inertia: "J".into(),
        force: "F".into(),
    };
    let mut units: std::collections::BTreeMap<String, String> = Default::default();
    for r in rows {
        for (name, unit) in &r.units {
            let u = units.entry(name.clone()).or_insert_with(|| unit.clone());
            if u != unit {
                let symbolic = symbols.parameter(name).unwrap_or_default();
                *u = format!("{symbolic} (D, F, J: each row's base_units)");
            }
        }
    }
    units
}

/// The fitted parameters (FORMATS.md §3 names) and extras, in the order of `summary.csv`'s
/// columns; [`parameters`] gives their values.
pub const PARAMETER_NAMES: [&str; 16] = [
    "clearance",
    "clearance_stderr",
    "clearance_extrapolated",
    "clearance_extrapolated_stderr",
    "stiffness",
    "stiffness_stderr",
    "viscous_damping",
    "viscous_damping_stderr",
    "coulomb_friction",
    "coulomb_friction_stderr",
    "amplitude_min",
    "amplitude_max",
    "inertia",
    "contact_stiffness",
    "inertia_estimated",
    "natural_frequency_at_amplitude_max",
];

/// The absolute parameters (inertia times the per-inertia ones, added after
/// [`PARAMETER_NAMES`]): NaN where no inertia is given or estimated. `contact_stiffness`
/// itself is among [`PARAMETER_NAMES`].
pub const ABSOLUTE_NAMES: [&str; 5] = [
    "contact_stiffness_stderr",
    "viscous_damping_absolute",
    "viscous_damping_absolute_stderr",
    "coulomb_friction_absolute",
    "coulomb_friction_absolute_stderr",
];

/// The isolated mode ([`crate::mode`]: its peak and band, Hz; NaN for the whole record)
/// and the damping ratio at the largest amplitude, added after [`ABSOLUTE_NAMES`] and the
/// refined names.
pub const MODE_NAMES: [&str; 4] = [
    "mode_frequency",
    "mode_fmin",
    "mode_fmax",
    "damping_ratio_at_amplitude_max",
];

/// Writes a file through a temporary file renamed into place.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), ReportError> {
    let err = |detail: String| ReportError {
        file: path.display().to_string(),
        detail,
    };
    let tmp = tmp_path(path);
    let done = std::fs::write(&tmp, bytes)
        .and_then(|()| std::fs::rename(&tmp, path))
        .map_err(|e| err(e.to_string()));
    if done.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    done
}

#[cfg(test)]
mod tests {
    use super::*;
    use hdf5::types::VarLenUnicode;

    /// The writer creates attributes and the later datasets of a layout with raw libhdf5
    /// calls; what a reader finds must be what the binding's builders make: the same
    /// types, chunking, filters and values.
    #[test]
    fn raw_created_attributes_and_datasets_match_the_binding_s() {
        let x: Vec<f64> = (0..10_000).map(|i| (i as f64 * 0.003).cos()).collect();
        let mask: Vec<u8> = (0..10_000).map(|i| u8::from(i % 3 == 0)).collect();
        let run = |path: &str, scale: f64| {
            let mut e = EncodedRun::new(path);
            e.str_attr("", "status", "ok");
            e.f64_attr("", "sample_rate", 1000.0);
            e.group("wavelet");
            e.group("wavelet/skeleton");
            let v: Vec<f64> = x.iter().map(|a| a * scale).collect();
            e.signal("wavelet", "response_amplitude", &v, true);
            e.dataset_attr("wavelet", "response_amplitude", "units", "rad");
            e.signal("wavelet", "response_frequency", &v, true);
            e.bytes("wavelet", "valid", &mask, 4);
            e.signal("wavelet/skeleton", "amplitude", &v[..12], false);
            e.str_attr("wavelet", "clearance_units", "rad · ü");
            e
        };
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("r.h5");
        let w = ResultsWriter::create_at(&file).unwrap();
        // The first run's datasets go through the builders, the second's are raw.
        for (path, scale) in [("/runs/a", 1.0), ("/runs/b", 2.0)] {
            w.write_encoded(&run(path, scale)).unwrap();
        }
        w.finish().unwrap();
        let f = hdf5::File::open(&file).unwrap();
        let layout = |p: &str| {
            let d = f.dataset(p).unwrap();
            let filters = d.filters();
            (d.chunk(), d.shape(), d.dtype().unwrap().size(), filters)
        };
        for name in ["response_amplitude", "response_frequency", "valid"] {
            let (a, b) = (
                format!("/runs/a/wavelet/{name}"),
                format!("/runs/b/wavelet/{name}"),
            );
            assert_eq!(
                format!("{:?}", layout(&a)),
                format!("{:?}", layout(&b)),
                "{name}"
            );
        }
        assert_eq!(
            format!("{:?}", layout("/runs/a/wavelet/skeleton/amplitude")),
            format!("{:?}", layout("/runs/b/wavelet/skeleton/amplitude"))
        );
        let plain: Vec<f64> = f
            .dataset("/runs/b/wavelet/skeleton/amplitude")
            .unwrap()
            .read_raw()
            .unwrap();
        assert_eq!(plain, x[..12].iter().map(|a| a * 2.0).collect::<Vec<_>>());
        let (chunk, _, _, filters) = layout("/runs/b/wavelet/response_amplitude");
        assert_eq!(chunk, Some(vec![encoded::CHUNK]));
        assert_eq!(filters.len(), 2, "shuffle and deflate: {filters:?}");
        let back: Vec<f64> = f
            .dataset("/runs/b/wavelet/response_amplitude")
            .unwrap()
            .read_raw()
            .unwrap();
        assert_eq!(back, x.iter().map(|a| a * 2.0).collect::<Vec<_>>());
        let valid: Vec<u8> = f
            .dataset("/runs/b/wavelet/valid")
            .unwrap()
            .read_raw()
            .unwrap();
        assert_eq!(valid, mask);
        let g = f.group("/runs/b/wavelet").unwrap();
        let text: VarLenUnicode = g.attr("clearance_units").unwrap().read_scalar().unwrap();
        assert_eq!(text.as_str(), "rad · ü");
        let units: VarLenUnicode = g
            .dataset("response_amplitude")
            .unwrap()
            .attr("units")
            .unwrap()
            .read_scalar()
            .unwrap();
        assert_eq!(units.as_str(), "rad");
        let fs: f64 = f
            .group("/runs/b")
            .unwrap()
            .attr("sample_rate")
            .unwrap()
            .read_scalar()
            .unwrap();
        assert_eq!(fs, 1000.0);
        assert_eq!(
            crate::h5util::read_attr(&g.attr("clearance_units").unwrap()).unwrap(),
            crate::h5util::AttrValue::Text("rad · ü".into())
        );
    }
}
