//! The rig model of FORMATS.md §2 (TOML): a single-DOF base-motion link with a dead-zone
//! joint (the default), or one mode of a structure driven by a measured force
//! (`kind = "force"`), and the vocabulary of effects beyond the nominal model.

use std::fmt;
use std::path::Path;

use serde::{Deserialize, Serialize};

/// Errors reading or checking a rig model.
#[derive(Debug, thiserror::Error)]
pub enum ModelError {
    /// File could not be read.
    // The cause is in the message and not a `source`: anyhow's `{:#}` printed both ("No
    // such file or directory" twice), and Python's message is this text alone.
    #[error("{file}: cannot read the rig model: {cause}")]
    Io { file: String, cause: std::io::Error },
    /// TOML syntax or an unknown/missing key.
    #[error("{file}: invalid rig model: {detail}")]
    Parse { file: String, detail: String },
    /// A value out of its physical range.
    #[error("{file}: invalid rig model: {detail}")]
    Invalid { file: String, detail: String },
}

/// J θ'' + c(θ'−φ') + k·D(θ−φ) − J·C·θ = 0 with D a dead zone of half-width clearance/2;
/// for `kind = "force"`, m y'' + c y' + k·D(y) = f with f the measured force.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RigModel {
    /// What drives it: the base motion (the default) or a measured force on one mode.
    #[serde(default, skip_serializing_if = "ModelKind::is_base_motion")]
    pub kind: ModelKind,
    /// The band the mode lives in (`[fmin, fmax]`, Hz): a force model is driven by the
    /// measured force band-passed to it, and the measurement and every simulation are
    /// identified in it. `None`: the band the measured run's own mode isolation chooses.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub band: Option<[f64; 2]>,
    /// J, kg m² (or the modal mass m, kg, of a force model; `mass` is read as this key).
    #[serde(alias = "mass")]
    pub inertia: f64,
    /// k, N m/rad: contact stiffness outside the clearance.
    pub stiffness: f64,
    /// c, N m s/rad: viscous damping on the relative velocity.
    pub damping: f64,
    /// Total free play 2δ, rad (0 = linear joint).
    #[serde(default)]
    pub clearance: f64,
    /// C = mgL/J, 1/s².
    #[serde(default)]
    pub gravity_stiffness: f64,
    /// Effects beyond the nominal model.
    #[serde(default, skip_serializing_if = "Effects::is_empty")]
    pub effects: Effects,
}

/// Parameter tables of the effect vocabulary; keys are part of the format contract.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Effects {
    /// Dry friction on the relative velocity (stick–slip).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub coulomb_friction: Option<TorqueParam>,
    /// Constant torque pressing the link onto one flank.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gravity_preload: Option<TorqueParam>,
    /// Clearance centre shifted from z = 0.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub asymmetric_clearance: Option<OffsetParam>,
    /// Contact law k·D + k3·D³.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cubic_stiffness: Option<CubicParam>,
    /// Extra damping while in contact.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub contact_damping: Option<ContactDampingParam>,
    /// Output encoder lag.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sensor_delay: Option<DelayParam>,
    /// Encoder resolution of both channels.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub quantization: Option<StepParam>,
    /// A bolted joint's microslip: an Iwan element (Jenkins elements in parallel).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub microslip: Option<MicroslipParam>,
}

/// What drives a model (FORMATS.md §2, `kind`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ModelKind {
    /// The paper's link on a moving base: driven by the measured base motion.
    #[default]
    BaseMotion,
    /// One mode of a structure: driven by the measured force.
    Force,
    /// One mode of a structure ringing down after an impact: started from the record's
    /// own state (displacement and velocity of the mode) where its envelope peaks, once
    /// the band-pass has let go of the impact.
    Free,
}

impl ModelKind {
    /// Whether it is the default kind (left out of the TOML written).
    pub fn is_base_motion(&self) -> bool {
        *self == ModelKind::BaseMotion
    }

    /// Name in TOML and JSON.
    pub fn name(self) -> &'static str {
        match self {
            ModelKind::BaseMotion => "base_motion",
            ModelKind::Force => "force",
            ModelKind::Free => "free",
        }
    }

    /// The effects that make sense for this kind (the search's default vocabulary): the
    /// rig's seven, or, for one mode driven by a force, those of a joint in a structure
    /// (no preload and no offset clearance: a band-passed force carries no static load).
    pub fn vocabulary(self) -> &'static [EffectKind] {
        match self {
            ModelKind::BaseMotion => &EffectKind::ALL,
            ModelKind::Force | ModelKind::Free => &EffectKind::FORCE,
        }
    }
}

