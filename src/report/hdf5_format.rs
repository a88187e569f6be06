//! The few on-disk structures of the HDF5 file format that `results.h5` is made of,
//! encoded byte by byte (HDF5 File Format Specification 3.0), for [`super::direct`]: the
//! version 0 superblock; version 1 object headers for datasets (as libhdf5 1.8–1.14 write
//! them at the default, earliest format); groups either as version 2 object headers that
//! hold their links (a "compact" group of HDF5 1.8) or with a symbol table (a local heap
//! of names, symbol table nodes and a B-tree, as libhdf5 writes them); a global heap
//! collection for variable-length strings; and a version 1 B-tree indexing a dataset's
//! chunks.
//!
//! Every structure here is one HDF5 1.8 and later read; the encodings of the messages
//! that libhdf5 itself writes for results.h5 (types, fill values, filters, layouts) are
//! the bytes it writes, checked in the tests below against a file libhdf5 wrote.

use super::encoded::Elem;

/// Bytes of an address or a length in the file (the superblock says 8).
const SIZE: u8 = 8;

/// The undefined address.
pub const UNDEF: u64 = u64::MAX;

/// Bytes of the version 0 superblock, root symbol table entry included.
pub const SUPERBLOCK_LEN: usize = 96;

/// Half the number of entries a chunk B-tree node holds (libhdf5's default, which a
/// version 0 superblock implies).
const CHUNK_BTREE_K: usize = 32;

/// The version 0 superblock: 8-byte addresses and lengths, the default B-tree ranks, the
/// root group's object header at `root` and the file `eof` bytes long.
pub fn superblock(root: u64, eof: u64) -> Vec<u8> {
    let mut b = Vec::with_capacity(SUPERBLOCK_LEN);
    b.extend_from_slice(b"\x89HDF\r\n\x1a\n");
    // Superblock, free-space, root symbol table and shared-header versions, a reserved
    // byte, then the sizes of offsets and lengths and another reserved byte.
    b.extend_from_slice(&[0, 0, 0, 0, 0, SIZE, SIZE, 0]);
    b.extend_from_slice(&4u16.to_le_bytes()); // group leaf node K
    b.extend_from_slice(&16u16.to_le_bytes()); // group internal node K
    b.extend_from_slice(&0u32.to_le_bytes()); // consistency flags
    b.extend_from_slice(&0u64.to_le_bytes()); // base address
    b.extend_from_slice(&UNDEF.to_le_bytes()); // free-space info
    b.extend_from_slice(&eof.to_le_bytes());
    b.extend_from_slice(&UNDEF.to_le_bytes()); // driver info

    // The root's symbol table entry: no name, its header, nothing cached.
    b.extend_from_slice(&0u64.to_le_bytes());
    b.extend_from_slice(&root.to_le_bytes());
    b.extend_from_slice(&[0; 24]);
    debug_assert_eq!(b.len(), SUPERBLOCK_LEN);
    b
}

/// An object header message: its type and its encoded body.
#[derive(Debug, Clone, PartialEq)]
pub struct Message {
    kind: u16,
    /// Message flags: 1 for a constant message (datatypes, fill values, filters).
    flags: u8,
    body: Vec<u8>,
}

/// Message types.
const DATASPACE: u16 = 0x01;
const LINK_INFO: u16 = 0x02;
const DATATYPE: u16 = 0x03;
const FILL_VALUE: u16 = 0x05;
const LINK: u16 = 0x06;
const LAYOUT: u16 = 0x08;
const GROUP_INFO: u16 = 0x0a;
const FILTERS: u16 = 0x0b;
const ATTRIBUTE: u16 = 0x0c;
const ATTRIBUTE_INFO: u16 = 0x15;
const SYMBOL_TABLE: u16 = 0x11;

/// The datatype message body of an element type (little-endian, as skelid stores them).
fn datatype(elem: Elem) -> Vec<u8> {
    match elem {
        // Floating point, version 1: little-endian, implied leading mantissa bit, sign at
        // bit 63; 64 bits from bit 0, exponent at 52 (11 bits), mantissa at 0 (52 bits),
        // bias 1023.
        Elem::F64 => vec![
            0x11, 0x20, 0x3f, 0x00, 8, 0, 0, 0, 0, 0, 64, 0, 52, 11, 0, 52, 0xff, 0x03, 0, 0,
        ],
        Elem::U8 => unsigned_byte(),
    }
}

/// Fixed-point, version 1: little-endian, unsigned, one byte of 8 bits from bit 0 (also
/// the base type of a variable-length string).
fn unsigned_byte() -> Vec<u8> {
    vec![0x10, 0, 0, 0, 1, 0, 0, 0, 0, 0, 8, 0]
}

