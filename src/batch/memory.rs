//! The memory the runs in flight may take together. `--jobs` bounds how many runs are
//! identified at once, but a run's working set grows with its length (about 0.5 kB a
//! sample with both methods), so a laptop's eight workers on 400 s records at 10 kHz
//! (4 × 10^6 samples, about 2 GB each) ask for 16 GB: the kernel kills the batch, and the
//! same command, resumed, is killed again at the same place. Here the reader admits a run
//! only when its estimated working set fits beside those already admitted; a run that alone
//! exceeds the budget is admitted when nothing else is in flight. The reader is the batch's
//! own thread, not a worker of the pool, so no rayon thread ever waits for memory (a
//! worker waiting inside a nested join could hold the very memory it waits for).
//! In: each delivered run's length; out: admissions that shrink to the run's results
//! once it is identified and give those back when the writer is done with them.

use std::path::Path;
use std::sync::{Condvar, Mutex};

use crate::track::Method;

/// Bytes of working set a sample of a run takes, by method (peak resident memory of
/// `skelid run --jobs 1` on one simulated run of 10^6 and 4 × 10^6 samples, less the
/// process's 66 MB: wavelet 231, Hilbert 286, both 514 bytes a sample), with a tenth more
/// for other lengths and settings.
const WAVELET_BYTES_PER_SAMPLE: u64 = 256;
/// See [`WAVELET_BYTES_PER_SAMPLE`].
const HILBERT_BYTES_PER_SAMPLE: u64 = 320;
/// A run's bytes besides its samples' (its results, plans and figures).
const RUN_BASE_BYTES: u64 = 8 << 20;

/// The working set of a run of `samples` samples identified by `methods`, estimated.
pub fn run_bytes(samples: usize, methods: &[Method]) -> u64 {
    let per_sample: u64 = methods
        .iter()
        .map(|m| match m {
            Method::Wavelet => WAVELET_BYTES_PER_SAMPLE,
            Method::Hilbert => HILBERT_BYTES_PER_SAMPLE,
        })
        .sum();
    RUN_BASE_BYTES + per_sample.saturating_mul(samples as u64)
}

/// Memory this process may still take: the kernel's `MemAvailable`, within the limit of
/// its cgroup (v2 or v1) where one is set; `None` where neither can be read.
pub fn available_bytes() -> Option<u64> {
    let meminfo = std::fs::read_to_string("/proc/meminfo").ok();
    let available = meminfo.as_deref().and_then(|m| {
        m.lines()
            .find_map(|l| l.strip_prefix("MemAvailable:"))
            .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok())
            .map(|kb| kb * 1024)
    });
    match (available, cgroup_room()) {
        (Some(a), Some(c)) => Some(a.min(c)),
        (a, c) => a.or(c),
    }
}

/// The room left under this process's cgroup memory limit, where one is set.
fn cgroup_room() -> Option<u64> {
    let own = std::fs::read_to_string("/proc/self/cgroup").ok()?;
    cgroup_room_in(Path::new("/sys/fs/cgroup"), &own)
}

