//! A run's results laid out for HDF5 but not yet written: its groups, attributes and
//! datasets, with every compressed dataset's chunks already shuffled and deflated.
//!
//! Why: libhdf5 (as Debian builds it) is not thread-safe, so the hdf5 crate runs every call
//! under one process-wide lock. Compressing inside libhdf5 put most of a batch's output
//! cost (a quarter of all CPU time) under that lock, and `--jobs 2` could not beat
//! `--jobs 1` by much. Encoding here is plain CPU work that the batch's workers do in
//! parallel; writing an encoded run ([`super::ResultsWriter::write_encoded`]) hands finished
//! chunks to `H5Dwrite_chunk`, which only copies them into the file. Any reader reads them
//! as it reads libhdf5's own: chunks of [`CHUNK`] elements through the standard shuffle +
//! deflate pipeline.

/// Chunk length (elements) of a compressed dataset: a 30 000-sample track is one chunk.
/// With 4096 (32 KiB of floats) the writer made eight chunk writes of a track where one
/// does: an index entry each under libhdf5's lock, and writes of 20–30 kB, which cost the
/// kernel more than twice as much per byte as writes of 256 kB and over. Measured on 200
/// runs of the throughput campaign: the writer busy 15–20 % less.
pub const CHUNK: usize = 32_768;

/// Bytes of a chunk deflated at a time ([`compress_chunks`]), at most: the fast level
/// deflates a chunk's 256 KiB 40 % slower than as eight independent pieces of 32 KiB. A
/// shuffled chunk's pieces are its byte planes (a chunk is at most [`CHUNK`] elements).
/// Keep pieces under 64 KiB: zlib-rs's stored level (level 0) may return from a flush with
/// a larger piece's tail still buffered, which [`deflate_into`]'s loop would take for done.
const PIECE: usize = 32 * 1024;

/// A byte plane whose sample slices deflate to at least this share of their length is
/// stored rather than deflated ([`incompressible`]). The low bytes of a measured signal's
/// floats are noise: the fast level spent most of its time on them and made them longer
/// (its fixed Huffman codes spend 9 bits on half the byte values). On the planes of 400
/// tracks of the throughput campaign: a third of the bytes stored, the chunks 2 % smaller,
/// deflating 1.2–1.3× as fast.
const STORE_ABOVE: f64 = 0.98;

/// Bytes a sync flush adds to a deflate stream beyond its blocks' content, about: the
/// probe ([`incompressible`]) ends each slice with one.
const SYNC_MARK: f64 = 4.0;

/// Signals shorter than this are stored contiguous even when compression is asked for.
pub const MIN_COMPRESSED: usize = 64;

/// Deflate level of compressed float signals (fast; the shuffle does most of the work).
pub const SIGNAL_LEVEL: u8 = 1;

/// An attribute's value.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub enum Scalar {
    /// A float attribute.
    F64(f64),
    /// A UTF-8 string attribute.
    Str(String),
}

/// How a dataset's bytes are stored.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub enum Storage {
    /// Contiguous f64 values (small datasets).
    Plain(Vec<f64>),
    /// Chunked with shuffle (when the element is wider than a byte) then deflate at `level`;
    /// each chunk is the filter pipeline's output for [`CHUNK`] elements (the last one
    /// zero-padded, as libhdf5 pads it with the fill value).
    Chunked {
        /// Deflate level the chunks were compressed at (stored in the filter pipeline).
        level: u8,
        /// The filtered chunks, in order (byte strings, so that the journal stores them
        /// with one copy each rather than byte by byte).
        chunks: Vec<serde_bytes::ByteBuf>,
    },
}

/// Element type of a dataset.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
pub enum Elem {
    /// 64-bit float.
    F64,
    /// Unsigned byte (masks).
    U8,
}

impl Elem {
    /// Bytes of one element.
    pub fn size(self) -> usize {
        match self {
            Elem::F64 => 8,
            Elem::U8 => 1,
        }
    }
}

/// One dataset of an encoded run.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Dataset {
    /// Group it lives in, relative to the run's group ("" for the run's group itself).
    pub group: String,
    /// Dataset name.
    pub name: String,
    /// Element type.
    pub elem: Elem,
    /// Elements.
    pub len: usize,
    /// The bytes.
    pub storage: Storage,
}

