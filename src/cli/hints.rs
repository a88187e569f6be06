//! The command line's names for the library's hints ([`skelid::hint`]): the flags a message
//! points the user to. Installed first thing, in every skelid process (the child processes
//! too, so that what they report reads the same).

use skelid::hint::Hint;

/// The flag (and value, where one is meant) that a hint points to.
pub(crate) fn flag(h: Hint) -> &'static str {
    match h {
        Hint::SampleRate => "--sample-rate",
        Hint::ChannelNames => "--input-name/--output-name",
        Hint::RunGlob => "--run-glob",
        Hint::Kind => "--kind",
        Hint::Band => "--band",
        Hint::FrequencyRange => "--fmin/--fmax",
        Hint::Bandwidth => "--bandwidth",
        Hint::Refine => "--refine",
        Hint::Shard => "--shard",
        Hint::Force => "--force",
        Hint::CpuBackend => "--backend cpu",
        Hint::GpuBackend => "--backend gpu",
        Hint::ReportRuns => "--report-runs",
    }
}
