//! The child's side of the stream: archives opened and their runs read one at a time, each
//! sent as a frame (or as where its samples lie), from where a child before it died.

use std::io::{BufRead, Write};
use std::path::PathBuf;
use std::time::Duration;

use super::frame::{write_frame, Frame, Samples, FRAME_BUFFER};
use crate::batch::Shard;
use crate::ingest::{Archive, IngestOptions};
use crate::profile::Stage;

/// Reads `files` in this process and hands every frame (with the run's samples) to `emit`,
/// which returns false to stop. The child's side of the protocol, and the in-process reader.
/// With `place` (the child), a run whose channels lie as plain float64 bytes goes without
/// its samples, only where they lie ([`Archive::placed`]), for the parent to read. `after`:
/// this shard's runs of the first archive that a child before this one dealt with (the last
/// of them the one it died on, unless that run is to be read again), passed over without a
/// frame.
pub fn serve(
    files: &[PathBuf],
    options: &IngestOptions,
    shard: Option<Shard>,
    place: bool,
    after: usize,
    emit: &mut dyn FnMut(Frame, Option<Samples>) -> bool,
) {
    for (i, f) in files.iter().enumerate() {
        // Listed only: each run's attributes are read with the run, so that libhdf5 crashing
        // on one run's corrupt attribute costs that run, not the archive.
        let opened = crate::profile::time(Stage::Read, || Archive::open_listed(f, options));
        let archive = match opened {
            Ok(a) => a,
            Err(e) => {
                let close = Frame::Close {
                    archive: i,
                    error: Some(e.to_string()),
                    error_kind: Some(e.kind().to_string()),
                };
                if !emit(close, None) {
                    return;
                }
                continue;
            }
        };
        let takes = |path: &str| shard.is_none_or(|s| s.takes(archive.file_name(), path));
        let paths: Vec<String> = (archive.listed.iter())
            .filter(|e| takes(&e.path))
            .map(|e| e.path.clone())
            .collect();
        let open = Frame::Open {
            archive: i,
            not_runs: archive.not_runs.clone(),
            paths,
            entries: archive.listed.len(),
        };
        if !emit(open, None) {
            return;
        }
        // The entries up to the `after`-th run of this shard, other shards' included: the
        // child before this one sent their frames.
        let mut passed = if i == 0 { after } else { 0 };
        for entry in &archive.listed {
            if passed > 0 {
                passed -= usize::from(takes(&entry.path));
                continue;
            }
            if !takes(&entry.path) {
                if !emit(Frame::Skip { archive: i }, None) {
                    return;
                }
                continue;
            }
            let meta = crate::profile::time(Stage::Read, || archive.read_meta(entry));
            let placed = match &meta {
                Ok(m) if place => archive.placed(m),
                _ => None,
            };
            let (meta, samples) = match (meta, placed) {
                (Ok(m), Some(_)) => (Ok(m), None),
                (meta, _) => {
                    let run =
                        meta.and_then(|m| crate::profile::time(Stage::Read, || archive.load(&m)));
                    match run {
                        Ok(run) => (Ok(run.meta), Some((run.input, run.output))),
                        Err(e) => (Err(e), None),
                    }
                }
            };
            let error_kind = meta.as_ref().err().map(|e| e.kind().to_string());
            let has_input = match placed {
                Some(p) => p.input.is_some(),
                None => samples.as_ref().is_some_and(|s| s.0.is_some()),
            };
            let frame = Frame::Run {
                archive: i,
                path: entry.path.clone(),
                meta: meta.map_err(|e| e.to_string()),
                error_kind,
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
                error_kind: None,
            },
            None,
        ) {
            return;
        }
    }
}

