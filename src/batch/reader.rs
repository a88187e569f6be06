//! The batch's one reader: opens the archives in order, reads every run of this shard and
//! hands each to the workers through a bounded queue, so workers never touch an input
//! archive and compute never waits on a read.
//!
//! Isolated reading (the default of `skelid run`) happens in a child process of this
//! executable ([`READ_SUBCOMMAND`]) that streams the runs back over a pipe: libhdf5 crashes
//! or loops forever on some corrupt files, and no in-process handling catches a segfault.
//! One child reads archive after archive, so a campaign of a thousand files costs one
//! process start, not a thousand, and every sample is read once (the old per-file probe
//! read them all a second time before the work started). When the child dies or stalls on
//! an archive, that archive is recorded unreadable with the reason and a new child takes
//! the remaining ones; runs the dead child had already delivered stand.
//!
//! Protocol, child to parent, one frame after another: a little-endian `u32` length, a JSON
//! [`Frame`], then for a [`Frame::Run`] that was read the samples as little-endian `f64`
//! (input first when there is one, then output). A run whose channels lie in the archive as
//! plain float64 bytes ([`Archive::placed`]) is sent without its samples, only where they
//! lie and what the file was: the parent reads them from the file itself with one plain
//! read each (no libhdf5 in the parent), after checking that it opened the same file, and
//! checks them as the child would have. The pipe carried every sample twice through the
//! kernel and woke the other side every 64 kB: on this project's 2-core machine that cost
//! the child and the parent more CPU than libhdf5's reading, time that `--jobs 1` hides on
//! the second core and `--jobs 2` cannot. The price: those plain reads are the parent's,
//! outside the watchdog, so a file system that hangs exactly between the child's reading
//! of an archive's structure and the parent's reading of its samples hangs the batch.

use std::io::{BufRead, Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};

use super::Shard;
use crate::child::ChildCommand;
use crate::ingest::{Archive, IngestOptions, PlacedRun, Run, RunMeta};
use crate::inspect::crash_detail;
use crate::profile::Stage;

/// One message of the reader's stream.
// A frame is serialised once per run onto the reader's pipe and dropped: the run's
// metadata inline costs nothing worth a box.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Serialize, Deserialize)]
pub enum Frame {
    /// The archive (index into the list given) is open; its runs follow.
    Open {
        /// Archive index.
        archive: usize,
        /// Groups of the archive with datasets that are not runs.
        #[serde(default)]
        not_runs: Vec<crate::ingest::NotARun>,
        /// This shard's runs in the archive, known once it is open: the progress's total
        /// counts them before they are read.
        #[serde(default)]
        runs: Option<usize>,
    },
    /// One run of this shard; samples follow when `meta` is `Ok` and it is not `placed`.
    Run {
        /// Archive index.
        archive: usize,
        /// Group path.
        path: String,
        /// The run's metadata, or why it cannot be read.
        meta: Result<RunMeta, String>,
        /// Whether the run has input samples (sent before the output's, or placed).
        has_input: bool,
        /// Where the samples lie in the archive, when they are not sent: the parent reads
        /// them there.
        placed: Option<PlacedRun>,
    },
    /// A run of another shard (counted, not read).
    Skip {
        /// Archive index.
        archive: usize,
    },
    /// The archive is done; `error` when it could not be opened at all.
    Close {
        /// Archive index.
        archive: usize,
        /// Why the archive could not be opened.
        error: Option<String>,
    },
}

/// A run's samples as read: input (when the run has one), output.
pub type Samples = (Option<Vec<f64>>, Vec<f64>);

/// What the reader delivers.
pub enum Delivery {
    /// A run of this shard, or why it could not be read.
    Run {
        /// Archive file name as given.
        source: String,
        /// Group path.
        path: String,
        /// The run (boxed: a run's metadata is far larger than the other variant).
        run: Box<Result<Run, String>>,
    },
    /// An archive that could not be read (or not to the end), with the reason.
    Unreadable {
        /// The archive.
        file: PathBuf,
        /// Why.
        error: String,
    },
}

