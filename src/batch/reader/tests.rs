//! The reader's parent and child sides driven frame by frame, against counts worked out
//! by hand.

use std::path::Path;

use super::restart::{Death, How};
use super::*;

/// An archive of `runs` runs of 1000 samples each, named `r1`, `r2`, ….
fn archive_of(path: &Path, runs: usize) {
    let f = hdf5::File::create(path).unwrap();
    let x: Vec<f64> = (0..1000).map(|i| (i as f64 * 0.03).sin()).collect();
    for r in 1..=runs {
        let g = f.create_group(&format!("r{r}")).unwrap();
        g.new_attr::<f64>()
            .create("sample_rate")
            .unwrap()
            .write_scalar(&1000.0)
            .unwrap();
        for name in ["input", "output"] {
            g.new_dataset_builder().with_data(&x).create(name).unwrap();
        }
    }
}

/// The total projected while reading, written out: the opened archives' runs, the
/// failures, and the mean of the opened archives for each archive not yet opened.
fn projected(opened_runs: usize, failures: usize, unopened: usize, opened: usize) -> usize {
    opened_runs + failures + (unopened as f64 * opened_runs as f64 / opened as f64).round() as usize
}

/// Counts as `read_all` starts them for `archives` archives.
fn counts_for(archives: usize) -> Counts {
    let counts = Counts::default();
    counts.tally(|t| {
        t.known = archives;
        t.unopened = archives;
    });
    counts
}

/// The frame of an archive (index `archive`) opened with this shard's `paths` among
/// `entries` runs of every shard.
fn opened(archive: usize, paths: Vec<String>, entries: usize) -> Frame {
    Frame::Open {
        archive,
        not_runs: Vec::new(),
        paths,
        entries,
    }
}

/// `/r1` … `/rN`.
fn names(n: usize) -> Vec<String> {
    (1..=n).map(|r| format!("/r{r}")).collect()
}

/// The frame of a run whose metadata is not the test's concern.
fn run_frame(archive: usize, path: &str) -> Frame {
    Frame::Run {
        archive,
        path: path.into(),
        meta: Err("not read in this test".into()),
        error_kind: Some("corrupt".into()),
        has_input: false,
        placed: None,
    }
}

/// The progress's total counts an open archive by the runs it holds, not as one: read
/// run by run, a single archive of many runs showed a total one ahead of the runs done.
/// Archives not yet opened count at the mean of those opened, an unreadable one at one;
/// a shard counts only its own runs; the total is exact once every archive is open.
#[test]
fn the_total_counts_the_open_archives_runs_before_they_are_read() {
    let dir = tempfile::tempdir().unwrap();
    let (a, b) = (dir.path().join("a.h5"), dir.path().join("b.h5"));
    archive_of(&a, 5);
    archive_of(&b, 3);
    let files = [a.clone(), b.clone(), dir.path().join("missing.h5")];
    let estimates = |shard: Option<Shard>| {
        let counts = Counts::default();
        let mut seen = Vec::new();
        let options = IngestOptions::default();
        read_all(&files, &options, shard, None, &counts, &mut |d| {
            let source = match d {
                Delivery::Run { source, .. } => source,
                Delivery::Unreadable { file, .. } => file.display().to_string(),
            };
            seen.push((
                crate::journal::base_name(&source).to_string(),
                counts.estimate(),
            ));
            Ok(())
        })
        .unwrap();
        (seen, counts.estimate())
    };
    let expect = |in_a: usize, in_b: usize, file: &str| match file {
        // a.h5 open: its runs, b.h5 and missing.h5 one each, projected at a's mean.
        "a.h5" => projected(in_a, 0, 2, 1),
        "b.h5" => projected(in_a + in_b, 0, 1, 2),
        _ => in_a + in_b + 1,
    };
    let (seen, total) = estimates(None);
    println!("{seen:?}");
    assert_eq!(total, 9, "5 + 3 runs and the unreadable archive");
    assert_eq!(seen.len(), 9);
    for (file, estimate) in &seen {
        assert_eq!(*estimate, expect(5, 3, file), "{file}: {seen:?}");
    }
    assert_eq!((expect(5, 3, "a.h5"), expect(5, 3, "b.h5")), (15, 12));
    let shard = Shard { index: 1, count: 2 };
    let ours = |f: &Path, n: usize| {
        let name = f.file_name().unwrap().to_str().unwrap();
        (1..=n)
            .filter(|r| shard.takes(name, &format!("/r{r}")))
            .count()
    };
    let (seen, total) = estimates(Some(shard));
    let (in_a, in_b) = (ours(&a, 5), ours(&b, 3));
    println!("shard {shard}: {in_a} of a.h5, {in_b} of b.h5: {seen:?}");
    assert_eq!(total, in_a + in_b + 1);
    for (file, estimate) in &seen {
        assert_eq!(*estimate, expect(in_a, in_b, file), "{file}: {seen:?}");
    }
}