/// [`cgroup_room`] with the cgroup file systems mounted under `sys` and `own` the
/// process's `/proc/self/cgroup`.
fn cgroup_room_in(sys: &Path, own: &str) -> Option<u64> {
    let number = |p: &Path| {
        std::fs::read_to_string(p)
            .ok()
            .and_then(|v| v.trim().parse::<u64>().ok())
    };
    let stat = |p: &Path, key: &str| {
        std::fs::read_to_string(p).ok().and_then(|t| {
            t.lines().find_map(|l| {
                let (k, v) = l.split_once(' ')?;
                (k == key).then(|| v.trim().parse::<u64>().ok()).flatten()
            })
        })
    };
    for line in own.lines() {
        let mut fields = line.splitn(3, ':');
        let (Some(_), Some(controllers), Some(path)) =
            (fields.next(), fields.next(), fields.next())
        else {
            continue;
        };
        // v2 ("0::/path"), then v1's memory controller (controllers joined by commas).
        // The usage counts the page cache, which the kernel drops before it kills: the
        // inactive part of it is taken off, or a group that has read a few files would
        // look full.
        let (mount, limit, usage, inactive) = match controllers {
            "" => (
                sys.to_path_buf(),
                "memory.max",
                "memory.current",
                "inactive_file",
            ),
            c if c.split(',').any(|c| c == "memory") => (
                sys.join("memory"),
                "memory.limit_in_bytes",
                "memory.usage_in_bytes",
                "total_inactive_file",
            ),
            _ => continue,
        };
        let parts: Vec<&str> = path
            .split('/')
            .filter(|p| !p.is_empty() && *p != "." && *p != "..")
            .collect();
        // The process's own group: its path whole, or, inside a container (whose own group
        // is mounted as the root while the path is the host's), the path's tail.
        let Some(group) = (0..=parts.len())
            .map(|i| parts[i..].iter().fold(mount.clone(), |d, p| d.join(p)))
            .find(|d| d.join(usage).is_file())
        else {
            continue;
        };
        // Its limit and every ancestor's up to the mount (a Slurm job's, a systemd slice's,
        // a pod's): the least room binds. "max" (v2) or v1's page-rounded i64::MAX is none.
        let mut room: Option<u64> = None;
        let mut d = group.as_path();
        loop {
            if let (Some(l), Some(u)) = (number(&d.join(limit)), number(&d.join(usage))) {
                if l < 1 << 60 {
                    let cache = stat(&d.join("memory.stat"), inactive).unwrap_or(0);
                    let r = l.saturating_sub(u.saturating_sub(cache));
                    room = Some(room.map_or(r, |x| x.min(r)));
                }
            }
            match d.parent() {
                Some(p) if d != mount && p.starts_with(&mount) => d = p,
                _ => break,
            }
        }
        if room.is_some() {
            return room;
        }
    }
    None
}

/// The memory the runs in flight may take together, and what they hold now.
pub struct Budget {
    limit: u64,
    /// Workers: when that many runs of a size exceed the limit, the limit can bind them.
    jobs: usize,
    state: Mutex<State>,
    freed: Condvar,
}

#[derive(Default)]
struct State {
    /// Bytes admitted and not yet given back.
    held: u64,
    /// Runs admitted and not yet written.
    runs: usize,
    /// Of those, runs not yet identified (queued for a worker, or in one).
    working: usize,
    /// The most runs in flight at once, and how often a run waited for room.
    most: usize,
    waits: usize,
    /// The largest run's bytes.
    largest: u64,
}

/// What the budget did over a batch, for the log and the terminal.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Usage {
    /// The budget, bytes.
    pub limit: u64,
    /// The most runs admitted at once: queued for a worker, in one, or identified and
    /// waiting for the writer.
    pub most_at_once: usize,
    /// Runs that waited for room.
    pub waits: usize,
    /// The largest run's estimated working set, bytes.
    pub largest_run: u64,
}

/// What a budget that held runs back did, in a sentence.
pub fn held_back(u: &Usage) -> String {
    format!(
        "{} run(s) waited for memory, so at most {} were in flight at once (the largest about \
         {}, all of them within {}); --memory GB sets the budget, --jobs the workers",
        u.waits,
        u.most_at_once,
        super::disk::size(u.largest_run),
        super::disk::size(u.limit),
    )
}

impl Budget {
    /// A budget of `limit` bytes for `jobs` workers.
    pub fn new(limit: u64, jobs: usize) -> Budget {
        Budget {
            limit,
            jobs,
            state: Mutex::new(State::default()),
            freed: Condvar::new(),
        }
    }

    /// The bytes it allows.
    pub fn limit(&self) -> u64 {
        self.limit
    }

    /// Waits until `bytes` fit beside what is held (or nothing is held), then holds them
    /// until the admission is dropped.
    pub fn admit(&self, bytes: u64) -> Admission<'_> {
        let mut s = self.state.lock().unwrap_or_else(|p| p.into_inner());
        let fits = |s: &State| s.runs == 0 || s.held.saturating_add(bytes) <= self.limit;
        if !fits(&s) {
            // Only a wait with fewer runs to identify than workers kept a worker idle: with
            // more, the queues were full anyway.
            if s.working < self.jobs {
                s.waits += 1;
            }
            while !fits(&s) {
                s = self.freed.wait(s).unwrap_or_else(|p| p.into_inner());
            }
        }
        s.held += bytes;
        s.runs += 1;
        s.working += 1;
        s.most = s.most.max(s.runs);
        s.largest = s.largest.max(bytes);
        Admission {
            budget: self,
            bytes,
            working: true,
        }
    }

    /// What it did so far.
    pub fn usage(&self) -> Usage {
        let s = self.state.lock().unwrap_or_else(|p| p.into_inner());
        Usage {
            limit: self.limit,
            most_at_once: s.most,
            waits: s.waits,
            largest_run: s.largest,
        }
    }
}