/// One item of an encoded run, written in order.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub enum Item {
    /// Create a group (relative to the run's group; parents are created first).
    Group(String),
    /// Set an attribute on a group (relative path).
    Attr {
        /// Group ("" for the run's group).
        group: String,
        /// Attribute name.
        name: String,
        /// Value.
        value: Scalar,
    },
    /// Create a dataset.
    Dataset(Dataset),
    /// Set a string attribute on a dataset created before (its `units`).
    DatasetAttr {
        /// Group of the dataset (relative path).
        group: String,
        /// Dataset name.
        dataset: String,
        /// Attribute name.
        name: String,
        /// Value.
        value: String,
    },
}

/// A run's results, ready to be written under its absolute group path.
#[derive(Debug, Clone, Default, serde::Serialize, serde::Deserialize)]
pub struct EncodedRun {
    /// Absolute group path of the run (e.g. `/runs/run_001`).
    pub path: String,
    /// Groups, attributes and datasets, in the order they are written.
    pub items: Vec<Item>,
    /// The compressed datasets as given, while the run is fresh in memory: never stored.
    #[serde(skip)]
    kept: Kept,
}

/// Two encoded runs are equal when what they write is: the kept copies are a cache.
impl PartialEq for EncodedRun {
    fn eq(&self, other: &Self) -> bool {
        self.path == other.path && self.items == other.items
    }
}

/// The values of a fresh run's compressed datasets, by (group, name): the worker draws the
/// report's plots of the run it has just encoded, and inflating its chunks again for that
/// cost 3.5–4.6 ms of CPU a drawn run (200 runs of the throughput campaign: encoding 3.1 →
/// 2.65 s; `perf` gave it 7 % of a 40-run batch, every run drawn).
#[derive(Clone, Default)]
struct Kept(Vec<(String, String, Decoded)>);

impl std::fmt::Debug for Kept {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Kept({} datasets)", self.0.len())
    }
}

impl EncodedRun {
    /// An empty run at `path`.
    pub fn new(path: &str) -> EncodedRun {
        EncodedRun {
            path: path.to_string(),
            items: Vec::new(),
            kept: Kept::default(),
        }
    }

    /// Bytes of its datasets as stored (compressed chunks, plain values): what one copy of
    /// the run takes on disk, but for a few kB of names and headers.
    pub fn data_bytes(&self) -> u64 {
        let stored = |s: &Storage| match s {
            Storage::Plain(v) => (v.len() * 8) as u64,
            Storage::Chunked { chunks, .. } => chunks.iter().map(|c| c.len() as u64).sum(),
        };
        self.items
            .iter()
            .map(|i| match i {
                Item::Dataset(d) => stored(&d.storage),
                _ => 0,
            })
            .sum()
    }

    /// Drops the kept copies of the compressed datasets (the run reads its chunks from
    /// then on): for a run that waits in a queue after its plots are drawn.
    pub fn forget_kept(&mut self) {
        self.kept = Kept::default();
    }

    /// Sets a string attribute on the dataset `name` of `group`, added before.
    pub fn dataset_attr(&mut self, group: &str, dataset: &str, name: &str, value: &str) {
        self.items.push(Item::DatasetAttr {
            group: group.to_string(),
            dataset: dataset.to_string(),
            name: name.to_string(),
            value: value.to_string(),
        });
    }

    /// Adds a group.
    pub fn group(&mut self, group: &str) {
        self.items.push(Item::Group(group.to_string()));
    }

    /// Adds a float attribute.
    pub fn f64_attr(&mut self, group: &str, name: &str, value: f64) {
        self.items.push(Item::Attr {
            group: group.to_string(),
            name: name.to_string(),
            value: Scalar::F64(value),
        });
    }

    /// Adds a string attribute.
    pub fn str_attr(&mut self, group: &str, name: &str, value: &str) {
        self.items.push(Item::Attr {
            group: group.to_string(),
            name: name.to_string(),
            value: Scalar::Str(value.to_string()),
        });
    }

