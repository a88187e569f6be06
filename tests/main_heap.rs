//! The main thread's freed arrays are reused, not given back to the kernel and faulted in
//! again. A one-signal group (one long record: `skelid track`, `bench` of a 2^20-sample
//! record) is completed on the thread that asked for it, the main thread, since rayon runs
//! a parallel iterator of one item in place, so its arrays come from glibc's main heap.
//! Without libtest's harness (`harness = false` in Cargo.toml): its tests run on threads of
//! their own, whose heaps are not the main heap.

fn main() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    linux::check();
}

#[cfg(all(target_os = "linux", target_env = "gnu"))]
mod linux {
    /// Page faults of the calling thread so far: fresh pages mapped and zeroed by the kernel.
    fn faults() -> u64 {
        skelid::profile::Events::now().faults
    }

    /// Samples of the long record (2^20) and the per-sample arrays its track holds at once:
    /// the seven series and two more (about 75 MB, all below glibc's 32 MiB mapping limit).
    const SAMPLES: usize = 1 << 20;
    const ARRAYS: usize = 9;

    /// One track's arrays, written (not calloc's untouched zeros), then all freed.
    fn track() {
        let v: Vec<Vec<f64>> = (0..ARRAYS).map(|_| vec![1.0f64; SAMPLES]).collect();
        drop(std::hint::black_box(v));
    }

    /// Page faults of the best of three rounds after a first one.
    fn faults_again() -> u64 {
        track();
        (0..3)
            .map(|_| {
                let before = faults();
                track();
                faults() - before
            })
            .min()
            .expect("three rounds")
    }

    pub fn check() {
        // skelid's own setting, whatever the caller's environment asks.
        std::env::remove_var("SKELID_MALLOC");
        assert!(
            skelid::backend::keep_freed_memory().is_none(),
            "skelid's setting, no note"
        );
        let kept = faults_again();
        // The check itself can fail: with the old 64 MiB trim threshold the freed top of
        // the main heap (75 MB) is given back each time.
        // SAFETY: mallopt only sets the allocator's parameters.
        unsafe { libc::mallopt(libc::M_TRIM_THRESHOLD, 64 << 20) };
        let trimmed = faults_again();
        let pages = (ARRAYS * SAMPLES * 8 / 4096) as u64;
        println!(
            "a 2^20-sample track's {ARRAYS} arrays ({pages} pages) freed and made again on the \
             main thread: {kept} page faults with skelid's setting, {trimmed} with a 64 MiB \
             trim threshold"
        );
        assert!(
            trimmed > pages / 2,
            "the old threshold should give the pages back: {trimmed} faults"
        );
        assert!(
            kept < pages / 50,
            "{kept} page faults for a track's arrays made again on the main thread"
        );
    }
}