/// Counts the reader keeps while it reads, for the progress display and the manifest.
#[derive(Default)]
pub struct Counts {
    /// Runs seen in the archives so far, all shards (an unreadable archive counts one).
    pub runs_in_inputs: AtomicUsize,
    /// Deliveries of this shard so far.
    pub delivered: AtomicUsize,
    /// What the total is estimated from, changed together (see [`Tally`]).
    pub tally: Mutex<Tally>,
    /// Groups with datasets that are not runs, with their archive (as given).
    pub not_runs: std::sync::Mutex<Vec<(String, crate::ingest::NotARun)>>,
}

/// This shard's runs as far as the reader knows them, under one lock: an archive's opening
/// changes several of them, and a total read between two of the changes was one too high.
#[derive(Debug, Default, Clone, Copy)]
pub struct Tally {
    /// Runs known: an archive not yet opened counts one, an opened one the runs it
    /// announced, one the reading child died in the runs it delivered and one for its
    /// failure.
    pub known: usize,
    /// Archives neither opened nor found unreadable yet.
    pub unopened: usize,
    /// Archives opened.
    pub opened: usize,
    /// The runs of this shard the opened archives announced together.
    pub announced: usize,
}

impl Tally {
    /// The total projected: each archive not yet opened at the mean of those opened (its
    /// one in `known` replaced), exact once every archive is open.
    pub fn projected(&self) -> usize {
        if self.opened == 0 {
            return self.known;
        }
        let mean = self.announced as f64 / self.opened as f64;
        self.known.saturating_sub(self.unopened) + (self.unopened as f64 * mean).round() as usize
    }
}

impl Counts {
    /// The best guess of this shard's total while reading ([`Tally::projected`]), never
    /// below the runs delivered. Before 2026-12-07 the archive being read counted one, so
    /// one archive of 1000 runs showed a total one ahead of the runs done all night, and
    /// ten of 100 runs a total of 109 while the first was read.
    pub fn estimate(&self) -> usize {
        let tally = *self.tally.lock().unwrap_or_else(|p| p.into_inner());
        tally
            .projected()
            .max(self.delivered.load(Ordering::Relaxed))
    }

    /// Changes the tally, under its lock.
    fn tally(&self, change: impl FnOnce(&mut Tally)) {
        change(&mut self.tally.lock().unwrap_or_else(|p| p.into_inner()));
    }
}

/// The archive a reading child is in: the runs it announced (this shard's), those it has
/// delivered, and the last one's path.
#[derive(Debug, Clone, Default)]
struct Reading {
    announced: Option<usize>,
    delivered: usize,
    last: Option<String>,
}

/// Why the reader stopped early: the consumer went away.
#[derive(Debug)]
pub struct Stopped;

/// Reads `files` in order and calls `deliver` for each run and each unreadable archive;
/// stops early when `deliver` says so. `isolate`: the executable to run the reading child
/// of and the time one step of it may take, opening an archive or reading a run (not
/// counting the parent's own handling of what it sent: a placed run's read, and the time
/// `deliver` blocks).
pub fn read_all(
    files: &[PathBuf],
    options: &IngestOptions,
    shard: Option<Shard>,
    isolate: Option<(&ChildCommand, Duration)>,
    counts: &Counts,
    deliver: &mut dyn FnMut(Delivery) -> Result<(), Stopped>,
) -> Result<(), Stopped> {
    counts.tally(|t| {
        t.known = files.len();
        t.unopened = files.len();
    });
    if let Some((command, timeout)) = isolate {
        let mut next = 0;
        while next < files.len() {
            match read_in_child(command, &files[next..], options, timeout, counts, deliver)? {
                ChildEnd::Finished => break,
                // The child could not be started: read in-process rather than not at all.
                ChildEnd::NotStarted => {
                    return read_in_process(&files[next..], options, shard, counts, deliver)
                }
                ChildEnd::Died {
                    done,
                    detail,
                    reading,
                } => {
                    next += done;
                    let file = &files[next];
                    let e = crate::ingest::IngestError::Corrupt {
                        file: file.display().to_string(),
                        run: None,
                        detail,
                    };
                    deliver(unreadable(counts, file, e.to_string(), reading.as_ref()))?;
                    next += 1;
                }
            }
        }
        Ok(())
    } else {
        read_in_process(files, options, shard, counts, deliver)
    }
}

