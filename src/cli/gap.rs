//! `skelid gap`: why a rig's simulation does not match its measurements, and its
//! self-check.

use anyhow::{bail, Context, Result};
use clap::{Args, ValueEnum};
use skelid::ingest::Archive;
use skelid::model::RigModel;
use std::path::PathBuf;
use std::process::ExitCode;

use super::args::{
    report_fallbacks, BackendArg, BackendArgs, FiguresArgs, IdentifyArgs, IngestArgs,
};
use skelid::gap::export as out;

/// Options of `skelid gap`.
#[derive(Args)]
pub(crate) struct GapArgs {
    /// Rig model to compare with the measurements (TOML, FORMATS.md §2): the paper's
    /// base-motion link, or one mode of a structure driven by a force (`kind = "force"`).
    /// Its inertia is held (unless --fit-inertia; a force model's modal mass is always
    /// refitted); stiffness, damping, clearance and gravity stiffness are refitted before
    /// any effect is tried.
    #[arg(long, value_name = "RIG.toml", required_unless_present = "self_check")]
    pub(crate) model: Option<PathBuf>,
    /// Campaign archive with the measured runs: base-motion runs (input = base angle,
    /// output = link angle) for a base-motion model, force runs (input = force, output =
    /// displacement, velocity or acceleration) for a force model.
    #[arg(value_name = "ARCHIVE", required_unless_present = "self_check")]
    pub(crate) archive: Option<PathBuf>,
    /// Run group to diagnose (repeatable); every run of the model's kind in the archive by
    /// default. Each is diagnosed alone, on alternate time blocks.
    #[arg(long = "run", value_name = "PATH")]
    pub(crate) runs: Vec<String>,
    /// Runs of one structure fitted together (paths or globs, comma-separated or
    /// repeated, e.g. '/sine_sweep/level_[1357]'): the model's parameters and each
    /// effect's are fitted on all of them at once, each run driven by its own measured
    /// input, and every gap, shrink and verdict is scored on the --holdout runs, which the
    /// fits never see. Needs --holdout.
    #[arg(long, value_name = "RUNS", value_delimiter = ',', requires = "holdout")]
    pub(crate) fit: Vec<String>,
    /// Runs held out from a --fit: scored whole, never fitted on (paths or globs).
    #[arg(long, value_name = "RUNS", value_delimiter = ',', requires = "fit")]
    pub(crate) holdout: Vec<String>,
    /// Output folder: gap.json, gap.html, the fitted model(s); self-check.json with
    /// --self-check.
    #[arg(long, default_value = "skelid-gap", value_name = "DIR")]
    pub(crate) out: PathBuf,
    /// Length of the alternate time blocks (s): fits see the even ones, gaps are scored on
    /// the odd ones.
    #[arg(
        allow_negative_numbers = true,
        long,
        default_value_t = 1.0,
        value_name = "SECONDS"
    )]
    pub(crate) holdout_block: f64,
    /// Where the wavelet transforms of the gap's identifications run (the measured run's
    /// and every simulation's): `cpu` (the default: each run's search identifies one
    /// simulation at a time, where a GPU's batching gains little), `auto` (a hardware GPU
    /// when one opens, else the CPU) or `gpu` (any adapter, or an error). Runs diagnosed
    /// at once hand their simulations to the GPU together. The transforms differ in their
    /// last digits (the GPU's estimate runs in f32), so the simplex searches take slightly
    /// different paths: verdicts agree, gaps may differ in their second digit.
    #[arg(long, value_enum, default_value = "cpu", value_name = "BACKEND")]
    pub(crate) backend: BackendArg,
    #[command(flatten)]
    pub(crate) figures: FiguresArgs,
    /// Runs diagnosed at once (default: one per core). A run's own search is a chain of
    /// simplex steps, each waiting for the last, so one run keeps about one core busy;
    /// an archive of several runs is diagnosed N at a time. Each run in flight holds its
    /// record and a few simulations of it.
    #[arg(long, short, value_name = "N")]
    pub(crate) jobs: Option<usize>,
    /// Simulations spent refitting the model's own parameters.
    #[arg(long, default_value_t = 150, value_name = "N")]
    pub(crate) baseline_evaluations: usize,
    /// Simulations per refined candidate (and per pair of effects).
    #[arg(long, default_value_t = 45, value_name = "N")]
    pub(crate) candidate_evaluations: usize,
    /// Scan points refined by the simplex: every effect is scanned on the baseline and on
    /// the nominal model, and the best N of those 2 × 6 starts are refined (fewer is
    /// faster, and may leave an effect the baseline absorbed undetected).
    #[arg(long, default_value_t = 12, value_name = "N")]
    pub(crate) refine: usize,
    /// Never try pairs of effects.
    #[arg(long)]
    pub(crate) no_pairs: bool,
    /// Refit the inertia too (held at the model's value otherwise).
    #[arg(long)]
    pub(crate) fit_inertia: bool,
    /// Refit the effects the model already has (its [effects.*] tables) with its own
    /// parameters in the baseline, instead of holding them at the model's values: a
    /// fitted model from an earlier diagnosis updated on these runs. The candidates then
    /// add effects to that baseline. More parameters: consider a larger
    /// --baseline-evaluations (300 for the F-16's verdict model, whose 9 parameters move)
    #[arg(long)]
    pub(crate) refit_effects: bool,
    /// Score the waveform within a cycle (the default; the flag is kept for scripts written
    /// when it was not): the third harmonic of the relative motion against its first, at
    /// resonance, as a fourth domain of the gap beside time, backbone and damping. Every
    /// other domain is of the first harmonic, where a hardening contact on one sweep looks
    /// like a stiffer, wider contact; the fraction of each cycle spent in contact does not.
    /// Base-motion runs with displacement channels only (others keep three domains).
    // Never read: the waveform is scored unless --no-waveform is given.
    #[arg(long, overrides_with = "no_waveform")]
    pub(crate) waveform: bool,
    /// Leave the waveform domain out: the gap of time, backbone and damping alone (the
    /// default before the waveform was; it names a hardening on one sweep less often).
    #[arg(long, overrides_with = "waveform")]
    pub(crate) no_waveform: bool,
    /// How far apart the zeros of the input and output encoders may be (rad; or m). A
    /// difference between their zeros shifts the measured relative motion exactly as an
    /// offset clearance does, so a shift of the motion's centre up to this is not counted
    /// in the gap, and an offset clearance must exceed it to be named. Overrides each
    /// run's `zero_tolerance` attribute (default: the attribute, else 0).
    #[arg(allow_negative_numbers = true, long, value_name = "RAD")]
    pub(crate) zero_tolerance: Option<f64>,
    /// Effects to try, comma-separated (default: the whole vocabulary).
    #[arg(long, value_delimiter = ',', value_name = "EFFECT,...")]
    pub(crate) effects: Vec<String>,
    /// Instead of diagnosing an archive, measure the diagnosis on simulated rigs that hide
    /// one effect (or none) from their model; prints a confusion matrix.
    #[arg(long)]
    pub(crate) self_check: bool,
    /// Self-check cases (the seven effects and none in turn).
    #[arg(long, default_value_t = 40, value_name = "N", requires = "self_check")]
    pub(crate) cases: usize,
    /// Self-check seed.
    #[arg(long, default_value_t = 1, value_name = "S", requires = "self_check")]
    pub(crate) seed: u64,
    /// What drives the self-check's rigs: `paper`, the paper's chirp (0 to 12 Hz in 30 s),
    /// or `two-level`, 3 to 9 Hz at the paper's rate (0.4 Hz/s) at the paper's level and
    /// then at 1.75 times it, in one 30 s record (one level maps only part of the skeleton:
    /// a hardening contact hides behind a stiffer contact and a wider clearance).
    #[arg(long, value_enum, default_value = "paper", requires = "self_check")]
    pub(crate) sweep: SweepArg,
    /// Which rigs the self-check draws: `paper`, the paper's rig with encoder noise, or
    /// `random`, paper-like rigs drawn at random (gravity stiffness 0.5-2 1/s²,
    /// contact at 9.7-11.4 Hz, clearance 1.3-1.7°, damping 10-21 N m s/rad, the chirp at
    /// 0.032-0.048 rad, 17-20 bit/rev encoders with DC offsets up to ±2e-4 rad and sub-step
    /// noise, a gravity_stiffness attribute ±10 % off, a zero_tolerance attribute of 4e-4
    /// rad); their quantization cases are a
    /// 12-14 bit/rev encoder whose steps carry acquisition noise of 1/60-1/15 of a step.
    #[arg(long, value_enum, default_value = "paper", requires = "self_check")]
    pub(crate) rigs: RigsArg,
    /// With --self-check: instead of the confusion matrix, find each effect's detection
    /// limit, the smallest parameter the diagnosis names in at least 80 % of cases, on a
    /// ladder of factors of its demo value (1, then halves down to 1/16 while named, or
    /// doublings up to 8 until named); --cases is the cases per rung. Optionally only the
    /// effects listed (comma-separated). Writes detection-limits.json.
    #[arg(
        long,
        value_name = "EFFECT,...",
        num_args = 0..,
        value_delimiter = ',',
        requires = "self_check"
    )]
    pub(crate) detection_limits: Option<Vec<String>>,
    /// How the measurement and every simulation are identified (wavelet method, on the
    /// CPU): the same options as `skelid run`, with the same defaults.
    #[command(flatten)]
    pub(crate) identify: IdentifyArgs,
    #[command(flatten)]
    pub(crate) ingest: IngestArgs,
}

