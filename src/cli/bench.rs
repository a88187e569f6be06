//! `skelid bench`: the benchmarks, each measured side by side in one run.

use anyhow::{bail, Context, Result};
use clap::{Args, ValueEnum};
use skelid::ingest::Archive;
use std::path::PathBuf;

use super::args::{report_fallbacks, IngestArgs};

/// `skelid bench ARCHIVE...`: both backends on the same signals, with their agreement.
pub(crate) fn cmd_bench_backends(a: &BenchArgs) -> Result<()> {
    use skelid::backend::{Backend, BackendChoice};
    let scales = a
        .scales
        .as_ref()
        .and_then(|s| s.first().copied())
        .unwrap_or(128);
    let ingest = a.ingest.options()?;
    let files = super::args::archives(&a.archives)?;
    let mut signals = Vec::new();
    let mut runs = 0usize;
    for f in &files {
        // Listed: `load_all` reads each run's metadata with its samples, once.
        let archive = Archive::open_listed(f, &ingest)
            .with_context(|| format!("cannot read {} for the benchmark", f.display()))?;
        for (path, run) in archive.load_all() {
            let run = run.with_context(|| format!("{}: run {path}", f.display()))?;
            let fs = run.meta.sample_rate;
            runs += 1;
            if let Some(x) = run.input {
                signals.push((x, fs));
            }
            signals.push((run.output, fs));
        }
    }
    if signals.is_empty() {
        bail!("no runs in {}", a.archives.join(" "));
    }
    let mut opened: Vec<(&str, Backend)> = Vec::new();
    for b in &a.backend {
        match b {
            BenchBackend::Cpu if !opened.iter().any(|o| o.0 == "cpu") => {
                opened.push(("cpu", Backend::cpu()))
            }
            BenchBackend::Gpu if !opened.iter().any(|o| o.0 == "gpu") => opened.push((
                "gpu",
                Backend::open(BackendChoice::Gpu).context(
                    "--backend gpu: no GPU could be opened (bench only the CPU with --backend cpu)",
                )?,
            )),
            _ => {}
        }
    }
    for n in opened.iter().flat_map(|(_, b)| b.notes()) {
        eprintln!("note: {n}");
    }
    let opt = skelid::track::WaveletOptions {
        scales,
        ..Default::default()
    };
    let samples: usize = signals.iter().map(|s| s.0.len()).sum();
    println!(
        "backend benchmark: {runs} run(s), {} signal(s), {samples} samples, {scales} scales, \
         wavelet track (first pass and refinement on the backend, the track's completion on {} CPU \
         threads), median of {}; {}",
        signals.len(),
        rayon::current_num_threads(),
        a.repeat.max(1),
        if a.hold_tracks {
            "every track of a repetition held until it ends (--hold-tracks)"
        } else {
            "each track let go as it is complete, as `skelid run` does"
        }
    );
    let backends: Vec<(&str, &Backend)> = opened.iter().map(|(n, b)| (*n, b)).collect();
    let mut result = skelid::bench::backends::compare(
        &signals,
        runs,
        &opt,
        &backends,
        a.repeat,
        a.hold_tracks,
        |stage| eprintln!("  {stage}"),
    );
    result.archives = files.iter().map(|f| f.display().to_string()).collect();
    println!(
        "\n{:>7} {:>10} {:>10} {:>16} {:>9}  adapter",
        "backend", "median s", "runs/s", "samples·scales/s", "fallback"
    );
    for t in &result.backends {
        println!(
            "{:>7} {:>10.3} {:>10.2} {:>16.3e} {:>9}  {}",
            t.backend,
            t.median_s,
            t.runs_per_s,
            t.samples_scales_per_s,
            t.fallbacks,
            match (&t.adapter, &t.precision, &t.spectra) {
                (Some(a), Some(p), Some(w)) => {
                    format!("{a}; shaders in {p}; padded spectra on the {w}")
                }
                (Some(a), Some(p), None) => format!("{a}; shaders in {p}"),
                (Some(a), None, _) => a.clone(),
                _ => "-".into(),
            }
        );
    }
    if let Some(r) = result.gpu_speedup {
        println!("\nGPU speed-up over the CPU (median time ratio): {r:.2}x");
        if opened.iter().any(|(_, b)| b.is_software_gpu()) {
            println!(
                "(a software adapter: it runs the shaders on these same CPU cores, so it shows \
                 the GPU code correct, not fast; run this on a machine with a hardware GPU \
                 and its Vulkan driver for the speed-up)"
            );
        }
    }
    if let Some(g) = &result.agreement {
        println!(
            "agreement over {} track(s), {} samples valid in both: envelope within {:.1e} \
             (relative), frequency within {:.1e} Hz, valid in one only: {} samples",
            g.tracks, g.valid_samples, g.envelope_rel, g.frequency_hz, g.mask_samples
        );
    }
    for t in &result.backends {
        if let Some(p) = &t.per_signal {
            println!(
                "{} traffic per signal: {:.0} signals per batch, {:.3} blocking syncs, \
                 {:.0} bytes up, {:.0} bytes down ({:.2} bytes down per sample); \
                 {} of {} submissions made while another was on the device; the \
                 dispatcher's own CPU time {:.3} ms per signal (serial; {:.3} of it \
                 inside the driver's waits for the device), and {:.3} ms per signal \
                 waiting for a core",
                t.backend,
                p.signals_per_batch,
                p.syncs,
                p.bytes_up,
                p.bytes_down,
                p.bytes_down * signals.len() as f64 / samples as f64,
                t.traffic.overlapped,
                t.traffic.submissions,
                1e3 * t.traffic.dispatcher_cpu_s / t.traffic.signals.max(1) as f64,
                1e3 * t.traffic.dispatcher_wait_cpu_s / t.traffic.signals.max(1) as f64,
                1e3 * t.traffic.dispatcher_core_wait_s / t.traffic.signals.max(1) as f64
            );
            println!(
                "{} refinement: {} grid points, {} ({:.2} %) solved again in f64 on the host \
                 where the f32 estimate was not trusted, {} of them refined whole on the CPU \
                 (no slot left for their W, W′, W″)",
                t.backend,
                t.traffic.grid_points,
                t.traffic.host_solved,
                100.0 * t.traffic.host_solved as f64 / t.traffic.grid_points.max(1) as f64,
                t.traffic.host_refined
            );
        }
    }
    print_host_share(&result);
    for t in &result.backends {
        println!(
            "{} backend's kernel share a repetition (the whole process): {:.0} page faults \
             (fresh memory mapped and zeroed), {:.3} s of system CPU time",
            t.backend, t.page_faults_per_repetition, t.system_s_per_repetition
        );
    }
    for (_, b) in &opened {
        report_fallbacks(b);
    }
    if !a.no_end_to_end {
        let reader = super::internal::reader_command(&ingest, None)?;
        let scratch = tempfile_dir()?;
        // Each backend's results.h5, kept for the agreement of the two.
        let kept = |n: &str| scratch.join(format!("results-{n}.h5"));
        for (name, backend) in &opened {
            eprintln!("  {name}: end to end (skelid run, both methods)");
            let batch = skelid::batch::BatchOptions {
                methods: vec![
                    skelid::track::Method::Wavelet,
                    skelid::track::Method::Hilbert,
                ],
                identify: skelid::identify::IdentifyOptions {
                    wavelet: opt.clone(),
                    ..Default::default()
                },
                isolation: skelid::batch::Isolation::Child {
                    command: &reader,
                    timeout: std::time::Duration::from_secs(300),
                },
                shard: None,
                force: true,
                jobs: None,
                report_runs: 100,
                backend,
                figures: None,
                memory: None,
            };
            let e = skelid::bench::backends::end_to_end(
                name,
                &files,
                &ingest,
                &batch,
                &scratch.join(format!("run-{name}")),
                Some(&kept(name)),
            )?;
            result.end_to_end.push(e);
        }
        // `opened` holds each backend once: two are the CPU and the GPU.
        if opened.len() == 2 {
            // A comparison that fails loses none of the timings: the JSON is written without it.
            match skelid::bench::backends::results_agreement(&kept("cpu"), &kept("gpu")) {
                Ok(g) => result.end_to_end_agreement = Some(g),
                Err(e) => eprintln!(
                    "warning: the two backends' end-to-end results.h5 could not be compared \
                     ({e}); skelid-bench.json has no end_to_end_agreement"
                ),
            }
        }
        let _ = std::fs::remove_dir_all(&scratch);
        print_stages(&result.end_to_end);
        if let Some(g) = &result.end_to_end_agreement {
            println!(
                "end-to-end agreement (`run`'s wavelet results, a forced response guided by its \
                 input as `run` tracks it) over {} run(s), {} samples valid in both: envelope \
                 within {:.1e} (relative), frequency within {:.1e} Hz, {} sample(s) valid in one \
                 backend only",
                g.tracks, g.valid_samples, g.envelope_rel, g.frequency_hz, g.mask_samples
            );
        }
    }
    result.end_to_end_gpu_speedup = result.end_to_end_speedup();
    // The headline comes last as well: the end-to-end part pushes the speed-up line far up,
    // and a script that keeps the output's tail (the device measurement's `tail -8`) lost it.
    if let Some(line) = in_short(&result) {
        println!("{line}");
    }
    std::fs::write(&a.out, serde_json::to_string_pretty(&result)? + "\n")
        .with_context(|| format!("cannot write {}", a.out.display()))?;
    println!("wrote {}", a.out.display());
    Ok(())
}

