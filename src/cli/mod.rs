//! The command line, one file per subcommand (`main.rs` parses and dispatches), and the
//! arguments several share (`args`).

pub mod args;
pub mod bench;
pub mod gap;
pub mod inspect;
pub mod run;
pub mod simulate;
pub mod track;
pub mod validate;

/// Identification options on the CPU: what `gap` and `validate` identify with (their
/// simulations are identified one after another, where a GPU's batching gains nothing).
pub(crate) struct CpuIdentifier {
    options: skelid::identify::IdentifyOptions,
    cpu: skelid::backend::Backend,
}

impl CpuIdentifier {
    pub(crate) fn new(options: skelid::identify::IdentifyOptions) -> CpuIdentifier {
        CpuIdentifier {
            options,
            cpu: skelid::backend::Backend::cpu(),
        }
    }

    /// The options and backend, handed on together.
    pub(crate) fn get(&self) -> skelid::identify::Identifier<'_> {
        skelid::identify::Identifier {
            options: &self.options,
            backend: &self.cpu,
        }
    }
}
