//! `skelid run`'s reading child against an in-process read. In a test binary of its own:
//! the child it starts would inherit the descriptors (and libhdf5's locks) of files that
//! other tests' threads hold open at that moment, and those tests could then fail to open
//! them again (see `common::release_locks`).

mod common;
use common::*;

use skelid::ingest::{Archive, IngestOptions};

/// `skelid run`'s reading child sends a run whose channels lie in the archive as plain
/// float64 bytes without its samples, and the parent reads them from the file itself
/// (`Archive::placed`, `read_placed`). Whatever the layout, what the batch is handed must be
/// what an in-process read hands it: the same runs, the samples to the bit, and the same
/// words for a bad run.
#[test]
fn the_reading_child_delivers_what_an_in_process_read_does() {
    use skelid::batch::reader::{read_all, Counts, Delivery};
    let d = tmpdir();
    // Placed: contiguous float64, good or not finite, with an input or a free decay, and
    // behind a user block (offsets count from the file's start).
    let plain = file_in(d.path(), "plain.h5");
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
        put(
            &g,
            "input",
            &bad[10..]
                .iter()
                .chain(&bad[..10])
                .copied()
                .collect::<Vec<_>>(),
        );
        put(&g, "output", &bad);
        let g = group(&f, "/runs/free");
        set_str(&g, "kind", "free");
        put(&g, "output", &sine(1000, 4.0, 1000.0));
    }
    let user_block = file_in(d.path(), "user_block.h5");
    {
        let f = hdf5::File::with_options()
            .with_fcpl(|p| p.userblock(512))
            .create(&user_block)
            .unwrap();
        set_f64(&group(&f, "/runs"), "sample_rate", 1000.0);
        let g = group(&f, "/runs/good");
        put(&g, "input", &sine(1000, 2.0, 1000.0));
        put(&g, "output", &sine(1000, 7.0, 1000.0));
    }
    // Not placed: chunked and deflated, float32, one placed channel beside a chunked one.
    let packed = file_in(d.path(), "packed.h5");
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
    }
    let files = [plain.clone(), user_block.clone(), packed.clone()];
    for f in &files {
        release_locks(f);
    }
    let o = IngestOptions::default();
    let deliveries = |isolate: Option<(&skelid::child::ChildCommand, std::time::Duration)>| {
        let mut got = Vec::new();
        read_all(&files, &o, None, isolate, &Counts::default(), &mut |d| {
            got.push(match d {
                Delivery::Run { source, path, run } => {
                    let run = run.map(|r| {
                        let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                        (
                            serde_json::to_string(&r.meta).unwrap(),
                            r.input.as_deref().map(bits),
                            bits(&r.output),
                        )
                    });
                    (source, path, run)
                }
                Delivery::Unreadable { file, error } => {
                    (file.display().to_string(), String::new(), Err(error))
                }
            });
            Ok(())
        })
        .unwrap();
        got
    };
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
    let from_child = deliveries(Some((&child, std::time::Duration::from_secs(60))));
    let in_process = deliveries(None);
    let paths: Vec<&str> = from_child.iter().map(|d| d.1.as_str()).collect();
    assert_eq!(paths.len(), 8, "{paths:?}");
    assert!(from_child == in_process, "the two reads differ: {paths:?}");
    let error = |path: &str| {
        from_child
            .iter()
            .find(|d| d.1 == path)
            .and_then(|d| d.2.clone().err())
            .unwrap_or_else(|| panic!("{path} fails"))
    };
    let bad = error("/runs/bad_output");
    assert!(bad.contains("output") && bad.contains("2 non-finite") && bad.contains("sample 250"));
    // The output's error wins when both channels are bad, as in `load`.
    assert_eq!(
        error("/runs/bad_both"),
        bad.replace("bad_output", "bad_both")
    );
    // And the child did take the plain way where it could (the same test it makes).
    let placed = |file: &std::path::Path| {
        let a = Archive::open(file, &o).unwrap();
        a.runs
            .iter()
            .map(|r| (r.path.clone(), a.placed(r.meta.as_ref().unwrap())))
            .collect::<Vec<_>>()
    };
    for (path, p) in placed(&plain) {
        let (input, output) = p.unwrap_or_else(|| panic!("{path} is placed"));
        assert_eq!(input.is_none(), path == "/runs/free", "{path}");
        assert_eq!(output.samples, 1000);
    }
    let (input, output) = placed(&user_block)[0].1.unwrap();
    assert!(input.unwrap().offset >= 512 && output.offset >= 512);
    for (path, p) in placed(&packed) {
        assert!(p.is_none(), "{path} is not plain float64 in one block");
    }
}