    /// Adds a float64 vector: chunked, shuffled and deflated when `compress` and long
    /// enough to be worth it, contiguous otherwise — the layout `campaign::write_signal`
    /// gives through libhdf5.
    pub fn signal(&mut self, group: &str, name: &str, data: &[f64], compress: bool) {
        let storage = if compress && data.len() >= MIN_COMPRESSED {
            self.keep(group, name, Decoded::F64(data.to_vec()));
            Storage::Chunked {
                level: SIGNAL_LEVEL,
                chunks: byte_bufs(compress_chunks(
                    bytemuck::cast_slice(data),
                    Elem::F64,
                    SIGNAL_LEVEL,
                )),
            }
        } else {
            Storage::Plain(data.to_vec())
        };
        self.dataset(group, name, Elem::F64, data.len(), storage);
    }

    /// Adds a byte vector, chunked and deflated at `level` (masks compress very well).
    pub fn bytes(&mut self, group: &str, name: &str, data: &[u8], level: u8) {
        self.keep(group, name, Decoded::U8(data.to_vec()));
        let storage = Storage::Chunked {
            level,
            chunks: byte_bufs(compress_chunks(data, Elem::U8, level)),
        };
        self.dataset(group, name, Elem::U8, data.len(), storage);
    }

    /// The value of the attribute `name` of `group` ("" for the run's group), when set.
    pub fn attr(&self, group: &str, name: &str) -> Option<&Scalar> {
        self.items.iter().find_map(|i| match i {
            Item::Attr {
                group: g,
                name: n,
                value,
            } if g == group && n == name => Some(value),
            _ => None,
        })
    }

    /// The string attribute `name` of the dataset `dataset` of `group`, when set.
    pub fn dataset_attr_text(&self, group: &str, dataset: &str, name: &str) -> Option<&str> {
        self.items.iter().find_map(|i| match i {
            Item::DatasetAttr {
                group: g,
                dataset: d,
                name: n,
                value,
            } if g == group && d == dataset && n == name => Some(value.as_str()),
            _ => None,
        })
    }

    /// Whether the run holds the group `group` (relative path).
    pub fn has_group(&self, group: &str) -> bool {
        self.items
            .iter()
            .any(|i| matches!(i, Item::Group(g) if g == group))
    }

    /// The elements of the dataset `name` of `group` as stored (inflated and unshuffled
    /// as a reader of the file would get them), or `None` when it has none such.
    pub fn read(&self, group: &str, name: &str) -> Option<Decoded> {
        let d = self.items.iter().find_map(|i| match i {
            Item::Dataset(d) if d.group == group && d.name == name => Some(d),
            _ => None,
        })?;
        if let Some((.., v)) = self.kept.0.iter().find(|(g, n, _)| g == group && n == name) {
            return Some(v.clone());
        }
        match &d.storage {
            Storage::Plain(v) => Some(Decoded::F64(v.clone())),
            Storage::Chunked { chunks, .. } => {
                let bytes = inflate_chunks(chunks, d.elem, d.len)?;
                Some(match d.elem {
                    Elem::F64 => Decoded::F64(
                        bytes
                            .chunks_exact(8)
                            .map(|b| f64::from_le_bytes(b.try_into().expect("8 bytes")))
                            .collect(),
                    ),
                    Elem::U8 => Decoded::U8(bytes),
                })
            }
        }
    }

    fn keep(&mut self, group: &str, name: &str, values: Decoded) {
        self.kept
            .0
            .push((group.to_string(), name.to_string(), values));
    }

    fn dataset(&mut self, group: &str, name: &str, elem: Elem, len: usize, storage: Storage) {
        self.items.push(Item::Dataset(Dataset {
            group: group.to_string(),
            name: name.to_string(),
            elem,
            len,
            storage,
        }));
    }
}

fn byte_bufs(chunks: Vec<Vec<u8>>) -> Vec<serde_bytes::ByteBuf> {
    chunks.into_iter().map(serde_bytes::ByteBuf::from).collect()
}

/// The chunk length a dataset of `len` elements is created with.
pub fn chunk_len(len: usize) -> usize {
    len.clamp(1, CHUNK)
}

