//! Campaign ingestion against FORMATS.md §1: every layout it must accept, and one specific
//! error for every way an archive can be wrong, with the other runs still listed.

mod common;
use common::*;

use hdf5::types::VarLenUnicode;
use skelid::ingest::{Archive, IngestError, IngestOptions, Quantity, RunKind, MIN_SAMPLES};

fn open(path: &std::path::Path) -> Archive {
    Archive::open(path, &IngestOptions::default()).unwrap()
}

/// The run's error after loading, or None when it loads.
fn run_error(a: &Archive, run: &str) -> Option<IngestError> {
    let entry = a.runs.iter().find(|r| r.path == run).expect("run listed");
    match &entry.meta {
        Err(e) => Some(e.clone()),
        Ok(m) => a.load(m).err(),
    }
}

#[test]
fn finds_runs_at_any_depth_with_inherited_sample_rate_and_attributes() {
    let d = tmpdir();
    let p = file_in(d.path(), "c.h5");
    {
        let f = hdf5::File::create(&p).unwrap();
        let runs = group(&f, "/campaign/day1");
        set_f64(&f.group("campaign").unwrap(), "sample_rate", 1000.0);
        set_f64(&runs, "inertia", 3.16);
        good_run(&f, "/campaign/day1/run_a");
        good_run(&f, "/campaign/day1/deeper/still/run_b");
        // A run's own attribute beats its ancestors'.
        let c = group(&f, "/campaign/day2/run_c");
        set_f64(&c, "sample_rate", 2000.0);
        set_str(&c, "kind", "force");
        put(&c, "input", &sine(1000, 5.0, 2000.0));
        put(&c, "output", &sine(1000, 5.0, 2000.0));
        // A free decay: output only.
        let free = group(&f, "/campaign/free_1");
        set_str(&free, "kind", "free");
        set_str(&free, "output_quantity", "acceleration");
        put(&free, "output", &sine(1000, 5.0, 1000.0));
    }
    let a = open(&p);
    let paths: Vec<_> = a.runs.iter().map(|r| r.path.as_str()).collect();
    println!("runs found: {paths:?}");
    assert_eq!(
        paths,
        [
            "/campaign/day1/deeper/still/run_b",
            "/campaign/day1/run_a",
            "/campaign/day2/run_c",
            "/campaign/free_1"
        ]
    );
    let m = |i: usize| a.runs[i].meta.as_ref().unwrap().clone();
    assert_eq!(m(0).sample_rate, 1000.0);
    assert_eq!(m(0).inertia, Some(3.16));
    assert_eq!(m(2).sample_rate, 2000.0);
    assert_eq!(m(2).kind, RunKind::Force);
    assert_eq!(m(2).input_quantity, Some(Quantity::Force));
    assert_eq!(m(3).kind, RunKind::Free);
    assert_eq!(m(3).output_quantity, Quantity::Acceleration);
    let free = a.load(&m(3)).unwrap();
    assert!(free.input.is_none());
    assert_eq!(free.output.len(), 1000);
}