/// The rigs of the self-check.
#[derive(Clone, Copy, ValueEnum)]
pub(crate) enum RigsArg {
    /// The paper's rig.
    Paper,
    /// Random paper-like rigs (the ranges of `skelid validate`), with DC offsets and noise.
    Random,
}

/// The drive of the self-check's rigs.
#[derive(Clone, Copy, ValueEnum)]
pub(crate) enum SweepArg {
    /// The paper's chirp.
    Paper,
    /// 3 to 9 Hz at the paper's rate, at the paper's level then 1.75 times it.
    TwoLevel,
    /// The same two sweeps as two runs fitted together.
    TwoRuns,
}

pub(crate) fn gap_search_options(a: &GapArgs) -> Result<skelid::gap::SearchOptions> {
    if !a.holdout_block.is_finite() || a.holdout_block <= 0.0 {
        bail!("--holdout-block must be a positive number of seconds");
    }
    let effects = parse_effects("--effects", &a.effects)?;
    if a.zero_tolerance
        .is_some_and(|t| !(t >= 0.0 && t.is_finite()))
    {
        bail!("--zero-tolerance is how far apart the encoders' zeros may be, in rad: give 0 or more (e.g. 4e-4 for two encoders zeroed to ±2e-4 rad each)");
    }
    if a.baseline_evaluations < 10 || a.candidate_evaluations < 5 {
        bail!(
            "--baseline-evaluations must be at least 10 and --candidate-evaluations at least 5 (a simplex needs one simulation per parameter and a few steps); the defaults are 150 and 45"
        );
    }
    Ok(skelid::gap::SearchOptions {
        blocks: skelid::gap::Blocks {
            seconds: a.holdout_block,
        },
        baseline_evaluations: a.baseline_evaluations,
        refine: a.refine,
        candidate_evaluations: a.candidate_evaluations,
        pairs: !a.no_pairs,
        fit_inertia: a.fit_inertia,
        refit_effects: a.refit_effects,
        effects,
        waveform: !a.no_waveform,
        zero_tolerance: a.zero_tolerance,
    })
}

