//! `skelid gap --self-check --detection-limits`: for each effect, the smallest parameter the
//! diagnosis still names. The self-check's cases of one effect are run at a fixed size on a
//! ladder of factors of its demo value ([`effect_value`]): from 1 down by halves while at
//! least [`RATE`] of a rung's cases are named, or up by doublings until they are. The
//! limit is the smallest size of the unbroken run of named rungs.

use super::search::SearchOptions;
use super::selfcheck::{draw, run_case, Draw, Outcome, Rigs, Sweep};
use super::GapError;
use crate::identify::Identifier;
use crate::model::EffectKind;
use crate::rig::effect_value;

/// The share of a rung's cases that must be named for the effect to count as detected.
pub const RATE: f64 = 0.8;
/// The ladder's ends: factors of the demo value below and above which it stops.
pub const SMALLEST: f64 = 1.0 / 16.0;
/// See [`SMALLEST`].
pub const LARGEST: f64 = 8.0;

/// One rung: a size and how often the diagnosis named the effect there.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Rung {
    /// Factor of the demo value.
    pub factor: f64,
    /// The effect's parameter (its unit).
    pub value: f64,
    /// Cases whose verdict named the effect.
    pub named: usize,
    /// Cases diagnosed (cases that failed outright are left out and listed in `errors`).
    pub cases: usize,
    /// The verdicts, one per case.
    pub verdicts: Vec<String>,
    /// Cases that could not be diagnosed.
    pub errors: Vec<String>,
}

impl Rung {
    /// Whether at least [`RATE`] of its cases were named.
    pub fn detected(&self) -> bool {
        self.cases > 0 && self.named as f64 >= RATE * self.cases as f64
    }
}

/// One effect's ladder and the limit it found.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Limit {
    /// The effect's name.
    pub effect: &'static str,
    /// Its parameter's name and unit.
    pub param: &'static str,
    /// See `param`.
    pub unit: &'static str,
    /// The demo value (factor 1).
    pub demo_value: f64,
    /// The rungs in the order they were run.
    pub rungs: Vec<Rung>,
    /// The smallest parameter named in at least [`RATE`] of the cases, with every larger
    /// rung tried also named; `None` when not even [`LARGEST`] times the demo value was.
    pub limit: Option<f64>,
    /// Whether the ladder stopped at [`SMALLEST`] still detecting (the limit is lower).
    pub below_smallest: bool,
}

/// How a ladder's cases are drawn and run.
#[derive(Debug, Clone, Copy)]
pub struct Plan {
    /// Cases a rung.
    pub per_rung: usize,
    /// The seed every rung's own seed derives from.
    pub seed: u64,
    /// The rigs.
    pub rigs: Rigs,
    /// Their drive.
    pub sweep: Sweep,
}

/// Runs `effect`'s ladder as `plan` says; `each` sees every case as it is done.
pub fn ladder(
    effect: EffectKind,
    plan: Plan,
    opt: &SearchOptions,
    identifier: Identifier<'_>,
    each: &mut dyn FnMut(&Rung, Result<&Outcome, &GapError>),
) -> Limit {
    let Plan {
        per_rung,
        seed,
        rigs,
        sweep,
    } = plan;
    let mut run_rung = |factor: f64| -> Rung {
        // Each rung has its own seed: its cases are independent of the other rungs'.
        let rung_seed = seed
            .wrapping_mul(1_000_003)
            .wrapping_add((effect as u64) << 8)
            .wrapping_add(factor.log2().round() as i64 as u64);
        let cases = draw(
            per_rung,
            rung_seed,
            Draw {
                rigs,
                only: Some((effect, factor)),
            },
        );
        let mut rung = Rung {
            factor,
            value: effect_value(effect) * factor,
            named: 0,
            cases: 0,
            verdicts: Vec::new(),
            errors: Vec::new(),
        };
        for c in &cases {
            let r = run_case(c, opt, sweep, identifier);
            match &r {
                Ok(o) => {
                    rung.cases += 1;
                    rung.named += usize::from(o.right());
                    rung.verdicts.push(o.verdict.clone());
                }
                Err(e) => rung.errors.push(format!("case {}: {e}", c.index)),
            }
            each(&rung, r.as_ref());
        }
        rung
    };
    let rungs = climb(&mut run_rung);
    let (limit, below_smallest) = limit_of(&rungs);
    Limit {
        effect: effect.name(),
        param: effect.param(),
        unit: effect.unit(),
        demo_value: effect_value(effect),
        rungs,
        limit,
        below_smallest,
    }
}

/// The ladder's steps, each rung run by `run_rung(factor)`: from 1 down by halves while
/// detected (to [`SMALLEST`]), or up by doublings until detected (to [`LARGEST`]). The
/// rungs in the order they were run.
fn climb(run_rung: &mut dyn FnMut(f64) -> Rung) -> Vec<Rung> {
    let mut rungs = vec![run_rung(1.0)];
    let down = rungs[0].detected();
    let mut factor = if down { 0.5 } else { 2.0 };
    while (SMALLEST..=LARGEST).contains(&factor) {
        let r = run_rung(factor);
        let stop = r.detected() != down;
        rungs.push(r);
        if stop {
            break;
        }
        factor *= if down { 0.5 } else { 2.0 };
    }
    rungs
}