#[test]
fn reads_matlab_shapes_integer_counts_with_scale_gzip_chunks_and_float32() {
    let d = tmpdir();
    let p = file_in(d.path(), "m.h5");
    let x = sine(1000, 5.0, 1000.0);
    {
        let f = hdf5::File::create(&p).unwrap();
        set_f64(&f, "sample_rate", 1000.0);
        // MATLAB v7.3 stores vectors as 1xN or Nx1.
        let g = group(&f, "/row");
        let row = ndarray::Array2::from_shape_vec((1, 1000), x.clone()).unwrap();
        g.new_dataset_builder()
            .with_data(&row)
            .create("input")
            .unwrap();
        let col = ndarray::Array2::from_shape_vec((1000, 1), x.clone()).unwrap();
        g.new_dataset_builder()
            .with_data(&col)
            .create("output")
            .unwrap();
        // Integer encoder counts with a scale.
        let g = group(&f, "/counts");
        let counts: Vec<i32> = x.iter().map(|v| (v * 1000.0).round() as i32).collect();
        let ds = g
            .new_dataset_builder()
            .with_data(&counts)
            .create("input")
            .unwrap();
        set_f64(&ds, "scale", 1e-3);
        let ds = g
            .new_dataset_builder()
            .with_data(&counts)
            .create("output")
            .unwrap();
        set_f64(&ds, "scale", 1e-3);
        // gzip + shuffle, chunked, float32.
        let g = group(&f, "/gzip");
        let x32: Vec<f32> = x.iter().map(|&v| v as f32).collect();
        g.new_dataset_builder()
            .with_data(&x32)
            .chunk(128)
            .shuffle()
            .deflate(6)
            .create("input")
            .unwrap();
        g.new_dataset_builder()
            .with_data(&x32)
            .chunk(100)
            .deflate(9)
            .create("output")
            .unwrap();
    }
    let a = open(&p);
    for (path, tol) in [("/row", 0.0), ("/counts", 5e-4), ("/gzip", 1e-7)] {
        let e = a.runs.iter().find(|r| r.path == path).unwrap();
        let run = a.load(e.meta.as_ref().unwrap()).unwrap();
        let err = run
            .output
            .iter()
            .zip(&x)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        println!("{path}: max |read - written| = {err:e}");
        assert!(err <= tol, "{path}: {err}");
        assert_eq!(run.input.unwrap().len(), 1000);
    }
}

#[test]
fn time_dataset_gives_the_sample_rate_and_non_uniform_time_is_rejected() {
    let d = tmpdir();
    let p = file_in(d.path(), "t.h5");
    {
        let f = hdf5::File::create(&p).unwrap();
        let g = group(&f, "/uniform");
        let t: Vec<f64> = (0..1000).map(|i| i as f64 / 500.0).collect();
        put(&g, "time", &t);
        good_run_into(&g);
        let g = group(&f, "/jittery");
        let mut t2 = t.clone();
        t2[500] += 1e-4;
        put(&g, "time", &t2);
        good_run_into(&g);
        let g = group(&f, "/backwards");
        let mut t3 = t.clone();
        t3.swap(10, 11);
        put(&g, "time", &t3);
        good_run_into(&g);
    }
    let a = open(&p);
    let ok = a.runs.iter().find(|r| r.path == "/uniform").unwrap();
    assert!((ok.meta.as_ref().unwrap().sample_rate - 500.0).abs() < 1e-9);
    for run in ["/jittery", "/backwards"] {
        let e = run_error(&a, run).unwrap();
        println!("{e}");
        assert!(matches!(e, IngestError::NonUniformTime { .. }), "{e}");
        assert!(e.to_string().contains(run));
    }
}

fn good_run_into(g: &hdf5::Group) {
    put(g, "input", &sine(1000, 5.0, 500.0));
    put(g, "output", &sine(1000, 5.0, 500.0));
}

#[test]
fn options_read_other_layouts() {
    let d = tmpdir();
    let p = file_in(d.path(), "other.h5");
    {
        let f = hdf5::File::create(&p).unwrap();
        for name in ["test_01", "test_02", "calib"] {
            let g = group(&f, &format!("/bench/{name}"));
            put(&g, "phi", &sine(1000, 5.0, 1000.0));
            put(&g, "theta", &sine(1000, 5.0, 1000.0));
        }
    }
    // Default names find nothing, and the error says what was seen and what to pass.
    let e = Archive::open(&p, &IngestOptions::default()).unwrap_err();
    println!("{e}");
    assert!(matches!(e, IngestError::NoRuns { .. }));
    // The hint, as whichever front end names it (the command line: --input-name/...).
    let hint = skelid::hint::Hint::ChannelNames.to_string();
    assert!(e.to_string().contains("phi") && e.to_string().contains(&hint));
    let opts = IngestOptions {
        input_name: "phi".into(),
        output_name: "theta".into(),
        sample_rate: Some(2500.0),
        run_glob: Some(glob::Pattern::new("/bench/test_*").unwrap()),
        ..IngestOptions::default()
    };
    let a = Archive::open(&p, &opts).unwrap();
    let paths: Vec<_> = a.runs.iter().map(|r| r.path.clone()).collect();
    assert_eq!(paths, ["/bench/test_01", "/bench/test_02"]);
    let m = a.runs[0].meta.as_ref().unwrap();
    assert_eq!(m.sample_rate, 2500.0);
    assert_eq!(a.load(m).unwrap().output.len(), 1000);
}