/// The effects `names` lists (all of them when empty), or an error naming `flag` and the
/// vocabulary.
fn parse_effects(flag: &str, names: &[String]) -> Result<Vec<skelid::model::EffectKind>> {
    use skelid::model::EffectKind;
    if names.is_empty() {
        return Ok(EffectKind::ALL.to_vec());
    }
    names
        .iter()
        .map(|e| {
            EffectKind::parse(e).with_context(|| {
                format!(
                    "{flag}: unknown effect `{e}`; the vocabulary is {}",
                    EffectKind::EVERY.map(|k| k.name()).join(", ")
                )
            })
        })
        .collect()
}

/// `--resonance` for a `kind = "force"` model (and its self-check) unless given: within
/// ±2 % of ω0. The F-16's held-out gap shrank by 47 % there against 41 % at the general
/// 0.1; the force self-check's 42 cases gave the same verdicts at both (top-1 97 %).
const FORCE_RESONANCE: f64 = 0.02;

pub(crate) fn cmd_gap(a: GapArgs) -> Result<ExitCode> {
    super::args::refuse_file_as_folder("--out", &a.out)?;
    use skelid::run::RunKind;
    let mut opt = gap_search_options(&a)?;
    let mut options = a.identify.options("gap", None)?;
    // A structure's lightly damped mode is compared near resonance unless the command
    // line says otherwise (see `--resonance`).
    let force_resonance = |options: &mut skelid::identify::IdentifyOptions| {
        if a.identify.resonance.is_none() {
            options.resonance = FORCE_RESONANCE;
        }
    };
    if a.self_check {
        if a.ingest.kind == Some(RunKind::Force) {
            force_resonance(&mut options);
        }
        let engine = super::Engine::new(options, BackendArgs { backend: a.backend }.open()?);
        create_out(&a.out)?;
        return gap_self_check(&a, &opt, &engine);
    }
    let (Some(model_path), Some(archive_path)) = (&a.model, &a.archive) else {
        bail!("give --model RIG.toml and an ARCHIVE (or --self-check)");
    };
    let model = RigModel::load(model_path)?;
    let model_warnings = warn_model(model_path, &model);
    if a.effects.is_empty() {
        opt.effects = model.vocabulary();
    }
    // The model's band isolates its mode where the command line leaves the choice open.
    if let (Some([lo, hi]), skelid::mode::ModeChoice::ByKind) = (model.band, options.mode) {
        options.mode = skelid::mode::ModeChoice::Band(lo, hi);
    }
    if model.kind == skelid::model::ModelKind::Force {
        force_resonance(&mut options);
    }
    let resonance = options.resonance;
    let engine = super::Engine::new(options, BackendArgs { backend: a.backend }.open()?);
    let ingest = a.ingest.options()?;
    let archive = Archive::open(archive_path, &ingest)?;
    let wanted_kind = match model.kind {
        skelid::model::ModelKind::BaseMotion => RunKind::BaseMotion,
        skelid::model::ModelKind::Force => RunKind::Force,
        skelid::model::ModelKind::Free => RunKind::Free,
    };
    let together = !a.fit.is_empty();
    let (fit_paths, holdout_paths) = if together {
        if !a.runs.is_empty() {
            bail!("--run diagnoses runs one at a time; --fit/--holdout fits runs together: give one or the other");
        }
        let paths: Vec<&str> = archive.runs.iter().map(|e| e.path.as_str()).collect();
        let fit = match_runs("--fit", &a.fit, &paths, archive_path)?;
        let holdout = match_runs("--holdout", &a.holdout, &paths, archive_path)?;
        if let Some(both) = fit.iter().find(|p| holdout.contains(p)) {
            bail!("{both} is both in --fit and in --holdout: a held-out run must be one the fit never sees");
        }
        (fit, holdout)
    } else {
        (Vec::new(), Vec::new())
    };
    let mut chosen = Vec::new();
    let mut failed: Vec<(String, String)> = Vec::new();
    for entry in &archive.runs {
        let wanted = if together {
            fit_paths.contains(&entry.path) || holdout_paths.contains(&entry.path)
        } else {
            a.runs.is_empty() || a.runs.iter().any(|r| r == &entry.path)
        };
        if !wanted {
            continue;
        }
        let meta = match &entry.meta {
            Ok(meta) => meta,
            Err(e) if a.runs.is_empty() && !together => {
                eprintln!("error: {}: {e} (skipped; the other runs go on)", entry.path);
                failed.push((entry.path.clone(), e.to_string()));
                continue;
            }
            Err(e) => bail!("{}: {e}", entry.path),
        };
        if meta.kind != wanted_kind {
            if a.runs.is_empty() && !together {
                eprintln!(
                    "note: {} skipped: a {} run (the model is a {} model; it simulates {} runs)",
                    entry.path,
                    meta.kind.as_str(),
                    model.kind.name(),
                    wanted_kind.as_str()
                );
                continue;
            }
            bail!("{}: a {} run; the model ({}) is a {} model, simulated under a measured {}, so it needs kind = \"{}\" runs", entry.path, meta.kind.as_str(), model_path.display(), model.kind.name(), if wanted_kind == RunKind::Force { "force" } else { "base motion" }, wanted_kind.as_str());
        }
        chosen.push(meta.clone());
    }
    for r in &a.runs {
        if !archive.runs.iter().any(|e| &e.path == r) {
            bail!(
                "{}: no run {r} (list the runs with `skelid inspect {}`)",
                archive_path.display(),
                archive_path.display()
            );
        }
    }
    if chosen.is_empty() {
        bail!(
            "{}: no {} run to diagnose. skelid gap drives the model ({}, a {} model, FORMATS.md §2) with each run's measured {}; give a model of the runs' kind (`kind = \"force\"` for force runs), or identify free decays with `skelid run`",
            archive_path.display(),
            wanted_kind.as_str(),
            model_path.display(),
            model.kind.name(),
            if wanted_kind == RunKind::Force { "force" } else { "base angle" },
        );
    }
    // Made once the runs are chosen: a wrong --run or archive leaves no empty folder.
    create_out(&a.out)?;
    let settings = serde_json::json!({
        "model": model_path.display().to_string(),
        "archive": archive_path.display().to_string(),
        "holdout": if together {
            format!("runs fitted together: {}; held out whole: {}", fit_paths.join(", "), holdout_paths.join(", "))
        } else {
            format!("alternate {} s blocks: fits on the even ones (from t = 0, a free decay's from its release), gaps scored on the odd ones", a.holdout_block)
        },
        "model_kind": model.kind.name(),
        "fit_runs": fit_paths,
        "holdout_runs": holdout_paths,
        "baseline_evaluations": opt.baseline_evaluations,
        "candidate_evaluations": opt.candidate_evaluations,
        "refine": opt.refine,
        "pairs": opt.pairs,
        "backend": if engine.backend().is_gpu() { "gpu" } else { "cpu" },
        "fit_inertia": opt.fit_inertia,
        "refit_effects": opt.refit_effects,
        "waveform": opt.waveform,
        "zero_tolerance": opt.zero_tolerance,
        "resonance": resonance,
        "min_shrink": skelid::gap::search::MIN_SHRINK,
        "min_drop": skelid::gap::search::MIN_DROP,
        "model_warnings": model_warnings,
    });
    let exporter = Terminal {
        out: &a.out,
        model_path,
        title: archive_path.display().to_string(),
        settings,
        several: chosen.len() > 1,
        effects: opt.effects.len(),
        bar: indicatif::ProgressBar::new(chosen.len() as u64).with_style(
            indicatif::ProgressStyle::with_template(
                "{bar:25} {pos}/{len} runs, {elapsed} elapsed, ~{eta} left · {wide_msg}",
            )
            .expect("a valid template"),
        ),
        running: Default::default(),
        figures: a.figures.format(),
    };
    let jobs = a
        .jobs
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    let done = if together {
        let pick = |paths: &[String]| -> Vec<skelid::run::RunMeta> {
            paths
                .iter()
                .filter_map(|p| chosen.iter().find(|m| &m.path == p).cloned())
                .collect()
        };
        let (fit, holdout) = (pick(&fit_paths), pick(&holdout_paths));
        if fit.is_empty() || holdout.is_empty() {
            bail!(
                "{}: no readable {} run left to {} (see the errors above)",
                archive_path.display(),
                wanted_kind.as_str(),
                if fit.is_empty() { "fit on" } else { "hold out" }
            );
        }
        skelid::gap::runner::diagnose_together(
            &archive,
            &fit,
            &holdout,
            &model,
            &opt,
            engine.get(),
            failed,
            &exporter,
        )
    } else {
        skelid::gap::runner::diagnose_runs(
            &archive,
            &chosen,
            &model,
            &opt,
            engine.get(),
            jobs,
            failed,
            &exporter,
        )
    }
    .map_err(|e| match e {
        skelid::gap::runner::RunnerError::Export(e) => anyhow::anyhow!(e),
        other => anyhow::Error::new(other).context("--jobs"),
    })?;
    exporter.bar.finish_and_clear();
    report_fallbacks(engine.backend());
    let reports: Vec<&skelid::gap::GapRun> = done.runs.iter().collect();
    let (json, page) = exporter.write(&reports, &done.failed)?;
    println!(
        "wrote {}, {} and the fitted model(s) in {}",
        json.display(),
        page.display(),
        a.out.display()
    );
    Ok(if done.failed.is_empty() {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(1)
    })
}

