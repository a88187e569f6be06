//! `skelid merge`: the output folders of a `--shard K/N` batch joined into one, refusing
//! missing or doubled shards, runs in two shards and folders made with other settings. In:
//! shard folders; out: one folder as an unsharded run writes it.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use crate::journal::{base_name, Journal, RUNS_DIR};
use crate::report::ReportError;

use super::*;

/// Joins the output folders of the shards of one batch into `out` (drawing the first
/// `report_runs` runs in its report.html): refuses folders made
/// with different settings, a shard given twice or missing, a run present in two shards,
/// or a shard whose runs are not all committed.
pub fn merge(dirs: &[PathBuf], out: &Path, report_runs: usize) -> Result<BatchSummary, BatchError> {
    let bad = |m: String| BatchError::Merge(m);
    let mut manifests = Vec::new();
    for d in dirs {
        let f = d.join(MANIFEST);
        let text = std::fs::read_to_string(&f).map_err(|e| {
            bad(format!(
                "{}: {e} (is {} the output folder of a finished `skelid run`?)",
                f.display(),
                d.display()
            ))
        })?;
        let m: Manifest = serde_json::from_str(&text)
            .map_err(|e| bad(format!("{}: not a skelid manifest: {e}", f.display())))?;
        manifests.push((d.clone(), m));
    }
    let Some((_, first)) = manifests.first() else {
        return Err(bad("no folders given".into()));
    };
    let settings = first.settings.clone();
    let count = first.shard.map_or(1, |s| s.count);
    let mut seen_shards = BTreeMap::new();
    for (d, m) in &manifests {
        if m.settings != settings {
            return Err(bad(format!(
                "{} was made with other settings (skelid version, methods or options) than {}",
                d.display(),
                manifests[0].0.display()
            )));
        }
        if runs_listed(m) != runs_listed(first) {
            return Err(bad(format!(
                "{} saw {} runs in its inputs, {} saw {}: the shards were not given the same \
                 archives, an archive changed between them, or one could not open an archive \
                 that another read (see their skelid.log){}",
                d.display(),
                runs_listed(m),
                manifests[0].0.display(),
                runs_listed(first),
                given_up_in_one(m, first)
            )));
        }
        let s = m.shard.unwrap_or(Shard { index: 1, count: 1 });
        if s.count != count {
            return Err(bad(format!(
                "{} is shard {s}, others are of {count}",
                d.display()
            )));
        }
        if let Some(other) = seen_shards.insert(s.index, d.clone()) {
            return Err(bad(format!(
                "shard {s} is given twice: {} and {}",
                other.display(),
                d.display()
            )));
        }
    }
    let missing: Vec<String> = (1..=count)
        .filter(|k| !seen_shards.contains_key(k))
        .map(|k| format!("{k}/{count}"))
        .collect();
    if !missing.is_empty() {
        return Err(bad(format!(
            "shard(s) {} missing: run them (or pass their folders) before merging",
            missing.join(", ")
        )));
    }
    // The lowest shard's record of an archive every shard failed is the one kept, in
    // whatever order the folders were given.
    manifests.sort_by_key(|(_, m)| m.shard.map_or(1, |s| s.index));
    let first = &manifests[0].1;
    // Every shard is checked before the output folder is made: a refused merge leaves
    // nothing behind (it left the runs copied so far, 16 MB for nine campaign runs).
    let mut owner: BTreeMap<(String, String), PathBuf> = BTreeMap::new();
    let mut failures = std::collections::BTreeSet::new();
    let (mut entries, mut copies, mut runs) = (Vec::new(), Vec::new(), 0);
    for (d, m) in &manifests {
        let src = Journal::open(d)?;
        for r in &m.runs {
            // An archive no child could open is every shard's failure, the same error (its
            // journal key hashes it) in each: kept once. Failures that differ (two shards'
            // children gave it up at different runs, or two archives of one file name in
            // different folders) are each kept, placed beside one another.
            if r.path.starts_with(UNREADABLE) {
                if !failures.insert(r.key.clone()) {
                    continue;
                }
            } else if let Some(other) = owner.insert((r.source.clone(), r.path.clone()), d.clone())
            {
                return Err(bad(format!(
                    "run {} of {} is in both {} and {}",
                    r.path,
                    r.source,
                    other.display(),
                    d.display()
                )));
            } else {
                runs += 1;
            }
            let e = src.lookup(&r.key).ok_or_else(|| {
                bad(format!(
                    "{}: run {} is listed but its file {} is missing or unreadable (damaged, or written by another skelid version: rerun that shard with this one)",
                    d.display(),
                    r.path,
                    src.file(&r.key).display()
                ))
            })?;
            copies.push(src.file(&r.key));
            entries.push(e);
        }
    }
    let incomplete = incomplete_of(&manifests);
    let expected = runs_read(first, &manifests, &incomplete);
    if runs != expected {
        return Err(bad(format!(
            "the shards hold {runs} runs but their inputs list {expected} (less the runs \
             their reading children left unread)"
        )));
    }
    let journal = Journal::open(out)?;
    for from in copies {
        let dst = out
            .join(RUNS_DIR)
            .join(from.file_name().expect("a journal file has a name"));
        if !dst.exists() {
            std::fs::copy(&from, &dst).map_err(|e| ReportError {
                file: dst.display().to_string(),
                detail: e.to_string(),
            })?;
        }
    }
    let mut manifest = Manifest::new(
        settings,
        None,
        entries.len(),
        &mut entries,
        first.not_runs.clone(),
        first.settings_full.clone(),
    );
    // Every shard's child opens and closes every archive, but one may have died closing
    // it where another did not: every shard's are kept, each archive once, named with the
    // shard whose note it is (its counts are that shard's runs).
    for (_, m) in &manifests {
        for d in &m.damaged_archives {
            if !manifest
                .damaged_archives
                .iter()
                .any(|k| k.archive == d.archive)
            {
                let shard = m.shard.map(|s| format!("shard {s}: ")).unwrap_or_default();
                manifest.damaged_archives.push(DamagedArchive {
                    archive: d.archive.clone(),
                    detail: format!("{shard}{}", d.detail),
                });
            }
        }
    }
    manifest.incomplete_archives = incomplete.clone();
    let results = journal.assemble(out, &entries, manifest.settings_full.as_ref())?;
    let (rows, failed_runs) = write_outputs(&results, out, &entries, &manifest, report_runs)?;
    Ok(BatchSummary {
        rows,
        results,
        failed_runs,
        runs: entries.len(),
        skipped: 0,
        not_runs: manifest.not_runs.clone(),
        damaged: manifest.damaged_archives.clone(),
        incomplete,
        memory_held_back: None,
    })
}

