//! One reading child run and watched: started with its list, its frames handed to the
//! assembler, stopped when one step of it takes longer than `--timeout`, and how it ended.

use std::io::{Read, Write};
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use super::assemble::Assembler;
use super::frame::{read_frame, FRAME_BUFFER};
use super::restart::{Death, How, Reading};
use super::{Counts, Delivery, Stopped};
use crate::child::ChildCommand;
use crate::ingest::IngestOptions;
use crate::inspect::crash_detail;
use crate::profile::Stage;

/// How one reading child ended.
// One a child, returned once: the two readings inline cost nothing worth a box.
#[allow(clippy::large_enum_variant)]
pub(super) enum ChildEnd {
    /// Every archive given to it was read.
    Finished,
    /// It could not be started.
    NotStarted,
    /// It died (or was stopped) after finishing `done` archives; `death` says how,
    /// `reading` where it was in the next one when it had opened it, and `reopening` where
    /// it was to take that archive up when it died before opening it.
    Died {
        done: usize,
        death: Death,
        reading: Option<Reading>,
        reopening: Option<Reading>,
    },
}

/// Time the child's current step (opening an archive, reading one run) has taken, not
/// counting the time the parent spent on what the child sent before (reading a placed
/// run's samples, handing runs on): the child then waits on a full pipe through no fault of
/// its own, or is ahead, which costs it nothing either.
pub(super) struct Clock {
    /// When the step began; `None` while the parent handles what the child sent.
    since: Option<Instant>,
    finished: bool,
    timed_out: bool,
}

/// The environment variable that gives the reader child the batch's process id.
pub const BATCH_PID: &str = "SKELID_BATCH_PID";

/// One reading child over `files`, from where `start` says a child before it died in the
/// first.
pub(super) fn read_in_child(
    command: &ChildCommand,
    files: &[PathBuf],
    options: &IngestOptions,
    timeout: Duration,
    counts: &Counts,
    start: Option<Reading>,
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
    let after = start.as_ref().map_or(0, |r| r.delivered);
    let list: String = std::iter::once(format!("{after}\n"))
        .chain(files.iter().map(|f| format!("{}\n", f.display())))
        .collect();
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
    // Dropped when the stream ends, which wakes the watchdog at once: a watchdog asleep for
    // its next 20 ms held every child's end by 10 ms on average, which `skelid inspect`
    // (one child an archive) paid once per archive.
    let (stop, stopped) = std::sync::mpsc::channel::<()>();
    let watchdog = {
        let (child, clock) = (Arc::clone(&child), Arc::clone(&clock));
        std::thread::spawn(move || loop {
            if let Err(std::sync::mpsc::RecvTimeoutError::Disconnected) | Ok(()) =
                stopped.recv_timeout(Duration::from_millis(20))
            {
                return;
            }
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
    let mut assemble = Assembler::new(files, counts, options, start);
    let mut result = Ok(());
    let mut broken: Option<std::io::Error> = None;
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
                // An archive given up while this child reads it: the child is stopped
                // rather than left to read it to the end for nothing.
                let abandoned = assemble.reading.as_ref().is_some_and(|r| r.abandoned);
                if result.is_err() || abandoned {
                    break;
                }
            }
            Ok(None) => break,
            Err(e) => {
                broken = Some(e);
                break;
            }
        }
    }
    let timed_out = {
        let mut c = clock.lock().unwrap_or_else(|p| p.into_inner());
        c.finished = true;
        c.timed_out
    };
    drop(stop);
    let _ = watchdog.join();
    let (status, ended_itself) = {
        let mut ch = child.lock().unwrap_or_else(|p| p.into_inner());
        // Whether it had ended before it was stopped here: a stream broken part-way by a
        // child that died is that death, one broken by a child still running is ours.
        let ended_itself = matches!(ch.try_wait(), Ok(Some(_)));
        let abandoned = assemble.reading.as_ref().is_some_and(|r| r.abandoned);
        if result.is_err() || broken.is_some() || abandoned {
            let _ = ch.kill();
        }
        (ch.wait(), ended_itself)
    };
    let _ = feeder.join();
    let err = err_tail.join().unwrap_or_default();
    result?;
    let done = assemble.done;
    if done == files.len() {
        return Ok(ChildEnd::Finished);
    }
    // Every run dealt with: it died closing the archive; none opened: opening one.
    let step = match &assemble.reading {
        Some(r) if r.rest() == 0 => "closing it",
        Some(_) => "reading it",
        None => "opening it",
    };
    let (detail, how) = if timed_out {
        (assemble.hang_detail(timeout), How::Hung)
    } else if let (Some(e), false) = (&broken, ended_itself) {
        // Not libhdf5's doing: what a running child sent could not be read (a bug of
        // skelid's).
        let detail = format!("the reading child's stream broke ({e}); please report it");
        (detail, How::StreamBroke)
    } else {
        let detail = match status {
            Ok(s) => crash_detail(s, &err, step),
            Err(e) => format!("libhdf5 crashed {step} ({e})"),
        };
        (detail, How::Crashed)
    };
    let death = Death {
        detail,
        how,
        first_run: assemble.steps == 0,
    };
    Ok(ChildEnd::Died {
        done,
        death,
        reading: assemble.reading,
        reopening: assemble.resumed,
    })
}