/// `{ slip_force = N m, joint_stiffness = N m/rad, spread = 1 }`: an Iwan element of
/// [`IWAN_ELEMENTS`] Jenkins elements (a spring in series with a slider) in parallel,
/// with slip displacements spread evenly about their mean u = slip_force/joint_stiffness,
/// over ((1 − spread)·u, (1 + spread)·u]. Stuck, it is a spring of
/// `joint_stiffness`, which is part of the model's `stiffness` (the stiffness at small
/// amplitude); as the amplitude grows its elements slip one after another (softening and
/// hysteretic damping growing with amplitude, the microslip of a bolted interface) until
/// it slides as a whole at `slip_force` (macroslip: the stiffness has fallen to
/// `stiffness − joint_stiffness`). Optional, `fine_stiffness` and `fine_slip`: a second,
/// fine population beside it (then macroslip leaves `stiffness − joint_stiffness −
/// fine_stiffness`, and the joint slides at `slip_force` plus the fine population's
/// fine_stiffness·fine_slip·(m + 1)/(2m), m = [`FINE_ELEMENTS`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MicroslipParam {
    /// The joint's force when it slides as a whole, N m (N).
    pub slip_force: f64,
    /// The joint's stiffness while stuck, N m/rad (N/m); at most the model's `stiffness`.
    pub joint_stiffness: f64,
    /// How widely the elements' slip displacements spread about their mean, in (0, 1]
    /// (1: optional, the default). At 1 the first elements slip at the smallest amplitude
    /// (Iwan's uniform density: loss and softening grow from zero); near 0 they all slip
    /// together at u (one Jenkins element: no loss below u, then a sudden onset, as a
    /// bolted interface that holds until its preload gives).
    #[serde(default = "full_spread", skip_serializing_if = "is_full_spread")]
    pub spread: f64,
    /// The stiffness of a second, fine population of the joint, N m/rad (N/m; 0:
    /// optional, the default, none): [`FINE_ELEMENTS`] Jenkins elements whose slip
    /// displacements lie at `fine_slip`·i/m (i = 1..m: evenly over (0, `fine_slip`]), part
    /// of the model's `stiffness` like `joint_stiffness`. The small asperities of an
    /// interface: loss that rises from zero amplitude and saturates at `fine_slip`, beside
    /// a joint that holds until a sharp onset (below the onset or beyond it, as fitted).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub fine_stiffness: f64,
    /// The fine population's largest slip displacement, rad (m): every one of its elements
    /// slides beyond it (with `fine_stiffness`; 0 without a fine population).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub fine_slip: f64,
}

fn is_zero(v: &f64) -> bool {
    *v == 0.0
}

impl MicroslipParam {
    /// Whether the joint has a fine population.
    pub fn has_fine(&self) -> bool {
        self.fine_stiffness > 0.0 && self.fine_slip > 0.0
    }
}

fn full_spread() -> f64 {
    1.0
}

fn is_full_spread(v: &f64) -> bool {
    *v == 1.0
}

/// Jenkins elements of a [`MicroslipParam`]'s Iwan element.
pub const IWAN_ELEMENTS: usize = 16;

/// Jenkins elements of a [`MicroslipParam`]'s fine population.
pub const FINE_ELEMENTS: usize = 8;

/// The slip displacements of an Iwan element's [`IWAN_ELEMENTS`] Jenkins elements: spread
/// evenly over ((1 − spread)·u, (1 + spread)·u] about their mean `u` = slip force / joint
/// stiffness, so that their slip forces sum to the joint's (the simulator's elements, and
/// the describing function the search reads a joint off the skeleton with).
pub fn iwan_slips(u: f64, spread: f64) -> impl Iterator<Item = f64> {
    let n = IWAN_ELEMENTS;
    let w = spread.clamp(1e-6, 1.0);
    (0..n).map(move |i| u * (1.0 - w + w * (2 * i + 1) as f64 / n as f64))
}

/// The joint stiffness a microslip effect starts with when it is added to a model without
/// one, as a share of the model's stiffness.
pub const JOINT_SHARE: f64 = 0.1;

/// `{ torque = N m }`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TorqueParam {
    /// N m.
    pub torque: f64,
}
/// `{ offset = rad }`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OffsetParam {
    /// rad.
    pub offset: f64,
}
/// `{ k3 = N m/rad³, limit = rad }`: the contact law k·D + k3·D³, optionally with the
/// cubic term's stiffness saturating beyond a deflection.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CubicParam {
    /// N m/rad³.
    pub k3: f64,
    /// Where the cubic term stops stiffening or softening, rad (m; 0: optional, the
    /// default, nowhere): beyond |D| = `limit` its force goes on along its tangent,
    /// k3·(3·limit²·D − 2·limit³·sgn D), so its stiffness stays at 3·k3·limit². An
    /// elastic softening that saturates, as a bolted joint's once its slip has finished.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub limit: f64,
}

impl CubicParam {
    /// The cubic term's force at the deflection `d` (with its limit, if any).
    #[inline]
    pub fn force(&self, d: f64) -> f64 {
        let l = self.limit;
        if l > 0.0 && d.abs() > l {
            self.k3 * (3.0 * l * l * d - 2.0 * l * l * l * d.signum())
        } else {
            self.k3 * d * d * d
        }
    }

    /// The cubic term's potential energy at the deflection `d` (the integral of
    /// [`force`](Self::force) from 0).
    pub fn energy(&self, d: f64) -> f64 {
        let (l, a) = (self.limit, d.abs());
        if l > 0.0 && a > l {
            self.k3 * (0.25 * l.powi(4) + 1.5 * l * l * (a * a - l * l) - 2.0 * l.powi(3) * (a - l))
        } else {
            0.25 * self.k3 * d.powi(4)
        }
    }

    /// The smallest deflection d > 0 where a spring of stiffness `k` and this term push
    /// back no more (k·d + force(d) = 0): where a softening term lets the motion run
    /// away. `None` where the force never vanishes (a stiffening term, or a limit reached
    /// while the tangent stiffness k + 3·k3·limit² is still positive).
    pub fn vanishes_at(&self, k: f64) -> Option<f64> {
        if self.k3 >= 0.0 || k <= 0.0 {
            return None;
        }
        let free = (k / -self.k3).sqrt();
        let l = self.limit;
        if l <= 0.0 || free <= l {
            return Some(free);
        }
        // Beyond the limit: (k + 3·k3·l²)·d − 2·k3·l³ = 0.
        let tangent = k + 3.0 * self.k3 * l * l;
        (tangent < 0.0).then(|| 2.0 * self.k3 * l.powi(3) / tangent)
    }
}
/// `{ c_contact = N m s/rad }`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ContactDampingParam {
    /// N m s/rad.
    pub c_contact: f64,
}
/// `{ delay = s }`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DelayParam {
    /// s.
    pub delay: f64,
}
/// `{ step = rad }`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StepParam {
    /// rad.
    pub step: f64,
}