/// A run's place in the budget, given back when dropped.
pub struct Admission<'a> {
    budget: &'a Budget,
    bytes: u64,
    /// Not yet shrunk to its run's results.
    working: bool,
}

impl Admission<'_> {
    /// Holds only `bytes` from now on (a run's results, waiting for the writer, once its
    /// working set is gone). A large run's memory first goes back to the kernel where the
    /// budget cannot hold a run of its size on every worker: glibc keeps freed blocks in
    /// the arena of the thread that freed them, so without this the next run, on another
    /// worker's arena, took fresh memory beside the kept. Four runs of 4 × 10^6 samples one
    /// at a time on 2 workers (`--memory 3`) peaked at 4.1 GB, two runs' worth, and 2.6 GB
    /// with it. Where the budget holds every worker's run the arenas keep their memory for
    /// their next runs: giving it back cost 4 % (the same runs on one worker, 34.5 s
    /// against 32.5 s, a million more page faults).
    pub fn shrink(&mut self, bytes: u64) {
        let b = self.budget;
        let given = self.bytes.saturating_sub(bytes);
        if given >= GIVE_BACK_ABOVE && self.bytes.saturating_mul(b.jobs as u64) > b.limit {
            crate::backend::give_freed_memory_back();
        }
        let mut s = b.state.lock().unwrap_or_else(|p| p.into_inner());
        s.held -= given;
        self.bytes -= given;
        if std::mem::take(&mut self.working) {
            s.working -= 1;
        }
        drop(s);
        b.freed.notify_all();
    }
}

/// Runs at least this large give their memory back to the kernel when done, where the
/// budget binds runs of their size ([`Admission::shrink`]); smaller ones keep it for the
/// next run, as the campaign's do.
const GIVE_BACK_ABOVE: u64 = 256 << 20;