/// The child's main: from standard input, the runs of the first archive to pass over (a
/// decimal count on the first line, see [`serve`]'s `after`), then the archive paths one a
/// line; frames to standard output.
pub fn serve_stdio(options: &IngestOptions, shard: Option<Shard>) -> std::io::Result<()> {
    let mut lines = std::io::stdin()
        .lock()
        .lines()
        .collect::<std::io::Result<Vec<String>>>()?
        .into_iter();
    let after = lines
        .next()
        .and_then(|l| l.trim().parse::<usize>().ok())
        .ok_or_else(|| std::io::Error::other("the first line is not the runs to pass over"))?;
    let files: Vec<PathBuf> = lines.filter(|l| !l.is_empty()).map(PathBuf::from).collect();
    let mut out = std::io::BufWriter::with_capacity(FRAME_BUFFER, std::io::stdout().lock());
    let mut failure = None;
    // `SKELID_READ_PAUSE_MS`: each run read this much slower, to rehearse `--timeout` on a
    // slow disk (the tests use it).
    let pause = std::env::var("SKELID_READ_PAUSE_MS")
        .ok()
        .and_then(|v| v.trim().parse::<u64>().ok())
        .map(Duration::from_millis);
    let faults = Faults::from_env();
    let (mut runs_sent, mut closed) = (0, 0);
    serve(
        &files,
        options,
        shard,
        true,
        after,
        &mut |frame, samples| {
            match &frame {
                Frame::Run { path, .. } => {
                    if let Some(pause) = pause {
                        std::thread::sleep(pause);
                    }
                    faults.meet(path, runs_sent);
                    runs_sent += 1;
                }
                // Met after the archive was closed, before the parent hears it: to the
                // parent, a death while closing.
                Frame::Close { archive, .. } => {
                    if let Some(name) = files[*archive].file_name() {
                        faults.meet_closing(&name.to_string_lossy());
                    }
                    closed += 1;
                }
                // Met once the archive is open, before the parent hears it: to the parent,
                // a death while opening it.
                Frame::Open { archive, .. } => {
                    if let Some(name) = files[*archive].file_name() {
                        faults.meet_opening(&name.to_string_lossy(), runs_sent + closed);
                    }
                }
                _ => {}
            }
            match write_frame(&mut out, &frame, samples.as_ref()) {
                Ok(()) => true,
                Err(e) => {
                    // The parent went away (a stopped batch): nothing left to do.
                    failure = Some(e);
                    false
                }
            }
        },
    );
    match failure {
        Some(e) => Err(e),
        None => out.flush(),
    }
}

/// `SKELID_READ_FAULT=crash:PATH,hang:PATH,crash-after-others:PATH,crash-closing:NAME,
/// crash-opening:NAME,crash-opening-after-others:NAME`: the reading child aborts, or stops
/// answering, where it would send the run of that group path (in any archive), as when
/// libhdf5 crashes or loops on that run's corrupt data; aborts there only when it has sent
/// other runs before, as when an earlier run corrupted libhdf5's heap and this one is
/// innocent; aborts once it has closed the archive of that file name, as when libhdf5
/// crashes closing a damaged file; or aborts once it has opened the archive of that file
/// name (always, or only after other runs or archives, as when an earlier archive left
/// libhdf5's heap corrupted). To rehearse a campaign with a bad run or file (the tests use
/// it).
#[derive(Default)]
pub(super) struct Faults {
    crash: Vec<String>,
    hang: Vec<String>,
    crash_after_others: Vec<String>,
    crash_closing: Vec<String>,
    crash_opening: Vec<String>,
    crash_opening_after_others: Vec<String>,
}

impl Faults {
    fn from_env() -> Faults {
        let mut faults = Faults::default();
        let spec = std::env::var("SKELID_READ_FAULT").unwrap_or_default();
        for item in spec.split(',') {
            match item.split_once(':') {
                Some(("crash", path)) => faults.crash.push(path.to_string()),
                Some(("hang", path)) => faults.hang.push(path.to_string()),
                Some(("crash-closing", name)) => faults.crash_closing.push(name.to_string()),
                Some(("crash-opening", name)) => faults.crash_opening.push(name.to_string()),
                Some(("crash-opening-after-others", name)) => {
                    faults.crash_opening_after_others.push(name.to_string())
                }
                Some(("crash-after-others", path)) => {
                    faults.crash_after_others.push(path.to_string())
                }
                _ => {}
            }
        }
        faults
    }

    /// At the run `path`, the child having sent `sent` runs before.
    fn meet(&self, path: &str, sent: usize) {
        if self.crash.iter().any(|p| p == path)
            || (sent > 0 && self.crash_after_others.iter().any(|p| p == path))
        {
            crash();
        }
        if self.hang.iter().any(|p| p == path) {
            loop {
                std::thread::sleep(Duration::from_secs(3600));
            }
        }
    }

    /// At the opening of the archive `name`, the child having sent `steps` runs and closes
    /// before.
    fn meet_opening(&self, name: &str, steps: usize) {
        if self.crash_opening.iter().any(|n| n == name)
            || (steps > 0 && self.crash_opening_after_others.iter().any(|n| n == name))
        {
            crash();
        }
    }

    fn meet_closing(&self, name: &str) {
        if self.crash_closing.iter().any(|n| n == name) {
            crash();
        }
    }
}

/// Aborts, as libhdf5 does on corrupt data, leaving no core file where core dumps are on.
fn crash() -> ! {
    let none = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: setrlimit reads the struct given and touches no other memory.
    unsafe { libc::setrlimit(libc::RLIMIT_CORE, &none) };
    std::process::abort();
}
