//! `skelid track`'s output (FORMATS.md §4): one signal's track as CSV or HDF5 — time,
//! amplitude, frequency, valid, and the scalogram when kept. In: a [`Track`]; out: a file.

use std::borrow::Cow;
use std::io::Write;
use std::path::Path;

use crate::campaign::{tmp_path, write_signal};
use crate::h5util::{write_f64_attr, write_str_attr};
use crate::track::Track;

use super::*;

/// Writes a track as HDF5 datasets, or as CSV columns when the name ends in `.csv`:
/// `time` (s), `amplitude`, `frequency` (Hz), `valid` (0/1) — the contract — then `phase`
/// (rad), `d_amplitude` (1/s), `d2_amplitude` (1/s²), `d_frequency` (Hz/s).
/// The file appears complete or not at all (written aside, then renamed).
pub fn write_track(path: &Path, track: &Track, source: &str) -> Result<(), ReportError> {
    let err = |detail: String| ReportError {
        file: path.display().to_string(),
        detail,
    };
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).map_err(|e| err(e.to_string()))?;
    }
    let tmp = tmp_path(path);
    let is_csv = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("csv"));
    let result = if is_csv {
        write_csv(&tmp, track).map_err(|e| e.to_string())
    } else {
        write_hdf5(&tmp, track, source).map_err(|e| e.to_string())
    };
    if let Err(e) = result {
        let _ = std::fs::remove_file(&tmp);
        return Err(err(e));
    }
    std::fs::rename(&tmp, path).map_err(|e| err(e.to_string()))
}

pub(super) fn columns(track: &Track) -> Vec<(&'static str, Cow<'_, [f64]>)> {
    vec![
        ("time", Cow::Owned(track.time())),
        ("amplitude", Cow::Borrowed(&track.amplitude)),
        ("frequency", Cow::Borrowed(&track.frequency)),
        (
            "valid",
            Cow::Owned(
                track
                    .valid
                    .iter()
                    .map(|&v| f64::from(u8::from(v)))
                    .collect(),
            ),
        ),
        ("phase", Cow::Borrowed(&track.phase)),
        ("d_amplitude", Cow::Borrowed(&track.d_amplitude)),
        ("d2_amplitude", Cow::Borrowed(&track.d2_amplitude)),
        ("d_frequency", Cow::Borrowed(&track.d_frequency)),
    ]
}

pub(super) fn write_csv(path: &Path, track: &Track) -> std::io::Result<()> {
    let mut w = std::io::BufWriter::new(std::fs::File::create(path)?);
    let cols = columns(track);
    let names: Vec<&str> = cols.iter().map(|c| c.0).collect();
    writeln!(w, "{}", names.join(","))?;
    for i in 0..track.len() {
        let row: Vec<String> = cols
            .iter()
            .map(|(name, v)| {
                if *name == "valid" {
                    format!("{}", v[i] as u8)
                } else {
                    format!("{:.10e}", v[i])
                }
            })
            .collect();
        writeln!(w, "{}", row.join(","))?;
    }
    w.flush()
}

pub(super) fn write_hdf5(path: &Path, track: &Track, source: &str) -> hdf5::Result<()> {
    let file = hdf5::File::create(path)?;
    write_str_attr(&file, "format", "skelid-track/1")?;
    write_str_attr(&file, "method", track.method.as_str())?;
    write_str_attr(&file, "source", source)?;
    write_f64_attr(&file, "sample_rate", track.sample_rate)?;
    write_f64_attr(&file, "offset", track.offset)?;
    write_f64_attr(&file, "noise", track.noise)?;
    write_f64_attr(&file, "fmin", track.band.0)?;
    write_f64_attr(&file, "fmax", track.band.1)?;
    for (name, v) in columns(track) {
        if name == "valid" {
            let bytes: Vec<u8> = track.valid.iter().map(|&b| u8::from(b)).collect();
            file.new_dataset_builder().with_data(&bytes).create(name)?;
        } else {
            write_signal(&file, name, &v, false)?;
        }
    }
    if let Some(sc) = &track.scalogram {
        file.new_dataset::<f32>()
            .shape((sc.frequency.len(), sc.time.len()))
            .create("scalogram")?
            .write_raw(&sc.magnitude)?;
        write_signal(&file, "scalogram_frequency", &sc.frequency, false)?;
        write_signal(&file, "scalogram_time", &sc.time, false)?;
    }
    file.flush()
}
