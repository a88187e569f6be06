//! The command line's subcommands, one file each (the rest still live in `main.rs`, to be
//! moved here: issue 22).

pub mod validate;