/// Reads in this process (trusted files, tests) through the same frames the child sends.
fn read_in_process(
    files: &[PathBuf],
    options: &IngestOptions,
    shard: Option<Shard>,
    counts: &Counts,
    deliver: &mut dyn FnMut(Delivery) -> Result<(), Stopped>,
) -> Result<(), Stopped> {
    let mut stopped = false;
    let mut assemble = Assembler::new(files, counts, options);
    serve(files, options, shard, false, &mut |frame, samples| {
        if stopped {
            return false;
        }
        if let Some(d) = assemble.frame(frame, samples) {
            stopped = deliver(d).is_err();
        }
        !stopped
    });
    if stopped {
        Err(Stopped)
    } else {
        Ok(())
    }
}

/// Turns frames into deliveries and keeps the counts.
struct Assembler<'a> {
    files: &'a [PathBuf],
    counts: &'a Counts,
    /// Archives of this list finished.
    done: usize,
    /// The dataset names, for a placed run's errors.
    options: &'a IngestOptions,
    /// The archive whose placed runs are being read, kept open between its runs.
    open: Option<(usize, std::fs::File)>,
    /// The archive being read, once its child has opened it.
    reading: Option<Reading>,
}

impl<'a> Assembler<'a> {
    fn new(files: &'a [PathBuf], counts: &'a Counts, options: &'a IngestOptions) -> Self {
        Assembler {
            files,
            counts,
            done: 0,
            options,
            open: None,
            reading: None,
        }
    }

    /// Why the child was stopped after `timeout` without a frame: which step hung.
    fn hang_detail(&self, timeout: Duration) -> String {
        let step = match &self.reading {
            None => "opening it".to_string(),
            Some(r) if r.announced == Some(r.delivered) => {
                format!("closing it after its {} run(s)", r.delivered)
            }
            Some(r) => {
                let of = r.announced.map_or(String::new(), |n| format!(" of {n}"));
                match &r.last {
                    None => format!("reading its first run{of}"),
                    Some(path) => format!(
                        "reading its run {}{of}, the one after {path}",
                        r.delivered + 1
                    ),
                }
            }
        };
        format!(
            "{step}, the reading child went {} s without progress; libhdf5 loops on some \
             corrupt files (a run that is very large, or a slow disk, needs a longer \
             --timeout); the runs it had read stand, the rest of this archive is not read",
            timeout.as_secs()
        )
    }

    fn frame(&mut self, frame: Frame, samples: Option<Samples>) -> Option<Delivery> {
        let c = self.counts;
        match frame {
            Frame::Open {
                archive,
                not_runs,
                runs,
            } => {
                // The archive's one among the runs known becomes its runs (the child always
                // announces them; an archive that did not would count one until read).
                c.tally(|t| {
                    t.unopened = t.unopened.saturating_sub(1);
                    if let Some(n) = runs {
                        t.known = t.known + n - 1;
                        t.opened += 1;
                        t.announced += n;
                    }
                });
                self.reading = Some(Reading {
                    announced: runs,
                    ..Reading::default()
                });
                let file = self.files[archive].display().to_string();
                c.not_runs
                    .lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .extend(not_runs.into_iter().map(|g| (file.clone(), g)));
                None
            }
            Frame::Skip { .. } => {
                c.runs_in_inputs.fetch_add(1, Ordering::Relaxed);
                None
            }
            Frame::Run {
                archive,
                path,
                meta,
                placed,
                ..
            } => {
                c.runs_in_inputs.fetch_add(1, Ordering::Relaxed);
                c.delivered.fetch_add(1, Ordering::Relaxed);
                if let Some(r) = &mut self.reading {
                    r.delivered += 1;
                    r.last = Some(path.clone());
                }
                let run = meta.and_then(|meta| {
                    let (input, output) = match placed {
                        Some(p) => crate::profile::time(Stage::Read, || {
                            self.read_placed_run(archive, &meta, p)
                        })?,
                        None => samples.unwrap_or_default(),
                    };
                    Ok(Run {
                        meta,
                        input,
                        output,
                    })
                });
                Some(Delivery::Run {
                    source: self.files[archive].display().to_string(),
                    path,
                    run: Box::new(run),
                })
            }
            Frame::Close { archive, error } => {
                self.done = archive + 1;
                self.open = None;
                self.reading = None;
                error.map(|error| unreadable(c, &self.files[archive], error, None))
            }
        }
    }