fn create_out(out: &std::path::Path) -> Result<()> {
    std::fs::create_dir_all(out)
        .with_context(|| format!("cannot create the output folder {}", out.display()))
}

/// The archive's run paths that `patterns` (paths or globs) name, in archive order; an
/// error naming `flag` for a pattern that names none.
fn match_runs(
    flag: &str,
    patterns: &[String],
    paths: &[&str],
    archive: &std::path::Path,
) -> Result<Vec<String>> {
    let mut found = Vec::new();
    for p in patterns {
        let pattern =
            glob::Pattern::new(p).with_context(|| format!("{flag} {p}: not a run path or glob"))?;
        let hits: Vec<&str> = paths
            .iter()
            .copied()
            .filter(|path| *path == p || pattern.matches(path))
            .collect();
        if hits.is_empty() {
            bail!(
                "{flag} {p}: no run of {} matches (list the runs with `skelid inspect {}`)",
                archive.display(),
                archive.display()
            );
        }
        found.extend(hits.into_iter().map(String::from));
    }
    let mut ordered: Vec<String> = paths
        .iter()
        .filter(|p| found.iter().any(|f| f == *p))
        .map(|p| p.to_string())
        .collect();
    ordered.dedup();
    Ok(ordered)
}

/// `skelid gap`'s exporter: a progress bar (runs done; each running run's simulations in its
/// message), a summary of each run on the terminal, its fitted model, and gap.json and
/// gap.html rewritten (atomically) after every run.
struct Terminal<'a> {
    out: &'a std::path::Path,
    model_path: &'a std::path::Path,
    title: String,
    settings: serde_json::Value,
    several: bool,
    effects: usize,
    bar: indicatif::ProgressBar,
    running: std::sync::Mutex<std::collections::BTreeMap<String, usize>>,
    figures: Option<skelid::report::figure_files::FigureFormat>,
}

