//! The run as every stage sees it: its metadata and samples, its kind of excitation and
//! what its channels measure. The reader (`ingest`) makes runs from archives, the simulator
//! and the demo make them from models; identification, the gap, the journal and the
//! results take them in, without depending on the HDF5 reader.

use std::collections::BTreeMap;
use std::fmt;

use serde::Serialize;

/// How a run was excited (FORMATS.md §1 `kind`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, serde::Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum RunKind {
    /// Input is the base (drive-side) displacement; the joint sees z = output − input.
    #[default]
    BaseMotion,
    /// Input is an excitation force on the mass.
    Force,
    /// No input: free decay of the output.
    Free,
}

impl RunKind {
    /// The name used in archives.
    pub fn as_str(self) -> &'static str {
        match self {
            RunKind::BaseMotion => "base_motion",
            RunKind::Force => "force",
            RunKind::Free => "free",
        }
    }

    /// A kind as archives and `--kind` spell it (`base_motion`, `base-motion`, `base`,
    /// `force`, `free`, `free_decay`).
    pub fn parse(s: &str) -> Option<Self> {
        match s.trim().to_ascii_lowercase().replace('-', "_").as_str() {
            "base_motion" | "base" => Some(RunKind::BaseMotion),
            "force" => Some(RunKind::Force),
            "free" | "free_decay" => Some(RunKind::Free),
            _ => None,
        }
    }
}

impl fmt::Display for RunKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

/// What a channel measures (FORMATS.md §1 `input_quantity` / `output_quantity`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, serde::Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Quantity {
    /// Displacement (angle for rotary rigs).
    #[default]
    Displacement,
    /// Velocity; integrated once before identification.
    Velocity,
    /// Acceleration; integrated twice before identification.
    Acceleration,
    /// Force (input of a `force` run).
    Force,
}

impl Quantity {
    /// The name used in archives.
    pub fn as_str(self) -> &'static str {
        match self {
            Quantity::Displacement => "displacement",
            Quantity::Velocity => "velocity",
            Quantity::Acceleration => "acceleration",
            Quantity::Force => "force",
        }
    }

    /// A quantity as archives and `--input-quantity`/`--output-quantity` spell it.
    pub fn parse(s: &str) -> Option<Self> {
        match s.trim().to_ascii_lowercase().as_str() {
            "displacement" | "angle" | "position" => Some(Quantity::Displacement),
            "velocity" => Some(Quantity::Velocity),
            "acceleration" => Some(Quantity::Acceleration),
            "force" | "torque" => Some(Quantity::Force),
            _ => None,
        }
    }
}

/// Everything known about a run before its samples are read.
#[derive(Debug, Clone, Serialize, serde::Deserialize)]
pub struct RunMeta {
    /// Group path inside the archive, e.g. `/runs/run_001`.
    pub path: String,
    /// Number of samples.
    pub samples: usize,
    /// Sample rate, Hz.
    pub sample_rate: f64,
    /// Duration, s.
    pub duration: f64,
    /// Excitation kind.
    pub kind: RunKind,
    /// What the input channel measures (`None` for free decays).
    pub input_quantity: Option<Quantity>,
    /// What the output channel measures.
    pub output_quantity: Quantity,
    /// J (kg m²) or m (kg) if given.
    pub inertia: Option<f64>,
    /// C = mgL/J (1/s²), default 0.
    pub gravity_stiffness: f64,
    /// Units as stated by the archive (reported, never converted).
    pub units: Option<String>,
    /// Free-text excitation description.
    pub excitation: Option<String>,
    /// Every attribute of the run group itself, for display.
    pub attributes: BTreeMap<String, String>,
    /// The band of the mode to identify (`mode_fmin`, `mode_fmax`, Hz), if the archive
    /// names one ([`crate::mode`]).
    #[serde(default)]
    pub mode_band: Option<(f64, f64)>,
    /// The frequency near which the mode to identify lies (`mode_near`, Hz), if the archive
    /// names one.
    #[serde(default)]
    pub mode_near: Option<f64>,
    /// How far apart the zeros of the input and output encoders may be (`zero_tolerance`,
    /// rad; 0 when not stated): a shift of the relative motion within it is the sensors',
    /// not the joint's.
    #[serde(default)]
    pub zero_tolerance: f64,
}

/// A run with its samples, ready for analysis.
#[derive(Debug, Clone)]
pub struct Run {
    /// Metadata.
    pub meta: RunMeta,
    /// Input channel (base displacement or force); `None` for free decays.
    pub input: Option<Vec<f64>>,
    /// Output channel.
    pub output: Vec<f64>,
}