/// The closing line of a two-backend `bench` that also ran end to end: both speed-ups, with
/// the times they are the ratios of (`None` unless both backends ran both parts).
fn in_short(r: &skelid::bench::backends::BackendBench) -> Option<String> {
    Some(format!(
        "in short, GPU speed-up over the CPU: wavelet track {:.2}x (median {:.3} s against \
         {:.3} s a repetition), skelid run end to end {:.2}x ({:.2} s against {:.2} s)",
        r.gpu_speedup?,
        r.median_s("gpu")?,
        r.median_s("cpu")?,
        r.end_to_end_gpu_speedup?,
        r.end_to_end_s("gpu")?,
        r.end_to_end_s("cpu")?
    ))
}

/// The GPU backend's floor: what its tracks cost the CPU a repetition, which the device
/// and the dispatcher cannot hide (the calling thread prepares, then completes, on every
/// core), and the most the GPU backend can then gain over the CPU backend; then the
/// calling thread's wait for the device between the two, the rest of a repetition.
fn print_host_share(result: &skelid::bench::backends::BackendBench) {
    let cpu = result.backends.iter().find(|t| t.backend == "cpu");
    for t in result.backends.iter().filter(|t| t.traffic.signals > 0) {
        let reps = result.repeat.max(1) as f64;
        let (prepare, complete, wait) = (
            t.traffic.host_prepare_s / reps,
            t.traffic.host_complete_s / reps,
            t.traffic.host_wait_s / reps,
        );
        let floor = prepare + complete;
        let ceiling = cpu
            .filter(|_| floor > 0.0)
            .map(|c| {
                format!(
                    "; the device and the dispatcher cannot hide these, so it cannot beat the \
                     CPU backend by more than {:.1}x here",
                    c.median_s / floor
                )
            })
            .unwrap_or_default();
        let median = t.median_s.max(1e-12);
        println!(
            "{} backend's CPU share a repetition (wall time, every core): preparing the \
             signals {:.3} s, completing the tracks {:.3} s ({:.0} % of its median){ceiling}",
            t.backend,
            prepare,
            complete,
            100.0 * floor / median
        );
        // The rest of a repetition, nearly: its first group's path through the dispatcher
        // and the device, less what preparing the next group covered.
        println!(
            "{} backend's wait for the device a repetition (wall time, between preparing and \
             completing): {:.3} s ({:.0} % of its median)",
            t.backend,
            wait,
            100.0 * wait / median
        );
    }
}

