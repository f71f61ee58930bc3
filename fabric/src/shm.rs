//! A card's shared memory as real shared memory. The paper's render nodes read their card's
//! memory by DMA; processes on one machine can do the same through a memory-mapped file. A
//! fork node publishes the items its card holds as one segment (a file in the machine's
//! shared-memory directory, read-only), and tells the render nodes its name, its size and a
//! random nonce written into its header. A render node that can open the file, map it and
//! find that nonce shares the machine with the fork node and reads from the mapping; one that
//! cannot (another machine, a container without the fork node's IPC namespace, a stale or
//! foreign file) stays on TCP. Either way the render node checks what it reads before it
//! uses it: the segment is trusted no more than the network (see
//! `renderer::chunk::Chunk::from_region` for what is checked up front and what where it is
//! read).
//!
//! Besides an item's words as they travel, a segment can hold a chunk's walking form (the
//! tree as rays walk it, which each render node would otherwise compute for itself from the
//! words, in memory of its own): render nodes then walk the chunk in place in the mapping,
//! with nothing copied or transcoded, and check it before use as they check everything else.
//!
//! Layout, in native-endian `u32` words: a header of [`HEADER_WORDS`] (magic, version, the
//! nonce's four words, the item count, zero), then one entry of [`ENTRY_WORDS`] per item
//! (kind, index, offset and length in words as two words each, low first), then the items'
//! words, each starting on a multiple of [`ITEM_ALIGN_WORDS`] (64 bytes, a cache line, so
//! that what is read in place is aligned as the reader's types need). Files are named
//! `magg-card-PID-CARD-NONCE`, so a fork node that starts can remove the segments of fork
//! nodes that died without removing their own (see [`remove_stale`]).

use std::{
    collections::HashMap,
    fs::{File, OpenOptions},
    io::{BufWriter, Write},
    os::unix::fs::{OpenOptionsExt, PermissionsExt},
    path::{Path, PathBuf},
};

use protocol::{DataId, NodeId};

/// Where segments live: the tmpfs that POSIX shared memory uses on Linux.
pub const SHM_DIR: &str = "/dev/shm";

/// Which shared memory this process sees: its machine's boot id and the identity of the
/// filesystem mounted at [`SHM_DIR`] (device and inode). Processes with the same domain can
/// open each other's segments; a container has a `/dev/shm` of its own unless it shares
/// another's IPC namespace, so two containers on one machine (one boot id) may not. Empty
/// when there is no such directory: nothing can be shared.
pub fn domain(boot_id: &str) -> String {
    use std::os::unix::fs::MetadataExt;
    match std::fs::metadata(SHM_DIR) {
        Ok(m) if !boot_id.is_empty() => format!("{boot_id}/{:x}:{}", m.dev(), m.ino()),
        _ => String::new(),
    }
}

const MAGIC: u32 = u32::from_le_bytes(*b"MGSM");
const VERSION: u32 = 2;
pub const HEADER_WORDS: usize = 8;
pub const ENTRY_WORDS: usize = 6;
pub const ITEM_ALIGN_WORDS: usize = 16;
const PREFIX: &str = "magg-card-";
const KIND_CHUNK: u32 = 0;
const KIND_TILE: u32 = 1;
const KIND_CHUNK_WALK: u32 = 2;

/// Which form of an item a segment entry holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Part {
    /// The words as they travel over a socket.
    Words,
    /// A chunk's walking form (only chunks have one).
    Walk,
}

/// One entry to publish. Its words are written from `pieces`, one after another, as they
/// lie in memory: a chunk's walking form is its header, nodes and leaves, which joined first
/// would be copied into fresh memory (about 70 MB for a million triangles, on the way from
/// the prepared scene to the segments the render nodes wait for).
pub struct Item<'a> {
    pub id: DataId,
    pub part: Part,
    pub pieces: Vec<&'a [u32]>,
}