/// One effect of the vocabulary, each with exactly one parameter.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum EffectKind {
    /// Dry friction, parameter `torque`.
    CoulombFriction,
    /// Constant torque, parameter `torque`.
    GravityPreload,
    /// Clearance centre offset, parameter `offset`.
    AsymmetricClearance,
    /// Cubic contact stiffness, parameter `k3`.
    CubicStiffness,
    /// Damping in contact, parameter `c_contact`.
    ContactDamping,
    /// Output lag, parameter `delay`.
    SensorDelay,
    /// Encoder step, parameter `step`.
    Quantization,
    /// Iwan-element microslip, parameters `slip_force` and `joint_stiffness`.
    Microslip,
}

impl EffectKind {
    /// Every effect of the vocabulary, in the order of FORMATS.md.
    pub const EVERY: [EffectKind; 8] = [
        EffectKind::CoulombFriction,
        EffectKind::GravityPreload,
        EffectKind::AsymmetricClearance,
        EffectKind::CubicStiffness,
        EffectKind::ContactDamping,
        EffectKind::SensorDelay,
        EffectKind::Quantization,
        EffectKind::Microslip,
    ];

    /// The effects of a force model's search ([`ModelKind::vocabulary`]).
    pub const FORCE: [EffectKind; 6] = [
        EffectKind::CoulombFriction,
        EffectKind::CubicStiffness,
        EffectKind::ContactDamping,
        EffectKind::SensorDelay,
        EffectKind::Quantization,
        EffectKind::Microslip,
    ];

    /// The base-motion rig's effects, in the order of FORMATS.md (the search's default for
    /// the rig).
    pub const ALL: [EffectKind; 7] = [
        EffectKind::CoulombFriction,
        EffectKind::GravityPreload,
        EffectKind::AsymmetricClearance,
        EffectKind::CubicStiffness,
        EffectKind::ContactDamping,
        EffectKind::SensorDelay,
        EffectKind::Quantization,
    ];

    /// Whether it changes the waveform within a cycle of the relative motion (the gap's
    /// waveform domain): every effect of the joint and the delay between the encoders do;
    /// the encoders' resolution only adds a noise floor.
    pub fn shapes_waveform(self) -> bool {
        self != EffectKind::Quantization
    }

    /// Whether, in a model of `kind`, it acts on the gap's time domain alone. A force or
    /// free model's record is an accelerometer's (or a velocity pickup's): its converter
    /// step is a floor under the recorded envelope where the response is small (the time
    /// domain's resolution term), while the backbone and the damping are read where the
    /// mode rings, many steps up, and there the step's error is a noise the
    /// accelerometer's own already exceeds. Scored on all three, a step that explains the
    /// whole time-domain gap was drowned by the damping domain's noise (force self-check:
    /// shrink 7 %, never named).
    pub fn acts_on_time_alone(self, kind: ModelKind) -> bool {
        self == EffectKind::Quantization && kind != ModelKind::BaseMotion
    }

    /// Name in TOML and JSON.
    pub fn name(self) -> &'static str {
        match self {
            EffectKind::CoulombFriction => "coulomb_friction",
            EffectKind::GravityPreload => "gravity_preload",
            EffectKind::AsymmetricClearance => "asymmetric_clearance",
            EffectKind::CubicStiffness => "cubic_stiffness",
            EffectKind::ContactDamping => "contact_damping",
            EffectKind::SensorDelay => "sensor_delay",
            EffectKind::Quantization => "quantization",
            EffectKind::Microslip => "microslip",
        }
    }

    /// Name of its (first) parameter, the one the scan sweeps.
    pub fn param(self) -> &'static str {
        match self {
            EffectKind::CoulombFriction | EffectKind::GravityPreload => "torque",
            EffectKind::AsymmetricClearance => "offset",
            EffectKind::CubicStiffness => "k3",
            EffectKind::ContactDamping => "c_contact",
            EffectKind::SensorDelay => "delay",
            EffectKind::Quantization => "step",
            EffectKind::Microslip => "slip_force",
        }
    }

    /// Unit of its parameter.
    pub fn unit(self) -> &'static str {
        match self {
            EffectKind::CoulombFriction | EffectKind::GravityPreload | EffectKind::Microslip => {
                "N m"
            }
            EffectKind::AsymmetricClearance | EffectKind::Quantization => "rad",
            EffectKind::CubicStiffness => "N m/rad^3",
            EffectKind::ContactDamping => "N m s/rad",
            EffectKind::SensorDelay => "s",
        }
    }

    /// Parses a vocabulary name.
    pub fn parse(name: &str) -> Option<EffectKind> {
        EffectKind::EVERY.into_iter().find(|k| k.name() == name)
    }
}

impl fmt::Display for EffectKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl Effects {
    /// True when no effect is set.
    pub fn is_empty(&self) -> bool {
        EffectKind::EVERY.iter().all(|&k| self.get(k).is_none())
    }

    /// The parameter of an effect, if present.
    pub fn get(&self, kind: EffectKind) -> Option<f64> {
        match kind {
            EffectKind::CoulombFriction => self.coulomb_friction.map(|p| p.torque),
            EffectKind::GravityPreload => self.gravity_preload.map(|p| p.torque),
            EffectKind::AsymmetricClearance => self.asymmetric_clearance.map(|p| p.offset),
            EffectKind::CubicStiffness => self.cubic_stiffness.map(|p| p.k3),
            EffectKind::ContactDamping => self.contact_damping.map(|p| p.c_contact),
            EffectKind::SensorDelay => self.sensor_delay.map(|p| p.delay),
            EffectKind::Quantization => self.quantization.map(|p| p.step),
            EffectKind::Microslip => self.microslip.map(|p| p.slip_force),
        }
    }