    /// A placed run's samples, read from its archive (opened once for all its runs), or
    /// why they cannot be ([`crate::ingest::read_placed`]).
    fn read_placed_run(
        &mut self,
        archive: usize,
        meta: &RunMeta,
        placed: PlacedRun,
    ) -> Result<Samples, String> {
        let path = &self.files[archive];
        let name = path.display().to_string();
        if self.open.as_ref().is_none_or(|(a, _)| *a != archive) {
            let file = std::fs::File::open(path).map_err(|e| {
                crate::ingest::IngestError::Unreadable {
                    file: name.clone(),
                    detail: e.to_string(),
                }
                .to_string()
            })?;
            self.open = Some((archive, file));
        }
        let (_, file) = self.open.as_ref().expect("opened above");
        crate::ingest::read_placed(file, &name, meta, self.options, placed)
            .map_err(|e| e.to_string())
    }
}

/// The delivery of an archive that could not be read (to the end), counted: it stands for
/// one run of the inputs and is done with. `reading`: where its child died in it, when it
/// had opened it (its runs not delivered are no longer expected; the failure counts one).
fn unreadable(counts: &Counts, file: &Path, error: String, reading: Option<&Reading>) -> Delivery {
    counts.runs_in_inputs.fetch_add(1, Ordering::Relaxed);
    counts.delivered.fetch_add(1, Ordering::Relaxed);
    counts.tally(|t| match reading {
        None => t.unopened = t.unopened.saturating_sub(1),
        // Its runs not delivered no longer count; its failure does.
        Some(Reading {
            announced: Some(n),
            delivered,
            ..
        }) => t.known = (t.known + delivered + 1).saturating_sub(*n),
        Some(_) => {}
    });
    Delivery::Unreadable {
        file: file.to_path_buf(),
        error,
    }
}

/// Reads `files` in this process and hands every frame (with the run's samples) to `emit`,
/// which returns false to stop. The child's side of the protocol, and the in-process reader.
/// With `place` (the child), a run whose channels lie as plain float64 bytes goes without
/// its samples, only where they lie ([`Archive::placed`]), for the parent to read.
pub fn serve(
    files: &[PathBuf],
    options: &IngestOptions,
    shard: Option<Shard>,
    place: bool,
    emit: &mut dyn FnMut(Frame, Option<Samples>) -> bool,
) {
    for (i, f) in files.iter().enumerate() {
        let archive = match crate::profile::time(Stage::Read, || Archive::open(f, options)) {
            Ok(a) => a,
            Err(e) => {
                let close = Frame::Close {
                    archive: i,
                    error: Some(e.to_string()),
                };
                if !emit(close, None) {
                    return;
                }
                continue;
            }
        };
        let takes = |path: &str| shard.is_none_or(|s| s.takes(archive.file_name(), path));
        let open = Frame::Open {
            archive: i,
            not_runs: archive.not_runs.clone(),
            runs: Some(archive.runs.iter().filter(|e| takes(&e.path)).count()),
        };
        if !emit(open, None) {
            return;
        }
        for entry in &archive.runs {
            if !takes(&entry.path) {
                if !emit(Frame::Skip { archive: i }, None) {
                    return;
                }
                continue;
            }
            let placed = match &entry.meta {
                Ok(m) if place => archive.placed(m),
                _ => None,
            };
            let (meta, samples) = match (&entry.meta, placed) {
                (Ok(m), Some(_)) => (Ok(m.clone()), None),
                (meta, _) => {
                    let run = meta.as_ref().map_err(|e| e.to_string()).and_then(|m| {
                        crate::profile::time(Stage::Read, || archive.load(m))
                            .map_err(|e| e.to_string())
                    });
                    match run {
                        Ok(run) => (Ok(run.meta), Some((run.input, run.output))),
                        Err(e) => (Err(e), None),
                    }
                }
            };
            let has_input = match placed {
                Some(p) => p.input.is_some(),
                None => samples.as_ref().is_some_and(|s| s.0.is_some()),
            };
            let frame = Frame::Run {
                archive: i,
                path: entry.path.clone(),
                meta,
                has_input,
                placed,
            };
            if !emit(frame, samples) {
                return;
            }
        }
        // Closed before it is said closed: a close that hangs or crashes in libhdf5 is then
        // this archive's failure, not the next one's.
        drop(archive);
        if !emit(
            Frame::Close {
                archive: i,
                error: None,
            },
            None,
        ) {
            return;
        }
    }
}