/// A reading child that dies on a run fails that run alone: a new child takes the
/// archive up after it, until three runs in a row have stopped a child, when the rest of
/// the archive is given up as one failure. A child that dies opening the archive again
/// gives it up too. Every run announced is delivered once (read, or failed), and the
/// total stays exact throughout.
#[test]
fn a_child_dying_on_a_run_fails_that_run_and_a_new_child_goes_on_after_it() {
    let files = [PathBuf::from("a.h5"), PathBuf::from("b.h5")];
    let (counts, options) = (counts_for(2), IngestOptions::default());
    let open = |archive, runs| opened(archive, names(runs), runs);
    let run = run_frame;
    let mut seen: Vec<(String, String)> = Vec::new();
    let mut see = |d: Delivery| {
        seen.push(match d {
            Delivery::Run { path, run, .. } => (path, run.err().unwrap_or_default()),
            Delivery::Unreadable { error, .. } => ("unreadable".into(), error),
        })
    };
    // A child reads /r1 and /r2 of a.h5's 8 runs, and dies on /r3.
    let mut assemble = Assembler::new(&files, &counts, &options, None);
    assemble.frame(open(0, 8), None);
    assert_eq!(counts.estimate(), 8 + 8, "b.h5 projected at a.h5's 8 runs");
    for p in ["/r1", "/r2"] {
        see(assemble.frame(run(0, p), None).unwrap());
    }
    let hung = assemble.hang_detail(Duration::from_secs(7));
    println!("{hung}");
    assert!(
        hung.starts_with("reading its run 3 of 8, the one after /r2"),
        "{hung}"
    );
    let died =
        |a: Assembler, how: &str| after_death(&counts, &files[0], how.into(), a.reading, a.resumed);
    let (failed, mut resume) = died(assemble, "libhdf5 crashed reading it (signal 11)");
    failed.into_iter().for_each(&mut see);
    assert_eq!(counts.estimate(), 16, "the failed run was one of the 8");
    // The next child passes over /r1-/r3 (its opening no news), reads /r4, dies on /r5;
    // two more die on /r6 and /r7: three in a row, so /r8 is given up.
    let mut assemble = Assembler::new(&files, &counts, &options, resume.take());
    assemble.frame(open(0, 8), None);
    see(assemble.frame(run(0, "/r4"), None).unwrap());
    let hung = assemble.hang_detail(Duration::from_secs(7));
    assert!(
        hung.starts_with("reading its run 5 of 8, the one after /r4"),
        "{hung}"
    );
    let (failed, resumed) = died(assemble, &hung);
    failed.into_iter().for_each(&mut see);
    resume = resumed;
    for _ in 0..2 {
        let mut assemble = Assembler::new(&files, &counts, &options, resume.take());
        assemble.frame(open(0, 8), None);
        let (failed, resumed) = died(assemble, "libhdf5 crashed reading it (signal 6)");
        failed.into_iter().for_each(&mut see);
        resume = resumed;
    }
    assert!(resume.is_none(), "a.h5 given up");
    assert_eq!(counts.estimate(), 8 + 8, "7 runs and a failure for /r8");
    // b.h5: /r1 read, /r2 stops the child, the next dies opening it again.
    let mut assemble = Assembler::new(&files[1..], &counts, &options, None);
    assemble.frame(open(0, 3), None);
    see(assemble.frame(run(0, "/r1"), None).unwrap());
    let death = |a: Assembler| {
        after_death(
            &counts,
            &files[1],
            "libhdf5 crashed reading it (signal 11)".into(),
            a.reading,
            a.resumed,
        )
    };
    let (failed, resume) = death(assemble);
    failed.into_iter().for_each(&mut see);
    let (failed, resume) = death(Assembler::new(&files[1..], &counts, &options, resume));
    failed.into_iter().for_each(&mut see);
    assert!(resume.is_none());
    for (path, error) in &seen {
        println!("{path}: {error}");
    }
    let paths: Vec<&str> = seen.iter().map(|(p, _)| p.as_str()).collect();
    assert_eq!(
        paths,
        [
            "/r1",
            "/r2",
            "/r3",
            "/r4",
            "/r5",
            "/r6",
            "/r7",
            "unreadable"
        ]
        .into_iter()
        .chain(["/r1", "/r2", "unreadable"])
        .collect::<Vec<_>>()
    );
    let error = |i: usize| seen[i].1.as_str();
    assert!(
        error(2).starts_with(
            "a.h5: truncated or corrupt HDF5 file (run /r3): libhdf5 crashed reading it \
             (signal 11); the archive's other runs"
        ) && error(2).ends_with("the archive's other runs are read by a new reading child"),
        "{}",
        error(2)
    );
    assert!(error(4).contains(
        "reading its run 5 of 8, the one after /r4, the reading child went 7 s without progress"
    ));
    assert!(
        error(6).ends_with("(signal 6); the reading child is not started on this archive again"),
        "{}",
        error(6)
    );
    assert!(
        error(7).ends_with("3 runs in a row stopped the reading child, the last /r7, so the archive's 1 run(s) after it are not read"),
        "{}",
        error(7)
    );
    assert!(
        error(10).contains("(opening it again after a run stopped the reading child), so the archive's 1 run(s) after /r2 are not read"),
        "{}",
        error(10)
    );
    assert_eq!(counts.delivered.load(Ordering::Relaxed), 11);
    assert_eq!(counts.estimate(), 11, "8 of a.h5 and 3 of b.h5, each once");
}