    /// Sets (or with `None` removes) an effect.
    pub fn set(&mut self, kind: EffectKind, value: Option<f64>) {
        match kind {
            EffectKind::CoulombFriction => {
                self.coulomb_friction = value.map(|torque| TorqueParam { torque })
            }
            EffectKind::GravityPreload => {
                self.gravity_preload = value.map(|torque| TorqueParam { torque })
            }
            EffectKind::AsymmetricClearance => {
                self.asymmetric_clearance = value.map(|offset| OffsetParam { offset })
            }
            // The limit is kept, as the microslip keeps its joint.
            EffectKind::CubicStiffness => {
                let limit = self.cubic_stiffness.map_or(0.0, |p| p.limit);
                self.cubic_stiffness = value.map(|k3| CubicParam { k3, limit })
            }
            EffectKind::ContactDamping => {
                self.contact_damping = value.map(|c_contact| ContactDampingParam { c_contact })
            }
            EffectKind::SensorDelay => self.sensor_delay = value.map(|delay| DelayParam { delay }),
            EffectKind::Quantization => self.quantization = value.map(|step| StepParam { step }),
            // The joint stiffness is kept; a microslip set where there was none has none
            // until `RigModel::set_effect` (or `set_joint_stiffness`) gives it one.
            EffectKind::Microslip => {
                let kept = self.microslip.unwrap_or(MicroslipParam {
                    slip_force: 0.0,
                    joint_stiffness: 0.0,
                    spread: 1.0,
                    fine_stiffness: 0.0,
                    fine_slip: 0.0,
                });
                self.microslip = value.map(|slip_force| MicroslipParam { slip_force, ..kept })
            }
        }
    }

    /// The microslip's joint stiffness, if there is a microslip.
    pub fn joint_stiffness(&self) -> Option<f64> {
        self.microslip.map(|p| p.joint_stiffness)
    }

    /// Sets the microslip's joint stiffness (nothing without a microslip).
    pub fn set_joint_stiffness(&mut self, value: f64) {
        if let Some(p) = &mut self.microslip {
            p.joint_stiffness = value;
        }
    }

    /// Sets the microslip's spread (nothing without a microslip).
    pub fn set_spread(&mut self, value: f64) {
        if let Some(p) = &mut self.microslip {
            p.spread = value;
        }
    }

    /// The cubic term's limit, where there is a cubic term with one (> 0).
    pub fn cubic_limit(&self) -> Option<f64> {
        self.cubic_stiffness.map(|p| p.limit).filter(|&l| l > 0.0)
    }

    /// Sets the cubic term's limit (nothing without a cubic term; 0 removes it).
    pub fn set_cubic_limit(&mut self, value: f64) {
        if let Some(p) = &mut self.cubic_stiffness {
            p.limit = value;
        }
    }

    /// Sets the microslip's fine population, stiffness and largest slip (nothing without a
    /// microslip; zeros remove it).
    pub fn set_fine(&mut self, stiffness: f64, slip: f64) {
        if let Some(p) = &mut self.microslip {
            p.fine_stiffness = stiffness;
            p.fine_slip = slip;
        }
    }

    /// The effects present, with their parameters.
    pub fn present(&self) -> Vec<(EffectKind, f64)> {
        EffectKind::EVERY
            .into_iter()
            .filter_map(|k| self.get(k).map(|v| (k, v)))
            .collect()
    }
}

impl RigModel {
    /// The paper's rig: J = 3.16 kg m², 1.5° total clearance, contact natural frequency ≈ 11 Hz.
    pub fn paper() -> Self {
        RigModel {
            kind: ModelKind::BaseMotion,
            band: None,
            inertia: 3.16,
            stiffness: 15_000.0,
            damping: 13.0,
            clearance: 0.0262,
            gravity_stiffness: 0.0,
            effects: Effects::default(),
        }
    }

    /// Sets (or with `None` removes) an effect as [`Effects::set`] does; a microslip added
    /// where there was none gets a joint stiffness of [`JOINT_SHARE`] of the stiffness.
    pub fn set_effect(&mut self, kind: EffectKind, value: Option<f64>) {
        let had = self.effects.joint_stiffness().is_some_and(|k| k > 0.0);
        self.effects.set(kind, value);
        if kind == EffectKind::Microslip && !had {
            self.effects
                .set_joint_stiffness(JOINT_SHARE * self.stiffness);
        }
    }

    /// The effects a search of this model tries by default: its kind's vocabulary
    /// ([`ModelKind::vocabulary`]), without contact damping where a force model has no
    /// clearance (there it is in contact all the time: viscous damping by another name).
    pub fn vocabulary(&self) -> Vec<EffectKind> {
        self.kind
            .vocabulary()
            .iter()
            .copied()
            .filter(|&k| {
                !(self.kind != ModelKind::BaseMotion
                    && self.clearance <= 0.0
                    && k == EffectKind::ContactDamping)
            })
            .collect()
    }

    /// Half-gap δ = clearance / 2, rad.
    pub fn half_gap(&self) -> f64 {
        0.5 * self.clearance
    }

    /// Natural frequency in contact, sqrt(k/J)/2π, Hz.
    pub fn contact_frequency_hz(&self) -> f64 {
        (self.stiffness / self.inertia).sqrt() / (2.0 * std::f64::consts::PI)
    }

    /// Parses TOML text; `origin` names the source in errors.
    pub fn from_toml_str(text: &str, origin: &str) -> Result<Self, ModelError> {
        let m: RigModel = toml::from_str(text).map_err(|e| ModelError::Parse {
            file: origin.to_string(),
            detail: e.to_string(),
        })?;
        m.validate().map_err(|detail| ModelError::Invalid {
            file: origin.to_string(),
            detail,
        })?;
        Ok(m)
    }