/// Bytes buffered on each side of the reading child's pipe. Small on purpose: a frame's
/// header goes through the buffer, but a run's samples (hundreds of kilobytes) are longer,
/// so the buffers pass them straight between the pipe and the values instead of copying
/// them once more on each side, as a 1 MB buffer did.
const FRAME_BUFFER: usize = 64 << 10;

/// The child's main: archive paths from standard input, frames to standard output.
pub fn serve_stdio(options: &IngestOptions, shard: Option<Shard>) -> std::io::Result<()> {
    let files: Vec<PathBuf> = std::io::stdin()
        .lock()
        .lines()
        .collect::<std::io::Result<Vec<String>>>()?
        .into_iter()
        .filter(|l| !l.is_empty())
        .map(PathBuf::from)
        .collect();
    let mut out = std::io::BufWriter::with_capacity(FRAME_BUFFER, std::io::stdout().lock());
    let mut failure = None;
    // `SKELID_READ_PAUSE_MS`: each run read this much slower, to rehearse `--timeout` on a
    // slow disk (the tests use it).
    let pause = std::env::var("SKELID_READ_PAUSE_MS")
        .ok()
        .and_then(|v| v.trim().parse::<u64>().ok())
        .map(Duration::from_millis);
    serve(&files, options, shard, true, &mut |frame, samples| {
        if let (Some(pause), Frame::Run { .. }) = (pause, &frame) {
            std::thread::sleep(pause);
        }
        match write_frame(&mut out, &frame, samples.as_ref()) {
            Ok(()) => true,
            Err(e) => {
                // The parent went away (a stopped batch): nothing left to do.
                failure = Some(e);
                false
            }
        }
    });
    match failure {
        Some(e) => Err(e),
        None => out.flush(),
    }
}

fn write_frame(
    out: &mut impl Write,
    frame: &Frame,
    samples: Option<&Samples>,
) -> std::io::Result<()> {
    let header = serde_json::to_vec(frame).map_err(std::io::Error::other)?;
    out.write_all(&(header.len() as u32).to_le_bytes())?;
    out.write_all(&header)?;
    if let Some((input, output)) = samples {
        for v in input.iter().chain(std::iter::once(output)) {
            out.write_all(&(v.len() as u64).to_le_bytes())?;
            // The samples' bytes as they lie in memory where that is little-endian (one
            // copy, not 60 000 calls: a tenth of the reader's CPU time).
            if cfg!(target_endian = "little") {
                out.write_all(bytemuck::cast_slice(v))?;
            } else {
                for x in v {
                    out.write_all(&x.to_le_bytes())?;
                }
            }
        }
    }
    // Each frame reaches the parent at once: its watchdog measures progress by them.
    out.flush()
}

/// Reads one frame; `None` at a clean end of the stream.
fn read_frame(inp: &mut impl Read) -> std::io::Result<Option<(Frame, Option<Samples>)>> {
    let mut len = [0u8; 4];
    match inp.read_exact(&mut len) {
        Ok(()) => {}
        Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof => return Ok(None),
        Err(e) => return Err(e),
    }
    let mut header = vec![0u8; u32::from_le_bytes(len) as usize];
    inp.read_exact(&mut header)?;
    let frame: Frame = serde_json::from_slice(&header).map_err(std::io::Error::other)?;
    let samples = match &frame {
        Frame::Run {
            meta: Ok(_),
            has_input,
            placed: None,
            ..
        } => {
            let input = if *has_input {
                Some(read_vector(inp)?)
            } else {
                None
            };
            Some((input, read_vector(inp)?))
        }
        _ => None,
    };
    Ok(Some((frame, samples)))
}