/// One archive with one bad run of every kind beside good ones.
#[test]
fn every_bad_run_gets_its_specific_error_and_the_good_runs_are_still_listed() {
    let d = tmpdir();
    let p = file_in(d.path(), "bad.h5");
    {
        let f = hdf5::File::create(&p).unwrap();
        set_f64(&group(&f, "/runs"), "sample_rate", 1000.0);
        good_run(&f, "/runs/good_1");
        good_run(&f, "/runs/good_2");
        // No sample rate anywhere above it.
        let g = group(&f, "/elsewhere/no_rate");
        good_run_into(&g);
        // Length mismatch.
        let g = group(&f, "/runs/mismatch");
        put(&g, "input", &sine(1000, 5.0, 1000.0));
        put(&g, "output", &sine(999, 5.0, 1000.0));
        // 2-D data.
        let g = group(&f, "/runs/two_d");
        let m = ndarray::Array2::<f64>::zeros((3, 1000));
        g.new_dataset_builder()
            .with_data(&m)
            .create("input")
            .unwrap();
        put(&g, "output", &sine(1000, 5.0, 1000.0));
        // Strings where numbers belong.
        let g = group(&f, "/runs/strings");
        let s: Vec<VarLenUnicode> = (0..1000).map(|_| "x".parse().unwrap()).collect();
        g.new_dataset_builder()
            .with_data(&s)
            .create("input")
            .unwrap();
        put(&g, "output", &sine(1000, 5.0, 1000.0));
        // NaN and Inf.
        let g = group(&f, "/runs/nan");
        let mut x = sine(1000, 5.0, 1000.0);
        x[250] = f64::NAN;
        x[700] = f64::INFINITY;
        x[701] = f64::NAN;
        put(&g, "input", &sine(1000, 5.0, 1000.0));
        put(&g, "output", &x);
        // Too short.
        let g = group(&f, "/runs/short");
        put(&g, "input", &sine(100, 5.0, 1000.0));
        put(&g, "output", &sine(100, 5.0, 1000.0));
        // Output without input and not a free decay.
        let g = group(&f, "/runs/no_input");
        put(&g, "output", &sine(1000, 5.0, 1000.0));
        // Unknown kind.
        let g = group(&f, "/runs/bad_kind");
        set_str(&g, "kind", "impact");
        good_run_into(&g);
        // A negative encoders' zero tolerance.
        let g = group(&f, "/runs/negative_zero_tolerance");
        set_f64(&g, "zero_tolerance", -1e-4);
        good_run_into(&g);
        // A zero tolerance stated on the campaign's group reaches its runs.
        let g = group(&f, "/tolerant");
        set_f64(&g, "sample_rate", 1000.0);
        set_f64(&g, "zero_tolerance", 4e-4);
        good_run_into(&group(&f, "/tolerant/run"));
        // Integer counts without a scale.
        let g = group(&f, "/runs/counts_no_scale");
        let c: Vec<i16> = vec![1; 1000];
        g.new_dataset_builder()
            .with_data(&c)
            .create("input")
            .unwrap();
        g.new_dataset_builder()
            .with_data(&c)
            .create("output")
            .unwrap();
    }
    let a = open(&p);
    let expect: &[(&str, &str)] = &[
        ("/elsewhere/no_rate", "missing_sample_rate"),
        ("/runs/mismatch", "length_mismatch"),
        ("/runs/two_d", "not_one_d"),
        ("/runs/strings", "unsupported_type"),
        ("/runs/nan", "non_finite"),
        ("/runs/short", "too_short"),
        ("/runs/no_input", "missing_input"),
        ("/runs/bad_kind", "bad_attribute"),
        ("/runs/negative_zero_tolerance", "bad_attribute"),
        ("/runs/counts_no_scale", "unsupported_type"),
    ];
    for (run, kind) in expect {
        let e = run_error(&a, run).unwrap_or_else(|| panic!("{run} should fail"));
        println!("{run}: {e}");
        assert_eq!(e.kind(), *kind, "{run}: {e}");
        let msg = e.to_string();
        assert!(msg.contains(p.to_str().unwrap()), "names the file: {msg}");
        assert!(msg.contains(run), "names the run: {msg}");
    }
    // Specific details the user needs.
    let nan = run_error(&a, "/runs/nan").unwrap().to_string();
    assert!(
        nan.contains("3 non-finite") && nan.contains("sample 250"),
        "{nan}"
    );
    let short = run_error(&a, "/runs/short").unwrap().to_string();
    assert!(short.contains(&MIN_SAMPLES.to_string()), "{short}");
    let mism = run_error(&a, "/runs/mismatch").unwrap().to_string();
    assert!(mism.contains("1000") && mism.contains("999"), "{mism}");
    for good in ["/runs/good_1", "/runs/good_2"] {
        assert!(run_error(&a, good).is_none(), "{good} loads");
    }
    let tol = run_error(&a, "/runs/negative_zero_tolerance")
        .unwrap()
        .to_string();
    assert!(tol.contains("zero_tolerance"), "{tol}");
    let tolerant = a.runs.iter().find(|r| r.path == "/tolerant/run").unwrap();
    assert_eq!(tolerant.meta.as_ref().unwrap().zero_tolerance, 4e-4);
    let good = a.runs.iter().find(|r| r.path == "/runs/good_1").unwrap();
    assert_eq!(good.meta.as_ref().unwrap().zero_tolerance, 0.0);
}