    /// Reads a TOML rig model file.
    pub fn load(path: &Path) -> Result<Self, ModelError> {
        let file = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|cause| ModelError::Io {
            file: file.clone(),
            cause,
        })?;
        Self::from_toml_str(&text, &file)
    }

    /// TOML text of this model.
    pub fn to_toml(&self) -> String {
        toml::to_string(self).expect("a rig model always serialises")
    }

    /// Checks physical ranges; the message says which key is wrong.
    pub fn validate(&self) -> Result<(), String> {
        let finite = |name: &str, v: f64| {
            if v.is_finite() {
                Ok(())
            } else {
                Err(format!("`{name}` must be a finite number, got {v}"))
            }
        };
        finite("inertia", self.inertia)?;
        finite("stiffness", self.stiffness)?;
        finite("damping", self.damping)?;
        finite("clearance", self.clearance)?;
        finite("gravity_stiffness", self.gravity_stiffness)?;
        if self.inertia <= 0.0 {
            return Err(format!(
                "`inertia` must be > 0 (kg m^2), got {}",
                self.inertia
            ));
        }
        for (key, v, unit) in [
            ("stiffness", self.stiffness, "N m/rad"),
            ("damping", self.damping, "N m s/rad"),
            ("clearance", self.clearance, "rad"),
        ] {
            if v < 0.0 {
                return Err(format!("`{key}` must be >= 0 ({unit}), got {v}"));
            }
        }
        for (kind, v) in self.effects.present() {
            finite(kind.param(), v)?;
            let ok = match kind {
                EffectKind::CoulombFriction
                | EffectKind::ContactDamping
                | EffectKind::SensorDelay => v >= 0.0,
                EffectKind::Quantization | EffectKind::Microslip => v > 0.0,
                _ => true,
            };
            if !ok {
                return Err(format!(
                    "effect `{}`: `{}` = {v} {} is out of range (must be {})",
                    kind.name(),
                    kind.param(),
                    kind.unit(),
                    if matches!(kind, EffectKind::Quantization | EffectKind::Microslip) {
                        "> 0"
                    } else {
                        ">= 0"
                    }
                ));
            }
        }
        if let Some(p) = self.effects.microslip {
            finite("spread", p.spread)?;
            if !(p.spread > 0.0 && p.spread <= 1.0) {
                return Err(format!(
                    "effect `microslip`: `spread` = {} is out of range (must be > 0 and at most 1: the share of the mean slip displacement the elements' slips spread over either side of it)",
                    p.spread
                ));
            }
        }
        if let Some(kj) = self.effects.joint_stiffness() {
            finite("joint_stiffness", kj)?;
            if !(kj > 0.0 && kj <= self.stiffness) {
                return Err(format!(
                    "effect `microslip`: `joint_stiffness` = {kj} N m/rad is out of range (must be > 0 and at most `stiffness` = {}: the joint's stiffness is part of the model's)",
                    self.stiffness
                ));
            }
        }
        if let Some(p) = self.effects.microslip {
            finite("fine_stiffness", p.fine_stiffness)?;
            finite("fine_slip", p.fine_slip)?;
            // In the model kind's own units (N/m and m for a mode of a structure).
            let unit = |key| key_unit_of(key, self.kind).unwrap_or("");
            let (ks, ls) = (unit("fine_stiffness"), unit("fine_slip"));
            if p.fine_stiffness < 0.0 || p.fine_slip < 0.0 {
                return Err(format!(
                    "effect `microslip`: `fine_stiffness` = {} {ks} and `fine_slip` = {} {ls} must not be negative",
                    p.fine_stiffness, p.fine_slip
                ));
            }
            if (p.fine_stiffness > 0.0) != (p.fine_slip > 0.0) {
                return Err(format!(
                    "effect `microslip`: a fine population needs both `fine_stiffness` and `fine_slip` (got {} {ks} and {} {ls}): give both, or neither",
                    p.fine_stiffness, p.fine_slip
                ));
            }
            // A relative margin: a fit shrinks both populations to within 1e-9 of it.
            if p.joint_stiffness + p.fine_stiffness > self.stiffness * (1.0 + 1e-12) {
                return Err(format!(
                    "effect `microslip`: `joint_stiffness` + `fine_stiffness` = {} {ks} is more than `stiffness` = {} {ks} (both populations are part of the model's stiffness)",
                    p.joint_stiffness + p.fine_stiffness,
                    self.stiffness
                ));
            }
        }
        // Read whole: `cubic_limit` leaves out the values this refuses.
        if let Some(l) = self.effects.cubic_stiffness.map(|p| p.limit) {
            finite("limit", l)?;
            if l < 0.0 {
                let unit = key_unit_of("limit", self.kind).unwrap_or("");
                return Err(format!(
                    "effect `cubic_stiffness`: `limit` = {l} {unit} must not be negative (0 or left out: no limit)"
                ));
            }
        }
        if let Some(k) = self.kind_mismatch() {
            return Err(k);
        }
        if let Some([lo, hi]) = self.band {
            if !(lo > 0.0 && hi > lo && hi.is_finite()) {
                return Err(format!(
                    "`band` = [{lo}, {hi}] Hz must be two increasing positive frequencies [fmin, fmax]"
                ));
            }
        }
        Ok(())
    }

    /// Why this model's effects do not fit its kind, if they do not.
    fn kind_mismatch(&self) -> Option<String> {
        let allowed = self.kind.vocabulary();
        self.effects
            .present()
            .into_iter()
            .find(|(k, _)| !allowed.contains(k) && *k != EffectKind::Microslip)
            .map(|(k, _)| {
                format!(
                    "effect `{}` is not one of a {} model's ({})",
                    k.name(),
                    self.kind.name(),
                    allowed
                        .iter()
                        .map(|k| k.name())
                        .collect::<Vec<_>>()
                        .join(", ")
                )
            })
    }

    /// Values that are possible but unlikely to be meant, each naming its key: a clearance
    /// above [`MAX_PLAUSIBLE_CLEARANCE`] (degrees for radians?), a contact frequency outside
    /// 0.01 Hz–10 kHz, an over-damped contact, a gravity stiffness beyond the contact's,
    /// a clearance offset beyond the half-gap, a sensor delay over 0.1 s.
    pub fn warnings(&self) -> Vec<String> {
        let mut w = Vec::new();
        if self.clearance > MAX_PLAUSIBLE_CLEARANCE {
            w.push(format!(
                "`clearance` = {} rad ({:.1}°) is above {MAX_PLAUSIBLE_CLEARANCE} rad: was it given in degrees? ({} degrees would be {:.4} rad)",
                self.clearance,
                self.clearance.to_degrees(),
                self.clearance,
                self.clearance.to_radians()
            ));
        }
        if self.stiffness > 0.0 {
            let f = self.contact_frequency_hz();
            if !(0.01..=1e4).contains(&f) {
                w.push(format!(
                    "`stiffness` / `inertia` = {:.4e} 1/s² puts the contact natural frequency at {f:.4e} Hz, outside 0.01 Hz–10 kHz: are both in SI units (N m/rad, kg m²)?",
                    self.stiffness / self.inertia
                ));
            }
            let zeta = self.damping / (2.0 * (self.stiffness * self.inertia).sqrt());
            if zeta > 1.0 {
                w.push(format!(
                    "`damping` = {} N m s/rad is {zeta:.1}× critical in contact (2√(kJ) = {:.4e}): over-damped",
                    self.damping,
                    2.0 * (self.stiffness * self.inertia).sqrt()
                ));
            }
            let kj = self.stiffness / self.inertia;
            if self.gravity_stiffness.abs() > kj {
                w.push(format!(
                    "`gravity_stiffness` = {} 1/s² exceeds the contact's k/J = {kj:.4e} 1/s² in size: the link could not rest in contact",
                    self.gravity_stiffness
                ));
            }
        }
        if let Some(o) = self.effects.get(EffectKind::AsymmetricClearance) {
            if o.abs() > self.half_gap() && self.clearance > 0.0 {
                w.push(format!(
                    "effect `asymmetric_clearance`: `offset` = {o} rad is beyond the half-gap {} rad: the link never reaches one flank",
                    self.half_gap()
                ));
            }
        }
        if let Some(d) = self.effects.get(EffectKind::SensorDelay) {
            if d > 0.1 {
                w.push(format!(
                    "effect `sensor_delay`: `delay` = {d} s is over 0.1 s: milliseconds given as seconds?"
                ));
            }
        }
        w
    }
}