/// The end-to-end table: wall time, then each stage's CPU seconds and share per backend.
pub(crate) fn print_stages(runs: &[skelid::bench::backends::EndToEnd]) {
    let Some(first) = runs.first() else { return };
    println!("\nend to end (skelid run, both methods, read and write included):");
    print!("{:>14}", "");
    for r in runs {
        print!(" {:>18}", r.backend);
    }
    println!();
    print!("{:>14}", "wall s");
    for r in runs {
        print!(
            " {:>18}",
            format!("{:.2} ({:.1} runs/s)", r.seconds, r.runs_per_s)
        );
    }
    println!();
    for (i, (stage, _)) in first.stages.iter().enumerate() {
        print!("{stage:>14}");
        for r in runs {
            let total: f64 = r.stages.iter().map(|s| s.1).sum::<f64>().max(1e-12);
            let s = r.stages[i].1;
            print!(" {:>18}", format!("{s:.2} s {:>3.0} %", 100.0 * s / total));
        }
        println!();
    }
    println!(
        "(CPU seconds summed over every thread; a GPU first pass and refinement in wall seconds \
         of their submissions)"
    );
    for r in runs {
        if let Some(p) = &r.per_signal {
            println!(
                "{} end to end: {:.0} signals per batch, {:.3} blocking syncs, {:.0} bytes \
                 up, {:.0} bytes down per signal",
                r.backend, p.signals_per_batch, p.syncs, p.bytes_up, p.bytes_down
            );
        }
    }
}