#[test]
fn file_level_errors_name_the_file() {
    let d = tmpdir();
    let empty = file_in(d.path(), "empty.h5");
    std::fs::write(&empty, b"").unwrap();
    let text = file_in(d.path(), "notes.h5");
    std::fs::write(&text, b"time,input,output\n0,1,2\n").unwrap();
    let good = file_in(d.path(), "good.h5");
    {
        let f = hdf5::File::create(&good).unwrap();
        set_f64(&f, "sample_rate", 1000.0);
        good_run(&f, "/runs/r1");
        let g = group(&f, "/runs/r2");
        put(&g, "extra", &[1.0, 2.0]);
    }
    let bytes = std::fs::read(&good).unwrap();
    let truncated = file_in(d.path(), "truncated.h5");
    std::fs::write(&truncated, &bytes[..bytes.len() / 2]).unwrap();
    let no_runs = file_in(d.path(), "no_runs.h5");
    {
        let f = hdf5::File::create(&no_runs).unwrap();
        let g = group(&f, "/stuff");
        put(&g, "signal", &[1.0, 2.0]);
    }
    let cases = [
        (&empty, "empty_file"),
        (&text, "not_hdf5"),
        (&truncated, "corrupt"),
        (&no_runs, "no_runs"),
    ];
    for (path, kind) in cases {
        let e = Archive::open(path, &IngestOptions::default()).unwrap_err();
        println!("{e}");
        assert_eq!(e.kind(), kind, "{e}");
        assert!(e.to_string().contains(path.to_str().unwrap()));
    }
    let missing = file_in(d.path(), "nope.h5");
    let e = Archive::open(&missing, &IngestOptions::default()).unwrap_err();
    assert_eq!(e.kind(), "unreadable");
    // The good file opens beside them.
    assert_eq!(open(&good).runs.len(), 1);
}