/// Unit of a rig-model key or effect parameter (`stiffness`, `torque`, or
/// `coulomb_friction.torque` as a pair of effects names it), as FORMATS.md §2 gives them.
pub fn key_unit(key: &str) -> Option<&'static str> {
    let key = key.rsplit('.').next().unwrap_or(key);
    Some(match key {
        "inertia" => "kg m^2",
        "stiffness" => "N m/rad",
        "damping" => "N m s/rad",
        "clearance" => "rad",
        "gravity_stiffness" => "1/s^2",
        "joint_stiffness" | "fine_stiffness" => "N m/rad",
        "fine_slip" | "limit" => "rad",
        _ => EffectKind::EVERY
            .into_iter()
            .find(|k| k.param() == key)?
            .unit(),
    })
}

/// [`key_unit`] for a model of `kind`: a force model's mode moves in metres under forces
/// in newtons (N/m for N m/rad, m for rad, kg for kg m²).
pub fn key_unit_of(key: &str, kind: ModelKind) -> Option<&'static str> {
    if key.rsplit('.').next() == Some("spread") {
        return Some("");
    }
    let unit = key_unit(key)?;
    Some(match kind {
        ModelKind::BaseMotion => unit,
        ModelKind::Force | ModelKind::Free => match unit {
            "kg m^2" => "kg",
            "N m/rad" => "N/m",
            "N m s/rad" => "N s/m",
            "N m/rad^3" => "N/m^3",
            "N m" => "N",
            "rad" => "m",
            other => other,
        },
    })
}

/// Clearances above this (rad, about 29°) are warned about: likely degrees.
pub const MAX_PLAUSIBLE_CLEARANCE: f64 = 0.5;

#[cfg(test)]
mod tests {
    #[test]
    fn a_softening_cubic_term_lets_go_where_its_force_cancels_the_spring() {
        use super::CubicParam;
        let k = 15000.0;
        for (k3, limit) in [
            (-1.0e8, 0.0),
            (-1.0e8, 0.02),
            (-1.0e8, 0.011),
            (-3.0e7, 0.012),
        ] {
            let c = CubicParam { k3, limit };
            let total = |d: f64| k * d + c.force(d);
            // Against the force itself: positive below, zero at, negative just past.
            let at = c.vanishes_at(k);
            println!("k3 {k3:e}, limit {limit}: the force vanishes at {at:?}");
            match at {
                Some(d) => {
                    assert!(total(d).abs() < 1e-9 * k * d, "{k3} {limit}: {}", total(d));
                    assert!(total(0.999 * d) > 0.0 && total(1.001 * d) < 0.0);
                    let below = (1..1000).map(|i| total(d * i as f64 / 1000.0));
                    assert!(below.into_iter().all(|f| f > 0.0), "{k3} {limit}");
                }
                None => {
                    let grid = (1..100_000).map(|i| total(i as f64 * 1e-4));
                    assert!(grid.into_iter().all(|f| f > 0.0), "{k3} {limit}");
                }
            }
        }
        // sqrt(15000/1e8) without a limit; past a limit of 11 mrad the tangent is
        // 15000 − 3e8·1.21e-4 < 0 and the force vanishes at 2e8·1.331e-6/(36300 − 15000);
        // with 3e7 at 12 mrad the tangent stays positive: it never lets go.
        assert!(
            (CubicParam {
                k3: -1.0e8,
                limit: 0.0
            }
            .vanishes_at(k)
            .unwrap()
                - 0.0122474)
                .abs()
                < 1e-6
        );
        assert!(
            (CubicParam {
                k3: -1.0e8,
                limit: 0.011
            }
            .vanishes_at(k)
            .unwrap()
                - 2.0e8 * 1.331e-6 / 21300.0)
                .abs()
                < 1e-9
        );
        assert_eq!(
            CubicParam {
                k3: -3.0e7,
                limit: 0.012
            }
            .vanishes_at(k),
            None
        );
        assert_eq!(
            CubicParam {
                k3: 1.0e8,
                limit: 0.0
            }
            .vanishes_at(k),
            None
        );
    }