/// The ends of a resumed archive: a child that finds it gone or changed when it opens it
/// again gives up the rest of it (once, however its child goes on); a death on the
/// archive's last run counts the other shards' runs after it without a new child. The
/// counts stay exact throughout.
#[test]
fn a_resumed_archive_gone_changed_or_at_its_last_run_is_counted_once() {
    let files = [PathBuf::from("a.h5"), PathBuf::from("b.h5")];
    let options = IngestOptions::default();
    let open = |paths, entries| opened(0, paths, entries);
    let run = |path: &str| run_frame(0, path);
    // A child read /r1 of a.h5's 4 runs and died on /r2: where a new child starts.
    let died_on_r2 = |counts: &Counts| {
        counts.tally(|t| {
            t.known = 2;
            t.unopened = 2;
        });
        let mut a = Assembler::new(&files, counts, &options, None);
        a.frame(open(names(4), 4), None);
        a.frame(run("/r1"), None).unwrap();
        let (failed, resume) =
            after_death(counts, &files[0], "crashed".into(), a.reading, a.resumed);
        assert_eq!(failed.len(), 1);
        resume.expect("a new child goes on")
    };
    let error_of = |d: Option<Delivery>| match d {
        Some(Delivery::Unreadable { error, .. }) => error,
        _ => panic!("the archive given up"),
    };

    // Gone: the new child cannot open it. /r3 and /r4 become one failure.
    let counts = Counts::default();
    let mut a = Assembler::new(&files, &counts, &options, Some(died_on_r2(&counts)));
    let close = Frame::Close {
        archive: 0,
        error: Some("a.h5: cannot read the file: No such file or directory".into()),
        error_kind: Some("unreadable".into()),
    };
    let error = error_of(a.frame(close, None));
    println!("{error}");
    assert!(error.ends_with("No such file or directory (opening it again after a run stopped the reading child), so the archive's 2 run(s) after /r2 are not read"), "{error}");
    assert!(a.resumed.is_none());
    assert_eq!(counts.delivered.load(Ordering::Relaxed), 3);
    // b.h5 projected at the 4 runs a.h5 announced.
    assert_eq!(
        counts.estimate(),
        3 + 4,
        "/r1, /r2 and a failure of a.h5, and b.h5"
    );

    // Changed: opened again, it holds other runs. Given up once; the child's frames of
    // it after that are no news, and its death in it delivers nothing more.
    let counts = Counts::default();
    let mut a = Assembler::new(&files, &counts, &options, Some(died_on_r2(&counts)));
    let other = vec![
        "/r0".to_string(),
        "/r1".into(),
        "/r2".into(),
        "/r3".into(),
        "/r4".into(),
    ];
    let error = error_of(a.frame(open(other, 5), None));
    println!("{error}");
    assert!(
        error.contains("the archive changed while it was read"),
        "{error}"
    );
    assert!(a.frame(run("/r3"), None).is_none());
    let (more, resume) = after_death(&counts, &files[0], "crashed".into(), a.reading, a.resumed);
    assert!(more.is_empty() && resume.is_none());
    assert_eq!(counts.delivered.load(Ordering::Relaxed), 3);
    assert_eq!(counts.estimate(), 3 + 4);

    // The last run: a shard's 2 runs among 5 entries, the fourth entry the last of them;
    // the child dies on it. The fifth, another shard's, is counted without a new child.
    let counts = counts_for(1);
    let mut a = Assembler::new(&files[..1], &counts, &options, None);
    a.frame(open(vec!["/r2".into(), "/r4".into()], 5), None);
    a.frame(Frame::Skip { archive: 0 }, None);
    a.frame(run("/r2"), None).unwrap();
    a.frame(Frame::Skip { archive: 0 }, None);
    let (failed, resume) = after_death(&counts, &files[0], "crashed".into(), a.reading, a.resumed);
    let Some(Delivery::Run { path, run, .. }) = failed.into_iter().next() else {
        panic!("the run failed");
    };
    let error = run.err().unwrap();
    assert_eq!(path, "/r4");
    assert!(
        error.ends_with("crashed; it was the archive's last run"),
        "{error}"
    );
    assert!(resume.is_none(), "no new child for it");
    assert_eq!(counts.runs_in_inputs.load(Ordering::Relaxed), 5);
    assert_eq!(counts.estimate(), 2);
}

