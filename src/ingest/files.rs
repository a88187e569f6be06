//! The inputs as a user gives them — files, folders, globs — expanded to the archives they
//! name, and a clear error when they name none. In: command-line arguments; out: paths.

use std::path::{Path, PathBuf};

/// What the inputs name: the archives to read, and the files a folder search passed over
/// as skelid's own results.
#[derive(Debug, Default)]
pub struct Inputs {
    /// The archives, sorted, each once.
    pub archives: Vec<PathBuf>,
    /// `results.h5` files found in folders a batch wrote (beside the `manifest.json` of
    /// `skelid run`, `demo` or `merge`, or its `skelid.log` and `runs/`: an output folder
    /// inside the campaign's tree, a resumed batch's own folder, the demo's), and the
    /// journal files of an earlier version in such a folder's `runs/`: not campaigns, so
    /// not read. A file named by itself is always read.
    pub passed_over: Vec<PathBuf>,
}

/// Expands command-line arguments (files, folders searched recursively for `.h5`, `.hdf5`,
/// `.he5`, `.mat`, and glob patterns) to the archives they name, sorted and each once, and
/// the results files the folder searches passed over.
pub fn expand_inputs(args: &[String]) -> Result<Inputs, String> {
    let mut out = Inputs::default();
    for a in args {
        let p = Path::new(a);
        if p.is_dir() {
            collect_dir(p, &mut out).map_err(|e| format!("{a}: cannot list folder: {e}"))?;
        } else if p.exists() {
            out.archives.push(p.to_path_buf());
        } else if a.contains(['*', '?', '[']) {
            let paths = glob::glob(a).map_err(|e| format!("{a}: bad glob pattern: {e}"))?;
            let before = out.archives.len() + out.passed_over.len();
            for entry in paths.flatten() {
                if entry.is_dir() {
                    collect_dir(&entry, &mut out)
                        .map_err(|e| format!("{}: {e}", entry.display()))?;
                } else {
                    out.archives.push(entry);
                }
            }
            if out.archives.len() + out.passed_over.len() == before {
                return Err(format!("{a}: the pattern matches no file"));
            }
        } else {
            return Err(format!("{a}: no such file or folder"));
        }
    }
    // One file named two ways (`camp.h5` and `./camp.h5`, an absolute path, a link) is
    // read once: twice, its runs were counted twice, skipped as "done earlier" and stored
    // twice under different names. The first spelling in name order stays.
    let mut seen = std::collections::HashSet::new();
    for list in [&mut out.archives, &mut out.passed_over] {
        list.sort();
        list.dedup();
        list.retain(|p| seen.insert(same_file_key(p)));
    }
    Ok(out)
}

/// What two names of one file share: its canonical path (the name itself where there is
/// none, e.g. a file that went away).
fn same_file_key(p: &Path) -> PathBuf {
    std::fs::canonicalize(p).unwrap_or_else(|_| p.to_path_buf())
}

/// What to tell the user about the files a folder search passed over (none: `None`).
pub fn passed_over_note(passed_over: &[PathBuf]) -> Option<String> {
    let first = passed_over.first()?;
    let more = match passed_over.len() {
        1 => String::new(),
        n => format!(" and {} more", n - 1),
    };
    Some(format!(
        "passed over {}{more}: skelid's own results (in a batch's output folder), not a \
         campaign archive; name such a file by itself to read it anyway",
        first.display()
    ))
}

/// No archive among the inputs: what was looked at and what was there instead.
#[derive(Debug, thiserror::Error)]
#[error(
    "no campaign archive found: {0}; pass .h5, .hdf5, .he5 or .mat files, folders holding \
     them, or a glob (nothing was done)"
)]
pub struct NothingFound(pub String);