/// Splits `bytes` (elements of `elem`) into chunks of [`chunk_len`] elements and runs each
/// through HDF5's filter pipeline as libhdf5 would: zero-pad to a whole chunk, shuffle
/// (bytes of equal significance together) when the element is wider than a byte, then zlib
/// at `level`. A chunk's stream is its pieces deflated independently (a shuffled chunk's
/// byte planes, each stored instead where deflate would gain next to nothing) between
/// zlib's header and checksum: any inflater reads it as one stream.
pub fn compress_chunks(bytes: &[u8], elem: Elem, level: u8) -> Vec<Vec<u8>> {
    let size = elem.size();
    let n = bytes.len() / size;
    let chunk = chunk_len(n);
    let chunk_bytes = chunk * size;
    let piece = if size > 1 { chunk } else { PIECE };
    let mut padded = vec![0u8; chunk_bytes];
    let mut shuffled = vec![0u8; chunk_bytes];
    let mut probe = Vec::new();
    with_deflater(level, |z| {
        bytes
            .chunks(chunk_bytes)
            .map(|part| {
                padded[..part.len()].copy_from_slice(part);
                padded[part.len()..].fill(0);
                let input = if size > 1 {
                    shuffle(&padded, size, &mut shuffled);
                    &shuffled
                } else {
                    &padded
                };
                // Room for what deflate makes of any input; `deflate_into` grows it if a
                // flush ever needs more.
                let mut out = Vec::with_capacity(chunk_bytes + chunk_bytes / 1000 + 64);
                out.extend_from_slice(&zlib_header(level));
                let pieces = input.chunks(piece);
                let last = pieces.len() - 1;
                for (i, p) in pieces.enumerate() {
                    let end = i == last;
                    if size > 1 && incompressible(z, p, &mut probe) {
                        store(p, end, &mut out);
                    } else {
                        // Every piece before the last ends on a byte boundary (a sync
                        // flush) with no final block; the last one ends the stream.
                        z.reset();
                        let flush = if end {
                            flate2::FlushCompress::Finish
                        } else {
                            flate2::FlushCompress::Sync
                        };
                        deflate_into(z, p, &mut out, flush);
                    }
                }
                out.extend_from_slice(&zlib_rs::adler32::adler32(1, input).to_be_bytes());
                out
            })
            .collect()
    })
}

thread_local! {
    /// This thread's raw deflaters (no zlib wrapper: [`compress_chunks`] writes the header
    /// and checksum around the pieces), one a level (a run's signals and masks alternate):
    /// made once, not once a dataset.
    static DEFLATERS: std::cell::RefCell<[Option<flate2::Compress>; 10]> =
        std::cell::RefCell::new(std::array::from_fn(|_| None));
}

/// Runs `f` with this thread's raw deflater at `level` (at most 9).
fn with_deflater<T>(level: u8, f: impl FnOnce(&mut flate2::Compress) -> T) -> T {
    let level = level.min(9);
    DEFLATERS.with(|cell| {
        let mut slots = cell.borrow_mut();
        let z = slots[usize::from(level)].get_or_insert_with(|| {
            flate2::Compress::new(flate2::Compression::new(u32::from(level)), false)
        });
        f(z)
    })
}

/// The two bytes zlib starts a stream with: deflate with a 32 KiB window, the level's class
/// (FLEVEL) as zlib writes it, and the check bits that make the pair a multiple of 31.
fn zlib_header(level: u8) -> [u8; 2] {
    let class: u16 = match level {
        0 | 1 => 0,
        2..=5 => 1,
        6 => 2,
        _ => 3,
    };
    let head = (0x78 << 8) | (class << 6);
    (head + 31 - head % 31).to_be_bytes()
}