/// A child that dies closing an archive whose runs of this shard were all dealt with
/// fails nothing: the archive is noted damaged with how the child died, the other shards'
/// runs it had not passed yet are counted, and the next archive is read by a new child.
/// A death on a run of it before is said; an archive without runs of this shard too.
#[test]
fn a_child_dying_while_closing_an_archive_read_to_the_end_fails_nothing() {
    let files = [PathBuf::from("a.h5"), PathBuf::from("b.h5")];
    let options = IngestOptions::default();
    let run = |path: &str| run_frame(0, path);
    let damaged = |counts: &Counts| counts.damaged.lock().unwrap().clone();

    // A shard's /r1 and /r3 of 4 entries: both read, /r2 passed, the child hangs closing it
    // before /r4's frame (another shard's).
    let counts = counts_for(2);
    let mut a = Assembler::new(&files, &counts, &options, None);
    a.frame(opened(0, vec!["/r1".into(), "/r3".into()], 4), None);
    a.frame(run("/r1"), None).unwrap();
    a.frame(Frame::Skip { archive: 0 }, None);
    a.frame(run("/r3"), None).unwrap();
    let hung = a.hang_detail(Duration::from_secs(7));
    assert!(hung.starts_with("closing it after its 2 run(s), the reading child went 7 s"));
    let (failed, resume) = after_death(&counts, &files[0], hung.into(), a.reading, a.resumed);
    assert!(failed.is_empty() && resume.is_none());
    assert_eq!(counts.runs_in_inputs.load(Ordering::Relaxed), 4);
    assert_eq!(counts.delivered.load(Ordering::Relaxed), 2);
    assert_eq!(counts.estimate(), 2 + 2, "b.h5 projected at a.h5's 2 runs");
    let noted = damaged(&counts);
    println!("{noted:?}");
    assert_eq!(noted.len(), 1);
    assert_eq!(noted[0].archive, "a.h5");
    assert!(noted[0].detail.starts_with(
        "read to the end (its 2 run(s) read), but not closed: closing it after its 2 \
         run(s), the reading child went 7 s without progress and was stopped; libhdf5 loops \
         on some corrupt files (a slow disk needs a longer --timeout). That costs no run"
    ));

    // /r2 of 3 killed a child, a new one read /r3 and crashed closing the archive.
    let counts = counts_for(1);
    let mut a = Assembler::new(&files[..1], &counts, &options, None);
    a.frame(opened(0, names(3), 3), None);
    a.frame(run("/r1"), None).unwrap();
    let (failed, resume) = after_death(&counts, &files[0], "crashed".into(), a.reading, a.resumed);
    assert_eq!(failed.len(), 1);
    let mut a = Assembler::new(&files[..1], &counts, &options, resume);
    a.frame(opened(0, names(3), 3), None);
    a.frame(run("/r3"), None).unwrap();
    let (failed, resume) = after_death(
        &counts,
        &files[0],
        "crashed again".into(),
        a.reading,
        a.resumed,
    );
    assert!(failed.is_empty() && resume.is_none());
    assert_eq!(counts.estimate(), 3);
    assert_eq!(counts.runs_in_inputs.load(Ordering::Relaxed), 3);
    let noted = damaged(&counts);
    assert!(noted[0].detail.starts_with(
        "read to the end (its 3 run(s) dealt with, 1 of them failed on their own), but not \
         closed: crashed again."
    ));

    // None of the archive's 2 runs is this shard's.
    let counts = counts_for(1);
    let mut a = Assembler::new(&files[..1], &counts, &options, None);
    a.frame(opened(0, Vec::new(), 2), None);
    a.frame(Frame::Skip { archive: 0 }, None);
    let (failed, _) = after_death(&counts, &files[0], "crashed".into(), a.reading, a.resumed);
    assert!(failed.is_empty());
    assert_eq!(counts.runs_in_inputs.load(Ordering::Relaxed), 2);
    assert_eq!(counts.estimate(), 0);
    assert!(damaged(&counts)[0]
        .detail
        .starts_with("read to the end (none of its runs is"));

    // skelid's own stream broken at the close (the child still running): not the file's
    // doing, so the archive fails as before and nothing is called damaged.
    let counts = counts_for(1);
    let mut a = Assembler::new(&files[..1], &counts, &options, None);
    a.frame(opened(0, names(2), 3), None);
    a.frame(run("/r1"), None).unwrap();
    a.frame(run("/r2"), None).unwrap();
    let broke = Death {
        detail: "the reading child's stream broke (bad frame); please report it".into(),
        how: How::StreamBroke,
        first_run: false,
    };
    let (failed, resume) = after_death(&counts, &files[0], broke, a.reading, a.resumed);
    assert!(resume.is_none() && damaged(&counts).is_empty());
    let [Delivery::Unreadable {
        error, error_kind, ..
    }] = &failed[..]
    else {
        panic!("the archive failed: {}", failed.len());
    };
    assert_eq!(error_kind, "corrupt");
    assert!(
        error.ends_with("please report it; its 2 run(s) were dealt with"),
        "{error}"
    );
    assert_eq!(
        counts.runs_in_inputs.load(Ordering::Relaxed),
        3 + 1,
        "the entries, the failure"
    );
    assert_eq!(counts.estimate(), 3, "2 runs and the failure");
}