fn read_vector(inp: &mut impl Read) -> std::io::Result<Vec<f64>> {
    let mut n = [0u8; 8];
    inp.read_exact(&mut n)?;
    let n = u64::from_le_bytes(n) as usize;
    // Read straight into the values, little-endian bits put in order where need be.
    let mut v = vec![0f64; n];
    inp.read_exact(bytemuck::cast_slice_mut(&mut v))?;
    if cfg!(target_endian = "big") {
        for x in &mut v {
            *x = f64::from_bits(u64::from_le(x.to_bits()));
        }
    }
    Ok(v)
}

/// How one reading child ended.
enum ChildEnd {
    /// Every archive given to it was read.
    Finished,
    /// It could not be started.
    NotStarted,
    /// It died (or was stopped) after finishing `done` archives; `detail` says how, and
    /// `reading` where it was in the next one when it had opened it.
    Died {
        done: usize,
        detail: String,
        reading: Option<Reading>,
    },
}

/// Time the child's current step (opening an archive, reading one run) has taken, not
/// counting the time the parent spent on what the child sent before (reading a placed
/// run's samples, handing runs on): the child then waits on a full pipe through no fault of
/// its own, or is ahead, which costs it nothing either.
struct Clock {
    /// When the step began; `None` while the parent handles what the child sent.
    since: Option<Instant>,
    finished: bool,
    timed_out: bool,
}

/// The environment variable that gives the reader child the batch's process id.
pub const BATCH_PID: &str = "SKELID_BATCH_PID";

fn read_in_child(
    command: &ChildCommand,
    files: &[PathBuf],
    options: &IngestOptions,
    timeout: Duration,
    counts: &Counts,
    deliver: &mut dyn FnMut(Delivery) -> Result<(), Stopped>,
) -> Result<ChildEnd, Stopped> {
    let mut cmd = Command::new(&command.exe);
    cmd.args(&command.args);
    // Whom the child is to die with: it checks that its parent is still this process
    // once it has asked the kernel to kill it when the parent ends.
    cmd.env(BATCH_PID, std::process::id().to_string());
    let child = cmd
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn();
    let Ok(mut child) = child else {
        return Ok(ChildEnd::NotStarted);
    };
    let mut stdin = child.stdin.take().expect("piped stdin");
    let mut stdout =
        std::io::BufReader::with_capacity(FRAME_BUFFER, child.stdout.take().expect("piped"));
    let mut stderr = child.stderr.take().expect("piped stderr");
    let list: String = files.iter().map(|f| format!("{}\n", f.display())).collect();
    // The child reads its whole list before it writes anything, so this cannot deadlock.
    let feeder = std::thread::spawn(move || {
        let _ = stdin.write_all(list.as_bytes());
    });
    let err_tail = std::thread::spawn(move || {
        let mut buf = Vec::new();
        let _ = stderr.read_to_end(&mut buf);
        buf
    });
    let child = Arc::new(Mutex::new(child));
    let clock = Arc::new(Mutex::new(Clock {
        since: Some(Instant::now()),
        finished: false,
        timed_out: false,
    }));
    let watchdog = {
        let (child, clock) = (Arc::clone(&child), Arc::clone(&clock));
        std::thread::spawn(move || loop {
            std::thread::sleep(Duration::from_millis(20));
            let mut c = clock.lock().unwrap_or_else(|p| p.into_inner());
            if c.finished {
                return;
            }
            let running = c.since.map_or(Duration::ZERO, |s| s.elapsed());
            if running > timeout {
                c.timed_out = true;
                c.finished = true;
                let _ = child.lock().unwrap_or_else(|p| p.into_inner()).kill();
                return;
            }
        })
    };
    let set = |f: &dyn Fn(&mut Clock)| f(&mut clock.lock().unwrap_or_else(|p| p.into_inner()));
    let mut assemble = Assembler::new(files, counts, options);
    let mut result = Ok(());
    let mut broken = false;
    loop {
        match crate::profile::time(Stage::Read, || read_frame(&mut stdout)) {
            Ok(Some((frame, samples))) => {
                // Every frame is progress: the next step (opening an archive, reading a
                // run) starts a clock of its own. Until 2026-12-07 only a new archive did,
                // so `--timeout` bounded a whole archive, and one holding a campaign of
                // large runs was cut off part-way as if libhdf5 had hung on it. What follows
                // is the parent's own work (a placed run's samples read from the archive,
                // the hand-over to the workers): the clock stands still meanwhile.
                set(&|c| c.since = None);
                if let Some(d) = assemble.frame(frame, samples) {
                    result = deliver(d);
                }
                set(&|c| c.since = Some(Instant::now()));
                if result.is_err() {
                    break;
                }
            }
            Ok(None) => break,
            Err(_) => {
                broken = true;
                break;
            }
        }
    }
    let timed_out = {
        let mut c = clock.lock().unwrap_or_else(|p| p.into_inner());
        c.finished = true;
        c.timed_out
    };
    let _ = watchdog.join();
    let status = {
        let mut ch = child.lock().unwrap_or_else(|p| p.into_inner());
        if result.is_err() || broken {
            let _ = ch.kill();
        }
        ch.wait()
    };
    let _ = feeder.join();
    let err = err_tail.join().unwrap_or_default();
    result?;
    let done = assemble.done;
    if done == files.len() {
        return Ok(ChildEnd::Finished);
    }
    let detail = if timed_out {
        assemble.hang_detail(timeout)
    } else {
        match status {
            Ok(s) => crash_detail(s, &err),
            Err(e) => format!("libhdf5 crashed reading it ({e})"),
        }
    };
    Ok(ChildEnd::Died {
        done,
        detail,
        reading: assemble.reading,
    })
}

