//! The inputs as a user gives them — files, folders, globs — expanded to the archives they
//! name, and a clear error when they name none. In: command-line arguments; out: paths.

use std::path::{Path, PathBuf};

/// Expands command-line arguments (files, folders searched recursively for `.h5`, `.hdf5`,
/// `.mat`, and glob patterns) to a sorted, de-duplicated list of files.
pub fn expand_inputs(args: &[String]) -> Result<Vec<PathBuf>, String> {
    let mut out = Vec::new();
    for a in args {
        let p = Path::new(a);
        if p.is_dir() {
            collect_dir(p, &mut out).map_err(|e| format!("{a}: cannot list folder: {e}"))?;
        } else if p.exists() {
            out.push(p.to_path_buf());
        } else if a.contains(['*', '?', '[']) {
            let paths = glob::glob(a).map_err(|e| format!("{a}: bad glob pattern: {e}"))?;
            let before = out.len();
            for entry in paths.flatten() {
                if entry.is_dir() {
                    collect_dir(&entry, &mut out)
                        .map_err(|e| format!("{}: {e}", entry.display()))?;
                } else {
                    out.push(entry);
                }
            }
            if out.len() == before {
                return Err(format!("{a}: the pattern matches no file"));
            }
        } else {
            return Err(format!("{a}: no such file or folder"));
        }
    }
    out.sort();
    out.dedup();
    Ok(out)
}

/// No archive among the inputs: what was looked at and what was there instead.
#[derive(Debug, thiserror::Error)]
#[error(
    "no campaign archive found: {0}; pass .h5, .hdf5, .he5 or .mat files, folders holding \
     them, or a glob (nothing was done)"
)]
pub struct NothingFound(pub String);

/// [`expand_inputs`], refusing an empty result with what each argument held instead.
pub fn find_archives(args: &[String]) -> Result<Vec<PathBuf>, FindError> {
    let files = expand_inputs(args).map_err(FindError::Bad)?;
    if !files.is_empty() {
        return Ok(files);
    }
    let seen: Vec<String> = args
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

fn collect_dir(dir: &Path, out: &mut Vec<PathBuf>) -> std::io::Result<()> {
    let mut entries: Vec<_> = std::fs::read_dir(dir)?
        .flatten()
        .map(|e| e.path())
        .collect();
    entries.sort();
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
            out.push(p);
        }
    }
    Ok(())
}