/// A variable-length UTF-8 string, null-terminated, as libhdf5 makes it (`H5T_VARIABLE`):
/// length, heap collection address and object index on disk.
fn vlen_utf8() -> Vec<u8> {
    let mut b = vec![0x19, 0x01, 0x01, 0x00];
    b.extend_from_slice(&16u32.to_le_bytes());
    b.extend_from_slice(&unsigned_byte());
    b
}

/// A version 1 dataspace: scalar (`None`) or one dimension of `n` elements, its maximum
/// stored too (as libhdf5 stores a fixed size).
fn dataspace(n: Option<u64>) -> Vec<u8> {
    match n {
        None => vec![1, 0, 0, 0, 0, 0, 0, 0],
        Some(n) => {
            let mut b = vec![1, 1, 1, 0, 0, 0, 0, 0];
            b.extend_from_slice(&n.to_le_bytes());
            b.extend_from_slice(&n.to_le_bytes());
            b
        }
    }
}

/// A heap ID: where a variable-length string lives in a global heap collection.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct HeapId {
    /// Address of the collection.
    pub collection: u64,
    /// Index of the object in it (from 1).
    pub index: u32,
    /// Bytes of the string.
    pub len: u32,
}

/// An attribute's value.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum AttrValue {
    /// A float64 scalar.
    F64(f64),
    /// A variable-length UTF-8 string scalar, in a global heap.
    Text(HeapId),
}

/// An attribute message (version 3: its name's character set UTF-8), scalar.
pub fn attribute(name: &str, value: AttrValue) -> Message {
    let (dtype, data) = match value {
        AttrValue::F64(x) => (datatype(Elem::F64), x.to_le_bytes().to_vec()),
        AttrValue::Text(id) => {
            let mut d = id.len.to_le_bytes().to_vec();
            d.extend_from_slice(&id.collection.to_le_bytes());
            d.extend_from_slice(&id.index.to_le_bytes());
            (vlen_utf8(), d)
        }
    };
    let space = dataspace(None);
    let mut b = vec![3, 0];
    b.extend_from_slice(&(name.len() as u16 + 1).to_le_bytes());
    b.extend_from_slice(&(dtype.len() as u16).to_le_bytes());
    b.extend_from_slice(&(space.len() as u16).to_le_bytes());
    b.push(1);
    b.extend_from_slice(name.as_bytes());
    b.push(0);
    b.extend_from_slice(&dtype);
    b.extend_from_slice(&space);
    b.extend_from_slice(&data);
    Message {
        kind: ATTRIBUTE,
        flags: 0,
        body: b,
    }
}

/// How a dataset's bytes lie in the file.
#[derive(Debug, Clone, PartialEq)]
pub enum Storage {
    /// Contiguous at an address, this many bytes.
    Contiguous { addr: u64, len: u64 },
    /// Chunks of `chunk` elements indexed by the B-tree at `btree` (`UNDEF` where none
    /// was written), filtered by shuffle (when `shuffle`) then deflate at `level`, or not
    /// filtered (`None`).
    Chunked {
        btree: u64,
        chunk: u32,
        shuffle: bool,
        level: Option<u8>,
    },
}

/// The messages of a one-dimensional dataset of `len` elements of `elem`, stored as
/// `storage`, in the order libhdf5 writes them; its attributes follow.
pub fn dataset(elem: Elem, len: u64, storage: &Storage) -> Vec<Message> {
    let constant = |kind, body| Message {
        kind,
        flags: 1,
        body,
    };
    let mut m = vec![
        Message {
            kind: DATASPACE,
            flags: 0,
            body: dataspace(Some(len)),
        },
        constant(DATATYPE, datatype(elem)),
    ];
    match *storage {
        Storage::Contiguous { addr, len } => {
            // Version 2: allocated late, fill written if set, the default fill defined.
            m.push(constant(FILL_VALUE, vec![2, 2, 2, 1, 0, 0, 0, 0]));
            let mut l = vec![3, 1];
            l.extend_from_slice(&addr.to_le_bytes());
            l.extend_from_slice(&len.to_le_bytes());
            m.push(Message {
                kind: LAYOUT,
                flags: 0,
                body: l,
            });
        }
        Storage::Chunked {
            btree,
            chunk,
            shuffle,
            level,
        } => {
            // Allocated incrementally, fill written on allocation.
            m.push(constant(FILL_VALUE, vec![2, 3, 0, 1, 0, 0, 0, 0]));
            if let Some(level) = level {
                let mut filters = Vec::new();
                if shuffle {
                    filters.push(filter(2, b"shuffle\0", elem.size() as u32));
                }
                filters.push(filter(1, b"deflate\0", u32::from(level)));
                let mut f = vec![1, filters.len() as u8, 0, 0, 0, 0, 0, 0];
                f.extend(filters.into_iter().flatten());
                m.push(constant(FILTERS, f));
            }
            let mut l = vec![3, 2, 2];
            l.extend_from_slice(&btree.to_le_bytes());
            l.extend_from_slice(&chunk.to_le_bytes());
            l.extend_from_slice(&(elem.size() as u32).to_le_bytes());
            m.push(Message {
                kind: LAYOUT,
                flags: 0,
                body: l,
            });
        }
    }
    m
}

