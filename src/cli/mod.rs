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