impl<'a> Item<'a> {
    /// An entry whose words are one slice.
    pub fn whole(id: DataId, part: Part, words: &'a [u32]) -> Item<'a> {
        Item {
            id,
            part,
            pieces: vec![words],
        }
    }

    fn len(&self) -> usize {
        self.pieces.iter().map(|p| p.len()).sum()
    }
}

fn align_up(words: u64) -> u64 {
    words.next_multiple_of(ITEM_ALIGN_WORDS as u64)
}

/// Why a segment cannot be published or used; a render node that gets one stays on TCP.
#[derive(Debug, thiserror::Error)]
pub enum ShmError {
    #[error("segment name {0:?} is not one a fork node makes")]
    BadName(String),
    #[error("cannot create segment {path}: {source}")]
    Create {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot open segment {path}: {source}")]
    Open {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("segment {path} is {actual} bytes, not the {announced} announced")]
    Size {
        path: PathBuf,
        actual: u64,
        announced: u64,
    },
    #[error("segment {path} is not a magg card segment of this version")]
    Magic { path: PathBuf },
    #[error("segment {path} carries another nonce: not the fork node's segment")]
    Nonce { path: PathBuf },
    #[error("segment {path}: {what}")]
    Layout { path: PathBuf, what: String },
}

/// A segment this fork node published; dropping it removes the file (mappings made by
/// render nodes stay valid until they unmap).
#[derive(Debug)]
pub struct Published {
    path: PathBuf,
    pub name: String,
    pub nonce: [u32; 4],
    pub bytes: u64,
}

impl Published {
    /// Writes `items` as card `card`'s segment in `dir`, read-only for everyone.
    pub fn create(dir: &Path, card: NodeId, items: &[Item]) -> Result<Published, ShmError> {
        let mut nonce_bytes = [0u8; 16];
        getrandom::fill(&mut nonce_bytes).expect("the operating system's random source");
        let nonce: [u32; 4] = bytemuck::cast(nonce_bytes);
        let name = format!(
            "{PREFIX}{}-{card}-{:08x}{:08x}",
            std::process::id(),
            nonce[0],
            nonce[1]
        );
        let path = dir.join(&name);
        let create = |source| ShmError::Create {
            path: path.clone(),
            source,
        };
        let items: Vec<(u32, u32, &Item)> = items
            .iter()
            .filter_map(|item| match (item.id, item.part) {
                (DataId::Chunk(c), Part::Words) => Some((KIND_CHUNK, c, item)),
                (DataId::Chunk(c), Part::Walk) => Some((KIND_CHUNK_WALK, c, item)),
                (DataId::Tile(t), Part::Words) => Some((KIND_TILE, t, item)),
                _ => None,
            })
            .collect();
        let table_end = HEADER_WORDS + ENTRY_WORDS * items.len();
        let mut head: Vec<u32> = Vec::with_capacity(table_end);
        head.extend([MAGIC, VERSION]);
        head.extend(nonce);
        head.extend([items.len() as u32, 0]);
        // Where each item starts, aligned; the gaps are written as zeros.
        let mut starts = Vec::with_capacity(items.len());
        let mut offset = table_end as u64;
        for &(kind, index, item) in &items {
            offset = align_up(offset);
            starts.push(offset);
            let len = item.len() as u64;
            head.extend([kind, index, offset as u32, (offset >> 32) as u32]);
            head.extend([len as u32, (len >> 32) as u32]);
            offset += len;
        }
        let file = OpenOptions::new()
            .write(true)
            .create_new(true)
            .mode(0o600)
            .open(&path)
            .map_err(create)?;
        // From here on the file is ours: removed again if writing it fails.
        let published = Published {
            path: path.clone(),
            name,
            nonce,
            bytes: offset * 4,
        };
        let mut w = BufWriter::with_capacity(1 << 20, file);
        w.write_all(bytemuck::cast_slice(&head)).map_err(create)?;
        let mut at = head.len() as u64;
        let zeros = [0u32; ITEM_ALIGN_WORDS];
        for (&(_, _, item), &start) in items.iter().zip(&starts) {
            w.write_all(bytemuck::cast_slice(&zeros[..(start - at) as usize]))
                .map_err(create)?;
            for piece in &item.pieces {
                w.write_all(bytemuck::cast_slice(piece)).map_err(create)?;
            }
            at = start + item.len() as u64;
        }
        let file = w.into_inner().map_err(|e| create(e.into_error()))?;
        // Read-only, and for this user alone: the segment holds the scene, which others on
        // the machine may not read (its render nodes run as the same user, in containers
        // too).
        file.set_permissions(std::fs::Permissions::from_mode(0o400))
            .map_err(create)?;
        Ok(published)
    }

    pub fn path(&self) -> &Path {
        &self.path
    }
}

impl Drop for Published {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.path);
    }
}