#[test]
fn real_campaigns_written_by_h5py_are_listed() {
    let Some(real) = shared_real_data() else {
        println!("../shared/data/real not present in this checkout: skipped");
        return;
    };
    let f16 = real.join("f16-gvt-sine-sweep/f16_sine_sweep.h5");
    let a = open(&f16);
    assert_eq!(a.runs.len(), 7, "seven sine-sweep levels");
    for entry in &a.runs {
        let m = entry.meta.as_ref().unwrap();
        assert_eq!(m.kind, RunKind::Force);
        assert_eq!(m.sample_rate, 400.0);
        assert_eq!(m.output_quantity, Quantity::Acceleration);
        assert!(m.samples >= 108_477);
    }
    let run = a.load(a.runs[0].meta.as_ref().unwrap()).unwrap();
    assert_eq!(run.output.len(), 108_477);
    let brb = open(&real.join("brake-reuss-beam/brb_hammer.h5"));
    assert_eq!(brb.runs.len(), 3);
    let m = brb.runs[0].meta.as_ref().unwrap();
    assert_eq!(
        (m.kind, m.sample_rate, m.samples),
        (RunKind::Free, 12800.0, 65536)
    );
    println!(
        "F-16: {} runs, BRB: {} runs, first F-16 run {} samples",
        a.runs.len(),
        brb.runs.len(),
        run.output.len()
    );
}

/// A run group libhdf5 cannot list (its local heap, which holds its members' names,
/// pointing past the file) fails alone, with the reason; the archive's other runs read.
/// Until 2026-12-07 the whole archive was unreadable: 10 of 400 copies of a 20-run archive
/// with a few bits flipped were lost whole this way. Every local heap of the file is
/// corrupted in turn: the root's makes the archive unreadable, /runs' fails that group (and
/// so every run in it), and each run group's fails that run only, the others read.
#[test]
fn a_run_group_that_cannot_be_listed_fails_alone() {
    let d = tmpdir();
    let good = file_in(d.path(), "good.h5");
    skelid::campaign::write_campaign(&good, &[], &sine_runs(6, 2000, 1.0), false).unwrap();
    let bytes = std::fs::read(&good).unwrap();
    let heaps: Vec<usize> = (0..bytes.len() - 4)
        .filter(|&i| &bytes[i..i + 4] == b"HEAP")
        .collect();
    let mut failed_alone = Vec::new();
    for at in heaps {
        let mut data = bytes.clone();
        // Signature, version, reserved, data size and free-list offset; then the address
        // of the heap's data (8-byte offsets, libhdf5's default).
        data[at + 24..at + 32].copy_from_slice(&(1u64 << 40).to_le_bytes());
        let bad = file_in(d.path(), &format!("heap_{at}.h5"));
        std::fs::write(&bad, &data).unwrap();
        match Archive::open(&bad, &IngestOptions::default()) {
            Ok(a) => {
                let failed: Vec<(&str, String)> = (a.runs.iter())
                    .filter_map(|e| {
                        e.meta
                            .as_ref()
                            .err()
                            .map(|x| (e.path.as_str(), x.to_string()))
                    })
                    .collect();
                println!("heap at {at}: {} runs, failed: {failed:?}", a.runs.len());
                // A run group's heap: that run fails, the other five read. (The /runs
                // group's own heap leaves one failed entry, /runs, and no run.)
                if let ([(path, error)], 6) = (failed.as_slice(), a.runs.len()) {
                    assert!(error.contains(&format!("(run {path})")), "{error}");
                    failed_alone.push(path.to_string());
                }
            }
            Err(e) => println!("heap at {at}: archive unreadable: {e}"),
        }
    }
    failed_alone.sort();
    assert_eq!(
        failed_alone,
        (0..6)
            .map(|i| format!("/runs/run_{i:03}"))
            .collect::<Vec<_>>(),
        "each run group's heap corrupted fails that run alone"
    );
}
