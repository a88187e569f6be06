//! The batch's crash-safe record: every finished run is committed as its own file
//! `<out>/runs/<key>.run` (written beside, then renamed, so a run is either wholly there or
//! absent), keyed by a hash of the run's content and the settings. A rerun skips the keys it
//! finds; `results.h5` is written from the same encoded runs and renamed into place, so it
//! is never seen half-written either.
//!
//! Why not HDF5: libhdf5 runs under one process-wide lock, and committing each run to its
//! own HDF5 file was half of the batch's one writer thread, which no number of cores
//! speeds up. A `.run` file is the run's encoded results (the very chunks results.h5
//! receives) behind a small JSON head and a checksum, written by the worker that finished
//! the run. `<key>.h5` files of earlier versions are still read.

use crate::report::Status;
use std::path::{Path, PathBuf};

use crate::identify::IdentifyOptions;
use crate::report::encoded::EncodedRun;
use crate::report::{encode_run, summary_rows, ReportError, ResultsFile, RunOutcome, SummaryRow};
use crate::run::Run;
use crate::track::Method;

/// Folder of the committed runs inside the output folder.
pub const RUNS_DIR: &str = "runs";

/// Hash of everything that changes a run's result besides its data: the skelid version,
/// the methods and the identification options.
pub fn settings_fingerprint(methods: &[Method], options: &IdentifyOptions) -> String {
    let mut h = blake3::Hasher::new();
    h.update(env!("CARGO_PKG_VERSION").as_bytes());
    // What a run's results hold and how: bumped when a run written before lacks something
    // (units, layout 2) or is laid out otherwise (chunks of 32 768 elements, layout 3).
    h.update(b"results layout 3\0");
    for m in methods {
        h.update(m.as_str().as_bytes());
        h.update(b"\0");
    }
    // The options as serialised for settings_json: every field by name and value, so a
    // changed option changes the key (and the key reads from the same record the file keeps).
    h.update(
        serde_json::to_string(options)
            .expect("identification options serialise")
            .as_bytes(),
    );
    h.finalize().to_hex()[..32].to_string()
}

/// Everything that made a batch's results, spelled out so that a result can be reproduced
/// from its file alone (results.h5's `settings_json`, manifest.json's `settings_full`): the
/// skelid version, the methods, every identification option and the archive overrides.
pub fn settings_record(
    methods: &[Method],
    options: &IdentifyOptions,
    ingest: &crate::ingest::IngestOptions,
) -> serde_json::Value {
    serde_json::json!({
        "skelid_version": env!("CARGO_PKG_VERSION"),
        "fingerprint": settings_fingerprint(methods, options),
        "methods": methods.iter().map(|m| m.as_str()).collect::<Vec<_>>(),
        "identify": options,
        "ingest": {
            "input_name": ingest.input_name,
            "output_name": ingest.output_name,
            "sample_rate": ingest.sample_rate,
            "runs": ingest.run_glob.as_ref().map(|g| g.as_str().to_string()),
            "kind": ingest.kind,
            "inertia": ingest.inertia,
            "input_quantity": ingest.input_quantity,
            "output_quantity": ingest.output_quantity,
        },
        "command": std::env::args().collect::<Vec<_>>(),
    })
}

/// The key of one run: its archive's file name, its path, metadata and samples, and the
/// settings.
pub fn run_key(run: &Run, source: &str, settings: &str) -> String {
    let mut h = blake3::Hasher::new();
    h.update(settings.as_bytes());
    h.update(base_name(source).as_bytes());
    h.update(b"\0");
    h.update(run.meta.path.as_bytes());
    h.update(b"\0");
    h.update(
        serde_json::to_string(&run.meta)
            .expect("run metadata serialises")
            .as_bytes(),
    );
    if let Some(x) = &run.input {
        h.update(bytemuck::cast_slice(x));
    }
    h.update(b"\0output\0");
    h.update(bytemuck::cast_slice(&run.output));
    h.finalize().to_hex()[..32].to_string()
}

/// The key of a run that could not be read: its archive, path and error, and the settings.
pub fn failed_key(source: &str, path: &str, error: &str, settings: &str) -> String {
    let mut h = blake3::Hasher::new();
    for part in [settings, base_name(source), path, error] {
        h.update(part.as_bytes());
        h.update(b"\0");
    }
    h.finalize().to_hex()[..32].to_string()
}

/// The file name of an archive path (the folder it was given from does not matter).
pub fn base_name(source: &str) -> &str {
    source.rsplit('/').next().unwrap_or(source)
}

