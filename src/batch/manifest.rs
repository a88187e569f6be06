//! The batch's manifest (`manifest.json`): every input file with how it ended, every run
//! with its journal key and status, the groups that are not runs, the settings. Written at
//! the end of a batch and of a merge; read by `merge` and by resumes.

use crate::journal::Entry;
use crate::report::Status;

use super::*;

/// A group of an input archive that holds datasets but is not a run.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct GroupNotRun {
    /// Archive as given.
    pub archive: String,
    /// The group and its datasets.
    #[serde(flatten)]
    pub group: crate::ingest::NotARun,
}

/// An archive whose every run (of this shard) was read, but that the reading child died
/// closing (libhdf5 crashed, or hung past `--timeout`): its runs stand, each read and
/// checked before, and the file is likely damaged.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct DamagedArchive {
    /// Archive as given.
    pub archive: String,
    /// How the reading child died, and what that means for its runs.
    pub detail: String,
}

/// "damaged archive ARCHIVE: DETAIL", as the terminal, the log and the report say it.
impl std::fmt::Display for DamagedArchive {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "damaged archive {}: {}", self.archive, self.detail)
    }
}

/// The output folder's record of a batch: what was asked and which runs it holds.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct Manifest {
    /// `skelid-batch/1`.
    pub format: String,
    /// Settings fingerprint (version, methods, options).
    pub settings: String,
    /// The shard, when the batch was one.
    pub shard: Option<Shard>,
    /// Runs seen in the inputs before sharding (unreadable archives count one each).
    pub runs_in_inputs: usize,
    /// The runs of this folder.
    pub runs: Vec<ManifestRun>,
    /// The settings spelled out ([`crate::journal::settings_record`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub settings_full: Option<serde_json::Value>,
    /// Groups of the inputs that hold datasets but are not runs, so none goes unseen.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub not_runs: Vec<GroupNotRun>,
    /// Archives read to the end that the reading child died closing
    /// ([`DamagedArchive`]): no run is lost, but the files want checking.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub damaged_archives: Vec<DamagedArchive>,
}

/// One run of a manifest.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct ManifestRun {
    /// Archive file name.
    pub source: String,
    /// Run path.
    pub path: String,
    /// Journal key.
    pub key: String,
    /// `ok` or `failed`.
    pub status: Status,
}

impl Manifest {
    /// The manifest of a folder holding `entries`, which it puts in (archive, path) order
    /// for every output.
    pub(super) fn new(
        settings: String,
        shard: Option<Shard>,
        runs_in_inputs: usize,
        entries: &mut [Entry],
        not_runs: Vec<GroupNotRun>,
        settings_full: Option<serde_json::Value>,
    ) -> Manifest {
        entries.sort_by(|a, b| (&a.source, &a.path).cmp(&(&b.source, &b.path)));
        Manifest {
            format: "skelid-batch/1".into(),
            settings,
            shard,
            runs_in_inputs,
            not_runs,
            damaged_archives: Vec::new(),
            settings_full,
            runs: entries
                .iter()
                .map(|e| ManifestRun {
                    source: e.source.clone(),
                    path: e.path.clone(),
                    key: e.key.clone(),
                    status: if e.failed { Status::Failed } else { Status::Ok },
                })
                .collect(),
        }
    }
}

/// Manifest file name in an output folder.
pub const MANIFEST: &str = "manifest.json";