/// One filter of a version 1 pipeline: optional, its name, one client value (padded).
fn filter(id: u16, name: &[u8; 8], value: u32) -> Vec<u8> {
    let mut b = id.to_le_bytes().to_vec();
    b.extend_from_slice(&8u16.to_le_bytes());
    b.extend_from_slice(&1u16.to_le_bytes());
    b.extend_from_slice(&1u16.to_le_bytes());
    b.extend_from_slice(name);
    b.extend_from_slice(&value.to_le_bytes());
    b.extend_from_slice(&[0; 4]);
    b
}

/// A version 1 object header (what libhdf5 writes for a dataset at the earliest format):
/// its messages in one chunk, each padded to 8 bytes.
pub fn header_v1(messages: &[Message]) -> Vec<u8> {
    let size: usize = messages
        .iter()
        .map(|m| 8 + m.body.len().next_multiple_of(8))
        .sum();
    let mut b = Vec::with_capacity(16 + size);
    b.extend_from_slice(&[1, 0]);
    b.extend_from_slice(&(messages.len() as u16).to_le_bytes());
    b.extend_from_slice(&1u32.to_le_bytes()); // reference count
    b.extend_from_slice(&(size as u32).to_le_bytes());
    b.extend_from_slice(&[0; 4]);
    for m in messages {
        let padded = m.body.len().next_multiple_of(8);
        b.extend_from_slice(&m.kind.to_le_bytes());
        b.extend_from_slice(&(padded as u16).to_le_bytes());
        b.extend_from_slice(&[m.flags, 0, 0, 0]);
        b.extend_from_slice(&m.body);
        b.resize(b.len() + padded - m.body.len(), 0);
    }
    b
}

/// A hard link message to the object header at `addr`, named `name` (its character set
/// UTF-8 where it is not ASCII).
pub fn link(name: &str, addr: u64) -> Message {
    let n = name.len();
    let (width, len): (u8, Vec<u8>) = if n <= 0xff {
        (0, vec![n as u8])
    } else if n <= 0xffff {
        (1, (n as u16).to_le_bytes().to_vec())
    } else {
        (2, (n as u32).to_le_bytes().to_vec())
    };
    let utf8 = !name.is_ascii();
    let mut b = vec![1, width | if utf8 { 0x10 } else { 0 }];
    if utf8 {
        b.push(1);
    }
    b.extend_from_slice(&len);
    b.extend_from_slice(name.as_bytes());
    b.extend_from_slice(&addr.to_le_bytes());
    Message {
        kind: LINK,
        flags: 0,
        body: b,
    }
}

/// The messages that open a group's header: links and attributes kept in the header
/// (no fractal heap, no name index), the default group settings.
pub fn group_opening() -> Vec<Message> {
    let mut compact = vec![0, 0];
    compact.extend_from_slice(&UNDEF.to_le_bytes());
    compact.extend_from_slice(&UNDEF.to_le_bytes());
    vec![
        Message {
            kind: LINK_INFO,
            flags: 0,
            body: compact.clone(),
        },
        Message {
            kind: GROUP_INFO,
            flags: 0,
            body: vec![0, 0],
        },
        // Without it libhdf5 counts no attributes on a version 2 header (H5Oget_info).
        Message {
            kind: ATTRIBUTE_INFO,
            flags: 0,
            body: compact,
        },
    ]
}

/// A version 2 object header (HDF5 1.8; a group's here): one chunk, its size in 4 bytes,
/// no times, checksummed. Unlike version 1 it has no 16-bit message count, so a group may
/// hold any number of links.
pub fn header_v2(messages: &[Message]) -> Vec<u8> {
    let size: usize = messages.iter().map(|m| 4 + m.body.len()).sum();
    let mut b = Vec::with_capacity(14 + size);
    b.extend_from_slice(b"OHDR");
    b.extend_from_slice(&[2, 0x02]);
    b.extend_from_slice(&(size as u32).to_le_bytes());
    for m in messages {
        b.push(m.kind as u8);
        b.extend_from_slice(&(m.body.len() as u16).to_le_bytes());
        b.push(m.flags);
        b.extend_from_slice(&m.body);
    }
    let sum = lookup3(&b, 0);
    b.extend_from_slice(&sum.to_le_bytes());
    b
}