/// A committed run: its key and the summary rows stored with it.
#[derive(Debug, Clone)]
pub struct Entry {
    /// Content-and-settings key.
    pub key: String,
    /// Run path inside its archive.
    pub path: String,
    /// Archive file name.
    pub source: String,
    /// Whether the run failed.
    pub failed: bool,
    /// Its rows of summary.json.
    pub rows: Vec<SummaryRow>,
}

/// Where each of `entries` goes in results.h5: its own path, or, for the second and later
/// runs of the same path from different archives, `PATH@FILE` beside it, FILE the
/// archive's file name (`/runs/run_001@run_10.h5`), then `PATH@FILE~2`, `~3`, … where
/// archives in different folders share that name too. The archive's whole path would put
/// its slashes into the name and the run in groups nested below `/runs/run_001@`.
pub fn placements(entries: &[Entry]) -> Vec<String> {
    let mut seen = std::collections::HashSet::new();
    entries
        .iter()
        .map(|e| {
            let group = results_group(&e.path, &e.source);
            if seen.insert(group.clone()) {
                return group;
            }
            let named = format!("{group}@{}", base_name(&e.source));
            let mut at = named.clone();
            for n in 2.. {
                if seen.insert(at.clone()) {
                    break;
                }
                at = format!("{named}~{n}");
            }
            at
        })
        .collect()
}

/// The group of results.h5 a run's results go to: its own path, or, for a run at an
/// archive's root (MATLAB v7.3 saves its variables there), a group named after the
/// archive's file (`/bench` for `bench.mat`), since results.h5's root is not a run's.
pub fn results_group(path: &str, source: &str) -> String {
    if path != "/" {
        return path.to_string();
    }
    let name = base_name(source);
    let stem = Path::new(name)
        .file_stem()
        .and_then(|s| s.to_str())
        .filter(|s| !s.is_empty() && !s.starts_with('.'))
        .unwrap_or("root");
    format!("/{stem}")
}

/// A finished run made ready for its commit: results encoded (compressed) and summary rows
/// computed, all CPU work, so a batch's workers do it and the writer only writes.
pub struct Prepared {
    encoded: EncodedRun,
    rows: Vec<SummaryRow>,
    path: String,
    source: String,
    failed: bool,
    /// Bytes the journal grew by when the run was committed: its file, less the file of
    /// the same key it replaced (`--force`).
    journal_growth: u64,
}

impl Prepared {
    /// The run's group path.
    pub fn path(&self) -> &str {
        &self.path
    }

    /// The run's archive.
    pub fn source(&self) -> &str {
        &self.source
    }

    /// The run's results, encoded.
    pub fn encoded(&self) -> &EncodedRun {
        &self.encoded
    }

    /// Bytes the journal grew by when the run was committed (0 before).
    pub fn journal_growth(&self) -> u64 {
        self.journal_growth
    }

    /// Drops the encoded run's kept copies of its datasets (see [`EncodedRun::forget_kept`]).
    pub fn forget_kept(&mut self) {
        self.encoded.forget_kept();
    }

    /// Encodes `outcome` and computes its summary rows.
    pub fn new(outcome: &RunOutcome) -> Prepared {
        Prepared {
            encoded: encode_run(outcome),
            rows: summary_rows(outcome),
            path: outcome.path.clone(),
            source: outcome.source.clone(),
            failed: outcome.status() == Status::Failed,
            journal_growth: 0,
        }
    }
}

/// The committed runs of one output folder.
pub struct Journal {
    dir: PathBuf,
}

/// First bytes of a journal file (`runs/<key>.run`): what it is and its layout's version.
/// Version 2: chunks of [`crate::report::encoded::CHUNK`] = 32 768 elements (version 1's
/// were 4096, which this version would misplace: a version 1 file reads as damaged).
const MAGIC: &[u8; 17] = b"skelid-journal/2\n";

/// The head of a journal file: who the run is and its summary rows (JSON, so that the
/// rows' optional fields need no fixed layout).
#[derive(serde::Serialize, serde::Deserialize)]
struct Head {
    run: String,
    run_source: String,
    failed: bool,
    summary: String,
}

/// A committed run's results as the journal holds them.
pub enum Stored {
    /// Encoded by this version: written into results.h5 chunk by chunk.
    Encoded(EncodedRun),
    /// A `<key>.h5` file from a version before the `.run` files: copied group by group.
    Legacy(PathBuf),
}

impl Journal {
    /// Opens (creating) `<out>/runs`.
    pub fn open(out: &Path) -> Result<Journal, ReportError> {
        let dir = out.join(RUNS_DIR);
        std::fs::create_dir_all(&dir).map_err(|e| ReportError {
            file: dir.display().to_string(),
            detail: e.to_string(),
        })?;
        Ok(Journal { dir })
    }