#[derive(Args)]
pub(crate) struct BenchArgs {
    /// Campaign archives (files, folders or globs): time the wavelet track of every channel
    /// of every run on each backend of --backend, side by side in this process.
    #[arg(value_name = "ARCHIVE")]
    pub(crate) archives: Vec<String>,
    /// Backends to compare on the archives, comma-separated (`gpu` takes any adapter,
    /// lavapipe included).
    #[arg(long, value_enum, value_delimiter = ',', default_value = "cpu,gpu")]
    pub(crate) backend: Vec<BenchBackend>,
    /// Timed repetitions per backend after one warm-up; the median is reported.
    #[arg(long, default_value_t = 3, value_name = "N")]
    pub(crate) repeat: usize,
    /// Where the archive benchmark's figures are written as JSON (`skelid-bench/1`).
    #[arg(long, default_value = "skelid-bench.json", value_name = "FILE")]
    pub(crate) out: PathBuf,
    /// Our transform + ridge + skeleton against the plain full-length CWT + argmax ridge
    /// (synthetic log sweeps, no archive needed).
    #[arg(long)]
    pub(crate) transform: bool,
    /// --transform: record lengths as powers of two.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "14,17,20",
        value_name = "LOG2N"
    )]
    pub(crate) log2_samples: Vec<u32>,
    /// Scale counts (default: 64,256 for --transform; 128 for archives, of which only
    /// the first count is used).
    #[arg(long, value_delimiter = ',', value_name = "S")]
    pub(crate) scales: Option<Vec<usize>>,
    /// --transform: print JSON rows instead of a table.
    #[arg(long)]
    pub(crate) json: bool,
    /// Archives: skip the end-to-end batch per backend (`skelid run`, both methods, read
    /// and write included) that shows where the time goes, stage by stage.
    #[arg(long)]
    pub(crate) no_end_to_end: bool,
    /// Archives: hold every track of a repetition until the repetition ends, as `bench` did
    /// before 2026-12-03, instead of letting each go the moment it is complete (as `skelid
    /// run` does). Memory then grows with the campaign (about 1.7 MB a signal of 30 000
    /// samples, a backend) and each repetition maps fresh pages: for comparing with
    /// figures measured before.
    #[arg(long)]
    pub(crate) hold_tracks: bool,
    #[command(flatten)]
    pub(crate) ingest: IngestArgs,
}