/// The messages of a version 2 header written by [`header_v2`] (for a group to be
/// changed after it was written), or `None` where `bytes` does not hold one whole.
pub fn parse_v2(bytes: &[u8]) -> Option<Vec<Message>> {
    if bytes.len() < 14 || &bytes[..4] != b"OHDR" || bytes[4] != 2 || bytes[5] != 0x02 {
        return None;
    }
    let size = u32::from_le_bytes(bytes[6..10].try_into().ok()?) as usize;
    let end = 10 + size;
    let sum = u32::from_le_bytes(bytes.get(end..end + 4)?.try_into().ok()?);
    if lookup3(&bytes[..end], 0) != sum {
        return None;
    }
    let mut m = Vec::new();
    let mut p = 10;
    while p < end {
        let kind = u16::from(bytes[p]);
        let len = usize::from(u16::from_le_bytes(bytes[p + 1..p + 3].try_into().ok()?));
        let flags = bytes[p + 3];
        m.push(Message {
            kind,
            flags,
            body: bytes.get(p + 4..p + 4 + len)?.to_vec(),
        });
        p += 4 + len;
    }
    Some(m)
}

/// The whole length (prefix, messages, checksum) of the version 2 header whose first 10
/// bytes are `prefix`; `None` where they are not a version 2 header's.
pub fn v2_len(prefix: &[u8]) -> Option<usize> {
    (prefix.len() >= 10 && &prefix[..4] == b"OHDR")
        .then(|| 14 + u32::from_le_bytes(prefix[6..10].try_into().expect("4 bytes")) as usize)
}

impl Message {
    /// The target and name of a link message, `None` for any other message.
    pub fn as_link(&self) -> Option<(String, u64)> {
        if self.kind != LINK {
            return None;
        }
        let b = &self.body;
        let flags = *b.get(1)?;
        let mut p = 2 + usize::from(flags & 0x08 != 0) + 8 * usize::from(flags & 0x04 != 0);
        p += usize::from(flags & 0x10 != 0);
        let width = 1usize << (flags & 3);
        let mut n = [0u8; 8];
        n[..width].copy_from_slice(b.get(p..p + width)?);
        let n = u64::from_le_bytes(n) as usize;
        p += width;
        let name = String::from_utf8(b.get(p..p + n)?.to_vec()).ok()?;
        let addr = u64::from_le_bytes(b.get(p + n..p + n + 8)?.try_into().ok()?);
        Some((name, addr))
    }

    /// The name of an attribute message, `None` for any other message.
    pub fn attribute_name(&self) -> Option<&str> {
        if self.kind != ATTRIBUTE {
            return None;
        }
        let n = usize::from(u16::from_le_bytes(self.body.get(2..4)?.try_into().ok()?));
        std::str::from_utf8(self.body.get(9..9 + n.checked_sub(1)?)?).ok()
    }

    /// Whether this is one of the messages [`group_opening`] makes.
    pub fn opens_group(&self) -> bool {
        matches!(self.kind, LINK_INFO | GROUP_INFO | ATTRIBUTE_INFO)
    }
}

/// A global heap collection holding `objects` (variable-length strings' bytes, indexed
/// from 1 in order), at least 4096 bytes as libhdf5 requires, the rest free space.
pub fn heap_collection(objects: &[&[u8]]) -> Vec<u8> {
    let used: usize = 16
        + objects
            .iter()
            .map(|o| 16 + o.len().next_multiple_of(8))
            .sum::<usize>();
    // Room for the free-space object's header, so that it is one.
    let size = (used + 16).max(4096);
    let mut b = Vec::with_capacity(size);
    b.extend_from_slice(b"GCOL");
    b.extend_from_slice(&[1, 0, 0, 0]);
    b.extend_from_slice(&(size as u64).to_le_bytes());
    for (i, o) in objects.iter().enumerate() {
        b.extend_from_slice(&(i as u16 + 1).to_le_bytes());
        b.extend_from_slice(&[0; 6]); // reference count and reserved
        b.extend_from_slice(&(o.len() as u64).to_le_bytes());
        b.extend_from_slice(o);
        b.resize(b.len().next_multiple_of(8), 0);
    }
    // Object 0 is the free space, its size counting its own header.
    b.extend_from_slice(&[0; 8]);
    b.extend_from_slice(&((size - b.len() + 8) as u64).to_le_bytes());
    b.resize(size, 0);
    b
}

/// Objects one global heap collection may hold (its indices are 16 bits).
pub const HEAP_OBJECTS: usize = 0xfff0;

/// One chunk as the B-tree indexes it: where, how long (filtered), and its first element.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Chunk {
    /// Address of the filtered chunk.
    pub addr: u64,
    /// Its bytes.
    pub len: u32,
    /// Index of its first element.
    pub offset: u64,
}

/// Bytes of one node of a chunk B-tree of a one-dimensional dataset (libhdf5 reads nodes
/// whole, used or not).
#[cfg(test)]
pub const CHUNK_NODE_LEN: usize = node_len(CHUNK_BTREE_K, 24);