    /// The file of a key: `<key>.run`, or the `<key>.h5` an earlier version committed when
    /// only that one exists.
    pub fn file(&self, key: &str) -> PathBuf {
        let run = self.dir.join(format!("{key}.run"));
        let legacy = self.legacy_file(key);
        if !run.exists() && legacy.exists() {
            legacy
        } else {
            run
        }
    }

    /// Whether the journal holds any run committed by a version before the `.run` files
    /// (a `<key>.h5`): such runs are copied with libhdf5 ([`crate::report::ResultsFile`]).
    pub fn has_legacy_files(&self) -> bool {
        // A folder that cannot be listed counts as holding some: libhdf5's writer copes
        // with either kind of run.
        std::fs::read_dir(&self.dir).map_or(true, |entries| {
            entries
                .filter_map(|e| e.ok())
                .any(|e| e.path().extension().is_some_and(|x| x == "h5"))
        })
    }

    fn legacy_file(&self, key: &str) -> PathBuf {
        self.dir.join(format!("{key}.h5"))
    }

    /// The committed entry of `key`, if any. A file that cannot be read (it cannot be
    /// half-written, but it can be damaged by hand: every file carries a checksum) counts
    /// as absent and is redone.
    pub fn lookup(&self, key: &str) -> Option<Entry> {
        self.load(key).map(|(e, _)| e)
    }

    /// The committed entry of `key` and its results, if any (see [`lookup`](Self::lookup)).
    pub fn load(&self, key: &str) -> Option<(Entry, Stored)> {
        let f = self.dir.join(format!("{key}.run"));
        match std::fs::read(&f) {
            Ok(bytes) => {
                let (head, run) = decode(&bytes)?;
                let entry = Entry {
                    key: key.to_string(),
                    rows: serde_json::from_str(&head.summary).ok()?,
                    path: head.run,
                    source: head.run_source,
                    failed: head.failed,
                };
                Some((entry, Stored::Encoded(run)))
            }
            Err(_) => {
                let legacy = self.legacy_file(key);
                let entry = lookup_legacy(&legacy, key)?;
                Some((entry, Stored::Legacy(legacy)))
            }
        }
    }

    /// Commits a run prepared by [`Prepared::new`] under `key`, on any thread: no libhdf5
    /// call (the batch's workers commit in parallel), written beside and renamed, so the
    /// file is whole or absent. Gives the entry back with the prepared run, which the
    /// writer then puts into results.h5.
    pub fn commit(&self, key: &str, mut run: Prepared) -> Result<(Entry, Prepared), ReportError> {
        let f = self.dir.join(format!("{key}.run"));
        let err = |detail: String| ReportError {
            file: f.display().to_string(),
            detail,
        };
        let head = Head {
            run: run.path.clone(),
            run_source: run.source.clone(),
            failed: run.failed,
            summary: serde_json::to_string(&run.rows).map_err(|e| err(e.to_string()))?,
        };
        let bytes = encode(&head, &run.encoded).map_err(err)?;
        let replaced = std::fs::metadata(&f).map_or(0, |m| m.len());
        crate::report::write_atomic_released(&f, &bytes)?;
        run.journal_growth = (bytes.len() as u64).saturating_sub(replaced);
        let entry = Entry {
            key: key.to_string(),
            path: run.path.clone(),
            source: run.source.clone(),
            failed: run.failed,
            rows: run.rows.clone(),
        };
        Ok((entry, run))
    }

    /// Writes `<out>/results.h5` holding the runs of `entries` (from their files), through
    /// a temporary file renamed into place. Two runs with the same path from different
    /// archives: the second goes to `PATH@ARCHIVE`.
    pub fn assemble(
        &self,
        out: &Path,
        entries: &[Entry],
        settings: Option<&serde_json::Value>,
    ) -> Result<PathBuf, ReportError> {
        let w = ResultsFile::create(out, self.has_legacy_files())?;
        if let Some(s) = settings {
            w.write_settings(s)?;
        }
        // `SKELID_MERGE_PAUSE_MS`: a pause with results.h5.tmp begun, to rehearse a merge
        // stopped part-way (the tests use it).
        if let Some(ms) = std::env::var("SKELID_MERGE_PAUSE_MS")
            .ok()
            .and_then(|v| v.trim().parse::<u64>().ok())
        {
            std::thread::sleep(std::time::Duration::from_millis(ms));
        }
        for (e, dst) in entries.iter().zip(placements(entries)) {
            match self.load(&e.key) {
                Some((_, Stored::Encoded(run))) => w.write_encoded_as(&run, &dst)?,
                Some((_, Stored::Legacy(f))) => w.copy_run_from(&f, &e.path, &dst)?,
                None => {
                    return Err(ReportError {
                        file: self.file(&e.key).display().to_string(),
                        detail: "the committed run is missing or damaged: run the batch \
                                 again to redo it"
                            .into(),
                    })
                }
            }
        }
        w.finish()
    }
}