/// A crash after other runs of the same child may be theirs (libhdf5's heap corrupted by an
/// earlier run): the run is read again, first thing, by a new child, once. Read there, it
/// is delivered like any run; a crash there too fails it, said so; a hang is never
/// retried (it would cost `--timeout` again). Other shards' runs the dead child had passed
/// since its last run are sent again and counted once.
#[test]
fn a_run_crashed_on_after_others_is_read_again_first_by_a_new_child() {
    let files = [PathBuf::from("a.h5")];
    let options = IngestOptions::default();
    let run = |path: &str| run_frame(0, path);
    let later = |detail: &str, how: How| Death {
        detail: detail.into(),
        how,
        first_run: false,
    };
    // This shard's /r1 and /r3 of 4 entries: /r1 read, /r2 passed (another shard's), the
    // child crashes on /r3. A new child reads it first, and it is sound.
    let counts = counts_for(1);
    let mut a = Assembler::new(&files, &counts, &options, None);
    a.frame(opened(0, vec!["/r1".into(), "/r3".into()], 4), None);
    a.frame(run("/r1"), None).unwrap();
    a.frame(Frame::Skip { archive: 0 }, None);
    let crash = later("libhdf5 crashed reading it (signal 11)", How::Crashed);
    let (failed, resume) = after_death(&counts, &files[0], crash, a.reading, a.resumed);
    assert!(failed.is_empty(), "nothing failed yet");
    let resume = resume.expect("a new child reads /r3 again");
    assert_eq!((resume.delivered, resume.seen, resume.resent), (1, 2, 1));
    assert_eq!(
        resume.retrying(),
        Some("libhdf5 crashed reading it (signal 11)")
    );
    assert_eq!(
        counts.runs_in_inputs.load(Ordering::Relaxed),
        2,
        "/r1, and /r2 once"
    );
    let notes = counts.notes.lock().unwrap().clone();
    assert_eq!(notes, ["a.h5: the reading child crashed on /r3 after reading other runs (libhdf5 crashed reading it (signal 11)); a new reading child reads /r3 again, first"]);
    let mut a = Assembler::new(&files, &counts, &options, Some(resume));
    a.frame(opened(0, vec!["/r1".into(), "/r3".into()], 4), None);
    a.frame(Frame::Skip { archive: 0 }, None);
    let Some(Delivery::Run { path, .. }) = a.frame(run("/r3"), None) else {
        panic!("/r3 delivered");
    };
    assert_eq!(path, "/r3");
    a.frame(Frame::Skip { archive: 0 }, None);
    assert!(a
        .frame(
            Frame::Close {
                archive: 0,
                error: None,
                error_kind: None
            },
            None
        )
        .is_none());
    assert_eq!(counts.runs_in_inputs.load(Ordering::Relaxed), 4);
    assert_eq!(counts.delivered.load(Ordering::Relaxed), 2);
    assert_eq!(counts.estimate(), 2);

    // Crashed on again by the new child (its first run): failed, and said so.
    let counts = counts_for(1);
    let mut a = Assembler::new(&files, &counts, &options, None);
    a.frame(opened(0, names(3), 3), None);
    a.frame(run("/r1"), None).unwrap();
    let crash = later("libhdf5 crashed reading it (signal 11)", How::Crashed);
    let (failed, resume) = after_death(&counts, &files[0], crash, a.reading, a.resumed);
    assert!(failed.is_empty());
    let mut a = Assembler::new(&files, &counts, &options, resume);
    a.frame(opened(0, names(3), 3), None);
    let (failed, resume) = after_death(
        &counts,
        &files[0],
        "libhdf5 crashed reading it (signal 11)".into(),
        a.reading,
        a.resumed,
    );
    let [Delivery::Run {
        path, run: read, ..
    }] = &failed[..]
    else {
        panic!("/r2 failed");
    };
    let error = read.as_ref().as_ref().err().unwrap();
    assert_eq!(path, "/r2");
    assert!(error.contains("(signal 11) (a new reading child, reading it first after another had crashed on it, was stopped by it too); the archive's other runs are read by a new reading child"), "{error}");
    let resume = resume.expect("/r3 read by a new child");
    assert_eq!((resume.delivered, resume.died_in_row), (2, 1));

    // A hang after other runs fails the run at once.
    let counts = counts_for(1);
    let mut a = Assembler::new(&files, &counts, &options, None);
    a.frame(opened(0, names(3), 3), None);
    a.frame(run("/r1"), None).unwrap();
    let hang = later("reading its run 2 of 3, …", How::Hung);
    let (failed, _) = after_death(&counts, &files[0], hang, a.reading, a.resumed);
    assert_eq!(failed.len(), 1, "/r2 failed without a retry");

    // A child that had closed an archive before crashes on this one's first run, and no
    // new child can be started to read it again: the whole archive is given up, and the
    // message says none of it was read, and why the run was to be read again.
    let counts = counts_for(1);
    let mut a = Assembler::new(&files, &counts, &options, None);
    a.frame(opened(0, names(3), 3), None);
    let crash = later("crashed", How::Crashed);
    let (failed, resume) = after_death(&counts, &files[0], crash, a.reading, a.resumed);
    assert!(failed.is_empty());
    let Delivery::Unreadable { error, .. } = not_restarted(&counts, &files[0], &resume.unwrap())
    else {
        panic!("given up");
    };
    assert!(error.ends_with("so none of the archive's 3 run(s) is read (/r1 among them, to be read again first by a new child: a child that had read other runs crashed on it, crashed)"), "{error}");
    assert_eq!(counts.estimate(), 1, "the archive as one failure");
}

