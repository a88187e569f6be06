//! skelid — identification of non-linear joints (clearance, contact stiffness, viscous and
//! dry friction) from vibration test campaigns with skeleton methods, and diagnosis of the
//! gap between a rig's simulation model and its measurements.
//!
//! Pipeline stages, one module each: [`ingest`] (HDF5 campaigns in), [`simulate`] (the rig
//! model under any drive), [`campaign`] (archives out), [`demo`] (the built-in campaign),
//! [`transform`] (Hilbert and wavelet transforms), [`ridge`], [`skeleton`] and [`track`]
//! (instantaneous amplitude and frequency), [`forcevib`] (ω0²(t), h0(t)), [`fit`] (skeleton
//! curves and physical parameters), [`identify`] (one run through all of it), [`batch`] and
//! [`journal`] (many runs, crash-safe and resumable), [`report`] (results and report.html
//! out), [`gpu`] (the WGSL compute stages of the GPU backend), [`backend`] (the one place the
//! CPU or GPU backend is chosen).

pub mod backend;
pub mod batch;
pub mod bench;
pub mod campaign;
pub mod child;
pub mod condition;
pub mod demo;
pub mod filter;
pub mod fit;
pub mod forcevib;
pub mod gap;
pub mod gpu;
pub mod h5util;
pub mod hint;
pub mod identify;
pub mod ingest;
pub mod inspect;
pub mod journal;
pub mod mode;
pub mod model;
pub mod pagecache;
pub mod profile;
pub mod quality;
pub mod refine;
pub mod report;
pub mod ridge;
pub mod rig;
pub mod run;
pub mod simulate;
pub mod skeleton;
pub mod track;
pub mod transform;
pub mod units;
pub mod validate;