/// A backend `skelid bench` can time.
#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
pub(crate) enum BenchBackend {
    Cpu,
    Gpu,
}

pub(crate) fn cmd_bench(a: BenchArgs) -> Result<()> {
    use skelid::bench::{write_bench_archive, Measurement, Variant};
    if !a.archives.is_empty() {
        if a.transform {
            bail!("--transform uses its own synthetic signals: drop it, or the archives");
        }
        return cmd_bench_backends(&a);
    }
    if !a.transform {
        bail!(
            "choose a benchmark: campaign archives to compare the backends on (e.g. \
             `skelid bench demo-out/demo_campaign.h5`), or --transform"
        );
    }
    let scales = a.scales.clone().unwrap_or_else(|| vec![64, 256]);
    let exe = std::env::current_exe().context("cannot find the skelid executable")?;
    let dir = tempfile_dir()?;
    if !a.json {
        println!(
            "transform benchmark: log sweep {:.1}-{:.1} Hz at {} Hz, HDF5 in, {} threads",
            skelid::bench::BENCH_BAND.0,
            skelid::bench::BENCH_BAND.1,
            skelid::bench::BENCH_FS,
            rayon::current_num_threads()
        );
        println!(
            "{:>9} {:>7} | {:>10} {:>9} | {:>10} {:>9} | {:>7}",
            "samples", "scales", "skelid s", "peak MiB", "naive s", "peak MiB", "speed-up"
        );
    }
    for &p in &a.log2_samples {
        let n = 1usize << p;
        let file = dir.join(format!("bench_2e{p}.h5"));
        write_bench_archive(&file, n)?;
        for &s in &scales {
            let run = |v: Variant| -> Result<Measurement> {
                let name = v.name();
                let args: Vec<std::ffi::OsString> = vec![
                    "__bench-one".into(),
                    file.clone().into(),
                    "--variant".into(),
                    name.into(),
                    "--scales".into(),
                    s.to_string().into(),
                ];
                use skelid::child::{run_json, ChildFailure};
                run_json(&exe, &args, None).map_err(|e| match e {
                    ChildFailure::Spawn(e) => {
                        anyhow::anyhow!("cannot run the benchmark child process: {e}")
                    }
                    ChildFailure::Crash { stderr, .. } => {
                        anyhow::anyhow!("{name} failed: {}", String::from_utf8_lossy(&stderr))
                    }
                    ChildFailure::Hang => unreachable!("no time limit was set"),
                })
            };
            let fast = run(Variant::Fast)?;
            let naive = run(Variant::Naive)?;
            let ratio = naive.seconds / fast.seconds;
            if a.json {
                println!(
                    "{}",
                    serde_json::json!({"samples": n, "scales": s, "skelid": fast, "naive": naive, "speedup": ratio})
                );
            } else {
                println!(
                    "{:>9} {:>7} | {:>10.3} {:>9.1} | {:>10.3} {:>9.1} | {:>6.1}x",
                    format!("2^{p}"),
                    s,
                    fast.seconds,
                    fast.peak_mib,
                    naive.seconds,
                    naive.peak_mib,
                    ratio
                );
            }
        }
        let _ = std::fs::remove_file(&file);
    }
    let _ = std::fs::remove_dir(&dir);
    Ok(())
}

pub(crate) fn tempfile_dir() -> Result<PathBuf> {
    let dir = std::env::temp_dir().join(format!("skelid-bench-{}", std::process::id()));
    std::fs::create_dir_all(&dir)
        .with_context(|| format!("cannot create scratch folder {}", dir.display()))?;
    Ok(dir)
}
