//! `skelid validate`: the identification's error table on random paper-like rigs
//! ([`skelid::validate`]), printed and written to `DIR/validate.json`.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{bail, Context, Result};
use clap::Args;

use skelid::validate::{rigs, run_rig, table};

/// Arguments of `skelid validate`.
#[derive(Args)]
pub struct ValidateArgs {
    /// Random rigs to draw (issue 20's ranges; the effects dry friction, sensor delay,
    /// contact damping and none in turn).
    #[arg(long, default_value_t = 40, value_name = "N")]
    rigs: usize,
    /// Seed of the draw (the same seed gives the same rigs and noise).
    #[arg(long, default_value_t = 20)]
    seed: u64,
    /// Simulations per half of each refinement (`skelid run --refine-evaluations`).
    #[arg(long, default_value_t = skelid::refine::EVALUATIONS, value_name = "N")]
    evaluations: usize,
    /// Folder for validate.json.
    #[arg(long, default_value = "validate-out", value_name = "DIR")]
    out: PathBuf,
}

/// Runs the validation; exit status 1 when a rig could not be identified at all.
pub fn run(a: ValidateArgs) -> Result<ExitCode> {
    if a.rigs == 0 {
        bail!("--rigs 0: draw at least one rig");
    }
    if a.evaluations < 10 {
        bail!(
            "--evaluations {}: a simplex over six parameters needs at least 10",
            a.evaluations
        );
    }
    std::fs::create_dir_all(&a.out)
        .with_context(|| format!("cannot create the output folder {}", a.out.display()))?;
    let drawn = rigs(a.rigs, a.seed);
    eprintln!(
        "validate: {} random rigs (seed {}): 30 s of the paper's chirp at 1 kHz, encoders of 17-20 bit/rev with offsets and noise, identified blind by the skeleton (wavelet, Hilbert) and refined by simulation ({} simulations per half)",
        drawn.len(),
        a.seed,
        a.evaluations
    );
    let bar = indicatif::ProgressBar::new(drawn.len() as u64).with_style(
        indicatif::ProgressStyle::with_template(
            "{bar:30} {pos}/{len} rigs, {elapsed} elapsed, ~{eta} left",
        )
        .expect("a valid template"),
    );
    let pct = |e: Option<(f64, f64)>| {
        e.map_or("   -   /   -   ".to_string(), |(c, k)| {
            format!("{:+6.2}% / {:+6.2}%", 100.0 * c, 100.0 * k)
        })
    };
    let mut outcomes = Vec::new();
    let mut lines = Vec::new();
    // Blind identification as `skelid run` does it by default, on the CPU.
    let engine = super::Engine::cpu(skelid::identify::IdentifyOptions::default());
    let identifier = engine.get();
    for rig in &drawn {
        let o = run_rig(rig, a.evaluations, identifier);
        let line = format!(
            "rig {:>3} {:<18} {:>2} bit  clearance / k/J error: wavelet {}  hilbert {}  refined {}{}",
            rig.index,
            rig.effect.map_or("none", |e| e.name()),
            rig.bits,
            pct(o.wavelet),
            pct(o.hilbert),
            pct(o.refined),
            o.refinement
                .as_ref()
                .err()
                .map_or(String::new(), |e| format!(" ({e})"))
        );
        if bar.is_hidden() {
            eprintln!("{line}");
        } else {
            bar.println(line);
        }
        let err = |e: Option<(f64, f64)>| {
            e.map(|(c, k)| serde_json::json!({"clearance": c, "stiffness": k}))
        };
        lines.push(serde_json::json!({
            "rig": rig.index,
            "effect": rig.effect.map_or("none", |e| e.name()),
            "truth": rig.truth.to_toml(),
            "bits": rig.bits,
            "amplitude": rig.amplitude,
            "offsets": [rig.chain.offsets.0, rig.chain.offsets.1],
            "noise": rig.chain.noise,
            "gravity_attribute": rig.chain.gravity_attribute,
            "errors": {"wavelet": err(o.wavelet), "hilbert": err(o.hilbert), "refined": err(o.refined)},
            "refined_gap": o.refinement.as_ref().ok().map(|r| r.gap_holdout),
            "refined_seconds": o.refinement.as_ref().ok().map(|r| r.seconds),
            "refine_error": o.refinement.as_ref().err(),
        }));
        outcomes.push(o);
        bar.inc(1);
    }
    bar.finish_and_clear();
    let text = table(&outcomes);
    println!("\nrelative errors against the truth (|error|: median / 90th percentile):\n\n{text}");
    let path = a.out.join("validate.json");
    let doc = serde_json::json!({
        "format": "skelid-validate/1",
        "seed": a.seed,
        "evaluations": a.evaluations,
        "table": text,
        "rigs": lines,
    });
    skelid::report::write_atomic(&path, serde_json::to_string_pretty(&doc)?.as_bytes())?;
    println!("wrote {}", path.display());
    let none = outcomes
        .iter()
        .any(|o| o.wavelet.is_none() && o.hilbert.is_none() && o.refined.is_none());
    Ok(if none {
        ExitCode::from(1)
    } else {
        ExitCode::SUCCESS
    })
}