/// Deaths not in a row still end an archive: the tenth gives up the rest, each read run
/// between them resetting only the count in a row. Where no new child can be started,
/// the rest of the archive is given up at once, as unreadable, not read in-process.
#[test]
fn ten_deaths_in_an_archive_give_up_its_rest_and_so_does_no_child() {
    let files = [PathBuf::from("a.h5")];
    let (counts, options) = (counts_for(1), IngestOptions::default());
    let run = |path: &str| run_frame(0, path);
    let mut resume = None;
    let mut failures = Vec::new();
    // Every other run kills the child: /r2, /r4, … /r20 is the tenth.
    for k in 0..10 {
        let mut a = Assembler::new(&files, &counts, &options, resume.take());
        a.frame(opened(0, names(30), 30), None);
        a.frame(run(&format!("/r{}", 2 * k + 1)), None).unwrap();
        let (died, resumed) =
            after_death(&counts, &files[0], "crashed".into(), a.reading, a.resumed);
        failures.extend(died.into_iter().map(|d| match d {
            Delivery::Run { path, run, .. } => (path, run.err().unwrap()),
            Delivery::Unreadable { error, .. } => ("unreadable".into(), error),
        }));
        resume = resumed;
        assert_eq!(resume.is_some(), k < 9, "after death {}", k + 1);
    }
    let last = failures.last().unwrap();
    println!("{}", last.1);
    assert_eq!(failures.len(), 11, "ten runs and the rest");
    assert!(last.1.ends_with("10 of its runs stopped the reading child, the last /r20, so the archive's 10 run(s) after it are not read"), "{}", last.1);
    assert_eq!(counts.delivered.load(Ordering::Relaxed), 21);
    assert_eq!(
        counts.estimate(),
        21,
        "20 runs dealt with and the rest as one"
    );

    // No child to read on after /r2: the rest (28 runs) as one failure, counted exact.
    let counts = counts_for(1);
    let mut a = Assembler::new(&files, &counts, &options, None);
    a.frame(opened(0, names(30), 30), None);
    a.frame(run("/r1"), None).unwrap();
    let (_, resumed) = after_death(&counts, &files[0], "crashed".into(), a.reading, a.resumed);
    let Delivery::Unreadable { error, .. } = not_restarted(&counts, &files[0], &resumed.unwrap())
    else {
        panic!("the rest given up");
    };
    println!("{error}");
    assert_eq!(error, "a.h5: cannot read the file: no new reading child could be started after a run stopped the last, so the archive's 28 run(s) after /r2 are not read");
    assert_eq!(counts.estimate(), 3);
    assert_eq!(counts.delivered.load(Ordering::Relaxed), 3);
}

