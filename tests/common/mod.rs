//! Builders of small HDF5 archives for the tests, written with the HDF5 library directly
//! (not with skelid's writer), laid out the way other tools lay them out.
#![allow(dead_code)]

use std::path::{Path, PathBuf};

use hdf5::types::VarLenUnicode;

/// A sine of `n` samples, frequency f (cycles per sample rate fs).
pub fn sine(n: usize, f: f64, fs: f64) -> Vec<f64> {
    (0..n)
        .map(|i| (std::f64::consts::TAU * f * i as f64 / fs).sin())
        .collect()
}

/// `count` base-motion runs `/runs/run_000`, … of `n` samples at 1 kHz, in displacement:
/// input a 3 Hz sine, output a sine at 3 + `step` × i Hz.
pub fn sine_runs(count: usize, n: usize, step: f64) -> Vec<skelid::campaign::RunData> {
    (0..count)
        .map(|i| skelid::campaign::RunData {
            path: format!("/runs/run_{i:03}"),
            input: Some(sine(n, 3.0, 1000.0)),
            output: sine(n, 3.0 + i as f64 * step, 1000.0),
            sample_rate: 1000.0,
            kind: skelid::ingest::RunKind::BaseMotion,
            input_quantity: Some(skelid::ingest::Quantity::Displacement),
            output_quantity: skelid::ingest::Quantity::Displacement,
            attrs: vec![],
        })
        .collect()
}

/// Sets a string attribute.
pub fn set_str(loc: &hdf5::Location, name: &str, v: &str) {
    let v: VarLenUnicode = v.parse().unwrap();
    loc.new_attr::<VarLenUnicode>()
        .create(name)
        .unwrap()
        .write_scalar(&v)
        .unwrap();
}

/// Sets a float attribute.
pub fn set_f64(loc: &hdf5::Location, name: &str, v: f64) {
    loc.new_attr::<f64>()
        .create(name)
        .unwrap()
        .write_scalar(&v)
        .unwrap();
}

/// Writes a 1-D float dataset.
pub fn put(g: &hdf5::Group, name: &str, data: &[f64]) -> hdf5::Dataset {
    g.new_dataset_builder()
        .with_data(data)
        .create(name)
        .unwrap()
}

/// Creates (with parents) a group.
pub fn group(f: &hdf5::File, path: &str) -> hdf5::Group {
    f.create_group_builder()
        .create_intermediate_group(true)
        .create(path.trim_start_matches('/'))
        .unwrap()
}

/// A valid base-motion run at `path` with 1000 samples at 1 kHz inherited from `/runs`.
pub fn good_run(f: &hdf5::File, path: &str) {
    let g = group(f, path);
    put(&g, "input", &sine(1000, 5.0, 1000.0));
    put(&g, "output", &sine(1000, 5.0, 1000.0));
}

/// A fresh temporary folder.
/// Gives a file this test process wrote with libhdf5 a new inode, before a child process
/// opens it. libhdf5 opens files without O_CLOEXEC: a child that another test thread spawns
/// while the file is open inherits the descriptor with its `flock` lock and holds both as
/// long as it runs, and a child of this test opening the file then fails with "unable to
/// lock file, errno = 11". A copy renamed over the file carries no lock.
pub fn release_locks(path: &Path) {
    let tmp = path.with_extension("unlocked");
    std::fs::copy(path, &tmp).unwrap();
    std::fs::rename(&tmp, path).unwrap();
}

pub fn tmpdir() -> tempfile::TempDir {
    tempfile::tempdir().unwrap()
}

/// Path of a new file in `dir`.
pub fn file_in(dir: &Path, name: &str) -> PathBuf {
    dir.join(name)
}

/// The shared folder beside the repository, if this checkout has one.
pub fn shared_real_data() -> Option<PathBuf> {
    let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/real");
    p.is_dir().then_some(p)
}

/// summary.json rows without the timings, sorted: what must be identical.
pub fn summary_rows(out: &Path) -> Vec<serde_json::Value> {
    let text = std::fs::read_to_string(out.join("summary.json")).expect("summary.json");
    let v: serde_json::Value = serde_json::from_str(&text).unwrap();
    let mut rows: Vec<serde_json::Value> = v["rows"]
        .as_array()
        .unwrap()
        .iter()
        .cloned()
        .map(|mut r| {
            r.as_object_mut().unwrap().remove("seconds");
            // The archive's folder differs between outputs; its name does not.
            let src = r["source"].as_str().unwrap().to_string();
            r["source"] = Path::new(&src)
                .file_name()
                .unwrap()
                .to_str()
                .unwrap()
                .into();
            r
        })
        .collect();
    rows.sort_by_key(|r| format!("{}{}{}", r["source"], r["run"], r["method"]));
    rows
}