/// The runs a shard's inputs would have counted had its reading child read every archive it
/// opened to the end: an archive given up counts the runs its listing announced (one where
/// it was never opened), not what it counted, which depends on where the child gave it up.
/// Equal in every shard of one batch, whatever each shard's children gave up.
fn runs_listed(m: &Manifest) -> usize {
    (m.incomplete_archives.iter()).fold(m.runs_in_inputs, |n, a| {
        (n + a.runs_in_archive.unwrap_or(1)).saturating_sub(a.counted)
    })
}

/// ", given up in one of them only: A, B" where the two shards' archives given up differ,
/// to say which to look at when their counts do not agree.
fn given_up_in_one(a: &Manifest, b: &Manifest) -> String {
    let names = |m: &Manifest| -> std::collections::BTreeSet<String> {
        (m.incomplete_archives.iter())
            .map(|i| base_name(&i.archive).to_string())
            .collect()
    };
    let (a, b) = (names(a), names(b));
    let odd: Vec<String> = a.symmetric_difference(&b).cloned().collect();
    if odd.is_empty() {
        String::new()
    } else {
        format!("; given up in one of the two only: {}", odd.join(", "))
    }
}

/// The archives given up in any shard, each shard's record named with its shard (its runs
/// not read are that shard's); an archive no shard could open, the same in each, once.
fn incomplete_of(manifests: &[(PathBuf, Manifest)]) -> Vec<IncompleteArchive> {
    let mut all: Vec<IncompleteArchive> = Vec::new();
    for (_, m) in manifests {
        for a in &m.incomplete_archives {
            let never_opened = a.runs_in_archive.is_none();
            if never_opened
                && (all.iter()).any(|k| k.runs_in_archive.is_none() && k.archive == a.archive)
            {
                continue;
            }
            all.push(IncompleteArchive {
                shard: m.shard.filter(|_| !never_opened),
                ..a.clone()
            });
        }
    }
    all
}

/// The runs (failures of whole archives aside) a merge of shards that agree on their
/// [`runs_listed`] holds: every run listed, less those each shard's children left unread
/// in the archives they gave up and the archives no shard could open (each listed as one).
/// An archive never opened is in every shard's records; one opened by a shard is not a
/// failure of them all, so the fewest any shard has is the count.
fn runs_read(
    first: &Manifest,
    manifests: &[(PathBuf, Manifest)],
    incomplete: &[IncompleteArchive],
) -> usize {
    let unread: usize = incomplete.iter().map(|a| a.runs_not_read).sum();
    let never_opened = (manifests.iter())
        .map(|(_, m)| {
            (m.incomplete_archives.iter())
                .filter(|a| a.runs_in_archive.is_none())
                .count()
        })
        .min()
        .unwrap_or(0);
    runs_listed(first).saturating_sub(unread + never_opened)
}