/// The limit a ladder's rungs give: the smallest value detected (the last rung of the
/// unbroken detected run, since the ladder stops at the first change), and whether the
/// ladder ended at [`SMALLEST`] still detecting (the limit is lower still).
fn limit_of(rungs: &[Rung]) -> (Option<f64>, bool) {
    let limit = rungs
        .iter()
        .filter(|r| r.detected())
        .map(|r| r.value)
        .min_by(f64::total_cmp);
    let below = rungs
        .last()
        .is_some_and(|r| r.detected() && r.factor <= SMALLEST);
    (limit, below)
}

/// The format name of detection-limits.json (README, "Detection limits").
pub const FORMAT: &str = "skelid-detection-limits/1";

/// detection-limits.json: what was run and every effect's ladder.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Document {
    /// [`FORMAT`].
    pub format: &'static str,
    /// The seed.
    pub seed: u64,
    /// The drive's name.
    pub sweep: &'static str,
    /// The rigs' name.
    pub rigs: &'static str,
    /// Cases per rung.
    pub cases_per_rung: usize,
    /// [`RATE`].
    pub rate: f64,
    /// One ladder per effect.
    pub limits: Vec<Limit>,
}

/// The table the README quotes: per effect, each rung's score and the limit.
pub fn table(limits: &[Limit]) -> String {
    let mut t = format!(
        "{:<22} {:>12}  {:<44} {}\n",
        "effect", "demo value", "named per rung (factor of the demo value)", "detection limit"
    );
    for l in limits {
        let mut rungs: Vec<&Rung> = l.rungs.iter().collect();
        rungs.sort_by(|a, b| b.factor.total_cmp(&a.factor));
        let steps = rungs
            .iter()
            .map(|r| format!("{}: {}/{}", factor_label(r.factor), r.named, r.cases))
            .collect::<Vec<_>>()
            .join(", ");
        let limit = match (l.limit, l.below_smallest) {
            (Some(v), false) => format!("{v:.3e} {}", l.unit),
            (Some(v), true) => format!("< {v:.3e} {}", l.unit),
            (None, _) => format!("> {:.3e} {}", l.demo_value * LARGEST, l.unit),
        };
        t.push_str(&format!(
            "{:<22} {:>12.3e}  {:<44} {}\n",
            l.effect, l.demo_value, steps, limit
        ));
    }
    t
}

/// `1`, `1/2`, `4`: a ladder factor as people write it.
fn factor_label(f: f64) -> String {
    if f >= 1.0 {
        format!("{f:.0}")
    } else {
        format!("1/{:.0}", 1.0 / f)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rung(factor: f64, named: usize, cases: usize) -> Rung {
        Rung {
            factor,
            value: factor,
            named,
            cases,
            verdicts: vec![],
            errors: vec![],
        }
    }

    #[test]
    fn a_rung_is_detected_at_four_of_five_not_three() {
        assert!(rung(1.0, 4, 5).detected());
        assert!(!rung(1.0, 3, 5).detected());
        assert!(!rung(1.0, 0, 0).detected());
    }

    #[test]
    fn the_table_sorts_rungs_and_marks_open_limits() {
        let l = Limit {
            effect: "sensor_delay",
            param: "delay",
            unit: "s",
            demo_value: 0.005,
            rungs: vec![rung(1.0, 5, 5), rung(0.5, 5, 5), rung(0.25, 2, 5)],
            limit: Some(0.0025),
            below_smallest: false,
        };
        let t = table(&[l]);
        assert!(t.contains("1: 5/5, 1/2: 5/5, 1/4: 2/5"), "{t}");
        assert!(t.contains("2.500e-3 s"), "{t}");
        let none = Limit {
            limit: None,
            ..table_limit()
        };
        assert!(table(&[none]).contains("> 4.000e-2 s"));
    }

    /// The ladder against a detector that names the effect from `threshold` times its demo
    /// value up.
    fn ladder_at(threshold: f64) -> (Vec<f64>, Option<f64>, bool) {
        let rungs = climb(&mut |f| {
            let named = if f >= threshold { 5 } else { 2 };
            rung(f, named, 5)
        });
        let (limit, below) = limit_of(&rungs);
        (rungs.iter().map(|r| r.factor).collect(), limit, below)
    }

    #[test]
    fn the_ladder_walks_down_while_named_and_up_until_named() {
        assert_eq!(
            ladder_at(0.3),
            (vec![1.0, 0.5, 0.25], Some(0.5), false),
            "down by halves, the limit the last named rung"
        );
        let (f, limit, below) = ladder_at(0.0);
        assert_eq!(f, vec![1.0, 0.5, 0.25, 0.125, 0.0625]);
        assert_eq!(
            (limit, below),
            (Some(0.0625), true),
            "named down to the end"
        );
        assert_eq!(ladder_at(3.0), (vec![1.0, 2.0, 4.0], Some(4.0), false));
        assert_eq!(ladder_at(100.0), (vec![1.0, 2.0, 4.0, 8.0], None, false));
    }

    fn table_limit() -> Limit {
        Limit {
            effect: "sensor_delay",
            param: "delay",
            unit: "s",
            demo_value: 0.005,
            rungs: vec![rung(1.0, 0, 5)],
            limit: None,
            below_smallest: false,
        }
    }
}