#[cfg(test)]
mod tests {
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
        opened_runs
            + failures
            + (unopened as f64 * opened_runs as f64 / opened as f64).round() as usize
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

    /// A reading child that dies part-way through an archive leaves its runs delivered and
    /// one failure: the runs it announced and never sent no longer count, and the total
    /// ends exact.
    #[test]
    fn a_child_dying_in_an_archive_leaves_its_delivered_runs_and_one_failure() {
        let files = [PathBuf::from("a.h5"), PathBuf::from("b.h5")];
        let (counts, options) = (Counts::default(), IngestOptions::default());
        counts.tally(|t| {
            t.known = 2;
            t.unopened = 2;
        });
        let mut assemble = Assembler::new(&files, &counts, &options);
        let open = |archive, runs| Frame::Open {
            archive,
            not_runs: Vec::new(),
            runs: Some(runs),
        };
        let run = |archive, path: &str| Frame::Run {
            archive,
            path: path.into(),
            meta: Err("not read in this test".into()),
            has_input: false,
            placed: None,
        };
        assemble.frame(open(0, 5), None);
        assert_eq!(counts.estimate(), 5 + 5, "b.h5 projected at a.h5's 5 runs");
        for p in ["/r1", "/r2"] {
            assert!(assemble.frame(run(0, p), None).is_some());
        }
        let hung = assemble.hang_detail(Duration::from_secs(7));
        println!("{hung}");
        assert!(
            hung.starts_with("reading its run 3 of 5, the one after /r2"),
            "{hung}"
        );
        // The child died: a.h5's failure is delivered, a new child opens b.h5.
        let _ = unreadable(&counts, &files[0], "died".into(), assemble.reading.as_ref());
        let mut assemble = Assembler::new(&files[1..], &counts, &options);
        assemble.frame(open(0, 3), None);
        for p in ["/r1", "/r2", "/r3"] {
            assemble.frame(run(0, p), None);
        }
        let hung = assemble.hang_detail(Duration::from_secs(7));
        assert!(hung.starts_with("closing it after its 3 run(s)"), "{hung}");
        assert!(assemble
            .frame(
                Frame::Close {
                    archive: 0,
                    error: None
                },
                None
            )
            .is_none());
        assert_eq!(counts.delivered.load(Ordering::Relaxed), 6);
        assert_eq!(
            counts.estimate(),
            6,
            "2 runs and a failure of a.h5, 3 runs of b.h5"
        );
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
        serve(&files, &options, None, true, &mut |frame, samples| {
            if let Frame::Run { .. } = frame {
                assert!(samples.is_none(), "placed, not sent");
                sent.push(frame);
            }
            true
        });
        let frame = sent.pop().expect("one run");
        let counts = Counts::default();
        let deliver = |frame| match Assembler::new(&files, &counts, &options).frame(frame, None) {
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
}