    use super::*;

    #[test]
    fn formats_example_parses_and_round_trips() {
        let text = r#"
inertia = 3.16
stiffness = 15000.0
damping = 13.0
clearance = 0.0262
gravity_stiffness = 0.0

[effects]
coulomb_friction = { torque = 2.5 }
"#;
        let m = RigModel::from_toml_str(text, "example").unwrap();
        assert_eq!(m.effects.get(EffectKind::CoulombFriction), Some(2.5));
        let back = RigModel::from_toml_str(&m.to_toml(), "round-trip").unwrap();
        assert_eq!(m, back);
    }

    #[test]
    fn unknown_keys_and_bad_values_are_rejected_with_the_key_named() {
        let e =
            RigModel::from_toml_str("inertia = 1\nstiffness = 1\ndamping = 0\nstifness = 2", "f")
                .unwrap_err()
                .to_string();
        assert!(e.contains("stifness"), "{e}");
        let e = RigModel::from_toml_str("inertia = -1\nstiffness = 1\ndamping = 0", "f")
            .unwrap_err()
            .to_string();
        assert!(e.contains("inertia"), "{e}");
        let e = RigModel::from_toml_str(
            "inertia = 1\nstiffness = 1\ndamping = 0\n[effects]\nquantization = { step = 0.0 }",
            "f",
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("quantization"), "{e}");
    }

    #[test]
    fn a_negative_value_names_its_own_key_and_unit() {
        for (key, unit) in [
            ("stiffness", "N m/rad"),
            ("damping", "N m s/rad"),
            ("clearance", "rad"),
        ] {
            let mut text = String::from("inertia = 1\nstiffness = 1\ndamping = 1\n");
            text = text.replace(&format!("{key} = 1"), "");
            text.push_str(&format!("{key} = -2\n"));
            let e = RigModel::from_toml_str(&text, "f").unwrap_err().to_string();
            assert!(
                e.contains(&format!("`{key}` must be >= 0 ({unit}), got -2")),
                "{e}"
            );
        }
    }

    #[test]
    fn implausible_magnitudes_are_warned_about_by_key() {
        assert!(RigModel::paper().warnings().is_empty());
        let mut m = RigModel::paper();
        m.clearance = 1.5;
        let w = m.warnings();
        assert_eq!(w.len(), 1, "{w:?}");
        assert!(
            w[0].contains("`clearance`") && w[0].contains("degrees?"),
            "{w:?}"
        );
        let mut m = RigModel::paper();
        m.stiffness = 1.5e13;
        assert!(m.warnings().iter().any(|w| w.contains("`stiffness`")));
        let mut m = RigModel::paper();
        m.damping = 1e4;
        assert!(m.warnings().iter().any(|w| w.contains("over-damped")));
        let mut m = RigModel::paper();
        m.gravity_stiffness = -1e5;
        assert!(m
            .warnings()
            .iter()
            .any(|w| w.contains("`gravity_stiffness`")));
        let mut m = RigModel::paper();
        m.effects.set(EffectKind::SensorDelay, Some(2.0));
        assert!(m.warnings().iter().any(|w| w.contains("`delay`")));
        let mut m = RigModel::paper();
        m.effects.set(EffectKind::AsymmetricClearance, Some(0.02));
        assert!(m.warnings().iter().any(|w| w.contains("`offset`")));
    }