/// Removes segments in `dir` whose fork node process is gone (killed before it could remove
/// its own); segments of live processes are left alone. Returns how many went.
pub fn remove_stale(dir: &Path) -> usize {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return 0;
    };
    // Without /proc nothing can be known about other processes: remove nothing.
    if !Path::new("/proc/self").exists() {
        return 0;
    }
    let mut removed = 0;
    for e in entries.flatten() {
        let name = e.file_name();
        let Some(pid) = name
            .to_str()
            .and_then(|n| n.strip_prefix(PREFIX))
            .and_then(|rest| rest.split('-').next())
            .and_then(|pid| pid.parse::<u32>().ok())
        else {
            continue;
        };
        if !Path::new(&format!("/proc/{pid}")).exists() && std::fs::remove_file(e.path()).is_ok() {
            removed += 1;
        }
    }
    removed
}

/// Whether `name` could be a segment's file name: no path, only what [`Published`] writes.
fn valid_name(name: &str) -> bool {
    name.len() <= 100
        && name.starts_with(PREFIX)
        && name.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'-')
}

/// Another card's (or this card's) segment, mapped read-only and its table checked.
pub struct Segment {
    map: memmap2::Mmap,
    /// Where each item's words are: offset and length in words, all within the mapping.
    index: Index,
}

/// Where each part of each item lies: offset and length in words.
type Index = HashMap<(DataId, Part), (usize, usize)>;

impl Segment {
    /// Maps segment `name` in `dir` if it is the one announced: `bytes` long, with `nonce`
    /// in its header, and a table whose every entry lies within the file.
    pub fn open(dir: &Path, name: &str, nonce: [u32; 4], bytes: u64) -> Result<Segment, ShmError> {
        if !valid_name(name) {
            return Err(ShmError::BadName(name.to_string()));
        }
        let path = dir.join(name);
        let file = File::open(&path).map_err(|source| ShmError::Open {
            path: path.clone(),
            source,
        })?;
        let actual = file
            .metadata()
            .map_err(|source| ShmError::Open {
                path: path.clone(),
                source,
            })?
            .len();
        if actual != bytes || actual < (HEADER_WORDS * 4) as u64 || actual % 4 != 0 {
            return Err(ShmError::Size {
                path,
                actual,
                announced: bytes,
            });
        }
        // SAFETY: the mapping is read-only, of a file the fork node wrote completely before
        // announcing it and never writes again (it is read-only for everyone). What is read
        // in place is checked before use (`Chunk::from_region`), and the walk reads everything
        // with bounds checks, so what the words hold cannot break this process; a file
        // truncated by someone else after this size check would fault on access, which no
        // magg process does.
        let map = unsafe { memmap2::Mmap::map(&file) }.map_err(|source| ShmError::Open {
            path: path.clone(),
            source,
        })?;
        let index = read_table(&map, nonce).map_err(|e| match e {
            TableError::Magic => ShmError::Magic { path: path.clone() },
            TableError::Nonce => ShmError::Nonce { path: path.clone() },
            TableError::Layout(what) => ShmError::Layout {
                path: path.clone(),
                what,
            },
        })?;
        Ok(Segment { map, index })
    }

    /// Item `id`'s words where they lie, if the segment holds it. The caller validates them.
    pub fn read(&self, id: DataId) -> Option<&[u32]> {
        let (start, end) = self.place(id, Part::Words)?;
        Some(&self.words()[start..end])
    }

    /// Where the segment holds `part` of item `id`: words `start..end` of [`Segment::words`].
    pub fn place(&self, id: DataId, part: Part) -> Option<(usize, usize)> {
        let &(offset, len) = self.index.get(&(id, part))?;
        Some((offset, offset + len))
    }

    /// The whole mapping as words (a mapping starts on a page, so it is aligned).
    pub fn words(&self) -> &[u32] {
        bytemuck::cast_slice(&self.map[..])
    }

    /// The items of which the segment holds `part`, in no particular order.
    pub fn ids(&self, part: Part) -> impl Iterator<Item = DataId> + '_ {
        (self.index.keys()).filter_map(move |&(id, p)| (p == part).then_some(id))
    }

    pub fn len(&self) -> usize {
        self.index.len()
    }

    pub fn is_empty(&self) -> bool {
        self.index.is_empty()
    }
}

enum TableError {
    Magic,
    Nonce,
    Layout(String),
}

