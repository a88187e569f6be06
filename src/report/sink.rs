//! The one place a batch's `results.h5` writer is chosen: [`DirectWriter`], which lays
//! the file out itself, or libhdf5's [`ResultsWriter`] where runs must be copied from an
//! earlier version's journal files (`<key>.h5`, copied object by object with `H5Ocopy`),
//! or where `SKELID_LIBHDF5_WRITER=1` asks for it (to compare the two, or should a reader
//! ever fail on the direct writer's file).

use std::path::{Path, PathBuf};

use super::direct::{DirectWriter, PlacedData, Placer};
use super::encoded::EncodedRun;
use super::{ReportError, ResultsWriter};

/// A batch's results.h5 being written, by one writer or the other.
pub enum ResultsFile {
    /// Laid out without libhdf5 (the default).
    Direct(DirectWriter),
    /// Through libhdf5.
    Library(ResultsWriter),
}

/// Dispatches a call to whichever writer it is.
macro_rules! either {
    ($self:expr, $w:ident => $call:expr) => {
        match $self {
            ResultsFile::Direct($w) => $call,
            ResultsFile::Library($w) => $call,
        }
    };
}

impl ResultsFile {
    /// Starts `<dir>/results.h5`; through libhdf5 when `legacy` runs will be copied in or
    /// the environment asks for it.
    pub fn create(dir: &Path, legacy: bool) -> Result<ResultsFile, ReportError> {
        if legacy || library_asked() {
            ResultsWriter::create(dir).map(ResultsFile::Library)
        } else {
            DirectWriter::create(dir).map(ResultsFile::Direct)
        }
    }

    /// Stores a batch's settings on the file's root.
    pub fn write_settings(&self, record: &serde_json::Value) -> Result<(), ReportError> {
        either!(self, w => w.write_settings(record))
    }

    /// Adds one encoded run under the group path `dst`.
    pub fn write_encoded_as(&self, run: &EncodedRun, dst: &str) -> Result<(), ReportError> {
        self.write_placed_as(run, None, dst)
    }

    /// Adds one encoded run under `dst` whose data a worker may have put in the file
    /// already ([`placer`](Self::placer)); libhdf5's writer writes them all itself.
    pub fn write_placed_as(
        &self,
        run: &EncodedRun,
        placed: Option<&PlacedData>,
        dst: &str,
    ) -> Result<(), ReportError> {
        match self {
            ResultsFile::Direct(w) => w.write_placed_as(run, placed, dst),
            ResultsFile::Library(w) => w.write_encoded_as(run, dst),
        }
    }

    /// A handle for the batch's workers to put runs' data into the file themselves: the
    /// direct writer's only.
    pub fn placer(&self) -> Option<Placer> {
        match self {
            ResultsFile::Direct(w) => Some(w.placer()),
            ResultsFile::Library(_) => None,
        }
    }

    /// Copies the run at `src_path` of an earlier version's journal file `src` to `dst`
    /// (libhdf5's writer only: [`create`](Self::create) picks it when such files exist).
    pub fn copy_run_from(&self, src: &Path, src_path: &str, dst: &str) -> Result<(), ReportError> {
        match self {
            ResultsFile::Library(w) => w.copy_run_from(src, src_path, dst),
            ResultsFile::Direct(_) => Err(ReportError {
                file: src.display().to_string(),
                detail: "a journal file of an earlier version turned up after the batch \
                         started: run the batch again to include it"
                    .into(),
            }),
        }
    }

    /// Moves the run at group path `from` to `to`.
    pub fn move_run(&self, from: &str, to: &str) -> Result<(), ReportError> {
        either!(self, w => w.move_run(from, to))
    }

    /// Removes the object at `path`.
    pub fn remove(&self, path: &str) -> Result<(), ReportError> {
        either!(self, w => w.remove(path))
    }

    /// Finishes the file and renames it into place.
    pub fn finish(self) -> Result<PathBuf, ReportError> {
        either!(self, w => w.finish())
    }

    /// Closes and deletes the unfinished file.
    pub fn abandon(self) {
        either!(self, w => w.abandon())
    }
}

/// Whether `SKELID_LIBHDF5_WRITER` asks for libhdf5's writer (set, neither empty nor `0`).
fn library_asked() -> bool {
    std::env::var_os("SKELID_LIBHDF5_WRITER").is_some_and(|v| !v.is_empty() && v != "0")
}