    #[test]
    fn a_force_model_with_microslip_parses_round_trips_and_checks_its_joint() {
        let text = r#"
kind = "force"
band = [6.8, 8.8]
mass = 458.0
stiffness = 9.68e5
damping = 135.0

[effects]
microslip = { slip_force = 98.0, joint_stiffness = 1.0e5 }
"#;
        let m = RigModel::from_toml_str(text, "f16").unwrap();
        assert_eq!(m.kind, ModelKind::Force);
        assert_eq!(m.inertia, 458.0);
        assert_eq!(m.band, Some([6.8, 8.8]));
        assert_eq!(m.effects.get(EffectKind::Microslip), Some(98.0));
        assert_eq!(m.effects.joint_stiffness(), Some(1.0e5));
        let back = RigModel::from_toml_str(&m.to_toml(), "round-trip").unwrap();
        assert_eq!(m, back);
        assert!(!m.vocabulary().contains(&EffectKind::ContactDamping));
        assert!(!m.vocabulary().contains(&EffectKind::GravityPreload));
        let e = RigModel::from_toml_str(&text.replace("1.0e5", "2.0e6"), "f")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("joint_stiffness") && e.contains("stiffness"),
            "{e}"
        );
        let e = RigModel::from_toml_str(
            &text.replace("microslip = ", "gravity_preload = { torque = 1.0 }\nx = "),
            "f",
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("x") || e.contains("gravity_preload"), "{e}");
        let e = RigModel::from_toml_str(
            "kind = \"force\"\nmass = 1\nstiffness = 1\ndamping = 0\n[effects]\ngravity_preload = { torque = 1.0 }",
            "f",
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("gravity_preload") && e.contains("force model"),
            "{e}"
        );
        let e = RigModel::from_toml_str(&text.replace("[6.8, 8.8]", "[8.8, 6.8]"), "f")
            .unwrap_err()
            .to_string();
        assert!(e.contains("band"), "{e}");
        // A fine population: both keys, round-tripped, kept when the slip force is set;
        // one key alone, or both populations stiffer than the model, refused.
        let fine = text.replace(
            "joint_stiffness = 1.0e5 }",
            "joint_stiffness = 1.0e5, fine_stiffness = 5.0e3, fine_slip = 4.0e-4 }",
        );
        let mut m = RigModel::from_toml_str(&fine, "f").unwrap();
        let p = m.effects.microslip.unwrap();
        assert!(p.has_fine() && p.fine_stiffness == 5.0e3 && p.fine_slip == 4.0e-4);
        assert_eq!(RigModel::from_toml_str(&m.to_toml(), "rt").unwrap(), m);
        m.effects.set(EffectKind::Microslip, Some(120.0));
        assert_eq!(m.effects.microslip.unwrap().fine_slip, 4.0e-4);
        // A joint without one writes no fine keys (older readers of the model stay happy).
        let plain_joint = RigModel::from_toml_str(text, "f").unwrap();
        assert!(!plain_joint.to_toml().contains("fine"));
        let e = RigModel::from_toml_str(&fine.replace(", fine_slip = 4.0e-4", ""), "f")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("fine_slip") && e.contains("both") && e.contains("N/m"),
            "{e}"
        );
        let e = RigModel::from_toml_str(&fine.replace("5.0e3", "9.0e5"), "f")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("fine_stiffness") && e.contains("stiffness"),
            "{e}"
        );
        // Added where there was none, a microslip gets a tenth of the stiffness.
        let mut plain = RigModel::paper();
        plain.set_effect(EffectKind::Microslip, Some(5.0));
        assert_eq!(
            plain.effects.joint_stiffness(),
            Some(JOINT_SHARE * plain.stiffness)
        );
    }

    #[test]
    fn every_effect_round_trips_through_set_and_get() {
        let mut e = Effects::default();
        for (i, k) in EffectKind::EVERY.into_iter().enumerate() {
            e.set(k, Some(i as f64 + 0.5));
        }
        for (i, k) in EffectKind::EVERY.into_iter().enumerate() {
            assert_eq!(e.get(k), Some(i as f64 + 0.5));
            assert_eq!(EffectKind::parse(k.name()), Some(k));
        }
    }

    #[test]
    fn a_limited_cubic_term_goes_on_along_its_tangent_and_stores_its_work() {
        let (k3, l) = (-5.0e9, 2.0e-3);
        let free = CubicParam { k3, limit: 0.0 };
        let limited = CubicParam { k3, limit: l };
        for i in -300..=300 {
            let d = i as f64 * 1e-5;
            // Without a limit, and within one, the plain cubic to the bit.
            assert_eq!(free.force(d).to_bits(), (k3 * d * d * d).to_bits());
            assert_eq!(free.energy(d), 0.25 * k3 * d.powi(4));
            if d.abs() <= l {
                assert_eq!(limited.force(d).to_bits(), free.force(d).to_bits());
            } else {
                // Beyond it, the tangent at the limit: stiffness 3·k3·l², odd in d.
                let tangent = k3 * l.powi(3) * d.signum() + 3.0 * k3 * l * l * (d - l * d.signum());
                assert!((limited.force(d) - tangent).abs() <= 1e-9 * tangent.abs());
                assert_eq!(limited.force(-d), -limited.force(d));
            }
            // The energy is the force's integral (central differences) and even.
            let h = 1e-7;
            let slope = (limited.energy(d + h) - limited.energy(d - h)) / (2.0 * h);
            let scale = (3.0 * k3 * l * l * h).abs() + 1e-6 * limited.force(d).abs();
            assert!((slope - limited.force(d)).abs() <= scale, "{d}");
            assert_eq!(limited.energy(-d), limited.energy(d));
        }
        // Continuous at the limit, in force and stiffness.
        let (below, above) = (
            limited.force(l * (1.0 - 1e-12)),
            limited.force(l * (1.0 + 1e-12)),
        );
        assert!((below - above).abs() <= 1e-9 * below.abs());
    }

    #[test]
    fn a_cubic_terms_limit_is_optional_kept_and_checked() {
        let text = "kind = \"force\"\nmass = 300\nstiffness = 6.0e5\ndamping = 150\n\n[effects]\ncubic_stiffness = { k3 = -5.0e9, limit = 2.0e-3 }\n";
        let mut m = RigModel::from_toml_str(text, "f").unwrap();
        assert_eq!(m.effects.cubic_limit(), Some(2.0e-3));
        assert_eq!(RigModel::from_toml_str(&m.to_toml(), "rt").unwrap(), m);
        // Setting k3 keeps the limit; a term without one writes no `limit` key.
        m.effects.set(EffectKind::CubicStiffness, Some(-4.0e9));
        assert_eq!(m.effects.cubic_limit(), Some(2.0e-3));
        m.effects.set_cubic_limit(0.0);
        assert_eq!(m.effects.cubic_limit(), None);
        assert!(!m.to_toml().contains("limit"));
        let e = RigModel::from_toml_str(&text.replace("2.0e-3", "-1.0e-3"), "f")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("limit") && e.contains(" m ") && e.contains("negative"),
            "{e}"
        );
    }
}
