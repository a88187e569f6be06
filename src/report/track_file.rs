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

/// One column of a track file: reals, or the 0/1 `valid` flags.
enum Column<'a> {
    Real(Cow<'a, [f64]>),
    Flag(&'a [bool]),
}

fn columns(track: &Track) -> Vec<(&'static str, Column<'_>)> {
    fn real(v: &[f64]) -> Column<'_> {
        Column::Real(Cow::Borrowed(v))
    }
    vec![
        ("time", Column::Real(Cow::Owned(track.time()))),
        ("amplitude", real(&track.amplitude)),
        ("frequency", real(&track.frequency)),
        ("valid", Column::Flag(&track.valid)),
        ("phase", real(&track.phase)),
        ("d_amplitude", real(&track.d_amplitude)),
        ("d2_amplitude", real(&track.d2_amplitude)),
        ("d_frequency", real(&track.d_frequency)),
    ]
}

pub(super) fn write_csv(path: &Path, track: &Track) -> std::io::Result<()> {
    let mut w = std::io::BufWriter::new(std::fs::File::create(path)?);
    write_csv_to(&mut w, track, CSV_BLOCK)?;
    w.flush()
}

/// [`write_csv`]'s text into `w`, its rows formatted in tasks of `block` rows.
fn write_csv_to(w: &mut impl Write, track: &Track, block: usize) -> std::io::Result<()> {
    use rayon::prelude::*;
    let cols = columns(track);
    let names: Vec<&str> = cols.iter().map(|c| c.0).collect();
    writeln!(w, "{}", names.join(","))?;
    // Rows are formatted in blocks on every core and written in order: the same bytes as
    // one row after another (a 2^20-sample track is 117 MB of text; formatted on one
    // thread, a String a cell, it took 2.7 s against the track's 0.8 s on 2 cores). A
    // round of blocks at a time bounds the text held to a few blocks a thread.
    let n = track.len();
    let block = block.max(1);
    let round = block * 4 * rayon::current_num_threads();
    for start in (0..n).step_by(round) {
        let end = (start + round).min(n);
        let blocks: Vec<Vec<u8>> = (start..end)
            .into_par_iter()
            .step_by(block)
            .map(|b| csv_rows(&cols, b..(b + block).min(end)))
            .collect();
        for b in blocks {
            w.write_all(&b)?;
        }
    }
    Ok(())
}

/// Rows formatted by one task of [`write_csv`].
const CSV_BLOCK: usize = 8192;

/// The CSV text of rows `rows`: each real `{:.10e}`, each flag 0 or 1.
fn csv_rows(cols: &[(&str, Column<'_>)], rows: std::ops::Range<usize>) -> Vec<u8> {
    // About 17 bytes a value; writing into a Vec cannot fail.
    let mut out = Vec::with_capacity(rows.len() * cols.len() * 18);
    for i in rows {
        for (c, (_, col)) in cols.iter().enumerate() {
            if c > 0 {
                out.push(b',');
            }
            match col {
                Column::Real(v) => {
                    let _ = write!(out, "{:.10e}", v[i]);
                }
                Column::Flag(v) => out.push(if v[i] { b'1' } else { b'0' }),
            }
        }
        out.push(b'\n');
    }
    out
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
    for (name, col) in columns(track) {
        match col {
            Column::Real(v) => write_signal(&file, name, &v, false)?,
            Column::Flag(v) => {
                let bytes: Vec<u8> = v.iter().map(|&b| u8::from(b)).collect();
                file.new_dataset_builder().with_data(&bytes).create(name)?;
            }
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::track::{Device, Method};

    /// The CSV as it was written before its rows were formatted in parallel: a row at a
    /// time, a String a cell, the columns taken from the track's fields.
    fn row_by_row(t: &Track) -> Vec<u8> {
        let mut w = Vec::new();
        writeln!(
            w,
            "time,amplitude,frequency,valid,phase,d_amplitude,d2_amplitude,d_frequency"
        )
        .unwrap();
        let time = t.time();
        for (i, &time) in time.iter().enumerate() {
            let reals = [
                time,
                t.amplitude[i],
                t.frequency[i],
                f64::from(u8::from(t.valid[i])),
                t.phase[i],
                t.d_amplitude[i],
                t.d2_amplitude[i],
                t.d_frequency[i],
            ];
            let row: Vec<String> = reals
                .iter()
                .enumerate()
                .map(|(c, v)| {
                    if c == 3 {
                        format!("{}", *v as u8)
                    } else {
                        format!("{v:.10e}")
                    }
                })
                .collect();
            writeln!(w, "{}", row.join(",")).unwrap();
        }
        w
    }

    fn track(n: usize) -> Track {
        // Values of every kind a track may hold or that formatting treats apart: zero of
        // both signs, subnormals, the extremes, infinities, NaN, and ordinary values.
        let special = [
            0.0,
            -0.0,
            f64::MIN_POSITIVE / 3.0,
            f64::MAX,
            -f64::MIN_POSITIVE,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NAN,
            1.0,
            9.99999999995e-7,
        ];
        let series = |k: usize| -> Vec<f64> {
            (0..n)
                .map(|i| {
                    if (i + k) % 97 < special.len() {
                        special[(i + k) % 97]
                    } else {
                        ((i * (k + 3)) as f64 * 0.618_033_988_75).sin()
                            * 10f64.powi((i % 41) as i32 - 20)
                    }
                })
                .collect()
        };
        Track {
            method: Method::Wavelet,
            sample_rate: 1000.0,
            amplitude: series(0),
            frequency: series(1),
            phase: series(2),
            d_amplitude: series(3),
            d2_amplitude: series(4),
            d_frequency: series(5),
            valid: (0..n).map(|i| i % 3 != 0).collect(),
            offset: 0.0,
            noise: 0.0,
            band: (1.0, 2.0),
            backend: Device::Cpu,
            scalogram: None,
        }
    }

    #[test]
    fn csv_in_parallel_blocks_is_the_row_by_row_text() {
        // Lengths around the block and the round (block × 4 × threads), on 1 to 3 threads.
        for threads in [1, 2, 3] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            for (n, block) in [
                (0, 7),
                (1, 7),
                (6, 7),
                (7, 7),
                (8, 7),
                (300, 7),
                (301, 13),
                (2000, 8192),
            ] {
                let t = track(n);
                let mut got = Vec::new();
                pool.install(|| write_csv_to(&mut got, &t, block)).unwrap();
                assert!(
                    got == row_by_row(&t),
                    "{n} rows in blocks of {block} on {threads} threads differ"
                );
            }
        }
    }
}