/// Whether deflating `piece` would gain next to nothing: three slices of it (at a sixth, a
/// half and five sixths of the way), each a 24th of it, deflated come to at least
/// [`STORE_ABOVE`] of their length. An eighth of a deflate's work, which a plane of noise
/// repays eightfold.
///
/// Not its very start and end: a track's edges, where it is not valid, and a last chunk's
/// zero padding are constant and would pass for compressible, so that a plane of noise was
/// deflated whole for the few per cent its edges gain. Sliced inside, 200 runs of the
/// throughput campaign store 47 % more planes and deflate 12 % faster, for chunks 0.5 %
/// larger (README, *Since … forty-second session*).
///
/// The slices go through one stream, each ended by a sync flush, instead of one stream
/// each: a reset clears the deflater's 128 KiB hash table, a hundred times the bytes a
/// slice holds, and three of them were a third of the probe's time on a plane of noise.
/// A later slice may match an earlier one, which only makes a plane look compressible.
fn incompressible(z: &mut flate2::Compress, piece: &[u8], scratch: &mut Vec<u8>) -> bool {
    let w = piece.len() / 24;
    if w < 64 {
        return false;
    }
    z.reset();
    scratch.clear();
    [1, 3, 5].into_iter().all(|sixths| {
        let at = sixths * (piece.len() - w) / 6;
        let before = scratch.len();
        deflate_into(z, &piece[at..at + w], scratch, flate2::FlushCompress::Sync);
        // Less the sync flush's empty stored block (its length and complement, 4 bytes,
        // after the header's bits), which a stream's end would not have.
        (scratch.len() - before) as f64 >= STORE_ABOVE * w as f64 + SYNC_MARK
    })
}

/// Appends `piece` to a deflate stream as stored blocks, which start on the byte boundary
/// every piece before ends on; the last block is the stream's final one when `end`.
fn store(piece: &[u8], end: bool, out: &mut Vec<u8>) {
    let mut blocks = piece.chunks(usize::from(u16::MAX)).peekable();
    while let Some(b) = blocks.next() {
        // BFINAL, then BTYPE 00 (stored), then padding to the byte's end.
        out.push(u8::from(end && blocks.peek().is_none()));
        let len = b.len() as u16;
        out.extend_from_slice(&len.to_le_bytes());
        out.extend_from_slice(&(!len).to_le_bytes());
        out.extend_from_slice(b);
    }
}

/// Compresses all of `input` into `out` (grown as needed) with `flush`: to the stream's end
/// with [`Finish`](flate2::FlushCompress::Finish).
fn deflate_into(
    z: &mut flate2::Compress,
    mut input: &[u8],
    out: &mut Vec<u8>,
    flush: flate2::FlushCompress,
) {
    loop {
        if out.capacity() - out.len() < 64 {
            out.reserve(out.capacity().max(4096));
        }
        let before = z.total_in();
        let status = z
            .compress_vec(input, out, flush)
            .expect("deflate into a buffer with room cannot fail");
        input = &input[(z.total_in() - before) as usize..];
        let done = if flush == flate2::FlushCompress::Finish {
            status == flate2::Status::StreamEnd
        } else {
            input.is_empty() && out.len() < out.capacity()
        };
        if done {
            return;
        }
    }
}

/// A dataset's elements, decoded.
#[derive(Debug, Clone, PartialEq)]
pub enum Decoded {
    /// Float64 elements.
    F64(Vec<f64>),
    /// Byte elements.
    U8(Vec<u8>),
}

/// Undoes [`compress_chunks`]: inflates each chunk, unshuffles it and keeps the first
/// `len` elements; `None` when a chunk is not what the filter pipeline writes.
fn inflate_chunks(chunks: &[serde_bytes::ByteBuf], elem: Elem, len: usize) -> Option<Vec<u8>> {
    let size = elem.size();
    let chunk_bytes = chunk_len(len) * size;
    let mut out = Vec::with_capacity(chunks.len() * chunk_bytes);
    let mut raw = vec![0u8; chunk_bytes];
    let mut z = flate2::Decompress::new(true);
    for c in chunks {
        z.reset(true);
        let status = z
            .decompress(c, &mut raw, flate2::FlushDecompress::Finish)
            .ok()?;
        if status != flate2::Status::StreamEnd || z.total_out() as usize != chunk_bytes {
            return None;
        }
        let start = out.len();
        out.resize(start + chunk_bytes, 0);
        if size > 1 {
            unshuffle(&raw, size, &mut out[start..]);
        } else {
            out[start..].copy_from_slice(&raw);
        }
    }
    (out.len() >= len * size).then(|| {
        out.truncate(len * size);
        out
    })
}

/// HDF5's shuffle filter: byte j of element i goes to `j·n + i`.
fn shuffle(src: &[u8], size: usize, dst: &mut [u8]) {
    reorder(src, size, dst, true);
}

