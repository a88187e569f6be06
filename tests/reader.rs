//! `skelid run`'s reading child against an in-process read. In a test binary of its own:
//! the child it starts would inherit the descriptors (and libhdf5's locks) of files that
//! other tests' threads hold open at that moment, and those tests could then fail to open
//! them again (see `common::release_locks`).

mod common;
use common::*;

use std::path::{Path, PathBuf};

use skelid::batch::reader::{read_all, serve, Counts, Delivery, Frame};
use skelid::ingest::{read_placed, IngestOptions, Placed, PlacedRun};

/// Three archives: `plain.h5`, whose runs are all placed (good, not finite in one channel
/// or both, a free decay, a `time` dataset); `user_block.h5`, a placed run behind a
/// 512-byte user block and one whose output was never written; `packed.h5`, none placed
/// (chunked and deflated, float32, one channel chunked, an N × 1 matrix).
fn archives(dir: &Path) -> [PathBuf; 3] {
    let plain = file_in(dir, "plain.h5");
    {
        let f = hdf5::File::create(&plain).unwrap();
        set_f64(&group(&f, "/runs"), "sample_rate", 1000.0);
        good_run(&f, "/runs/good");
        let mut bad = sine(1000, 5.0, 1000.0);
        bad[250] = f64::NAN;
        bad[700] = f64::INFINITY;
        let g = group(&f, "/runs/bad_output");
        put(&g, "input", &sine(1000, 3.0, 1000.0));
        put(&g, "output", &bad);
        let g = group(&f, "/runs/bad_both");
        let shifted: Vec<f64> = bad[10..].iter().chain(&bad[..10]).copied().collect();
        put(&g, "input", &shifted);
        put(&g, "output", &bad);
        let g = group(&f, "/runs/free");
        set_str(&g, "kind", "free");
        put(&g, "output", &sine(1000, 4.0, 1000.0));
        let g = group(&f, "/timed/run");
        put(
            &g,
            "time",
            &(0..1000).map(|i| i as f64 / 500.0).collect::<Vec<_>>(),
        );
        put(&g, "input", &sine(1000, 6.0, 500.0));
        put(&g, "output", &sine(1000, 9.0, 500.0));
    }
    let user_block = file_in(dir, "user_block.h5");
    {
        let f = hdf5::File::with_options()
            .with_fcpl(|p| p.userblock(512))
            .create(&user_block)
            .unwrap();
        set_f64(&group(&f, "/runs"), "sample_rate", 1000.0);
        let g = group(&f, "/runs/good");
        put(&g, "input", &sine(1000, 2.0, 1000.0));
        put(&g, "output", &sine(1000, 7.0, 1000.0));
        // Never written: no block in the file, its reads the fill value.
        let g = group(&f, "/runs/unwritten");
        put(&g, "input", &sine(1000, 2.0, 1000.0));
        g.new_dataset::<f64>().shape(1000).create("output").unwrap();
    }
    let packed = file_in(dir, "packed.h5");
    {
        let f = hdf5::File::create(&packed).unwrap();
        set_f64(&group(&f, "/runs"), "sample_rate", 1000.0);
        let x = sine(1000, 5.0, 1000.0);
        let g = group(&f, "/runs/deflated");
        for name in ["input", "output"] {
            g.new_dataset_builder()
                .with_data(&x)
                .chunk(256)
                .deflate(4)
                .create(name)
                .unwrap();
        }
        let g = group(&f, "/runs/float32");
        let x32: Vec<f32> = x.iter().map(|&v| v as f32).collect();
        for name in ["input", "output"] {
            g.new_dataset_builder()
                .with_data(&x32)
                .create(name)
                .unwrap();
        }
        let g = group(&f, "/runs/mixed");
        put(&g, "input", &x);
        g.new_dataset_builder()
            .with_data(&x)
            .chunk(100)
            .create("output")
            .unwrap();
        let g = group(&f, "/runs/column");
        let column = ndarray::Array2::from_shape_vec((1000, 1), x.clone()).unwrap();
        for name in ["input", "output"] {
            g.new_dataset_builder()
                .with_data(&column)
                .create(name)
                .unwrap();
        }
    }
    let files = [plain, user_block, packed];
    for f in &files {
        release_locks(f);
    }
    files
}

/// A delivery, comparable: source, run path, and the run's metadata and samples as bits,
/// or its error and the error's kind.
type Compared = (
    String,
    String,
    Result<(String, Option<Vec<u64>>, Vec<u64>), (String, String)>,
);

