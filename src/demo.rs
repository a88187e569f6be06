//! The built-in demo campaign: the paper's rig under its chirp, plus one variant per effect
//! of the vocabulary, a linear joint, a force-input oscillator and a free decay. Every run
//! carries its true parameters as attributes (`true_*`, and the whole model as TOML in
//! `true_model`), so identification can be scored against them. The drives, the effects'
//! magnitudes and the simulation of a case are the rig's ([`crate::rig`]).

use crate::model::{EffectKind, RigModel};
use crate::rig::{effect_value, paper_chirp, RigCase};
use crate::simulate::{Drive, Excitation};

/// The demo campaign's cases.
pub fn cases() -> Vec<RigCase> {
    let mut out = Vec::new();
    let mut paper = RigModel::paper();
    paper.effects.set(EffectKind::CoulombFriction, Some(2.5));
    out.push(RigCase {
        path: "/demo/paper_rig".into(),
        model: paper,
        drive: Drive::Base(paper_chirp()),
        seed: 11,
        description:
            "paper's rig: 1.5 deg clearance, 11 Hz contact mode, viscous + Coulomb damping".into(),
    });
    for (i, kind) in EffectKind::ALL.into_iter().enumerate() {
        let mut m = RigModel::paper();
        m.effects.set(kind, Some(effect_value(kind)));
        out.push(RigCase {
            path: format!("/demo/effects/{}", kind.name()),
            model: m,
            drive: Drive::Base(paper_chirp()),
            seed: 100 + i as u64,
            description: format!("nominal rig plus {} only", kind.name()),
        });
    }
    let mut linear = RigModel::paper();
    linear.clearance = 0.0;
    out.push(RigCase {
        path: "/demo/linear".into(),
        model: linear,
        drive: Drive::Base(paper_chirp()),
        seed: 21,
        description: "linear joint (no clearance)".into(),
    });
    out.push(RigCase {
        path: "/demo/force_oscillator".into(),
        model: RigModel {
            kind: crate::model::ModelKind::BaseMotion,
            band: None,
            inertia: 2.0,
            stiffness: 2.0 * (std::f64::consts::TAU * 5.0).powi(2),
            damping: 2.0 * 0.02 * 2.0 * std::f64::consts::TAU * 5.0,
            clearance: 0.0,
            gravity_stiffness: 0.0,
            effects: Default::default(),
        },
        drive: Drive::Force(Excitation::Chirp {
            f0: 1.0,
            f1: 10.0,
            duration: 30.0,
            amplitude: 10.0,
            rolloff: None,
        }),
        seed: 31,
        description: "force-input linear oscillator, 5 Hz, 2 % damping, sine sweep 1-10 Hz".into(),
    });
    out.push(RigCase {
        path: "/demo/free_decay".into(),
        model: RigModel::paper(),
        drive: Drive::Free {
            initial_offset: 0.08,
        },
        seed: 41,
        description: "free decay from 0.08 rad with the paper's clearance".into(),
    });
    out
}
