//! What a user can set to get past an error or a warning, as a typed hint that the front end
//! in use names: the command line installs its flag spellings (`--sample-rate`), another
//! front end its own; without one a hint reads as a plain phrase ("the sample rate option").
//! The library's messages say `{hint}` where they point at an option, and never spell a flag.

use std::fmt;
use std::sync::OnceLock;

/// An option a message points the user to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Hint {
    /// The sample rate given for archives that lack one.
    SampleRate,
    /// The names of the input and output datasets.
    ChannelNames,
    /// The pattern choosing which groups are runs.
    RunGlob,
    /// The kind of run an archive holds.
    Kind,
    /// The band of the mode to identify.
    Band,
    /// The wavelet's analysis range.
    FrequencyRange,
    /// The wavelet's bandwidth.
    Bandwidth,
    /// Simulation-refined identification.
    Refine,
    /// The share of a campaign one process takes.
    Shard,
    /// Identifying again what an earlier invocation committed.
    Force,
    /// The CPU backend.
    CpuBackend,
    /// The GPU backend (even a software adapter).
    GpuBackend,
    /// How many runs the report draws.
    ReportRuns,
}

impl Hint {
    /// The plain phrase used when no front end has named its options.
    pub fn phrase(self) -> &'static str {
        match self {
            Hint::SampleRate => "the sample rate option",
            Hint::ChannelNames => "the input and output name options",
            Hint::RunGlob => "the run pattern option",
            Hint::Kind => "the run kind option",
            Hint::Band => "the mode band option",
            Hint::FrequencyRange => "the frequency range options",
            Hint::Bandwidth => "the wavelet bandwidth option",
            Hint::Refine => "the refinement option",
            Hint::Shard => "the shard option",
            Hint::Force => "the force option",
            Hint::CpuBackend => "the CPU backend",
            Hint::GpuBackend => "the GPU backend option",
            Hint::ReportRuns => "the report's run count option",
        }
    }
}

/// How the front end names a hint.
pub type Namer = fn(Hint) -> &'static str;

static NAMER: OnceLock<Namer> = OnceLock::new();

/// Installs the front end's names for the hints, once per process (later calls are ignored).
pub fn set_namer(namer: Namer) {
    let _ = NAMER.set(namer);
}

impl fmt::Display for Hint {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(NAMER.get().map_or(self.phrase(), |name| name(*self)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_hint_has_a_phrase() {
        for h in [
            Hint::SampleRate,
            Hint::ChannelNames,
            Hint::RunGlob,
            Hint::Kind,
            Hint::Band,
            Hint::FrequencyRange,
            Hint::Bandwidth,
            Hint::Refine,
            Hint::Shard,
            Hint::Force,
            Hint::CpuBackend,
            Hint::GpuBackend,
            Hint::ReportRuns,
        ] {
            assert!(!h.phrase().is_empty());
        }
    }
}
