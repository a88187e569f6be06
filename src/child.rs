//! One child process that prints JSON: started with its arguments, its output read while it
//! runs, stopped when it runs past a time limit, and its JSON parsed. `inspect` reads each
//! archive in one (a corrupt file that crashes or hangs libhdf5 takes the child down, not
//! skelid), and `bench --transform` measures each variant in one (its own peak memory).

use std::ffi::OsString;
use std::io::Read;
use std::path::Path;
use std::process::{Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

/// How to start one of skelid's own child processes: the front end's executable and the
/// arguments of its hidden command (the subcommand and the options it carries); the library
/// appends only what varies between children (an archive's path). The front end builds it,
/// so that the library never spells a command line.
#[derive(Debug, Clone)]
pub struct ChildCommand {
    /// The executable.
    pub exe: std::path::PathBuf,
    /// Its arguments.
    pub args: Vec<OsString>,
}

/// Why a child gave no answer.
#[derive(Debug)]
pub enum ChildFailure {
    /// It could not be started (no executable, no processes left).
    Spawn(std::io::Error),
    /// It ran past its limit and was stopped (or could no longer be waited for).
    Hang,
    /// It ended without printing what it should: how it ended and its stderr.
    Crash {
        /// Its exit status.
        status: ExitStatus,
        /// Everything it wrote on stderr.
        stderr: Vec<u8>,
    },
}

/// Runs `exe` with `args` and parses its stdout as JSON; stops it after `timeout` when one
/// is given.
pub fn run_json<T: serde::de::DeserializeOwned>(
    exe: &Path,
    args: &[OsString],
    timeout: Option<Duration>,
) -> Result<T, ChildFailure> {
    let mut child = Command::new(exe)
        .args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .map_err(ChildFailure::Spawn)?;
    // Both pipes are drained while the child runs: a child that fills one would block.
    let drain = |mut r: Box<dyn Read + Send>| {
        std::thread::spawn(move || {
            let mut buf = Vec::new();
            let _ = r.read_to_end(&mut buf);
            buf
        })
    };
    let out = drain(Box::new(child.stdout.take().expect("piped stdout")));
    let err = drain(Box::new(child.stderr.take().expect("piped stderr")));
    let start = Instant::now();
    let status = loop {
        match child.try_wait() {
            Ok(Some(status)) => break Some(status),
            Ok(None) if timeout.is_some_and(|t| start.elapsed() > t) => {
                let _ = child.kill();
                let _ = child.wait();
                break None;
            }
            Ok(None) => std::thread::sleep(Duration::from_millis(5)),
            Err(_) => break None,
        }
    };
    let Some(status) = status else {
        // Not waiting for its pipes: a process it started may still hold them open.
        return Err(ChildFailure::Hang);
    };
    let out = out.join().unwrap_or_default();
    let stderr = err.join().unwrap_or_default();
    // What it printed counts, however it ended (a child may crash on its way out).
    serde_json::from_slice(&out).map_err(|_| ChildFailure::Crash { status, stderr })
}

#[cfg(all(test, unix))]
mod tests {
    use super::*;

    fn sh(script: &str, timeout: Option<Duration>) -> Result<serde_json::Value, ChildFailure> {
        run_json(Path::new("/bin/sh"), &["-c".into(), script.into()], timeout)
    }

    #[test]
    fn answers_crashes_hangs_and_missing_executables_are_told_apart() {
        let v = sh(r#"echo '{"a": 1}'"#, None).unwrap();
        assert_eq!(v["a"], 1);
        match sh("echo 'libhdf5 gave up' >&2; exit 3", None) {
            Err(ChildFailure::Crash { status, stderr }) => {
                assert_eq!(status.code(), Some(3));
                assert_eq!(String::from_utf8_lossy(&stderr).trim(), "libhdf5 gave up");
            }
            other => panic!("{other:?}"),
        }
        let t0 = Instant::now();
        let limit = Duration::from_millis(200);
        assert!(matches!(
            sh("sleep 30", Some(limit)),
            Err(ChildFailure::Hang)
        ));
        assert!(
            t0.elapsed() < Duration::from_secs(20),
            "the child was stopped"
        );
        let missing = run_json::<serde_json::Value>(Path::new("/nonexistent/skelid"), &[], None);
        assert!(matches!(missing, Err(ChildFailure::Spawn(_))));
    }
}