fn deliveries(
    files: &[PathBuf],
    isolate: Option<(&skelid::child::ChildCommand, std::time::Duration)>,
) -> Vec<Compared> {
    let mut got = Vec::new();
    let o = IngestOptions::default();
    read_all(files, &o, None, isolate, &Counts::default(), &mut |d| {
        got.push(match d {
            Delivery::Run {
                source,
                path,
                run,
                error_kind,
            } => {
                let kind = error_kind.unwrap_or_default();
                let run = run.map_err(|e| (e, kind)).map(|r| {
                    let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                    (
                        serde_json::to_string(&r.meta).unwrap(),
                        r.input.as_deref().map(bits),
                        bits(&r.output),
                    )
                });
                (source, path, run)
            }
            Delivery::Unreadable {
                file,
                error,
                error_kind,
            } => (
                file.display().to_string(),
                String::new(),
                Err((error, error_kind)),
            ),
        });
        Ok(())
    })
    .unwrap();
    got
}

/// The child sends a run whose channels lie in the archive as plain float64 bytes without
/// its samples, and the parent reads them from the file itself (`Archive::placed`,
/// `read_placed`). Whatever the layout, what the batch is handed must be what an
/// in-process read hands it: the same runs, the samples to the bit, and the same words for
/// a bad run.
#[test]
fn the_reading_child_delivers_what_an_in_process_read_does() {
    let d = tmpdir();
    let files = archives(d.path());
    // The child first: this process opens the files with libhdf5 only after it has gone.
    let child = skelid::child::ChildCommand {
        exe: env!("CARGO_BIN_EXE_skelid").into(),
        args: [
            "__read-archives",
            "--input-name",
            "input",
            "--output-name",
            "output",
        ]
        .map(Into::into)
        .to_vec(),
    };
    let from_child = deliveries(&files, Some((&child, std::time::Duration::from_secs(60))));
    let in_process = deliveries(&files, None);
    let paths: Vec<&str> = from_child.iter().map(|d| d.1.as_str()).collect();
    assert_eq!(paths.len(), 11, "{paths:?}");
    assert!(from_child == in_process, "the two reads differ: {paths:?}");
    let error = |path: &str| {
        from_child
            .iter()
            .find(|d| d.1 == path)
            .and_then(|d| d.2.clone().err())
            .unwrap_or_else(|| panic!("{path} fails"))
    };
    let (bad, kind) = error("/runs/bad_output");
    assert!(bad.contains("output") && bad.contains("2 non-finite") && bad.contains("sample 250"));
    // Found by the parent in a placed run's samples, named as the child would name it.
    assert_eq!(kind, "non_finite");
    // The output's error wins when both channels are bad, as in `load`.
    assert_eq!(
        error("/runs/bad_both"),
        (bad.replace("bad_output", "bad_both"), kind)
    );

    // Which runs the child sends as placed: its side of the protocol, run here.
    let mut placed = Vec::new();
    serve(
        &files,
        &IngestOptions::default(),
        None,
        true,
        0,
        &mut |frame, samples| {
            if let Frame::Run {
                archive,
                path,
                placed: Some(p),
                ..
            } = frame
            {
                assert!(samples.is_none(), "{path}: placed and sent");
                placed.push((archive, path, p));
            }
            true
        },
    );
    let names: Vec<(usize, &str)> = placed.iter().map(|p| (p.0, p.1.as_str())).collect();
    assert_eq!(
        names,
        [
            (0, "/runs/bad_both"),
            (0, "/runs/bad_output"),
            (0, "/runs/free"),
            (0, "/runs/good"),
            (0, "/timed/run"),
            (1, "/runs/good"),
        ]
    );
    for (_, path, p) in &placed {
        assert_eq!(p.input.is_none(), path == "/runs/free", "{path}");
        assert_eq!(p.output.samples, 1000);
    }
    let behind = placed[5].2;
    assert!(behind.input.unwrap().offset >= 512 && behind.output.offset >= 512);
}

/// A place past the file's end is refused before anything is allocated for it (a corrupt
/// dataset's shape could ask for any length); the place itself reads the samples.
#[test]
fn a_place_past_the_end_of_the_file_is_refused() {
    let d = tmpdir();
    let files = archives(d.path());
    let plain = &files[0];
    let mut frames = Vec::new();
    serve(
        std::slice::from_ref(plain),
        &IngestOptions::default(),
        None,
        true,
        0,
        &mut |frame, _| {
            frames.push(frame);
            true
        },
    );
    let (meta, placed) = frames
        .iter()
        .find_map(|f| match f {
            Frame::Run {
                path,
                meta: Ok(m),
                placed: Some(p),
                ..
            } if path == "/runs/good" => Some((m.clone(), *p)),
            _ => None,
        })
        .unwrap();
    let file = std::fs::File::open(plain).unwrap();
    let name = plain.display().to_string();
    let o = IngestOptions::default();
    let past = PlacedRun {
        output: Placed {
            offset: placed.output.offset,
            samples: usize::MAX / 4,
        },
        ..placed
    };
    let e = read_placed(&file, &name, &meta, &o, past).unwrap_err();
    println!("{e}");
    assert!(e.to_string().contains("past the file's end"), "{e}");
    let (input, output) = read_placed(&file, &name, &meta, &o, placed).unwrap();
    assert_eq!(input.unwrap(), sine(1000, 5.0, 1000.0));
    assert_eq!(output, sine(1000, 5.0, 1000.0));
}