/// The item table of a mapped segment, every entry checked against the mapping's size.
fn read_table(map: &[u8], nonce: [u32; 4]) -> Result<Index, TableError> {
    // A mapping starts on a page boundary, so its bytes are always aligned for words.
    let words: &[u32] = bytemuck::try_cast_slice(map)
        .map_err(|e| TableError::Layout(format!("not whole aligned words: {e}")))?;
    if words.len() < HEADER_WORDS || words[0] != MAGIC || words[1] != VERSION {
        return Err(TableError::Magic);
    }
    if words[2..6] != nonce {
        return Err(TableError::Nonce);
    }
    let count = words[6] as usize;
    let table_end = count
        .checked_mul(ENTRY_WORDS)
        .and_then(|t| t.checked_add(HEADER_WORDS))
        .filter(|&t| t <= words.len())
        .ok_or_else(|| TableError::Layout(format!("a table of {count} items does not fit")))?;
    let mut index = HashMap::with_capacity(count);
    for e in words[HEADER_WORDS..table_end].chunks_exact(ENTRY_WORDS) {
        let id = match e[0] {
            KIND_CHUNK => (DataId::Chunk(e[1]), Part::Words),
            KIND_TILE => (DataId::Tile(e[1]), Part::Words),
            KIND_CHUNK_WALK => (DataId::Chunk(e[1]), Part::Walk),
            k => return Err(TableError::Layout(format!("unknown item kind {k}"))),
        };
        let offset = e[2] as u64 | (e[3] as u64) << 32;
        let len = e[4] as u64 | (e[5] as u64) << 32;
        let end = offset.checked_add(len);
        if offset < table_end as u64 || end.is_none_or(|end| end > words.len() as u64) {
            return Err(TableError::Layout(format!(
                "{id:?} at words {offset}+{len} lies outside the {} words of data",
                words.len()
            )));
        }
        if index.insert(id, (offset as usize, len as usize)).is_some() {
            return Err(TableError::Layout(format!("{id:?} is listed twice")));
        }
    }
    Ok(index)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dir() -> tempdir::Dir {
        tempdir::Dir::new()
    }

    /// Processes of one machine that see one /dev/shm share a domain; another machine's
    /// boot id makes another; a machine that gave no boot id shares nothing.
    #[test]
    fn the_shared_memory_domain_names_the_machine_and_its_shm_mount() {
        if !Path::new(SHM_DIR).is_dir() {
            eprintln!("SKIPPED: no {SHM_DIR} here");
            return;
        }
        let here = domain("boot-a");
        assert!(here.starts_with("boot-a/"), "{here}");
        assert_eq!(here, domain("boot-a"));
        assert_ne!(here, domain("boot-b"));
        assert_eq!(domain(""), "");
    }

    /// A private directory per test, removed at the end (no crate needed for so little).
    mod tempdir {
        pub struct Dir(pub std::path::PathBuf);
        impl Dir {
            pub fn new() -> Dir {
                let mut n = [0u8; 8];
                getrandom::fill(&mut n).unwrap();
                let p =
                    std::env::temp_dir().join(format!("magg-shm-test-{}", u64::from_ne_bytes(n)));
                std::fs::create_dir_all(&p).unwrap();
                Dir(p)
            }
        }
        impl Drop for Dir {
            fn drop(&mut self) {
                let _ = std::fs::remove_dir_all(&self.0);
            }
        }
    }

    fn item(id: DataId, part: Part, words: &[u32]) -> Item<'_> {
        Item::whole(id, part, words)
    }

    fn publish(d: &Path) -> Published {
        let a = [1u32, 2, 3];
        let b = [7u32; 5];
        let walk = [8u32; 32];
        Published::create(
            d,
            3,
            &[
                item(DataId::Chunk(4), Part::Words, &a),
                item(DataId::Chunk(4), Part::Walk, &walk),
                item(DataId::Tile(9), Part::Words, &b),
            ],
        )
        .unwrap()
    }

    #[test]
    fn a_published_segment_reads_back_what_was_written() {
        let d = dir();
        let p = publish(&d.0);
        let s = Segment::open(&d.0, &p.name, p.nonce, p.bytes).unwrap();
        assert_eq!(s.len(), 3);
        assert_eq!(s.read(DataId::Chunk(4)).unwrap(), &[1, 2, 3]);
        assert_eq!(s.read(DataId::Tile(9)).unwrap(), &[7; 5]);
        assert!(s.read(DataId::Chunk(9)).is_none());
        let mut words: Vec<_> = s.ids(Part::Words).collect();
        words.sort_by_key(|id| format!("{id:?}"));
        assert_eq!(words, [DataId::Chunk(4), DataId::Tile(9)]);
        assert_eq!(s.ids(Part::Walk).collect::<Vec<_>>(), [DataId::Chunk(4)]);
        let (start, end) = s.place(DataId::Chunk(4), Part::Walk).unwrap();
        assert_eq!(&s.words()[start..end], &[8; 32]);
        assert!(s.place(DataId::Tile(9), Part::Walk).is_none());
        for part in [Part::Words, Part::Walk] {
            let (start, _) = s.place(DataId::Chunk(4), part).unwrap();
            assert_eq!(
                start % ITEM_ALIGN_WORDS,
                0,
                "{part:?} starts on a cache line"
            );
        }
        let mode = std::fs::metadata(p.path()).unwrap().permissions().mode();
        assert_eq!(mode & 0o777, 0o400, "read-only, for its user alone");
    }

    #[test]
    fn dropping_the_published_segment_removes_its_file() {
        let d = dir();
        let p = publish(&d.0);
        let path = p.path().to_path_buf();
        let s = Segment::open(&d.0, &p.name, p.nonce, p.bytes).unwrap();
        drop(p);
        assert!(!path.exists());
        assert_eq!(
            s.read(DataId::Chunk(4)).unwrap(),
            &[1, 2, 3],
            "still mapped"
        );
    }

    #[test]
    fn a_wrong_nonce_is_refused() {
        let d = dir();
        let p = publish(&d.0);
        let mut other = p.nonce;
        other[3] ^= 1;
        let e = Segment::open(&d.0, &p.name, other, p.bytes).err().unwrap();
        assert!(matches!(e, ShmError::Nonce { .. }), "{e}");
    }

    #[test]
    fn a_truncated_or_resized_segment_is_refused() {
        let d = dir();
        let p = publish(&d.0);
        let e = Segment::open(&d.0, &p.name, p.nonce, p.bytes + 4)
            .err()
            .unwrap();
        assert!(matches!(e, ShmError::Size { .. }), "{e}");
        // Someone cuts the file short: its size no longer matches the announcement.
        let path = p.path().to_path_buf();
        std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o600)).unwrap();
        let f = OpenOptions::new().write(true).open(&path).unwrap();
        f.set_len(p.bytes - 8).unwrap();
        let e = Segment::open(&d.0, &p.name, p.nonce, p.bytes)
            .err()
            .unwrap();
        assert!(matches!(e, ShmError::Size { .. }), "{e}");
        // Announced with the cut size, the table now points past the end.
        let e = Segment::open(&d.0, &p.name, p.nonce, p.bytes - 8)
            .err()
            .unwrap();
        assert!(matches!(e, ShmError::Layout { .. }), "{e}");
    }

    #[test]
    fn names_that_are_not_segments_are_never_opened() {
        let d = dir();
        for name in [
            "../etc/passwd",
            "magg-card-1/../../x",
            "other",
            "magg-card-a b",
        ] {
            let e = Segment::open(&d.0, name, [0; 4], 64).err().unwrap();
            assert!(matches!(e, ShmError::BadName(_)), "{name}: {e}");
        }
        let e = Segment::open(&d.0, "magg-card-1-2-3", [0; 4], 64)
            .err()
            .unwrap();
        assert!(matches!(e, ShmError::Open { .. }), "{e}");
    }

    #[test]
    fn a_file_that_is_not_a_segment_is_refused() {
        let d = dir();
        let path = d.0.join("magg-card-1-1-00");
        std::fs::write(&path, [0u8; 64]).unwrap();
        let e = Segment::open(&d.0, "magg-card-1-1-00", [0; 4], 64)
            .err()
            .unwrap();
        assert!(matches!(e, ShmError::Magic { .. }), "{e}");
    }

    #[test]
    fn stale_segments_of_dead_processes_are_removed_and_live_ones_kept() {
        let d = dir();
        let live = publish(&d.0);
        // No process has pid u32::MAX - 1 (Linux pids stay below 2^22).
        let dead = d.0.join(format!("{PREFIX}{}-1-00", u32::MAX - 1));
        std::fs::write(&dead, [0u8; 4]).unwrap();
        let unrelated = d.0.join("something-else");
        std::fs::write(&unrelated, [0u8; 4]).unwrap();
        assert_eq!(remove_stale(&d.0), 1);
        assert!(!dead.exists());
        assert!(live.path().exists() && unrelated.exists());
    }
}