impl Terminal<'_> {
    fn show(&self, running: &std::collections::BTreeMap<String, usize>) {
        let parts: Vec<String> = running
            .iter()
            .map(|(run, n)| format!("{run}: {n} simulations"))
            .collect();
        self.bar.set_message(parts.join(", "));
    }

    fn write(
        &self,
        reports: &[&skelid::gap::GapRun],
        failed: &[(String, String)],
    ) -> Result<(PathBuf, PathBuf)> {
        let json = out::write_gap_json(self.out, reports, failed, self.settings.clone())?;
        let page = out::write_gap_page(self.out, &self.title, reports)?;
        Ok((json, page))
    }

    /// A diagnosed run's lines on the terminal and its fitted model written (and read back).
    /// Runs fitted together share one diagnosis and one fitted model: both come with the
    /// first fit run, and every run adds its line of the mode at its largest amplitude.
    fn report(&self, r: &skelid::gap::GapRun) -> Result<()> {
        let d = &r.diagnosis;
        let together = !r.together.0.is_empty();
        let first = !together || r.together.0.first() == Some(&d.run);
        let mut text = String::new();
        if first {
            text = self.diagnosis_text(r);
        }
        if together {
            if first {
                text += &format!(
                    "\n  the mode at each run's largest amplitude (frequency Hz, damping ratio %), measured · nominal · fitted{}; under it, the run's own gap under each model:",
                    if d.verdict.is_some() { "" } else { " (the refitted baseline) · the best candidate" }
                );
            }
            let at = |id: Option<&skelid::identify::Identification>| {
                id.and_then(|i| i.at_largest_amplitude())
                    .map_or("–".to_string(), |a| {
                        format!("{:.3} Hz {:.2} %", a.frequency, 100.0 * a.damping_ratio)
                    })
            };
            let best = r.best_candidate().map_or(String::new(), |(name, w)| {
                format!(" · {name} {}", at(Some(&w.identified)))
            });
            // The run's own gap under each model, by domain: which run, and which domain of
            // it, carries what the diagnosis leaves.
            let gaps: Vec<String> = r
                .own_gaps()
                .into_iter()
                .map(|(name, g)| format!("{name} {}", g.by_domain()))
                .collect();
            let line = format!(
                "\n    {:<32} {:<8} {} · {} · {}{best}\n    {:<41} its gap, {}: {}",
                d.run,
                r.role.name(),
                at(Some(&r.measured)),
                at(r.nominal.as_ref().map(|w| &w.identified)),
                at(Some(&r.fitted().identified)),
                "",
                r.baseline.gap.domains_label(),
                gaps.join(" · "),
            );
            if first {
                text += &line;
            } else {
                text = line.trim_start_matches('\n').to_string();
            }
        }
        if let Some(rel) = &r.release {
            text += &format!(
                "\n    the decay is compared from t = {:.3} s of its record, {}",
                rel.at_s,
                rel.describe()
            );
        }
        self.bar.suspend(|| println!("{text}"));
        if let Some(w) = r.release.and_then(|rel| rel.warning()) {
            say(&self.bar, format!("warning: {}: {w}", d.run));
        }
        if first {
            let several = self.several && !together;
            let path = out::fitted_model_path(self.out, self.model_path, &d.run, several);
            out::write_fitted_model(&path, r)?;
            let fitted =
                RigModel::load(&path).context("the fitted model written does not read back")?;
            for w in fitted.warnings() {
                say(&self.bar, format!("warning: {}: {w}", path.display()));
            }
        }
        if let Some(format) = self.figures {
            out::write_gap_figures(self.out, r, format)?;
        }
        Ok(())
    }

    /// The diagnosis on the terminal: the verdict, the gaps, the three best candidates.
    fn diagnosis_text(&self, r: &skelid::gap::GapRun) -> String {
        let d = &r.diagnosis;
        let name = if r.together.0.is_empty() {
            d.run.clone()
        } else {
            format!(
                "fitted on {} · held out {}",
                r.together.0.join(", "),
                r.together.1.join(", ")
            )
        };
        let mut text = format!(
            "{}: verdict {} · held-out gap nominal {:.4} → baseline {:.4}{} · {} simulations, {:.1} s",
            name,
            d.verdict_name(),
            d.nominal_score.holdout,
            d.baseline.score.holdout,
            d.verdict.map_or(String::new(), |i| {
                let c = &d.candidates[i];
                format!(
                    " → {:.4} with {} (shrink {:.0} %{})",
                    c.score.holdout,
                    c.name(),
                    100.0 * c.shrink,
                    shrink_note(c)
                )
            }),
            d.evaluations,
            d.seconds
        );
        for c in d.candidates.iter().take(3) {
            let p: Vec<String> = c
                .params()
                .iter()
                .map(|(k, v)| out::param_text(k, *v, c.model.kind))
                .collect();
            text += &format!(
                "\n    {:<40} held-out gap {:.4}  shrink {:>4.0} %{}  {}",
                c.name(),
                c.score.holdout,
                100.0 * c.shrink,
                shrink_note(c),
                p.join(", ")
            );
        }
        text
    }
}