/// A journal file's bytes: [`MAGIC`], the head's length (u32 LE) and JSON, the encoded run
/// (postcard), then the BLAKE3 hash of everything before it.
fn encode(head: &Head, run: &EncodedRun) -> Result<Vec<u8>, String> {
    let head = serde_json::to_vec(head).map_err(|e| e.to_string())?;
    let mut out = MAGIC.to_vec();
    out.extend_from_slice(&(head.len() as u32).to_le_bytes());
    out.extend_from_slice(&head);
    let out = postcard::to_extend(run, out).map_err(|e| e.to_string())?;
    let mut out = out;
    let hash = blake3::hash(&out);
    out.extend_from_slice(hash.as_bytes());
    Ok(out)
}

/// The head and run of a journal file, or `None` when it is not one or is damaged.
fn decode(bytes: &[u8]) -> Option<(Head, EncodedRun)> {
    let (body, hash) = bytes.split_at_checked(bytes.len().checked_sub(32)?)?;
    if blake3::hash(body).as_bytes() != hash {
        return None;
    }
    let rest = body.strip_prefix(MAGIC.as_slice())?;
    let (len, rest) = rest.split_at_checked(4)?;
    let len = u32::from_le_bytes(len.try_into().ok()?) as usize;
    let (head, rest) = rest.split_at_checked(len)?;
    let head: Head = serde_json::from_slice(head).ok()?;
    let run: EncodedRun = postcard::from_bytes(rest).ok()?;
    Some((head, run))
}

