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

/// An archive the reader gave up before its end, or could not open: recorded failed under
/// `/_unreadable/<file name>`, with what it counted in the manifest's `runs_in_inputs` and
/// what of it went unread, so that `skelid merge` can join shards whose reading children
/// gave it up at different places (or not at all), and say which runs are lost.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct IncompleteArchive {
    /// Archive as given.
    pub archive: String,
    /// The runs it holds, of every shard, as its listing said; `None` where it was never
    /// opened.
    pub runs_in_archive: Option<usize>,
    /// What it added to `runs_in_inputs`: the runs seen before it was given up, and one for
    /// its failure.
    pub counted: usize,
    /// This shard's runs of it that were neither read nor failed on their own (0 where it
    /// was never opened: its runs are not known).
    pub runs_not_read: usize,
    /// The shard whose reading child gave it up: none in an unsharded batch, nor in a
    /// merged one for an archive a shard could not open.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub shard: Option<Shard>,
    /// In a merged manifest, that shard's log (`DIR/skelid.log`), which says why.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub shard_log: Option<String>,
}

impl IncompleteArchive {
    /// Where runs of it went unread, what the terminal and the report say of it: "archive A
    /// was given up part-way (by shard K/N's reading child): N of its runs …".
    pub fn unread_note(&self) -> Option<String> {
        if self.runs_not_read == 0 {
            return None;
        }
        let (by, of) = match self.shard {
            Some(s) => (
                format!(" by shard {s}'s reading child"),
                "that shard's runs of it",
            ),
            None => (String::new(), "its runs"),
        };
        Some(format!(
            "archive {} was given up part-way{by}: {} of {of} are neither identified nor \
             failed in these results (why: its failure under /_unreadable/ and {})",
            self.archive,
            self.runs_not_read,
            self.shard_log.as_deref().unwrap_or("skelid.log"),
        ))
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
    /// Runs seen in the inputs before sharding: an archive no child could open counts one,
    /// one given up part-way the runs seen before and one for its failure. In a merged
    /// folder, the runs it holds.
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
    /// Archives given up before their end or never opened ([`IncompleteArchive`]), each
    /// also a failed `/_unreadable/` run.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub incomplete_archives: Vec<IncompleteArchive>,
    /// The shards a merged folder joined (`skelid merge`): such a folder is no shard.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub merged_shards: Option<usize>,
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
        entries.sort_by(order);
        Manifest {
            format: "skelid-batch/1".into(),
            settings,
            shard,
            runs_in_inputs,
            not_runs,
            damaged_archives: Vec::new(),
            incomplete_archives: Vec::new(),
            merged_shards: None,
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

/// The order of a folder's runs in every output: by archive, then path; then by key, so
/// that two archives of one file name in different folders that could not be read (whose
/// failures have the same name and path, `/_unreadable/bad.h5`) come in the same order
/// whichever worker finished first, and take the same places in results.h5
/// (`/_unreadable/bad.h5@bad.h5` beside the first) in every batch and merge.
pub(super) fn order(a: &Entry, b: &Entry) -> std::cmp::Ordering {
    (&a.source, &a.path, &a.key).cmp(&(&b.source, &b.path, &b.key))
}

/// Manifest file name in an output folder.
pub const MANIFEST: &str = "manifest.json";