/// A child told to pass over the runs a child before it dealt with sends no frame for
/// them (nor for other shards' runs among them), and reads on from the next.
#[test]
fn a_new_child_passes_over_the_runs_dealt_with() {
    let dir = tempfile::tempdir().unwrap();
    let (a, b) = (dir.path().join("a.h5"), dir.path().join("b.h5"));
    archive_of(&a, 9);
    archive_of(&b, 2);
    let files = [a, b];
    let shard = Shard { index: 1, count: 2 };
    let frames = |shard: Option<Shard>, after: usize| {
        let mut frames = Vec::new();
        serve(
            &files,
            &IngestOptions::default(),
            shard,
            true,
            after,
            &mut |f, _| {
                frames.push(match f {
                    Frame::Open { archive, paths, .. } => format!("open {archive} {}", paths.len()),
                    Frame::Run { archive, path, .. } => format!("{archive}{path}"),
                    Frame::Skip { archive } => format!("skip {archive}"),
                    Frame::Close { archive, .. } => format!("close {archive}"),
                });
                true
            },
        );
        frames
    };
    assert_eq!(
        frames(None, 4),
        ["open 0 9", "0/r5", "0/r6", "0/r7", "0/r8", "0/r9", "close 0"]
            .into_iter()
            .chain(["open 1 2", "1/r1", "1/r2", "close 1"])
            .collect::<Vec<_>>()
    );
    // With a shard: the frames after its second run, as they came when read whole.
    let whole = frames(Some(shard), 0);
    let second = whole
        .iter()
        .enumerate()
        .filter(|(_, f)| f.starts_with("0/"))
        .nth(1);
    let (at, _) = second.expect("the shard has two runs of a.h5");
    let mut expected = vec![whole[0].clone()];
    expected.extend(whole[at + 1..].iter().cloned());
    println!("shard {shard}: {whole:?}");
    assert_eq!(frames(Some(shard), 2), expected);
}

/// A placed run whose archive was replaced after the child read it (an export that
/// writes a new file and renames it over the old one) is refused with the reason,
/// and the same frame over the unchanged file reads the run.
#[test]
fn a_placed_run_of_a_replaced_archive_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("a.h5");
    {
        let f = hdf5::File::create(&path).unwrap();
        let g = f.create_group("run").unwrap();
        g.new_attr::<f64>()
            .create("sample_rate")
            .unwrap()
            .write_scalar(&1000.0)
            .unwrap();
        let x: Vec<f64> = (0..1000).map(|i| (i as f64 * 0.03).sin()).collect();
        for name in ["input", "output"] {
            g.new_dataset_builder().with_data(&x).create(name).unwrap();
        }
    }
    let files = [path.clone()];
    let options = IngestOptions::default();
    let mut sent = Vec::new();
    serve(&files, &options, None, true, 0, &mut |frame, samples| {
        if let Frame::Run { .. } = frame {
            assert!(samples.is_none(), "placed, not sent");
            sent.push(frame);
        }
        true
    });
    let frame = sent.pop().expect("one run");
    let counts = Counts::default();
    let deliver = |frame| match Assembler::new(&files, &counts, &options, None).frame(frame, None) {
        Some(Delivery::Run { run, .. }) => run.map(|r| r.output.len()),
        _ => panic!("a run"),
    };
    let resent = |f: &Frame| serde_json::from_slice(&serde_json::to_vec(f).unwrap()).unwrap();
    assert_eq!(deliver(resent(&frame)), Ok(1000));
    let copy = dir.path().join("b.h5");
    std::fs::copy(&path, &copy).unwrap();
    std::fs::rename(&copy, &path).unwrap();
    let refused = deliver(frame).unwrap_err();
    assert!(
        refused.contains("changed while run /run was being read"),
        "{refused}"
    );
}