impl skelid::gap::runner::Exporter for Terminal<'_> {
    fn started(&self, run: &skelid::run::RunMeta) {
        say(
            &self.bar,
            format!(
                "{}: refitting the model, then {} effects ...",
                run.path, self.effects
            ),
        );
    }

    fn simulations(&self, run: &skelid::run::RunMeta, n: usize) {
        let mut r = self.running.lock().unwrap_or_else(|p| p.into_inner());
        r.insert(run.path.clone(), n);
        self.show(&r);
        // Without a terminal (a log file), a line every 100 simulations.
        if self.bar.is_hidden() && n.is_multiple_of(100) {
            eprintln!("{}: {n} simulations", run.path);
        }
    }

    fn finished(
        &self,
        run: &skelid::run::RunMeta,
        result: Result<&skelid::gap::GapRun, &str>,
        done: &[&skelid::gap::GapRun],
        failed: &[(String, String)],
    ) -> Result<(), skelid::gap::runner::ExportError> {
        {
            let mut r = self.running.lock().unwrap_or_else(|p| p.into_inner());
            r.remove(&run.path);
            self.show(&r);
        }
        self.bar.inc(1);
        match result {
            Ok(r) => self.report(r)?,
            Err(e) => say(&self.bar, format!("error: {}: {e}", run.path)),
        }
        self.write(done, failed)?;
        Ok(())
    }
}