/// The entry of a `<key>.h5` journal file written before the `.run` files.
fn lookup_legacy(f: &Path, key: &str) -> Option<Entry> {
    if !f.exists() {
        return None;
    }
    let file = hdf5::File::open(f).ok()?;
    let text = |name: &str| -> Option<String> {
        let a = file.attr(name).ok()?;
        let s: hdf5::types::VarLenUnicode = a.read_scalar().ok()?;
        Some(String::from_utf8_lossy(s.as_bytes()).into_owned())
    };
    let rows: Vec<SummaryRow> = serde_json::from_str(&text("summary")?).ok()?;
    Some(Entry {
        key: key.to_string(),
        path: text("run")?,
        source: text("run_source")?,
        failed: text("run_status")? == "failed",
        rows,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::report::ResultsWriter;

    #[test]
    fn runs_sharing_a_path_are_placed_beside_it_by_archive_file_name() {
        let entry = |source: &str, path: &str| Entry {
            key: String::new(),
            path: path.into(),
            source: source.into(),
            failed: false,
            rows: Vec::new(),
        };
        let entries = [
            entry("/data/a/run_1.h5", "/runs/r"),
            entry("/data/a/run_2.h5", "/runs/r"),
            entry("/data/b/run_2.h5", "/runs/r"),
            entry("/data/c/run_2.h5", "/runs/r"),
            entry("/data/c/run_2.h5", "/runs/r@run_2.h5~2x"),
            entry("rel/run_3.h5", "/runs/s"),
            entry("/data/bench.mat", "/"),
            entry("/other/bench.mat", "/"),
        ];
        assert_eq!(
            placements(&entries),
            [
                "/runs/r",
                "/runs/r@run_2.h5",
                "/runs/r@run_2.h5~2",
                "/runs/r@run_2.h5~3",
                "/runs/r@run_2.h5~2x",
                "/runs/s",
                "/bench",
                "/bench@bench.mat",
            ]
        );
    }

    fn prepared(path: &str) -> Prepared {
        let mut run = EncodedRun::new(path);
        run.str_attr("", "status", Status::Ok.as_str());
        run.f64_attr("", "sample_rate", 1000.0);
        run.group("wavelet");
        let x: Vec<f64> = (0..10_000).map(|i| (i as f64 * 0.01).sin()).collect();
        run.signal("", "time", &x, true);
        run.signal("wavelet", "short", &x[..10], true);
        run.bytes("wavelet", "valid", &vec![1u8; 10_000], 4);
        let mut outcome = RunOutcome::new(path.into(), "bench.h5".into());
        outcome.error = Some("no output".into());
        Prepared {
            encoded: run,
            rows: summary_rows(&outcome),
            path: path.into(),
            source: "bench.h5".into(),
            failed: false,
            journal_growth: 0,
        }
    }

    #[test]
    fn a_committed_run_loads_back_exactly_and_a_damaged_one_is_absent() {
        let dir = tempfile::tempdir().unwrap();
        let journal = Journal::open(dir.path()).unwrap();
        let run = prepared("/runs/r1");
        let want = run.encoded.clone();
        let (entry, committed) = journal.commit("k1", run).unwrap();
        assert!(journal.file("k1").ends_with("runs/k1.run"));
        let len = std::fs::metadata(journal.file("k1")).unwrap().len();
        assert_eq!(
            committed.journal_growth(),
            len,
            "a new file grows it by its length"
        );
        let (_, again) = journal.commit("k1", prepared("/runs/r1")).unwrap();
        assert_eq!(
            again.journal_growth(),
            0,
            "the same file replaced (--force)"
        );
        let (loaded, stored) = journal.load("k1").expect("committed");
        assert_eq!(
            (loaded.path.as_str(), loaded.source.as_str()),
            ("/runs/r1", "bench.h5")
        );
        assert_eq!(loaded.rows.len(), entry.rows.len());
        assert_eq!(loaded.rows[0].error, entry.rows[0].error);
        match stored {
            Stored::Encoded(run) => assert_eq!(run, want),
            Stored::Legacy(_) => panic!("a .run file is not legacy"),
        }
        // One flipped bit anywhere, or a truncation, and the run is redone.
        let f = journal.file("k1");
        let bytes = std::fs::read(&f).unwrap();
        for at in [0, 20, bytes.len() / 2, bytes.len() - 1] {
            let mut bad = bytes.clone();
            bad[at] ^= 1;
            std::fs::write(&f, &bad).unwrap();
            assert!(journal.lookup("k1").is_none(), "bit flipped at {at}");
        }
        std::fs::write(&f, &bytes[..bytes.len() - 5]).unwrap();
        assert!(journal.lookup("k1").is_none());
        assert!(journal.lookup("absent").is_none());
    }

    #[test]
    fn a_version_1_file_whose_chunks_this_version_would_misplace_is_absent() {
        let dir = tempfile::tempdir().unwrap();
        let journal = Journal::open(dir.path()).unwrap();
        journal.commit("k1", prepared("/runs/r1")).unwrap();
        let f = journal.file("k1");
        let bytes = std::fs::read(&f).unwrap();
        // The same file as version 1 wrote it: its magic, its checksum intact.
        let mut old = bytes[..bytes.len() - 32].to_vec();
        old[..MAGIC.len()].copy_from_slice(b"skelid-journal/1\n");
        let hash = blake3::hash(&old);
        old.extend_from_slice(hash.as_bytes());
        std::fs::write(&f, &old).unwrap();
        assert!(journal.lookup("k1").is_none());
        std::fs::write(&f, &bytes).unwrap();
        assert!(journal.lookup("k1").is_some());
    }

    #[test]
    fn an_hdf5_journal_file_of_an_earlier_version_is_still_read() {
        let dir = tempfile::tempdir().unwrap();
        let journal = Journal::open(dir.path()).unwrap();
        let run = prepared("/runs/old");
        // What commit wrote before the .run files.
        let w = ResultsWriter::create_at(&dir.path().join(RUNS_DIR).join("k2.h5")).unwrap();
        w.write_encoded(&run.encoded).unwrap();
        let summary = serde_json::to_string(&run.rows).unwrap();
        for (name, value) in [
            ("run", "/runs/old"),
            ("run_source", "bench.h5"),
            ("run_status", "ok"),
            ("summary", summary.as_str()),
        ] {
            w.set_root_attr(name, value).unwrap();
        }
        w.finish().unwrap();
        assert!(journal.file("k2").ends_with("runs/k2.h5"));
        let (entry, stored) = journal.load("k2").expect("legacy file found");
        assert_eq!(entry.path, "/runs/old");
        assert!(matches!(stored, Stored::Legacy(_)));
        // And results.h5 assembled from it holds the run.
        let out = journal.assemble(dir.path(), &[entry], None).unwrap();
        let f = hdf5::File::open(out).unwrap();
        let time: Vec<f64> = f.dataset("/runs/old/time").unwrap().read_raw().unwrap();
        assert_eq!(time.len(), 10_000);
        assert_eq!(time[100], (100.0f64 * 0.01).sin());
    }
}