/// Undoes [`shuffle`]: byte `j·n + i` goes back to byte j of element i.
fn unshuffle(src: &[u8], size: usize, dst: &mut [u8]) {
    reorder(src, size, dst, false);
}

/// Moves n elements of `size` bytes between element order (byte j of element i at
/// `i·size + j`) and plane order (at `j·n + i`): to planes when `to_planes`. Eight-byte
/// elements go eight at a time through an 8×8 byte transpose in registers: byte by byte,
/// the shuffle was a sixth of a chunk's compression.
fn reorder(src: &[u8], size: usize, dst: &mut [u8], to_planes: bool) {
    let n = src.len() / size;
    let mut done = 0;
    if size == 8 {
        // Where block b's k-th word lies: element 8b + k in element order, plane k's
        // bytes 8b.. in plane order.
        let elements: fn(usize, usize, usize) -> usize = |b, k, _| 64 * b + 8 * k;
        let planes: fn(usize, usize, usize) -> usize = |b, k, n| k * n + 8 * b;
        let (from, to) = if to_planes {
            (elements, planes)
        } else {
            (planes, elements)
        };
        for b in 0..n / 8 {
            let mut w = [0u64; 8];
            for (k, w) in w.iter_mut().enumerate() {
                *w = u64::from_le_bytes(src[from(b, k, n)..][..8].try_into().expect("8 bytes"));
            }
            transpose8(&mut w);
            for (k, w) in w.iter().enumerate() {
                dst[to(b, k, n)..][..8].copy_from_slice(&w.to_le_bytes());
            }
        }
        done = n - n % 8;
    }
    for i in done..n {
        for j in 0..size {
            let (packed, planar) = (i * size + j, j * n + i);
            if to_planes {
                dst[planar] = src[packed];
            } else {
                dst[packed] = src[planar];
            }
        }
    }
}