/// The domains of a candidate's shrink where they are not those of the gaps beside it.
fn shrink_note(c: &skelid::gap::search::Candidate) -> String {
    if c.against.is_some() {
        format!(
            " on {}, against the model refitted there without it",
            c.shrink_domains().join("/")
        )
    } else if c.shrink_on_fewer_domains() {
        format!(" on {}", c.shrink_domains().join("/"))
    } else {
        String::new()
    }
}

/// Prints the rig model's implausible values on stderr ("warning: FILE: `clearance` = …")
/// and returns them.
pub(crate) fn warn_model(path: &std::path::Path, model: &RigModel) -> Vec<String> {
    let w = model.warnings();
    for line in &w {
        eprintln!("warning: {}: {line}", path.display());
    }
    w
}

/// A line above the progress bar, or on stderr when the bar is hidden (not a terminal: a
/// log file of an overnight self-check still gets every case).
pub(crate) fn say(bar: &indicatif::ProgressBar, line: String) {
    if bar.is_hidden() {
        eprintln!("{line}");
    } else {
        bar.println(line);
    }
}

pub(crate) fn gap_self_check(
    a: &GapArgs,
    opt: &skelid::gap::SearchOptions,
    engine: &super::Engine,
) -> Result<ExitCode> {
    use skelid::gap::selfcheck;
    let sweep = match a.sweep {
        SweepArg::Paper => selfcheck::Sweep::Paper,
        SweepArg::TwoLevel => selfcheck::Sweep::TwoLevel,
        SweepArg::TwoRuns => selfcheck::Sweep::TwoRuns,
    };
    // `--kind force` (the archive option, which a self-check has no archive for) asks for
    // the force model's self-check.
    use skelid::run::RunKind;
    let rigs = match (a.ingest.kind, a.rigs) {
        (Some(RunKind::Force), RigsArg::Paper) => selfcheck::Rigs::Structure,
        (Some(RunKind::Force), RigsArg::Random) => {
            bail!("--kind force draws one mode of a structure; --rigs random is for the base-motion rig (nothing was done)")
        }
        (Some(RunKind::Free), _) => {
            bail!("--self-check --kind free: the free-decay model's self-check is not built yet; use --kind force or base-motion (nothing was done)")
        }
        (_, RigsArg::Paper) => selfcheck::Rigs::Paper,
        (_, RigsArg::Random) => selfcheck::Rigs::Random,
    };
    if let Some(names) = &a.detection_limits {
        let effects = parse_effects("--detection-limits", names)?;
        return detection_limits(a, opt, engine, &effects, rigs, sweep);
    }
    let cases = selfcheck::draw(a.cases, a.seed, selfcheck::Draw { rigs, only: None });
    let drive = if rigs == selfcheck::Rigs::Structure {
        String::new()
    } else {
        format!(" under {} with encoder noise", sweep.describe())
    };
    eprintln!(
        "self-check: {} cases (seed {}), {}{drive}, one effect (or none) hidden from a model whose parameters are ~{:.0} % off",
        cases.len(),
        a.seed,
        rigs.describe(),
        100.0 * selfcheck::NOMINAL_ERROR
    );
    let bar = indicatif::ProgressBar::new(cases.len() as u64).with_style(
        indicatif::ProgressStyle::with_template(
            "{bar:30} {pos}/{len} cases, {elapsed} elapsed, ~{eta} left",
        )
        .expect("a valid template"),
    );
    let mut outcomes = Vec::new();
    let mut errors = Vec::new();
    let mut lines = Vec::new();
    let identifier = engine.get();
    for c in &cases {
        match selfcheck::run_case(c, opt, sweep, identifier) {
            Ok(o) => {
                let line = format!(
                    "case {:>3}: {:<22} {:>10.4e} → {:<22} {}",
                    c.index,
                    o.truth(),
                    c.value,
                    o.verdict,
                    if o.right() { "right" } else { "WRONG" }
                );
                say(&bar, line);
                lines.push(selfcheck::CaseRecord::from(&o));
                outcomes.push(o);
            }
            Err(e) => {
                say(&bar, format!("case {:>3}: error: {e}", c.index));
                errors.push(format!("case {}: {e}", c.index));
            }
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    report_fallbacks(engine.backend());
    let summary = selfcheck::summarize(&outcomes, errors);
    println!("\n{summary}");
    let doc = selfcheck::Document {
        format: selfcheck::FORMAT,
        seed: a.seed,
        sweep: sweep.name(),
        rigs: rigs.name(),
        summary,
        cases: lines,
    };
    write_json(&a.out.join("self-check.json"), &doc)
}

/// `--self-check --detection-limits`: each effect's ladder, the table and
/// detection-limits.json.
fn detection_limits(
    a: &GapArgs,
    opt: &skelid::gap::SearchOptions,
    engine: &super::Engine,
    effects: &[skelid::model::EffectKind],
    rigs: skelid::gap::selfcheck::Rigs,
    sweep: skelid::gap::selfcheck::Sweep,
) -> Result<ExitCode> {
    use skelid::gap::detection;
    if a.cases == 0 {
        bail!("--cases must be at least 1 (with --detection-limits it is the cases per rung; 5 is a good start)");
    }
    eprintln!(
        "detection limits: {} effect(s), {} cases a rung (seed {}), {} under {}; an effect is detected where {:.0} % of a rung's cases name it",
        effects.len(),
        a.cases,
        a.seed,
        rigs.describe(),
        sweep.describe(),
        100.0 * detection::RATE
    );
    let bar = indicatif::ProgressBar::new_spinner().with_style(
        indicatif::ProgressStyle::with_template("{spinner} {msg} ({elapsed})")
            .expect("a valid template"),
    );
    let identifier = engine.get();
    let path = a.out.join("detection-limits.json");
    let mut limits = Vec::new();
    for &k in effects {
        let mut each =
            |rung: &detection::Rung,
             r: Result<&skelid::gap::selfcheck::Outcome, &skelid::gap::GapError>| {
                let what = match r {
                    Ok(o) => format!(
                        "{} ({})",
                        o.verdict,
                        if o.right() { "named" } else { "missed" }
                    ),
                    Err(e) => format!("error: {e}"),
                };
                say(
                    &bar,
                    format!(
                        "{:<22} {:>10.3e} {}: {what}",
                        k.name(),
                        rung.value,
                        k.unit()
                    ),
                );
                bar.set_message(format!(
                    "{}: {} named of {} at {:.3e}",
                    k.name(),
                    rung.named,
                    rung.cases,
                    rung.value
                ));
                bar.tick();
            };
        let plan = detection::Plan {
            per_rung: a.cases,
            seed: a.seed,
            rigs,
            sweep,
        };
        limits.push(detection::ladder(k, plan, opt, identifier, &mut each));
        // Rewritten after every effect: a long night's ladders stopped half-way keep every
        // effect finished so far.
        let doc = detection::Document {
            format: detection::FORMAT,
            seed: a.seed,
            sweep: sweep.name(),
            rigs: rigs.name(),
            cases_per_rung: a.cases,
            rate: detection::RATE,
            limits: limits.clone(),
        };
        skelid::report::write_atomic(&path, serde_json::to_string_pretty(&doc)?.as_bytes())?;
    }
    bar.finish_and_clear();
    report_fallbacks(engine.backend());
    println!("\n{}", detection::table(&limits));
    println!("wrote {}", path.display());
    Ok(ExitCode::SUCCESS)
}

/// Writes a self-check's document as pretty JSON (atomically) and says where.
fn write_json(path: &std::path::Path, doc: &impl serde::Serialize) -> Result<ExitCode> {
    skelid::report::write_atomic(path, serde_json::to_string_pretty(doc)?.as_bytes())?;
    println!("wrote {}", path.display());
    Ok(ExitCode::SUCCESS)
}
