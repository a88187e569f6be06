//! `skelid merge`: the output folders of a `--shard K/N` batch joined into one, refusing
//! missing or doubled shards, runs in two shards, folders made with other settings and
//! shards whose inputs list other runs. An archive failed in several shards (none could
//! open it) is kept once; one that a shard's reading children gave up part-way is joined
//! with what the other shards read of it, the runs left unread counted. In: shard
//! folders; out: one folder as an unsharded run writes it.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use crate::journal::{base_name, Journal, RUNS_DIR};
use crate::report::ReportError;

use super::*;

/// Joins the output folders of the shards of one batch into `out` (drawing the first
/// `report_runs` runs in its report.html): refuses folders made with different settings, a
/// shard given twice or missing, a run present in two shards, shards whose inputs list
/// different runs ([`runs_listed`]), a shard whose runs are not all committed, a shard
/// whose batch still runs, or an `out` another process is writing ([`FolderLock`]).
pub fn merge(dirs: &[PathBuf], out: &Path, report_runs: usize) -> Result<BatchSummary, BatchError> {
    let bad = |m: String| BatchError::Merge(m);
    let mut manifests = Vec::new();
    for d in dirs {
        // A shard still running (or run again) has the last run's manifest or none.
        lock::finished(d)?;
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
        if let Some(n) = m.merged_shards {
            return Err(bad(format!(
                "{} is a merged folder (of {n} shards): merge the shards' own folders",
                d.display()
            )));
        }
        if runs_listed(m) != runs_listed(first) {
            return Err(bad(format!(
                "{} lists {} runs in its inputs, {} lists {} (each archive given up counted at \
                 the runs its listing announced): the shards were not given the same \
                 archives, an archive's listing differs between them, or one could not open \
                 an archive that another read (see their skelid.log){}",
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
    let (unread, never_opened) = not_read(&manifests, &incomplete);
    let listed = runs_listed(first);
    if runs + unread + never_opened != listed {
        return Err(bad(format!(
            "the shards hold {runs} runs (archives' failures aside), but their inputs list \
             {listed}, of which {unread} were left unread by reading children that gave \
             their archive up and {never_opened} are archives that no shard could open: \
             one shard could not open an archive that another read? (see their skelid.log, \
             and run that shard again)"
        )));
    }
    let lock = lock::FolderLock::take(out, "merge")?;
    let mut log = Log::open(out)?;
    log.line(&format!(
        "merge: {} shard folder(s) ({})",
        dirs.len(),
        (dirs.iter().map(|d| d.display().to_string()))
            .collect::<Vec<_>>()
            .join(", ")
    ));
    if let Some(why) = &lock.unguarded {
        log.line(&format!("note: {why}"));
    }
    let journal = Journal::open(out)?;
    for from in copies {
        let dst = out
            .join(RUNS_DIR)
            .join(from.file_name().expect("a journal file has a name"));
        if !dst.exists() {
            link_or_copy(&from, &dst).map_err(|e| ReportError {
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
    manifest.merged_shards = Some(count);
    // The report's runs are drawn from their journal files on every core while results.h5
    // is assembled.
    let (results, drawn) = std::thread::scope(|s| {
        let assembling =
            s.spawn(|| journal.assemble(out, &entries, manifest.settings_full.as_ref()));
        let shown = entries.len().min(report_runs);
        (
            assembling.join(),
            page_runs(&journal, &entries, vec![None; shown]),
        )
    });
    let results = match results {
        Ok(r) => r?,
        Err(panic) => std::panic::resume_unwind(panic),
    };
    let rows = write_pages(out, &entries, &manifest, drawn)?;
    write_manifest(out, &manifest)?;
    let failed_runs = entries.iter().filter(|e| e.failed).count();
    log.line(&format!(
        "end: {} run(s), {failed_runs} failed, merged into {}",
        entries.len(),
        results.display()
    ));
    let summary = BatchSummary {
        rows,
        results,
        failed_runs,
        runs: entries.len(),
        skipped: 0,
        not_runs: manifest.not_runs.clone(),
        damaged: manifest.damaged_archives.clone(),
        incomplete,
        memory_held_back: None,
        unguarded: lock.unguarded.clone(),
    };
    // Let go with everything written.
    drop(lock);
    Ok(summary)
}

/// A shard's journal file into the merged folder: a hard link where both are on one file
/// system, else a copy written beside and renamed (whole or absent, as a commit is). A
/// journal file is never changed in place (a rerun renames a new one over its name), so the
/// link keeps what was merged whatever the shard's folder does next. The copies were most
/// of a merge's writing: 384 of 787 MB for 200 campaign runs.
fn link_or_copy(from: &Path, dst: &Path) -> std::io::Result<()> {
    if std::fs::hard_link(from, dst).is_ok() {
        return Ok(());
    }
    let tmp = crate::campaign::tmp_path(dst);
    let copied = std::fs::copy(from, &tmp).and_then(|_| std::fs::rename(&tmp, dst));
    if copied.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    copied
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

/// The archives given up in any shard, each shard's record named with its shard and its
/// log (its runs not read are that shard's); an archive a shard could not open, the same
/// in each, once.
fn incomplete_of(manifests: &[(PathBuf, Manifest)]) -> Vec<IncompleteArchive> {
    let mut all: Vec<IncompleteArchive> = Vec::new();
    for (d, m) in manifests {
        for a in &m.incomplete_archives {
            let never_opened = a.runs_in_archive.is_none();
            if never_opened
                && (all.iter()).any(|k| k.runs_in_archive.is_none() && k.archive == a.archive)
            {
                continue;
            }
            let opened = |_: &_| !never_opened;
            all.push(IncompleteArchive {
                shard: m.shard.filter(opened),
                shard_log: (m.shard.filter(opened))
                    .map(|_| d.join("skelid.log").display().to_string()),
                ..a.clone()
            });
        }
    }
    all
}

/// Of the runs the shards list: those left unread by reading children that gave their
/// archive up, and the archives no shard could open (each listed as one run). An archive
/// never opened is in every shard's records; one that some shard opened is not, so the
/// fewest any shard has is the count.
fn not_read(manifests: &[(PathBuf, Manifest)], incomplete: &[IncompleteArchive]) -> (usize, usize) {
    let unread = incomplete.iter().map(|a| a.runs_not_read).sum();
    let never_opened = (manifests.iter())
        .map(|(_, m)| {
            (m.incomplete_archives.iter())
                .filter(|a| a.runs_in_archive.is_none())
                .count()
        })
        .min()
        .unwrap_or(0);
    (unread, never_opened)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A journal file is linked where it can be, and copied whole where it cannot (another
    /// file system: /dev/shm's tmpfs against the temporary folder's disk), leaving no
    /// `.tmp`; a file that cannot be read leaves nothing.
    #[test]
    fn journal_files_are_linked_or_copied_whole() {
        use std::os::unix::fs::MetadataExt;
        let tmp = tempfile::tempdir().unwrap();
        let from = tmp.path().join("a.run");
        std::fs::write(&from, b"skelid-journal/2 and the rest").unwrap();
        let linked = tmp.path().join("linked.run");
        link_or_copy(&from, &linked).unwrap();
        let ino = |p: &Path| std::fs::metadata(p).unwrap().ino();
        assert_eq!(ino(&linked), ino(&from));
        let elsewhere = tempfile::tempdir_in("/dev/shm").expect("the test needs /dev/shm, a tmpfs");
        let dev = |p: &Path| std::fs::metadata(p).unwrap().dev();
        assert_ne!(
            dev(elsewhere.path()),
            dev(tmp.path()),
            "the test needs /dev/shm on another file system than {}",
            tmp.path().display()
        );
        let copied = elsewhere.path().join("a.run");
        link_or_copy(&from, &copied).unwrap();
        assert_eq!(
            std::fs::read(&copied).unwrap(),
            std::fs::read(&from).unwrap()
        );
        let names = |d: &Path| -> Vec<String> {
            (std::fs::read_dir(d).unwrap())
                .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
                .collect()
        };
        assert_eq!(names(elsewhere.path()), ["a.run"]);
        let missing = link_or_copy(
            &tmp.path().join("gone.run"),
            &elsewhere.path().join("b.run"),
        );
        assert!(missing.is_err());
        assert_eq!(names(elsewhere.path()), ["a.run"]);
    }

    /// Shard `k` of 2's manifest: `runs_in_inputs`, and its archives given up as
    /// (archive, runs its listing announced, counted, runs not read).
    fn shard(
        k: usize,
        runs_in_inputs: usize,
        given_up: &[(&str, Option<usize>, usize, usize)],
    ) -> (PathBuf, Manifest) {
        let shard = Some(Shard { index: k, count: 2 });
        let mut m = Manifest::new("s".into(), shard, runs_in_inputs, &mut [], Vec::new(), None);
        m.incomplete_archives = (given_up.iter())
            .map(
                |&(archive, runs_in_archive, counted, runs_not_read)| IncompleteArchive {
                    archive: archive.into(),
                    runs_in_archive,
                    counted,
                    runs_not_read,
                    shard,
                    shard_log: None,
                },
            )
            .collect();
        (PathBuf::from(format!("shard-{k}")), m)
    }

    /// Counted by hand: a.h5 (10 runs, 6 of shard 1) given up by shard 1 after 5 entries
    /// (3 of its runs unread) and by shard 2 after 8 (1 unread); b.h5 (5 runs) read by
    /// both; c.h5 (3 runs, 2 of shard 1's) failed at its close by shard 1's stream only;
    /// bad.h5 opened by neither. Both shards list 19 runs; 4 are unread and 1 an archive,
    /// so the 3 + 3 runs of a.h5, 5 of b.h5 and 3 of c.h5 read make 14.
    #[test]
    fn shards_that_gave_archives_up_at_different_places_list_the_same_runs() {
        let one = shard(
            1,
            6 + 5 + 4 + 1,
            &[
                ("a.h5", Some(10), 6, 3),
                ("c.h5", Some(3), 4, 0),
                ("bad.h5", None, 1, 0),
            ],
        );
        let two = shard(
            2,
            9 + 5 + 3 + 1,
            &[("a.h5", Some(10), 9, 1), ("bad.h5", None, 1, 0)],
        );
        assert_eq!(runs_listed(&one.1), 10 + 5 + 3 + 1);
        assert_eq!(runs_listed(&two.1), runs_listed(&one.1));
        let both = [one, two];
        let incomplete = incomplete_of(&both);
        assert_eq!(incomplete.len(), 4, "bad.h5 once: {incomplete:?}");
        assert_eq!(not_read(&both, &incomplete), (4, 1));
        assert_eq!(runs_listed(&both[0].1) - 4 - 1, 3 + 3 + 5 + 3);
        // An archive one shard opened and another could not is no archive of them all.
        let opened = shard(2, 9 + 5 + 3 + 1, &[("a.h5", Some(10), 9, 1)]);
        let mixed = [both[0].clone(), opened];
        assert_eq!(not_read(&mixed, &incomplete_of(&mixed)).1, 0);
        assert_eq!(
            given_up_in_one(&mixed[0].1, &mixed[1].1),
            "; given up in one of the two only: bad.h5, c.h5"
        );
    }
}
