//! The reader's stream, child to parent: one frame after another, a little-endian `u32`
//! length, a JSON [`Frame`], then for a [`Frame::Run`] that was read the samples as
//! little-endian `f64` (input first when there is one, then output).

use std::io::{Read, Write};

use serde::{Deserialize, Serialize};

use crate::ingest::{PlacedRun, RunMeta};

/// One message of the reader's stream.
// A frame is serialised once per run onto the reader's pipe and dropped: the run's
// metadata inline costs nothing worth a box.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Serialize, Deserialize)]
pub enum Frame {
    /// The archive (index into the list given) is open; its runs follow.
    Open {
        /// Archive index.
        archive: usize,
        /// Groups of the archive with datasets that are not runs.
        #[serde(default)]
        not_runs: Vec<crate::ingest::NotARun>,
        /// This shard's runs in the archive, their group paths in the order they will be
        /// read: the progress's total counts them before they are read, and when the child
        /// dies reading one, the parent knows which run killed it, records that run failed,
        /// and a new child goes on after it.
        paths: Vec<String>,
        /// The archive's runs of every shard (this shard's are sent, the others' skipped):
        /// those after a run the child died on, as the archive's last, are counted unsent.
        entries: usize,
    },
    /// One run of this shard; samples follow when `meta` is `Ok` and it is not `placed`.
    Run {
        /// Archive index.
        archive: usize,
        /// Group path.
        path: String,
        /// The run's metadata, or why it cannot be read.
        meta: Result<RunMeta, String>,
        /// The kind of `meta`'s error ([`crate::ingest::IngestError::kind`]), for
        /// `skelid inspect --json`.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        error_kind: Option<String>,
        /// Whether the run has input samples (sent before the output's, or placed).
        has_input: bool,
        /// Where the samples lie in the archive, when they are not sent: the parent reads
        /// them there.
        placed: Option<PlacedRun>,
    },
    /// A run of another shard (counted, not read).
    Skip {
        /// Archive index.
        archive: usize,
    },
    /// The archive is done; `error` when it could not be opened at all.
    Close {
        /// Archive index.
        archive: usize,
        /// Why the archive could not be opened.
        error: Option<String>,
        /// The kind of `error` ([`crate::ingest::IngestError::kind`]).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        error_kind: Option<String>,
    },
}

/// A run's samples as read: input (when the run has one), output.
pub type Samples = (Option<Vec<f64>>, Vec<f64>);

/// Bytes buffered on each side of the reading child's pipe. Small on purpose: a frame's
/// header goes through the buffer, but a run's samples (hundreds of kilobytes) are longer,
/// so the buffers pass them straight between the pipe and the values instead of copying
/// them once more on each side, as a 1 MB buffer did.
pub(super) const FRAME_BUFFER: usize = 64 << 10;

pub(super) fn write_frame(
    out: &mut impl Write,
    frame: &Frame,
    samples: Option<&Samples>,
) -> std::io::Result<()> {
    let header = serde_json::to_vec(frame).map_err(std::io::Error::other)?;
    out.write_all(&(header.len() as u32).to_le_bytes())?;
    out.write_all(&header)?;
    if let Some((input, output)) = samples {
        for v in input.iter().chain(std::iter::once(output)) {
            out.write_all(&(v.len() as u64).to_le_bytes())?;
            // The samples' bytes as they lie in memory where that is little-endian (one
            // copy, not 60 000 calls: a tenth of the reader's CPU time).
            if cfg!(target_endian = "little") {
                out.write_all(bytemuck::cast_slice(v))?;
            } else {
                for x in v {
                    out.write_all(&x.to_le_bytes())?;
                }
            }
        }
    }
    // Each frame reaches the parent at once: its watchdog measures progress by them.
    out.flush()
}

/// Reads one frame; `None` at a clean end of the stream.
pub(super) fn read_frame(inp: &mut impl Read) -> std::io::Result<Option<(Frame, Option<Samples>)>> {
    let mut len = [0u8; 4];
    match inp.read_exact(&mut len) {
        Ok(()) => {}
        Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof => return Ok(None),
        Err(e) => return Err(e),
    }
    let mut header = vec![0u8; u32::from_le_bytes(len) as usize];
    inp.read_exact(&mut header)?;
    let frame: Frame = serde_json::from_slice(&header).map_err(std::io::Error::other)?;
    let samples = match &frame {
        Frame::Run {
            meta: Ok(_),
            has_input,
            placed: None,
            ..
        } => {
            let input = if *has_input {
                Some(read_vector(inp)?)
            } else {
                None
            };
            Some((input, read_vector(inp)?))
        }
        _ => None,
    };
    Ok(Some((frame, samples)))
}

pub(super) fn read_vector(inp: &mut impl Read) -> std::io::Result<Vec<f64>> {
    let mut n = [0u8; 8];
    inp.read_exact(&mut n)?;
    let n = u64::from_le_bytes(n) as usize;
    // Read straight into the values, little-endian bits put in order where need be.
    let mut v = vec![0f64; n];
    inp.read_exact(bytemuck::cast_slice_mut(&mut v))?;
    if cfg!(target_endian = "big") {
        for x in &mut v {
            *x = f64::from_bits(u64::from_le(x.to_bits()));
        }
    }
    Ok(v)
}