impl Drop for Admission<'_> {
    /// Gives the run's bytes back to the budget.
    fn drop(&mut self) {
        let mut s = self.budget.state.lock().unwrap_or_else(|p| p.into_inner());
        s.held -= self.bytes;
        s.runs -= 1;
        if self.working {
            s.working -= 1;
        }
        drop(s);
        self.budget.freed.notify_all();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn a_run_of_both_methods_takes_half_a_kilobyte_a_sample() {
        let both = run_bytes(4_000_000, &[Method::Wavelet, Method::Hilbert]);
        let wavelet = run_bytes(4_000_000, &[Method::Wavelet]);
        println!("4e6 samples: both {both} bytes, wavelet {wavelet}");
        // Measured 2.12 GB peak for one such run (66 MB of it the process): the estimate
        // is that and a tenth more.
        assert!((2.05e9..2.6e9).contains(&(both as f64)), "{both}");
        assert!(wavelet < both / 2 + RUN_BASE_BYTES);
    }

    /// A cgroup's limit is found where a container mounts its own group as the root (the
    /// host's path in /proc/self/cgroup, only its tail under the mount), for v1 and v2; an
    /// ancestor's limit binds when it leaves less room; the inactive page cache is not
    /// counted as used; no limit ("max", or v1's page-rounded i64::MAX) is none.
    #[test]
    fn a_cgroup_limit_is_found_under_a_containers_mount() {
        let sys = tempfile::tempdir().unwrap();
        let write = |rel: &str, v: &str| {
            let p = sys.path().join(rel);
            std::fs::create_dir_all(p.parent().unwrap()).unwrap();
            std::fs::write(p, v).unwrap();
        };
        write("memory/memory.limit_in_bytes", "9223372036854771712\n");
        write("memory/memory.usage_in_bytes", "5000\n");
        write("memory/night/memory.limit_in_bytes", "3000000\n");
        write("memory/night/memory.usage_in_bytes", "1000000\n");
        let v1 = "5:cpu:/\n4:memory,blkio:/process_api/1ec5/night\n0::/\n";
        assert_eq!(cgroup_room_in(sys.path(), v1), Some(2_000_000));
        // Most of the usage is cache it can drop.
        write(
            "memory/night/memory.stat",
            "cache 900000\ntotal_inactive_file 800000\n",
        );
        assert_eq!(cgroup_room_in(sys.path(), v1), Some(2_800_000));
        assert_eq!(
            cgroup_room_in(sys.path(), "4:memory:/process_api/1ec5\n"),
            None
        );
        assert_eq!(
            cgroup_room_in(sys.path(), "garbled\n4:memory:/night\n"),
            Some(2_800_000)
        );
        write("memory.max", "max\n");
        write("memory.current", "5000\n");
        write("job/memory.max", "8000000\n");
        write("job/memory.current", "500000\n");
        write("job/step/task/memory.max", "max\n");
        write("job/step/task/memory.current", "400000\n");
        let v2 = "0::/job/step/task\n";
        assert_eq!(
            cgroup_room_in(sys.path(), v2),
            Some(7_500_000),
            "the job's limit"
        );
        write("job/step/task/memory.max", "9000000\n");
        assert_eq!(
            cgroup_room_in(sys.path(), v2),
            Some(7_500_000),
            "the least room"
        );
        assert_eq!(cgroup_room_in(sys.path(), "0::/\n"), None);
    }

    #[test]
    fn available_memory_is_read_and_plausible() {
        let a = available_bytes().expect("/proc/meminfo on Linux");
        println!(
            "available: {a} bytes; the cgroup's room: {:?}",
            cgroup_room()
        );
        assert!(a > 16 << 20, "{a}");
    }

    /// Waits (up to a minute) until `n` admissions have waited for room.
    fn waits_reach(budget: &Budget, n: usize) {
        let deadline = std::time::Instant::now() + Duration::from_secs(60);
        while budget.usage().waits < n {
            assert!(std::time::Instant::now() < deadline, "no wait counted");
            std::thread::sleep(Duration::from_millis(1));
        }
    }

    /// Runs wait for room and go on when it is given back; a run larger than the budget
    /// waits until nothing else is held, then goes alone; a wait counts only where a
    /// worker was left idle; shrinking gives the room back at once.
    #[test]
    fn runs_wait_for_room_and_a_huge_one_goes_alone() {
        let budget = Budget::new(100, 3);
        let a = budget.admit(60);
        let mut b = budget.admit(40);
        let started = std::time::Instant::now();
        std::thread::scope(|s| {
            let waiting = s.spawn(|| budget.admit(30).bytes);
            waits_reach(&budget, 1);
            assert!(!waiting.is_finished(), "100 of 100 held: the third waits");
            b.shrink(10);
            assert_eq!(waiting.join().unwrap(), 30, "70 held: the third fits");
            println!("the third run waited {:?}", started.elapsed());
        });
        std::thread::scope(|s| {
            let huge = s.spawn(|| budget.admit(1_000).bytes);
            waits_reach(&budget, 2);
            assert!(
                !huge.is_finished(),
                "a huge run waits for every other to end"
            );
            drop(a);
            std::thread::sleep(Duration::from_millis(100));
            assert!(!huge.is_finished(), "b still holds 10");
            drop(b);
            assert_eq!(huge.join().unwrap(), 1_000, "alone, it goes");
        });
        let u = budget.usage();
        assert_eq!((u.most_at_once, u.waits, u.largest_run), (3, 2, 1_000));
        let budget = Budget::new(100, 2);
        let (_a, _b) = (budget.admit(60), budget.admit(40));
        std::thread::scope(|s| {
            s.spawn(|| budget.admit(30));
            std::thread::sleep(Duration::from_millis(50));
            drop(_a);
        });
        assert_eq!(
            budget.usage().waits,
            0,
            "two workers busy: the wait idled none"
        );
        drop(_b);
        let s = budget.state.lock().unwrap();
        assert_eq!((s.held, s.runs), (0, 0), "everything given back");
    }

    /// Admissions still in a queue whose consumers are gone are dropped with it, so a
    /// reader waiting for memory wakes (and then finds the queue closed): a writer that
    /// stops on an error cannot leave the batch waiting for ever.
    #[test]
    fn a_queue_dropped_with_admissions_in_it_wakes_a_waiting_reader() {
        let budget = Budget::new(100, 2);
        let (tx, rx) = std::sync::mpsc::sync_channel::<Admission<'_>>(2);
        tx.send(budget.admit(60)).unwrap();
        tx.send(budget.admit(40)).unwrap();
        std::thread::scope(|s| {
            let reader = s.spawn(|| {
                let a = budget.admit(50);
                tx.send(a).is_err()
            });
            std::thread::sleep(Duration::from_millis(100));
            assert!(!reader.is_finished());
            drop(rx);
            assert!(reader.join().unwrap(), "woken, it finds the queue closed");
        });
        let s = budget.state.lock().unwrap();
        assert_eq!((s.held, s.runs), (0, 0));
    }
}