/// Half the number of children a group B-tree node holds, and half the entries of a
/// symbol table node (libhdf5's defaults, which the superblock states).
const GROUP_BTREE_K: usize = 16;
const GROUP_LEAF_K: usize = 4;

/// Bytes of a version 1 B-tree node of rank `k` whose keys are `key_len` bytes.
const fn node_len(k: usize, key_len: usize) -> usize {
    24 + 2 * k * 8 + (2 * k + 1) * key_len
}

/// A version 1 B-tree of node type `kind` and rank `k` over `children` (in order), child
/// i holding what lies between `keys[i]` and the next key, `closing` after the last; its
/// nodes placed one after another from `at`, level by level. The nodes' bytes and the
/// root's address (the last node).
fn btree_v1(
    kind: u8,
    k: usize,
    mut keys: Vec<Vec<u8>>,
    mut children: Vec<u64>,
    closing: &[u8],
    at: u64,
) -> (Vec<u8>, u64) {
    let len = node_len(k, closing.len());
    let mut bytes = Vec::new();
    let mut depth = 0u8;
    loop {
        let per = 2 * k;
        let nodes = children.len().div_ceil(per).max(1);
        let base = at + bytes.len() as u64;
        let addr = |i: usize| base + (i * len) as u64;
        let (mut up_keys, mut up_children) = (Vec::new(), Vec::new());
        for i in 0..nodes {
            let lo = i * per;
            let hi = ((i + 1) * per).min(children.len());
            let start = bytes.len();
            bytes.extend_from_slice(b"TREE");
            bytes.extend_from_slice(&[kind, depth]);
            bytes.extend_from_slice(&((hi - lo) as u16).to_le_bytes());
            let left = if i == 0 { UNDEF } else { addr(i - 1) };
            let right = if i + 1 == nodes { UNDEF } else { addr(i + 1) };
            bytes.extend_from_slice(&left.to_le_bytes());
            bytes.extend_from_slice(&right.to_le_bytes());
            for j in lo..hi {
                bytes.extend_from_slice(&keys[j]);
                bytes.extend_from_slice(&children[j].to_le_bytes());
            }
            bytes.extend_from_slice(keys.get(hi).map_or(closing, |k| k));
            bytes.resize(start + len, 0);
            up_keys.push(keys.get(lo).map_or(closing.to_vec(), |k| k.clone()));
            up_children.push(addr(i));
        }
        if nodes == 1 {
            return (bytes, base);
        }
        (keys, children) = (up_keys, up_children);
        depth += 1;
    }
}

/// The version 1 B-tree indexing `chunks` (in order, of `chunk` elements of `elem_size`
/// bytes), its nodes placed one after another from `at`: the nodes' bytes, and the
/// root's address (the last node).
pub fn chunk_btree(chunks: &[Chunk], chunk: u64, elem_size: u64, at: u64) -> (Vec<u8>, u64) {
    // A chunk's key: its filtered size, its filter mask, and its offset in each dimension,
    // the datatype's included.
    let key = |len: u32, offset: u64, elem: u64| {
        let mut k = vec![0u8; 24];
        k[..4].copy_from_slice(&len.to_le_bytes());
        k[8..16].copy_from_slice(&offset.to_le_bytes());
        k[16..24].copy_from_slice(&elem.to_le_bytes());
        k
    };
    let last = chunks.last().map_or(0, |c| c.offset);
    // The right key libhdf5 writes past the last chunk: one chunk on, and one element's
    // size on in the datatype's dimension.
    let closing = key(0, last + chunk, elem_size);
    btree_v1(
        1,
        CHUNK_BTREE_K,
        chunks.iter().map(|c| key(c.len, c.offset, 0)).collect(),
        chunks.iter().map(|c| c.addr).collect(),
        &closing,
        at,
    )
}

/// Bytes of a symbol table node (libhdf5 reads nodes whole).
const SYMBOL_NODE_LEN: usize = 8 + 2 * GROUP_LEAF_K * 40;