/// [`expand_inputs`], refusing an empty result with what each argument held instead.
pub fn find_archives(args: &[String]) -> Result<Inputs, FindError> {
    let inputs = expand_inputs(args).map_err(FindError::Bad)?;
    if !inputs.archives.is_empty() {
        return Ok(inputs);
    }
    let mut seen: Vec<String> = args
        .iter()
        .map(|a| {
            let mut others = Vec::new();
            let _ = list_files(Path::new(a), &mut others);
            match others.len() {
                0 => format!("{a} is an empty folder"),
                n => {
                    let names: Vec<String> = others
                        .iter()
                        .take(3)
                        .map(|p| p.display().to_string())
                        .collect();
                    format!(
                        "{a} holds {n} other file(s) ({}{})",
                        names.join(", "),
                        if n > 3 { ", …" } else { "" }
                    )
                }
            }
        })
        .collect();
    seen.extend(passed_over_note(&inputs.passed_over));
    Err(FindError::Nothing(NothingFound(seen.join("; "))))
}

/// Why [`find_archives`] found nothing to read.
#[derive(Debug, thiserror::Error)]
pub enum FindError {
    /// A missing path or a bad pattern.
    #[error("{0}")]
    Bad(String),
    /// Inputs that exist but hold no archive.
    #[error(transparent)]
    Nothing(#[from] NothingFound),
}

/// Every file below `dir`, whatever its extension (to say what a folder held instead).
fn list_files(dir: &Path, out: &mut Vec<PathBuf>) -> std::io::Result<()> {
    for e in std::fs::read_dir(dir)?.flatten() {
        let p = e.path();
        if p.is_dir() {
            list_files(&p, out)?;
        } else {
            out.push(p);
        }
    }
    Ok(())
}

fn collect_dir(dir: &Path, out: &mut Inputs) -> std::io::Result<()> {
    let mut entries: Vec<_> = std::fs::read_dir(dir)?
        .flatten()
        .map(|e| e.path())
        .collect();
    entries.sort();
    // A batch's journal: its runs are `.run` files, but a batch made before 2026-11-23
    // committed each run as `runs/<key>.h5`, which a later batch still reads, and a
    // folder search took each for a campaign archive that holds no run. Only names that
    // are a run's key: a campaign kept in a folder called `runs` beside a log is read.
    let journal = dir
        .file_name()
        .is_some_and(|n| n == crate::journal::RUNS_DIR)
        && dir.parent().is_some_and(is_batch_folder);
    for p in entries {
        if p.is_dir() {
            collect_dir(&p, out)?;
        } else if matches!(
            p.extension()
                .and_then(|e| e.to_str())
                .map(|e| e.to_ascii_lowercase())
                .as_deref(),
            Some("h5" | "hdf5" | "he5" | "mat")
        ) {
            let key = p
                .file_stem()
                .and_then(|s| s.to_str())
                .is_some_and(is_run_key);
            if journal && key
                || p.file_name().is_some_and(|n| n == "results.h5") && is_batch_folder(dir)
            {
                out.passed_over.push(p);
            } else {
                out.archives.push(p);
            }
        }
    }
    Ok(())
}

/// Whether `name` is a run's journal key: 32 lowercase hexadecimal digits.
fn is_run_key(name: &str) -> bool {
    name.len() == 32 && name.bytes().all(|b| matches!(b, b'0'..=b'9' | b'a'..=b'f'))
}

/// Whether `dir` is a batch's output folder, so that its `results.h5` is that batch's: it
/// holds the `manifest.json` a batch writes last (`skelid-batch/…`), or, where a batch was
/// stopped after its results.h5 and before its manifest, the log and journal a batch writes
/// from its start (`skelid.log` and `runs/`).
fn is_batch_folder(dir: &Path) -> bool {
    if dir.join("skelid.log").is_file() && dir.join(crate::journal::RUNS_DIR).is_dir() {
        return true;
    }
    #[derive(serde::Deserialize)]
    struct Manifest {
        format: String,
    }
    std::fs::read(dir.join("manifest.json"))
        .ok()
        .and_then(|b| serde_json::from_slice::<Manifest>(&b).ok())
        .is_some_and(|m| m.format.starts_with("skelid-batch/"))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A folder search passes over a `results.h5` beside a batch's manifest (and an
    /// earlier version's journal files in its `runs/`) and nothing else: not a `results.h5` without one, nor one beside another program's
    /// `manifest.json`, nor other archives beside it, nor a results file named by itself.
    #[test]
    fn a_folder_search_passes_over_a_batchs_own_results_only() {
        let d = tempfile::tempdir().unwrap();
        let root = d.path();
        let touch = |rel: &str, text: &str| {
            let p = root.join(rel);
            std::fs::create_dir_all(p.parent().unwrap()).unwrap();
            std::fs::write(&p, text).unwrap();
            p
        };
        let campaign = touch("campaign.h5", "");
        let night = touch("night1/results.h5", "");
        touch(
            "night1/manifest.json",
            r#"{"format": "skelid-batch/1", "runs": []}"#,
        );
        let beside = touch("night1/extra.h5", "");
        let bare = touch("bare/results.h5", "");
        let other = touch("other/results.h5", "");
        touch("other/manifest.json", r#"{"format": "someone-else/3"}"#);
        let broken = touch("broken/results.h5", "");
        touch("broken/manifest.json", "{not json");
        // Stopped before its manifest: the log and the journal say it is a batch's.
        let stopped = touch("stopped/results.h5", "");
        touch("stopped/skelid.log", "");
        touch("stopped/runs/a.run", "");
        let logged_only = touch("logged/results.h5", "");
        touch("logged/skelid.log", "");
        // A batch's journal of an earlier version: its runs as `runs/<key>.h5`, passed
        // over; a campaign's own folder that happens to be called `runs`, read.
        let legacy = touch("night1/runs/0123456789abcdef0123456789abcdef.h5", "");
        let stopped_legacy = touch("stopped/runs/fedcba9876543210fedcba9876543210.h5", "");
        let own_runs = touch("bare/runs/r1.h5", "");
        // In a batch's `runs/`, a name that is no run's key: a campaign kept there.
        let kept = touch("stopped/runs/sweep.h5", "");
        let arg = |p: &Path| p.display().to_string();

        let found = expand_inputs(&[arg(root)]).unwrap();
        let mut want = vec![
            campaign.clone(),
            beside,
            bare,
            own_runs,
            other,
            broken,
            logged_only,
            kept,
        ];
        want.sort();
        assert_eq!(found.archives, want);
        let mut over = vec![night.clone(), legacy, stopped, stopped_legacy];
        over.sort();
        assert_eq!(found.passed_over, over);
        let note = passed_over_note(&found.passed_over).unwrap();
        assert!(note.contains(&arg(&night)) && note.contains("skelid's own results"));

        // One file named three ways: read once, under its first name in order.
        let again = expand_inputs(&[
            arg(&campaign),
            arg(&root.join("bare/../campaign.h5")),
            arg(&root.join("campaign.h5")),
        ])
        .unwrap();
        assert_eq!(again.archives.len(), 1, "{again:?}");
        #[cfg(unix)]
        {
            let link = root.join("link.h5");
            std::os::unix::fs::symlink(&campaign, &link).unwrap();
            let linked = expand_inputs(&[arg(&link), arg(&campaign)]).unwrap();
            assert_eq!(linked.archives, vec![campaign.clone()]);
            std::fs::remove_file(&link).unwrap();
        }

        // Named by itself, and named and found at once: read.
        let named = expand_inputs(&[arg(&night)]).unwrap();
        assert_eq!(
            (named.archives, named.passed_over.len()),
            (vec![night.clone()], 0)
        );
        let both = expand_inputs(&[arg(root), arg(&night)]).unwrap();
        assert!(both.archives.contains(&night) && !both.passed_over.contains(&night));

        // A folder of nothing but a batch's output holds no archive, and says why.
        std::fs::remove_file(root.join("night1/extra.h5")).unwrap();
        match find_archives(&[arg(&root.join("night1"))]) {
            Err(FindError::Nothing(e)) => {
                let text = e.to_string();
                assert!(
                    text.contains("passed over") && text.contains("results.h5"),
                    "{text}"
                );
            }
            other => panic!("{other:?}"),
        }
        assert!(passed_over_note(&[]).is_none());
    }
}