/// Every archive given up is recorded with what it counted in `runs_in_inputs` (exactly
/// what it added there), the runs its listing announced and this shard's runs left unread,
/// so that `skelid merge` can count shards that gave it up at different places: part-way
/// after three deaths in a row (another shard's run seen before), never opened, and at its
/// close when the child's stream broke.
#[test]
fn an_archive_given_up_is_recorded_with_its_counts() {
    let files = [PathBuf::from("a.h5")];
    let options = IngestOptions::default();
    let records = |counts: &Counts| counts.take_incomplete();
    let added = |counts: &Counts| counts.runs_in_inputs.load(Ordering::Relaxed);

    // This shard's /r1-/r5 among 8 entries: another shard's run, /r1 read, then /r2, /r3
    // and /r4 each stop a child: /r5 is left unread.
    let counts = counts_for(1);
    let mut a = Assembler::new(&files, &counts, &options, None);
    a.frame(opened(0, names(5), 8), None);
    a.frame(Frame::Skip { archive: 0 }, None);
    a.frame(run_frame(0, "/r1"), None).unwrap();
    let (_, mut resume) = after_death(&counts, &files[0], "crashed".into(), a.reading, None);
    for _ in 0..2 {
        let mut a = Assembler::new(&files, &counts, &options, resume.take());
        a.frame(opened(0, names(5), 8), None);
        let (_, next) = after_death(&counts, &files[0], "crashed".into(), a.reading, a.resumed);
        resume = next;
    }
    assert!(resume.is_none(), "given up");
    let [r] = &records(&counts)[..] else {
        panic!("one record")
    };
    assert_eq!(
        (
            r.archive.as_str(),
            r.runs_in_archive,
            r.counted,
            r.runs_not_read
        ),
        ("a.h5", Some(8), added(&counts), 1)
    );
    assert_eq!(r.counted, 1 + 4 + 1, "the skip, /r1-/r4, the failure");

    // Never opened: it counts one, its runs unknown.
    let counts = counts_for(1);
    let mut a = Assembler::new(&files, &counts, &options, None);
    let close = Frame::Close {
        archive: 0,
        error: Some("a.h5: not an HDF5 file".into()),
        error_kind: Some("unreadable".into()),
    };
    assert!(matches!(
        a.frame(close, None),
        Some(Delivery::Unreadable { .. })
    ));
    let [r] = &records(&counts)[..] else {
        panic!("one record")
    };
    assert_eq!(
        (r.runs_in_archive, r.counted, r.runs_not_read),
        (None, 1, 0)
    );
    assert_eq!(added(&counts), 1);

    // Its 2 runs of 3 entries read, the stream broken at the close: every entry and the
    // failure counted (the third entry, another shard's, not yet seen), nothing unread.
    let counts = counts_for(1);
    let mut a = Assembler::new(&files, &counts, &options, None);
    a.frame(opened(0, names(2), 3), None);
    a.frame(run_frame(0, "/r1"), None).unwrap();
    a.frame(run_frame(0, "/r2"), None).unwrap();
    let broke = Death {
        detail: "the reading child's stream broke (bad frame); please report it".into(),
        how: How::StreamBroke,
        first_run: false,
    };
    let (failed, _) = after_death(&counts, &files[0], broke, a.reading, a.resumed);
    assert_eq!(failed.len(), 1);
    let [r] = &records(&counts)[..] else {
        panic!("one record")
    };
    assert_eq!(
        (r.runs_in_archive, r.counted, r.runs_not_read),
        (Some(3), added(&counts), 0)
    );
    assert_eq!(r.counted, 3 + 1);
}

/// A crash opening an archive is checked by a new child only where it followed other steps
/// of the same child, and once: not on a child's first step, not after a hang, not after
/// the retry; each retry and second death noted for the log. An archive whose retry finds
/// no child to start fails with the first crash, counted as one run of the inputs.
#[test]
fn a_crash_opening_an_archive_after_others_is_checked_once() {
    use super::restart::{not_reopened, open_again};
    let file = Path::new("b.h5");
    let death = |how: How, first_run: bool| Death {
        detail: "libhdf5 crashed opening it (signal 11)".into(),
        how,
        first_run,
    };
    let counts = counts_for(1);
    assert!(!open_again(
        &counts,
        file,
        &death(How::Crashed, true),
        false
    ));
    assert!(!open_again(&counts, file, &death(How::Hung, false), false));
    assert!(counts.notes.lock().unwrap().is_empty());
    assert!(open_again(
        &counts,
        file,
        &death(How::Crashed, false),
        false
    ));
    assert!(!open_again(&counts, file, &death(How::Crashed, true), true));
    let notes = counts.notes.lock().unwrap().clone();
    println!("{notes:#?}");
    assert_eq!(
        notes,
        [
            "b.h5: the reading child crashed opening it after reading other archives \
             (libhdf5 crashed opening it (signal 11)); a new reading child opens it again, first",
            "b.h5: the new reading child, opening it first, was stopped by it too (libhdf5 \
             crashed opening it (signal 11)): it is recorded unreadable"
        ]
    );

    let counts = counts_for(1);
    let Delivery::Unreadable { error, .. } = not_reopened(
        &counts,
        file,
        "libhdf5 crashed opening it (signal 11)".into(),
    ) else {
        panic!("the archive given up");
    };
    assert_eq!(
        error,
        "b.h5: truncated or corrupt HDF5 file: libhdf5 crashed opening it (signal 11)"
    );
    assert_eq!(counts.runs_in_inputs.load(Ordering::Relaxed), 1);
    assert_eq!(counts.estimate(), 1);
    let [r] = &counts.take_incomplete()[..] else {
        panic!("one record")
    };
    assert_eq!((r.runs_in_archive, r.counted), (None, 1));
    assert!(counts.notes.lock().unwrap()[0].contains("no new reading child could be started"));
}