/// A group as libhdf5 writes it at the earliest format, placed from `at`: a local heap of
/// its link names, symbol table nodes of 8 entries, a B-tree over them (lookups by name in
/// logarithmic time, where a compact group's are linear), and a version 1 object header
/// holding the symbol table message and `attrs`. `links` must be sorted by name, as
/// `strcmp` orders them (byte order). The bytes, and the header's address.
pub fn symbol_table_group(links: &[(&str, u64)], attrs: &[Message], at: u64) -> (Vec<u8>, u64) {
    // The heap's data: the empty name at 0 (the first key), then each name, each
    // NUL-terminated and padded to 8 bytes.
    let mut names = vec![0u8; 8];
    let mut offsets = Vec::with_capacity(links.len());
    for (name, _) in links {
        offsets.push(names.len() as u64);
        names.extend_from_slice(name.as_bytes());
        names.push(0);
        names.resize(names.len().next_multiple_of(8), 0);
    }
    let heap = at;
    let mut b = Vec::new();
    b.extend_from_slice(b"HEAP");
    b.extend_from_slice(&[0; 4]);
    b.extend_from_slice(&(names.len() as u64).to_le_bytes());
    // No free block: libhdf5 writes 1 for none.
    b.extend_from_slice(&1u64.to_le_bytes());
    b.extend_from_slice(&(heap + 32).to_le_bytes());
    b.extend_from_slice(&names);
    // Symbol table nodes, full but the last.
    let per = 2 * GROUP_LEAF_K;
    let mut node_keys = vec![0u64.to_le_bytes().to_vec()];
    let mut nodes = Vec::new();
    for (i, part) in links.chunks(per).enumerate() {
        nodes.push(at + b.len() as u64);
        let start = b.len();
        b.extend_from_slice(b"SNOD");
        b.extend_from_slice(&[1, 0]);
        b.extend_from_slice(&(part.len() as u16).to_le_bytes());
        for (j, (_, addr)) in part.iter().enumerate() {
            b.extend_from_slice(&offsets[i * per + j].to_le_bytes());
            b.extend_from_slice(&addr.to_le_bytes());
            // Nothing cached: readers open the object's header.
            b.extend_from_slice(&[0; 24]);
        }
        b.resize(start + SYMBOL_NODE_LEN, 0);
        node_keys.push(offsets[i * per + part.len() - 1].to_le_bytes().to_vec());
    }
    let closing = node_keys.pop().expect("the first key");
    let (tree, root) = btree_v1(
        0,
        GROUP_BTREE_K,
        node_keys,
        nodes,
        &closing,
        at + b.len() as u64,
    );
    b.extend_from_slice(&tree);
    let mut stab = root.to_le_bytes().to_vec();
    stab.extend_from_slice(&heap.to_le_bytes());
    let mut messages = vec![Message {
        kind: SYMBOL_TABLE,
        flags: 0,
        body: stab,
    }];
    messages.extend_from_slice(attrs);
    let header = at + b.len() as u64;
    b.extend_from_slice(&header_v1(&messages));
    (b, header)
}