/// Transposes the 8×8 byte matrix whose row r is `w[r]` (column c the bits 8c..8c+8):
/// afterwards byte r of `w[c]` is what byte c of `w[r]` was. The two off-diagonal 4×4
/// blocks trade places, then the 2×2 blocks within each 4×4, then single bytes.
fn transpose8(w: &mut [u64; 8]) {
    for r in 0..4 {
        let t = ((w[r] >> 32) ^ w[r + 4]) & 0x0000_0000_FFFF_FFFF;
        w[r] ^= t << 32;
        w[r + 4] ^= t;
    }
    for r in [0, 1, 4, 5] {
        let t = ((w[r] >> 16) ^ w[r + 2]) & 0x0000_FFFF_0000_FFFF;
        w[r] ^= t << 16;
        w[r + 2] ^= t;
    }
    for r in [0, 2, 4, 6] {
        let t = ((w[r] >> 8) ^ w[r + 1]) & 0x00FF_00FF_00FF_00FF;
        w[r] ^= t << 8;
        w[r + 1] ^= t;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Read;

    /// The shuffle filter done (`forward`) or undone the plain way, byte by byte, to check
    /// [`super::shuffle`] and [`super::unshuffle`] against.
    fn naive_shuffle(src: &[u8], size: usize, forward: bool) -> Vec<u8> {
        let n = src.len() / size;
        let mut out = vec![0u8; src.len()];
        for i in 0..n {
            for j in 0..size {
                let (packed, planar) = (i * size + j, j * n + i);
                if forward {
                    out[planar] = src[packed];
                } else {
                    out[packed] = src[planar];
                }
            }
        }
        out
    }

    #[test]
    fn a_run_reads_back_what_was_encoded() {
        let data: Vec<f64> = (0..10_000).map(|i| (i as f64 * 0.01).sin()).collect();
        let mask: Vec<u8> = (0..9_999).map(|i| u8::from(i % 7 == 0)).collect();
        let mut e = EncodedRun::new("/runs/r");
        e.group("wavelet");
        e.f64_attr("wavelet", "clearance", 0.5);
        e.signal("wavelet", "x", &data, true);
        e.signal("wavelet", "short", &data[..10], true);
        e.bytes("wavelet", "valid", &mask, 4);
        // Fresh (the kept copies), then from the chunks alone, as a journal gives it back.
        let fresh = e.clone();
        e.forget_kept();
        for e in [&fresh, &e] {
            assert_eq!(e.read("wavelet", "x"), Some(Decoded::F64(data.clone())));
            assert_eq!(
                e.read("wavelet", "short"),
                Some(Decoded::F64(data[..10].to_vec()))
            );
            assert_eq!(e.read("wavelet", "valid"), Some(Decoded::U8(mask.clone())));
            assert_eq!(e.read("", "x"), None);
        }
        assert_eq!(fresh, e, "the kept copies are no part of the run's value");
        assert_eq!(e.attr("wavelet", "clearance"), Some(&Scalar::F64(0.5)));
        assert!(e.has_group("wavelet") && !e.has_group("hilbert"));
    }

    #[test]
    fn a_fresh_run_reads_its_kept_copies_and_never_stores_them() {
        let data: Vec<f64> = (0..10_000).map(|i| (i as f64 * 0.01).cos()).collect();
        let mut e = EncodedRun::new("/runs/r");
        e.signal("", "x", &data, true);
        // Chunks that inflate to nothing: only the kept copy can give the values back.
        for item in &mut e.items {
            if let Item::Dataset(Dataset {
                storage: Storage::Chunked { chunks, .. },
                ..
            }) = item
            {
                chunks.iter_mut().for_each(|c| *c = vec![1, 2, 3].into());
            }
        }
        assert_eq!(e.read("", "x"), Some(Decoded::F64(data)));
        let stored: EncodedRun = postcard::from_bytes(&postcard::to_stdvec(&e).unwrap()).unwrap();
        assert_eq!(stored.read("", "x"), None, "read from the broken chunks");
        e.forget_kept();
        assert_eq!(e.read("", "x"), None);
    }

    /// Bytes that look random: splitmix64 of the index, its top byte.
    fn noise(len: usize) -> Vec<u8> {
        (0..len as u64)
            .map(|i| {
                let mut z = i.wrapping_add(1).wrapping_mul(0x9E37_79B9_7F4A_7C15);
                z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
                z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
                ((z ^ (z >> 31)) >> 56) as u8
            })
            .collect()
    }

    #[test]
    fn shuffles_equal_the_plain_byte_scatter_for_every_size_and_length() {
        for size in [1, 2, 4, 8] {
            for n in (0..70).chain([1000, 30_000, 32_768]) {
                let src = noise(n * size);
                let mut fast = vec![0u8; src.len()];
                shuffle(&src, size, &mut fast);
                assert_eq!(fast, naive_shuffle(&src, size, true), "size {size}, {n}");
                let mut back = vec![0u8; src.len()];
                unshuffle(&fast, size, &mut back);
                assert_eq!(back, naive_shuffle(&fast, size, false), "size {size}, {n}");
                assert_eq!(back, src, "size {size}, {n} elements");
            }
        }
    }

    #[test]
    fn the_zlib_header_is_the_one_zlib_writes_at_every_level() {
        for level in 0..=9u8 {
            let mut z = flate2::Compress::new(flate2::Compression::new(level.into()), true);
            let mut out = Vec::with_capacity(64);
            z.compress_vec(&[], &mut out, flate2::FlushCompress::Finish)
                .unwrap();
            assert_eq!(zlib_header(level), [out[0], out[1]], "level {level}");
        }
    }

    #[test]
    fn noise_planes_are_stored_and_the_others_deflated() {
        // Floats near 1 whose five low bytes are noise: those planes cannot shrink, the
        // three high ones (sign, exponent, top of the mantissa) nearly vanish.
        let n = 30_000;
        let bits = noise(8 * n);
        let data: Vec<f64> = (0..n)
            .map(|i| {
                let low = u64::from_le_bytes(bits[8 * i..8 * i + 8].try_into().unwrap());
                f64::from_bits(1.0f64.to_bits() | (low & 0xFF_FFFF_FFFF))
            })
            .collect();
        let bytes: &[u8] = bytemuck::cast_slice(&data);
        let chunks = compress_chunks(bytes, Elem::F64, 1);
        assert_eq!(chunks.len(), 1);
        let ours = chunks[0].len();
        // Five planes stored (5 bytes of block header each) and three deflated to little.
        assert!(ours >= 5 * n && ours < 5 * n + n / 10, "{ours} bytes");
        // One plain zlib stream of the shuffled chunk at the same level is longer.
        let mut shuffled = vec![0u8; bytes.len()];
        shuffle(bytes, 8, &mut shuffled);
        let mut z = flate2::Compress::new(flate2::Compression::new(1), true);
        let mut plain = Vec::new();
        deflate_into(&mut z, &shuffled, &mut plain, flate2::FlushCompress::Finish);
        assert!(ours < plain.len(), "{ours} against {}", plain.len());
        let mut raw = Vec::new();
        flate2::read::ZlibDecoder::new(&chunks[0][..])
            .read_to_end(&mut raw)
            .unwrap();
        assert_eq!(raw, shuffled);
        // Whole counts (an ADC's) leave no plane of noise: every one is deflated, the
        // chunk to a small part of its size.
        let counts: Vec<f64> = (0..n).map(|i| (i % 4096) as f64).collect();
        let counted = compress_chunks(bytemuck::cast_slice(&counts), Elem::F64, 1)[0].len();
        eprintln!(
            "{} bytes: noise {ours} (one plain stream {}), whole counts {counted}",
            8 * n,
            plain.len()
        );
        assert!(counted < 8 * n / 20, "{counted} bytes");
    }

    #[test]
    fn a_plane_of_noise_with_constant_edges_is_stored() {
        // A track of noise that is not valid in its first and last tenth (stored as NaN
        // there): its five low planes are noise between two constant runs. Deflated, they
        // would gain their edges' few per cent at the whole plane's cost; they are stored.
        let n = 30_000;
        let bits = noise(8 * n);
        let data: Vec<f64> = (0..n)
            .map(|i| {
                if i < n / 10 || i >= n - n / 10 {
                    return f64::NAN;
                }
                let low = u64::from_le_bytes(bits[8 * i..8 * i + 8].try_into().unwrap());
                f64::from_bits(1.0f64.to_bits() | (low & 0xFF_FFFF_FFFF))
            })
            .collect();
        let bytes: &[u8] = bytemuck::cast_slice(&data);
        let chunk = &compress_chunks(bytes, Elem::F64, 1)[0];
        // Five planes stored whole (each a stored block of its 30 000 bytes, the header's
        // length field n), three deflated to little.
        let stored_headers = chunk
            .windows(5)
            .filter(|h| {
                h[1..3] == (n as u16).to_le_bytes() && h[3..5] == (!(n as u16)).to_le_bytes()
            })
            .count();
        assert_eq!(stored_headers, 5, "{} bytes", chunk.len());
        assert!(chunk.len() < 5 * n + n / 10, "{} bytes", chunk.len());
        let mut raw = Vec::new();
        flate2::read::ZlibDecoder::new(&chunk[..])
            .read_to_end(&mut raw)
            .unwrap();
        let mut shuffled = vec![0u8; bytes.len()];
        shuffle(bytes, 8, &mut shuffled);
        assert_eq!(raw, shuffled);
    }

    #[test]
    fn chunks_inflate_and_unshuffle_to_the_padded_data() {
        // A track's kind of data: a smooth part and noise in the low bytes, over two whole
        // chunks and part of a third, each deflated in eight pieces.
        let data: Vec<f64> = (0..70_000u64)
            .map(|i| {
                (i as f64 * 0.01).sin()
                    + (i.wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 40) as f64 * 1e-12
            })
            .collect();
        let chunks = compress_chunks(bytemuck::cast_slice(&data), Elem::F64, 1);
        assert_eq!(chunks.len(), 3);
        let mut back = Vec::new();
        for c in &chunks {
            let mut raw = Vec::new();
            flate2::read::ZlibDecoder::new(&c[..])
                .read_to_end(&mut raw)
                .unwrap();
            assert_eq!(raw.len(), CHUNK * 8);
            back.extend(naive_shuffle(&raw, 8, false));
        }
        let back: &[f64] = bytemuck::cast_slice(&back);
        assert_eq!(&back[..data.len()], &data[..]);
        assert!(back[data.len()..].iter().all(|&x| x == 0.0));
    }
}