/// Bob Jenkins' lookup3 `hashlittle`, the checksum of HDF5's metadata.
pub fn lookup3(key: &[u8], init: u32) -> u32 {
    // lookup3's `mix` and `final`: (x, y, z, k) is x -= y; x ^= rot(y, k); y += z, and
    // (x, y, k) is x ^= y; x -= rot(y, k), on the state (a, b, c).
    const MIX: [(usize, usize, usize, u32); 6] = [
        (0, 2, 1, 4),
        (1, 0, 2, 6),
        (2, 1, 0, 8),
        (0, 2, 1, 16),
        (1, 0, 2, 19),
        (2, 1, 0, 4),
    ];
    const FINAL: [(usize, usize, u32); 7] = [
        (2, 1, 14),
        (0, 2, 11),
        (1, 0, 25),
        (2, 1, 16),
        (0, 2, 4),
        (1, 0, 14),
        (2, 1, 24),
    ];
    let start = 0xdeadbeefu32
        .wrapping_add(key.len() as u32)
        .wrapping_add(init);
    let mut h = [start; 3];
    // The words of a block of up to 12 bytes, zero-padded.
    let add = |h: &mut [u32; 3], block: &[u8]| {
        let mut b = [0u8; 12];
        b[..block.len()].copy_from_slice(block);
        for (i, w) in b.chunks_exact(4).enumerate() {
            h[i] = h[i].wrapping_add(u32::from_le_bytes(w.try_into().expect("4 bytes")));
        }
    };
    let mut k = key;
    while k.len() > 12 {
        add(&mut h, &k[..12]);
        for (x, y, z, r) in MIX {
            h[x] = h[x].wrapping_sub(h[y]);
            h[x] ^= h[y].rotate_left(r);
            h[y] = h[y].wrapping_add(h[z]);
        }
        k = &k[12..];
    }
    if k.is_empty() {
        return h[2];
    }
    add(&mut h, k);
    for (x, y, r) in FINAL {
        h[x] ^= h[y];
        h[x] = h[x].wrapping_sub(h[y].rotate_left(r));
    }
    h[2]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hex(s: &str) -> Vec<u8> {
        (0..s.len())
            .step_by(2)
            .map(|i| u8::from_str_radix(&s[i..i + 2], 16).unwrap())
            .collect()
    }

    /// The reference values of lookup3's own self-test (driver5 in lookup3.c).
    #[test]
    fn lookup3_matches_its_reference_values() {
        assert_eq!(lookup3(b"", 0), 0xdeadbeef);
        assert_eq!(lookup3(b"", 0xdeadbeef), 0xbd5b7dde);
        assert_eq!(lookup3(b"Four score and seven years ago", 0), 0x17770551);
        assert_eq!(lookup3(b"Four score and seven years ago", 1), 0xcd628161);
    }

    /// Message bodies as libhdf5 1.10 wrote them into a results.h5 of this project (the
    /// messages of `runs/run_001/hilbert/damping` and of a validity mask, and two of the
    /// run group's attributes), copied from the file.
    #[test]
    fn messages_are_the_bytes_libhdf5_writes() {
        let chunked = dataset(
            Elem::F64,
            30000,
            &Storage::Chunked {
                btree: 0x1c97b3,
                chunk: 30000,
                shuffle: true,
                level: Some(1),
            },
        );
        let want = [
            "010101000000000030750000000000003075000000000000",
            "11203f000800000000004000340b0034ff030000",
            "0203000100000000",
            "0102000000000000020008000100010073687566666c6500080000000000000001000800\
             010001006465666c617465000100000000000000",
            "030202b3971c00000000003075000008000000",
        ];
        assert_eq!(chunked.len(), want.len());
        for (m, w) in chunked.iter().zip(want) {
            assert_eq!(m.body, hex(w), "message {:#x}", m.kind);
        }
        let mask = dataset(
            Elem::U8,
            30000,
            &Storage::Chunked {
                btree: 0x0edf19,
                chunk: 30000,
                shuffle: false,
                level: Some(4),
            },
        );
        assert_eq!(mask[1].body, hex("100000000100000000000800"));
        assert_eq!(
            mask[3].body,
            hex("010100000000000001000800010001006465666c617465000400000000000000")
        );
        let plain = dataset(
            Elem::F64,
            40,
            &Storage::Contiguous {
                addr: 0x0f0c7c,
                len: 320,
            },
        );
        assert_eq!(plain[2].body, hex("0202020100000000"));
        assert_eq!(
            plain[3].body,
            hex("03017c0c0f000000000040010000000000000000000000")[..18]
        );
        // An empty dataset, chunked by one and never written, as the hdf5 crate makes it.
        let empty = dataset(
            Elem::F64,
            0,
            &Storage::Chunked {
                btree: UNDEF,
                chunk: 1,
                shuffle: false,
                level: None,
            },
        );
        assert_eq!(empty.len(), 4);
        assert_eq!(
            empty[0].body,
            hex("010101000000000000000000000000000000000000000000")
        );
        assert_eq!(empty[2].body, hex("0203000100000000"));
        assert_eq!(empty[3].body, hex("030202ffffffffffffffff0100000008000000"));
        let units = attribute(
            "units",
            AttrValue::Text(HeapId {
                collection: 2048,
                index: 0x4b,
                len: 3,
            }),
        );
        assert_eq!(
            units.body,
            hex(
                "030006001400080001756e69747300190101001000000010000000010000000000080001\
                 000000000000000300000000080000000000004b000000"
            )
        );
        let rate = attribute("sample_rate", AttrValue::F64(1000.0));
        assert_eq!(
            rate.body,
            hex(
                "03000c00140008000173616d706c655f726174650011203f000800000000004000340b00\
                 34ff03000001000000000000000000000000408f40"
            )
        );
    }

    #[test]
    fn a_v2_header_reads_back_with_its_links_and_attributes() {
        let mut m = group_opening();
        m.push(link("run_001", 4096));
        m.push(link("é", 1 << 40));
        m.push(link(&"x".repeat(300), 7));
        m.push(attribute("status", AttrValue::F64(1.5)));
        let h = header_v2(&m);
        assert_eq!(v2_len(&h[..10]), Some(h.len()));
        let back = parse_v2(&h).unwrap();
        assert_eq!(back, m);
        let links: Vec<_> = back.iter().filter_map(Message::as_link).collect();
        assert_eq!(
            links,
            [
                ("run_001".to_string(), 4096),
                ("é".to_string(), 1 << 40),
                ("x".repeat(300), 7)
            ]
        );
        assert_eq!(back[6].attribute_name(), Some("status"));
        let mut bad = h.clone();
        bad[12] ^= 1;
        assert_eq!(parse_v2(&bad), None);
    }

    /// The one-node B-tree of a one-chunk dataset, as libhdf5 wrote it (bytes from the
    /// same file); and a tree over more chunks than a node holds gets a level above.
    #[test]
    fn the_chunk_btree_is_libhdf5s() {
        let (b, root) = chunk_btree(
            &[Chunk {
                addr: 0x1c9fe3,
                len: 0x2729d,
                offset: 0,
            }],
            30000,
            8,
            0x1c97b3,
        );
        assert_eq!(root, 0x1c97b3);
        assert_eq!(b.len(), CHUNK_NODE_LEN);
        let want = hex("5452454501000100ffffffffffffffffffffffffffffffff\
             9d7202000000000000000000000000000000000000000000e39f1c0000000000\
             000000000000000030750000000000000800000000000000");
        assert_eq!(&b[..want.len()], &want[..]);
        assert!(b[want.len()..].iter().all(|&x| x == 0));
        let chunks: Vec<Chunk> = (0..130)
            .map(|i| Chunk {
                addr: 1000 + i * 10,
                len: 10,
                offset: i * 4,
            })
            .collect();
        let (b, root) = chunk_btree(&chunks, 4, 1, 0);
        // Three leaves (64, 64, 2 entries) and a root over them.
        assert_eq!(b.len(), 4 * CHUNK_NODE_LEN);
        assert_eq!(root, 3 * CHUNK_NODE_LEN as u64);
        let r = &b[3 * CHUNK_NODE_LEN..];
        assert_eq!((r[5], u16::from_le_bytes([r[6], r[7]])), (1, 3));
        let leaf3 = &b[2 * CHUNK_NODE_LEN..];
        assert_eq!(u16::from_le_bytes([leaf3[6], leaf3[7]]), 2);
        let u64_at = |n: &[u8], at: usize| u64::from_le_bytes(n[at..at + 8].try_into().unwrap());
        let node = CHUNK_NODE_LEN as u64;
        // Siblings: each leaf names its neighbours; the root has none.
        let leaf2 = &b[CHUNK_NODE_LEN..];
        assert_eq!((u64_at(leaf2, 8), u64_at(leaf2, 16)), (0, 2 * node));
        assert_eq!((u64_at(r, 8), u64_at(r, 16)), (UNDEF, UNDEF));
        // The root's keys: each leaf's first chunk (offsets 0, 256, 512), then the closing
        // key past the last chunk (129 × 4 + 4 = 520), with the element size.
        let key = |i: usize| (u64_at(r, 24 + i * 32 + 8), u64_at(r, 24 + i * 32 + 16));
        assert_eq!(
            [key(0), key(1), key(2), key(3)],
            [(0, 0), (256, 0), (512, 0), (520, 1)]
        );
        assert_eq!(
            [u64_at(r, 48), u64_at(r, 80), u64_at(r, 112)],
            [0, node, 2 * node]
        );
    }

    /// A symbol-table group laid out as libhdf5 lays one out (its heap's header as in a
    /// results.h5 libhdf5 wrote: no free block is 1); 20 links make three nodes of
    /// eight, and the tree's keys are the last name of each node.
    #[test]
    fn a_symbol_table_group_is_libhdf5s_layout() {
        let names: Vec<String> = (0..20).map(|i| format!("run_{i:06}")).collect();
        let links: Vec<(&str, u64)> = names.iter().map(|n| (n.as_str(), 7)).collect();
        let (b, header) = symbol_table_group(&links, &[attribute("x", AttrValue::F64(1.0))], 1000);
        let u64_at = |at: usize| u64::from_le_bytes(b[at..at + 8].try_into().unwrap());
        assert_eq!(&b[..8], b"HEAP\0\0\0\0");
        let data = 8 + 20 * 16;
        assert_eq!((u64_at(8), u64_at(16), u64_at(24)), (data as u64, 1, 1032));
        assert_eq!(&b[40..51], b"run_000000\0");
        let snod = 32 + data;
        assert_eq!(&b[snod..snod + 8], b"SNOD\x01\0\x08\0");
        let third = snod + 2 * SYMBOL_NODE_LEN;
        assert_eq!(&b[third + 6..third + 8], [4, 0]);
        // The B-tree: one leaf over three nodes, keys "" then the last name of each.
        let tree = snod + 3 * SYMBOL_NODE_LEN;
        assert_eq!(&b[tree..tree + 8], b"TREE\0\0\x03\0");
        let keys: Vec<u64> = (0..4).map(|i| u64_at(tree + 24 + 16 * i)).collect();
        assert_eq!(keys, [0, 8 + 7 * 16, 8 + 15 * 16, 8 + 19 * 16]);
        assert_eq!(header as usize - 1000, tree + node_len(GROUP_BTREE_K, 8));
        assert_eq!(&b[header as usize - 1000..][..4], [1, 0, 2, 0]);
    }

    #[test]
    fn a_heap_collection_is_at_least_4096_bytes_and_ends_in_free_space() {
        let h = heap_collection(&[b"ok", b"", b"skelid-results/1"]);
        assert_eq!(h.len(), 4096);
        assert_eq!(&h[..4], b"GCOL");
        // Objects: 16 + 8, 16 + 0, 16 + 16; the free space from there.
        let free = 16 + 24 + 16 + 32;
        assert_eq!(h[free..free + 2], [0, 0]);
        let size = u64::from_le_bytes(h[free + 8..free + 16].try_into().unwrap());
        assert_eq!(size as usize, 4096 - free);
        let big = vec![b'x'; 5000];
        assert_eq!(heap_collection(&[&big]).len(), 16 + 16 + 5000 + 16);
    }
}
