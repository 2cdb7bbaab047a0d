//! The on-disk dataset format: one task's transitions (docs/MODEL.md section 4) in an append-only
//! file of checksummed chunks, so a collector or the store can crash mid-write without poisoning
//! the data.
//!
//! A file is a file header followed by any number of chunks. Every integer is little-endian.
//!
//! **File header** (written once by [`DatasetWriter::create`]):
//!
//! | offset  | size | field                                                        |
//! | ------- | ---- | ------------------------------------------------------------ |
//! | 0       | 8    | magic `UAVMDSET`                                             |
//! | 8       | 2    | schema version, u16 ([`SCHEMA_VERSION`])                     |
//! | 10      | 2    | devices K, u16; an observation holds 2 + K values            |
//! | 12      | 4    | task id, u32 (the task's index in the config's `[[tasks]]`)  |
//! | 16      | 8    | world hash, u64 ([`Config::world_hash`])                     |
//! | 24      | 2    | task-name length n, u16                                      |
//! | 26      | n    | task name, UTF-8                                             |
//! | 26 + n  | 4    | CRC32 (IEEE) of bytes 0 .. 26 + n                            |
//!
//! **Chunk** (one per [`DatasetWriter::append`] call), at offset o:
//!
//! | offset      | size | field                                                  |
//! | ----------- | ---- | ------------------------------------------------------ |
//! | o + 0       | 4    | magic `UMCH`                                           |
//! | o + 4       | 2    | schema version, u16                                    |
//! | o + 6       | 2    | devices K, u16 (must equal the file header's)          |
//! | o + 8       | 4    | task id, u32 (must equal the file header's)            |
//! | o + 12      | 4    | transition count c, u32                                |
//! | o + 16      | 4    | payload length p in bytes, u32                         |
//! | o + 20      | p    | payload: the host tag, then c [`Transition`]s          |
//! | o + 20 + p  | 4    | CRC32 (IEEE) of bytes o .. o + 20 + p                  |
//!
//! The payload starts with the **host tag**, the host whose actors made the chunk's transitions:
//! its length h (1 byte) and h bytes of UTF-8, empty for the learner's own host and a remote
//! host's certificate name otherwise (written by the store, docs/REMOTE.md). The transitions
//! follow, postcard-encoded back to back. [`DatasetReader::provenance`] counts them per host.
//!
//! Postcard writes integers as varints and `reward` as 4 raw bytes, so a transition of the default
//! world (K = 10, coordinates and AoI below 128) takes about 40 bytes. Observations are the raw
//! `u16` values of the world; learners divide by `WorldConfig::observation_scale`.
//!
//! **Crash safety.** The writer only appends whole chunks. [`DatasetWriter::open_append`] scans
//! the file and cuts a torn or corrupt tail (a chunk cut short, or a last chunk whose checksum
//! fails) back to the end of the last good chunk, logs it and returns a [`Recovery`]. It refuses to
//! cut a bad chunk that is followed by a good one, since that is damage in the middle, not a crash.
//! [`DatasetReader::open`] is strict: any bad byte is an error naming the file and the offset.
//!
//! Nothing in a file depends on the time or the machine, so the same transitions written in the
//! same chunks give byte-identical files.

use std::fs::{File, OpenOptions};
use std::io::{self, BufWriter, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use rand::seq::SliceRandom;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::config::{Config, ConfigError};
use crate::fs::FileError;
use crate::layout::Layout;

/// The format version this build reads and writes; bump it on any change to the layout above or
/// to [`Transition`].
pub const SCHEMA_VERSION: u16 = 2;

/// The extension of a dataset file. A directory of meta-train datasets (`uavmeta meta-train
/// --datasets DIR`) holds one file per task named `<task-name>.uavds`.
pub const FILE_EXTENSION: &str = "uavds";

const FILE_MAGIC: &[u8; 8] = b"UAVMDSET";
const CHUNK_MAGIC: &[u8; 4] = b"UMCH";
/// File header bytes before the task name.
const FILE_FIXED_LEN: usize = 26;
const CHUNK_HEADER_LEN: usize = 20;
const CRC_LEN: usize = 4;

/// The host tag of the learner's own host: empty.
pub const LEARNER_HOST: &str = "";

/// One environment step (s, a, r, s', truncated) with where it came from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Transition {
    /// The task's index in the config's `[[tasks]]`.
    pub task: u32,
    /// The actor that made it.
    pub actor: u32,
    /// Episode index within that actor.
    pub episode: u64,
    /// Step t within the episode.
    pub step: u32,
    /// The actor's running sequence number, to find gaps and duplicates.
    pub seq: u64,
    /// Raw s(t) = [x_u, y_u, A_1..A_K].
    pub obs: Vec<u16>,
    /// a = move * K + device.
    pub action: u16,
    pub reward: f32,
    /// Raw s(t+1).
    pub next_obs: Vec<u16>,
    /// The step reached the horizon: a time limit, so learners still bootstrap from `next_obs`.
    pub truncated: bool,
}

/// What a file holds: one task of one world.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DatasetHeader {
    /// Devices K; observations hold 2 + K values.
    pub devices: u16,
    /// The task's index in the config's `[[tasks]]`.
    pub task: u32,
    pub task_name: String,
    /// [`Config::world_hash`] of the world the transitions come from.
    pub world_hash: u64,
}

impl DatasetHeader {
    /// The header of task `task_name`'s dataset under `config`.
    pub fn for_task(config: &Config, task_name: &str) -> Result<Self, ConfigError> {
        let task = config.task_id(task_name)?;
        Ok(Self {
            // Config::validate caps devices at MAX_DEVICES, far below u16::MAX.
            devices: config.world.devices as u16,
            task: task as u32,
            task_name: task_name.to_string(),
            world_hash: config.world_hash(),
        })
    }

    /// The observation and action layout of its world.
    pub fn layout(&self) -> Layout {
        Layout::new(self.devices as usize)
    }

    fn encode(&self) -> Vec<u8> {
        let mut bytes = Vec::with_capacity(FILE_FIXED_LEN + self.task_name.len() + CRC_LEN);
        bytes.extend_from_slice(FILE_MAGIC);
        bytes.extend_from_slice(&SCHEMA_VERSION.to_le_bytes());
        bytes.extend_from_slice(&self.devices.to_le_bytes());
        bytes.extend_from_slice(&self.task.to_le_bytes());
        bytes.extend_from_slice(&self.world_hash.to_le_bytes());
        // DatasetWriter::create refuses longer names.
        bytes.extend_from_slice(&(self.task_name.len() as u16).to_le_bytes());
        bytes.extend_from_slice(self.task_name.as_bytes());
        let crc = crc32fast::hash(&bytes);
        bytes.extend_from_slice(&crc.to_le_bytes());
        bytes
    }

    /// Parses the header at the start of `bytes`; returns it and its length.
    fn decode(bytes: &[u8], path: &Path) -> Result<(Self, usize), DatasetError> {
        let corrupt = |offset: usize, reason: String| DatasetError::Corrupt {
            path: path.to_path_buf(),
            offset: offset as u64,
            reason,
        };
        if bytes.len() < FILE_MAGIC.len() || &bytes[..FILE_MAGIC.len()] != FILE_MAGIC {
            return Err(DatasetError::BadMagic {
                path: path.to_path_buf(),
                found: bytes[..bytes.len().min(FILE_MAGIC.len())].to_vec(),
            });
        }
        if bytes.len() < FILE_FIXED_LEN {
            return Err(corrupt(
                bytes.len(),
                format!(
                    "file header cut short: {} of its first {FILE_FIXED_LEN} bytes",
                    bytes.len()
                ),
            ));
        }
        let version = u16_at(bytes, 8);
        if version != SCHEMA_VERSION {
            return Err(DatasetError::SchemaVersion {
                path: path.to_path_buf(),
                offset: 8,
                found: version,
            });
        }
        let name_len = u16_at(bytes, 24) as usize;
        let total = FILE_FIXED_LEN + name_len + CRC_LEN;
        if bytes.len() < total {
            return Err(corrupt(
                bytes.len(),
                format!(
                    "file header cut short: {} of its {total} bytes",
                    bytes.len()
                ),
            ));
        }
        let stored = u32_at(bytes, total - CRC_LEN);
        let computed = crc32fast::hash(&bytes[..total - CRC_LEN]);
        if stored != computed {
            return Err(corrupt(
                0,
                format!("file header CRC32 is {stored:#010x}, its bytes give {computed:#010x}"),
            ));
        }
        let task_name = std::str::from_utf8(&bytes[FILE_FIXED_LEN..FILE_FIXED_LEN + name_len])
            .map_err(|e| corrupt(FILE_FIXED_LEN, format!("task name is not UTF-8: {e}")))?
            .to_string();
        let header = Self {
            devices: u16_at(bytes, 10),
            task: u32_at(bytes, 12),
            task_name,
            world_hash: u64_at(bytes, 16),
        };
        Ok((header, total))
    }
}

/// A crash's torn tail that [`DatasetWriter::open_append`] cut off.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Recovery {
    /// Transitions in the whole chunks that were kept.
    pub kept_transitions: u64,
    /// Bytes removed from the end of the file.
    pub cut_bytes: u64,
    /// Where the file now ends: the offset of the first bad byte.
    pub offset: u64,
    /// What was wrong with the tail.
    pub reason: String,
}

/// Everything that can be wrong with a dataset file or a request on its contents.
#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    #[error(transparent)]
    File(#[from] FileError),
    #[error("{}: not a uavmeta dataset: it starts with {found:02x?}, expected the magic {:?}", path.display(), String::from_utf8_lossy(FILE_MAGIC))]
    BadMagic { path: PathBuf, found: Vec<u8> },
    #[error("{}: offset {offset}: schema version {found}, this build reads version {SCHEMA_VERSION}", path.display())]
    SchemaVersion {
        path: PathBuf,
        offset: u64,
        found: u16,
    },
    #[error("{}: offset {offset}: corrupt: {reason}", path.display())]
    Corrupt {
        path: PathBuf,
        offset: u64,
        reason: String,
    },
    #[error(
        "{}: offset {offset}: transition {index} of the chunk has a {field} of {found} values, the file header says 2 + K = {expected}",
        path.display()
    )]
    ObservationLength {
        path: PathBuf,
        offset: u64,
        index: usize,
        field: &'static str,
        found: usize,
        expected: usize,
    },
    #[error("{}: offset {offset}: transition {index} of the chunk: {reason}", path.display())]
    InvalidTransition {
        path: PathBuf,
        offset: u64,
        index: usize,
        reason: String,
    },
    #[error("{}: a task name of {bytes} bytes does not fit the file header's 65535", path.display())]
    TaskNameTooLong { path: PathBuf, bytes: usize },
    #[error("{}: holds {found}, expected {expected}", path.display())]
    HeaderMismatch {
        path: PathBuf,
        found: String,
        expected: String,
    },
    #[error("asked for {requested} distinct transitions: expected between 1 and the {available} available")]
    BadShots { requested: usize, available: usize },
    // The source is not in the message: `{:#}` prints the cause chain after it.
    #[error("{}", path.display())]
    Shots {
        path: PathBuf,
        source: Box<DatasetError>,
    },
    #[error("cannot split {available} transitions with support fraction {fraction}: expected a share strictly between 0 and 1 and at least 2 transitions")]
    BadSplit { fraction: f64, available: usize },
}

/// Appends chunks to one task's dataset file; see the module doc for the layout.
pub struct DatasetWriter {
    path: PathBuf,
    header: DatasetHeader,
    file: BufWriter<File>,
    transitions: u64,
    /// File length once buffered chunks are written: where the next chunk starts.
    len: u64,
    /// The chunk being encoded, reused across appends.
    chunk: Vec<u8>,
}

impl DatasetWriter {
    /// Creates (or replaces) `path` with a header and no chunks, synced to disk so a crash
    /// never leaves a file without its header.
    pub fn create(path: impl AsRef<Path>, header: DatasetHeader) -> Result<Self, DatasetError> {
        let path = path.as_ref().to_path_buf();
        if header.task_name.len() > u16::MAX as usize {
            return Err(DatasetError::TaskNameTooLong {
                path,
                bytes: header.task_name.len(),
            });
        }
        let encoded = header.encode();
        let write = || -> io::Result<File> {
            let mut file = File::create(&path)?;
            file.write_all(&encoded)?;
            file.sync_all()?;
            Ok(file)
        };
        let file = write().map_err(FileError::at(&path, "create"))?;
        Ok(Self {
            path,
            header,
            file: BufWriter::new(file),
            transitions: 0,
            len: encoded.len() as u64,
            chunk: Vec::new(),
        })
    }

    /// Opens an existing file to append to it. A torn or corrupt tail left by a crash is cut off
    /// (logged, and described by the returned [`Recovery`]); damage followed by a good chunk is an
    /// error, because cutting there would throw good data away.
    pub fn open_append(path: impl AsRef<Path>) -> Result<(Self, Option<Recovery>), DatasetError> {
        let path = path.as_ref().to_path_buf();
        let (bytes, header, header_len) = read_with_header(&path)?;
        let mut scan = Scan::new(&path, &bytes, &header, header_len);
        let mut transitions = 0u64;
        let recovery = loop {
            match scan.next_chunk() {
                Ok(None) => break None,
                Ok(Some((_, chunk))) => transitions += chunk.len() as u64,
                Err(error) if scan.good_chunk_after_bad() => return Err(error),
                Err(error) => {
                    let cut = Recovery {
                        kept_transitions: transitions,
                        cut_bytes: (bytes.len() - scan.offset) as u64,
                        offset: scan.offset as u64,
                        reason: error.to_string(),
                    };
                    tracing::warn!(
                        file = %path.display(),
                        offset = cut.offset,
                        cut_bytes = cut.cut_bytes,
                        kept_transitions = cut.kept_transitions,
                        "dataset has a torn tail, cutting it off: {}",
                        cut.reason
                    );
                    break Some(cut);
                }
            }
        };
        let len = scan.offset as u64;
        let reopen = || -> io::Result<File> {
            let mut file = OpenOptions::new().write(true).open(&path)?;
            if recovery.is_some() {
                file.set_len(len)?;
                file.sync_all()?;
            }
            file.seek(SeekFrom::Start(len))?;
            Ok(file)
        };
        let file = reopen().map_err(FileError::at(&path, "open for appending"))?;
        let writer = Self {
            path,
            header,
            file: BufWriter::new(file),
            transitions,
            len,
            chunk: Vec::new(),
        };
        Ok((writer, recovery))
    }

    /// Appends to `path` if it exists, after checking that it holds the dataset `header`
    /// describes, or creates it.
    pub fn open_or_create(
        path: impl AsRef<Path>,
        header: DatasetHeader,
    ) -> Result<(Self, Option<Recovery>), DatasetError> {
        let path = path.as_ref();
        if !path.exists() {
            return Ok((Self::create(path, header)?, None));
        }
        let (writer, recovery) = Self::open_append(path)?;
        if writer.header != header {
            return Err(DatasetError::HeaderMismatch {
                path: path.to_path_buf(),
                found: format!("{:?}", writer.header),
                expected: format!("{header:?}"),
            });
        }
        Ok((writer, recovery))
    }

    /// Writes `transitions`, made on the learner's own host, as one chunk ([`Self::append_from`]).
    pub fn append(&mut self, transitions: &[Transition]) -> Result<(), DatasetError> {
        self.append_from(LEARNER_HOST, transitions)
    }

    /// Writes `transitions`, made by `host`'s actors, as one chunk tagged with `host` (nothing
    /// for an empty slice). Each is checked against the header first, so a file never holds a
    /// transition its reader would reject.
    pub fn append_from(
        &mut self,
        host: &str,
        transitions: &[Transition],
    ) -> Result<(), DatasetError> {
        if transitions.is_empty() {
            return Ok(());
        }
        for (index, t) in transitions.iter().enumerate() {
            check_transition(t, &self.header, &self.path, self.len, index)?;
        }
        let invalid = |index: usize, reason: String| DatasetError::InvalidTransition {
            path: self.path.clone(),
            offset: self.len,
            index,
            reason,
        };
        let count = u32::try_from(transitions.len()).map_err(|_| {
            invalid(
                0,
                "a chunk holds at most u32::MAX transitions; append fewer at a time".into(),
            )
        })?;
        self.chunk.clear();
        self.chunk.extend_from_slice(CHUNK_MAGIC);
        self.chunk.extend_from_slice(&SCHEMA_VERSION.to_le_bytes());
        self.chunk
            .extend_from_slice(&self.header.devices.to_le_bytes());
        self.chunk
            .extend_from_slice(&self.header.task.to_le_bytes());
        self.chunk.extend_from_slice(&count.to_le_bytes());
        // The payload length is patched in once the payload is encoded.
        self.chunk.extend_from_slice(&0u32.to_le_bytes());
        let tag = u8::try_from(host.len())
            .map_err(|_| invalid(0, format!("host tag `{host}` is longer than 255 bytes")))?;
        self.chunk.push(tag);
        self.chunk.extend_from_slice(host.as_bytes());
        for (index, t) in transitions.iter().enumerate() {
            postcard::to_io(t, &mut self.chunk)
                .map_err(|e| invalid(index, format!("postcard cannot encode it: {e}")))?;
        }
        let payload_len = u32::try_from(self.chunk.len() - CHUNK_HEADER_LEN).map_err(|_| {
            invalid(
                0,
                "a chunk holds at most u32::MAX payload bytes; append fewer at a time".into(),
            )
        })?;
        self.chunk[16..20].copy_from_slice(&payload_len.to_le_bytes());
        let crc = crc32fast::hash(&self.chunk);
        self.chunk.extend_from_slice(&crc.to_le_bytes());
        self.file
            .write_all(&self.chunk)
            .map_err(FileError::at(&self.path, "append a chunk"))?;
        self.transitions += transitions.len() as u64;
        self.len += self.chunk.len() as u64;
        Ok(())
    }

    /// Hands buffered chunks to the operating system.
    pub fn flush(&mut self) -> Result<(), DatasetError> {
        self.file
            .flush()
            .map_err(FileError::at(&self.path, "flush"))
            .map_err(DatasetError::from)
    }

    /// Flushes and waits until the chunks are on disk: after it returns they survive a crash.
    pub fn sync(&mut self) -> Result<(), DatasetError> {
        self.flush()?;
        self.file
            .get_ref()
            .sync_data()
            .map_err(FileError::at(&self.path, "sync"))
            .map_err(DatasetError::from)
    }

    pub fn header(&self) -> &DatasetHeader {
        &self.header
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Transitions in the file, the kept ones and those appended since opening it.
    pub fn transitions(&self) -> u64 {
        self.transitions
    }

    /// Bytes in the file once buffered chunks are flushed.
    pub fn len_bytes(&self) -> u64 {
        self.len
    }
}

/// A whole dataset file, read and checked; see the module doc for the layout.
#[derive(Debug, Clone)]
pub struct DatasetReader {
    path: PathBuf,
    header: DatasetHeader,
    /// Chunks read, each with its CRC32 checked.
    chunks: usize,
    transitions: Vec<Transition>,
    /// Per chunk in file order, its host tag and how many transitions it holds.
    hosts: Vec<(String, usize)>,
}

/// The whole file with its decoded header and the header's length: where every scan starts.
fn read_with_header(path: &Path) -> Result<(Vec<u8>, DatasetHeader, usize), DatasetError> {
    let bytes = std::fs::read(path).map_err(FileError::at(path, "read"))?;
    let (header, header_len) = DatasetHeader::decode(&bytes, path)?;
    Ok((bytes, header, header_len))
}

impl DatasetReader {
    /// Reads every chunk of `path`. Any damage, including a torn tail that
    /// [`DatasetWriter::open_append`] would cut, is an error naming the file and the offset.
    pub fn open(path: impl AsRef<Path>) -> Result<Self, DatasetError> {
        let path = path.as_ref().to_path_buf();
        let (bytes, header, header_len) = read_with_header(&path)?;
        let mut scan = Scan::new(&path, &bytes, &header, header_len);
        let (mut transitions, mut hosts) = (Vec::new(), Vec::new());
        while let Some((host, chunk)) = scan.next_chunk()? {
            hosts.push((host, chunk.len()));
            transitions.extend(chunk);
        }
        Ok(Self {
            path,
            header,
            chunks: hosts.len(),
            transitions,
            hosts,
        })
    }

    /// Opens `path` as task `task_name`'s data collected in `config`'s world: the checks every
    /// learner makes before it trusts a file.
    pub fn open_task(
        path: impl AsRef<Path>,
        config: &Config,
        task_name: &str,
    ) -> Result<Self, DatasetError> {
        let reader = Self::open(path)?;
        reader.check_world(config)?;
        if reader.header.task_name != task_name {
            return Err(DatasetError::HeaderMismatch {
                path: reader.path.clone(),
                found: format!("task `{}`", reader.header.task_name),
                expected: format!("task `{task_name}`"),
            });
        }
        Ok(reader)
    }

    /// N shots of the file, [`sample_shots`] from `seed`: the one draw behind `uavmeta train
    /// --shots`, meta-test and `uavmeta dataset export --shots`, so they all see the same data.
    pub fn shots(&self, shots: usize, seed: u64) -> Result<Vec<Transition>, DatasetError> {
        sample_shots(&self.transitions, shots, seed).map_err(|source| DatasetError::Shots {
            path: self.path.clone(),
            source: Box::new(source),
        })
    }

    /// Checks that the file was collected in `config`'s world, so its observations and actions
    /// mean what the learner will assume.
    pub fn check_world(&self, config: &Config) -> Result<(), DatasetError> {
        let expected = (config.world.devices, config.world_hash());
        let found = (self.header.devices as usize, self.header.world_hash);
        if found != expected {
            return Err(DatasetError::HeaderMismatch {
                path: self.path.clone(),
                found: format!("a world of K = {} devices with world hash {:#018x}", found.0, found.1),
                expected: format!(
                    "the world of {} (K = {}, world hash {:#018x}); collect it again with this config",
                    config.origin, expected.0, expected.1
                ),
            });
        }
        Ok(())
    }

    pub fn header(&self) -> &DatasetHeader {
        &self.header
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    pub fn transitions(&self) -> &[Transition] {
        &self.transitions
    }

    /// Chunks in the file, every one of them checked against its CRC32.
    pub fn chunks(&self) -> usize {
        self.chunks
    }

    pub fn into_transitions(self) -> Vec<Transition> {
        self.transitions
    }

    /// Every transition with the host tag of its chunk ([`LEARNER_HOST`] for the learner's own).
    pub fn with_hosts(&self) -> impl Iterator<Item = (&str, &Transition)> {
        let tags = (self.hosts.iter()).flat_map(|(host, n)| std::iter::repeat_n(host.as_str(), *n));
        tags.zip(&self.transitions)
    }

    /// How many of the file's transitions each host made, by host tag.
    pub fn provenance(&self) -> std::collections::BTreeMap<&str, u64> {
        let mut counts = std::collections::BTreeMap::new();
        for (host, n) in &self.hosts {
            *counts.entry(host.as_str()).or_default() += *n as u64;
        }
        counts
    }
}

/// Walks the chunks of a file held in memory.
struct Scan<'a> {
    path: &'a Path,
    bytes: &'a [u8],
    header: &'a DatasetHeader,
    /// Start of the next chunk; after an error, the start of the bad one.
    offset: usize,
}

impl<'a> Scan<'a> {
    fn new(path: &'a Path, bytes: &'a [u8], header: &'a DatasetHeader, offset: usize) -> Self {
        Self {
            path,
            bytes,
            header,
            offset,
        }
    }

    /// The next chunk's host tag and transitions, `None` at a clean end of file. On error
    /// `offset` stays at the bad chunk.
    fn next_chunk(&mut self) -> Result<Option<(String, Vec<Transition>)>, DatasetError> {
        let rest = &self.bytes[self.offset..];
        if rest.is_empty() {
            return Ok(None);
        }
        let payload_len = self.check_frame(rest)?;
        self.check_fields(rest)?;
        let count = u32_at(rest, 12) as usize;
        let payload = &rest[CHUNK_HEADER_LEN..CHUNK_HEADER_LEN + payload_len];
        let (host, payload) = self.host_tag(payload)?;
        let transitions = self.decode(payload, count)?;
        self.offset += CHUNK_HEADER_LEN + payload_len + CRC_LEN;
        Ok(Some((host, transitions)))
    }

    /// The host tag that starts a chunk's payload, and the rest of the payload.
    fn host_tag<'p>(&self, payload: &'p [u8]) -> Result<(String, &'p [u8]), DatasetError> {
        let len = *payload
            .first()
            .ok_or_else(|| self.corrupt("the payload has no host tag".into()))?
            as usize;
        let (tag, rest) = payload[1..].split_at_checked(len).ok_or_else(|| {
            self.corrupt(format!(
                "host tag of {len} bytes in a payload of {}",
                payload.len()
            ))
        })?;
        let host = std::str::from_utf8(tag)
            .map_err(|_| self.corrupt(format!("host tag {tag:02x?} is not UTF-8")))?;
        Ok((host.to_string(), rest))
    }

    /// The bad chunk at `offset`, and why.
    fn corrupt(&self, reason: String) -> DatasetError {
        DatasetError::Corrupt {
            path: self.path.to_path_buf(),
            offset: self.offset as u64,
            reason,
        }
    }

    /// Checks that `rest` starts with a whole chunk (header, magic, length) whose CRC32 holds;
    /// returns its payload's length.
    fn check_frame(&self, rest: &[u8]) -> Result<usize, DatasetError> {
        if rest.len() < CHUNK_HEADER_LEN {
            return Err(self.corrupt(format!(
                "chunk header cut short: {} of its {CHUNK_HEADER_LEN} bytes",
                rest.len()
            )));
        }
        if &rest[..4] != CHUNK_MAGIC {
            return Err(self.corrupt(format!(
                "no chunk magic {:?} here, found {:02x?}",
                String::from_utf8_lossy(CHUNK_MAGIC),
                &rest[..4]
            )));
        }
        let payload_len = u32_at(rest, 16) as usize;
        let total = CHUNK_HEADER_LEN + payload_len + CRC_LEN;
        if rest.len() < total {
            return Err(self.corrupt(format!(
                "chunk cut short: {} of its {total} bytes",
                rest.len()
            )));
        }
        // The checksum comes before every other field is trusted, so a flipped bit anywhere in
        // the chunk is reported as such.
        let stored = u32_at(rest, total - CRC_LEN);
        let computed = crc32fast::hash(&rest[..total - CRC_LEN]);
        if stored != computed {
            return Err(self.corrupt(format!(
                "chunk CRC32 is {stored:#010x}, its bytes give {computed:#010x}"
            )));
        }
        Ok(payload_len)
    }

    /// Checks the chunk header's schema version, device count and task against the file's.
    fn check_fields(&self, rest: &[u8]) -> Result<(), DatasetError> {
        let version = u16_at(rest, 4);
        if version != SCHEMA_VERSION {
            return Err(DatasetError::SchemaVersion {
                path: self.path.to_path_buf(),
                offset: self.offset as u64 + 4,
                found: version,
            });
        }
        let (devices, task) = (u16_at(rest, 6), u32_at(rest, 8));
        if devices != self.header.devices || task != self.header.task {
            return Err(self.corrupt(format!(
                "chunk of task {task} with K = {devices} in the file of task {} with K = {}",
                self.header.task, self.header.devices
            )));
        }
        Ok(())
    }

    /// Decodes and checks the `count` transitions of a chunk's payload.
    fn decode(&self, mut payload: &[u8], count: usize) -> Result<Vec<Transition>, DatasetError> {
        // A count is at most the payload length, since every transition takes several bytes.
        let mut transitions = Vec::with_capacity(count.min(payload.len()));
        for index in 0..count {
            let (t, remaining) = postcard::take_from_bytes::<Transition>(payload).map_err(|e| {
                self.corrupt(format!(
                    "transition {index} of {count} does not decode: {e}"
                ))
            })?;
            check_transition(&t, self.header, self.path, self.offset as u64, index)?;
            transitions.push(t);
            payload = remaining;
        }
        if !payload.is_empty() {
            return Err(self.corrupt(format!(
                "{} bytes left in the payload after its {count} transitions",
                payload.len()
            )));
        }
        Ok(transitions)
    }

    /// After a bad chunk at `offset`: whether a good chunk starts anywhere after it. A crash only
    /// ever damages the end of a file, so that means damage in the middle. Every later occurrence
    /// of the chunk magic is tried, since the bad chunk's own length field may be the damage.
    fn good_chunk_after_bad(&self) -> bool {
        let start = self.offset + 1;
        (start..self.bytes.len().saturating_sub(CHUNK_MAGIC.len() - 1))
            .filter(|&at| &self.bytes[at..at + CHUNK_MAGIC.len()] == CHUNK_MAGIC)
            .any(|at| {
                Scan::new(self.path, self.bytes, self.header, at)
                    .next_chunk()
                    .is_ok()
            })
    }
}

/// The checks every transition passes before it is written and after it is read.
fn check_transition(
    t: &Transition,
    header: &DatasetHeader,
    path: &Path,
    offset: u64,
    index: usize,
) -> Result<(), DatasetError> {
    let expected = header.layout().observation_len();
    for (field, len) in [("obs", t.obs.len()), ("next_obs", t.next_obs.len())] {
        if len != expected {
            return Err(DatasetError::ObservationLength {
                path: path.to_path_buf(),
                offset,
                index,
                field,
                found: len,
                expected,
            });
        }
    }
    let invalid = |reason: String| DatasetError::InvalidTransition {
        path: path.to_path_buf(),
        offset,
        index,
        reason,
    };
    if t.task != header.task {
        return Err(invalid(format!(
            "task {} in the file of task {} (`{}`)",
            t.task, header.task, header.task_name
        )));
    }
    if t.action as usize >= header.layout().action_count() {
        return Err(invalid(format!(
            "action {} is not below 5K = {}",
            t.action,
            header.layout().action_count()
        )));
    }
    if !t.reward.is_finite() {
        return Err(invalid(format!(
            "reward {} is not a finite number",
            t.reward
        )));
    }
    Ok(())
}

/// Splits one task's data into a support set and a query set, the first holding
/// `round(support_fraction * n)` transitions (at least one each), drawn at random from `seed`.
/// Each set keeps the file's order.
pub fn split(
    transitions: &[Transition],
    support_fraction: f64,
    seed: u64,
) -> Result<(Vec<Transition>, Vec<Transition>), DatasetError> {
    let n = transitions.len();
    if n < 2 || !(support_fraction > 0.0 && support_fraction < 1.0) {
        return Err(DatasetError::BadSplit {
            fraction: support_fraction,
            available: n,
        });
    }
    let support_len = ((support_fraction * n as f64).round() as usize).clamp(1, n - 1);
    let mut order: Vec<usize> = (0..n).collect();
    order.shuffle(&mut ChaCha8Rng::seed_from_u64(seed));
    let (support, query) = order.split_at_mut(support_len);
    support.sort_unstable();
    query.sort_unstable();
    let pick = |indices: &[usize]| indices.iter().map(|&i| transitions[i].clone()).collect();
    Ok((pick(support), pick(query)))
}

/// N shots: `shots` distinct transitions drawn at random from `seed`.
pub fn sample_shots(
    transitions: &[Transition],
    shots: usize,
    seed: u64,
) -> Result<Vec<Transition>, DatasetError> {
    if shots == 0 || shots > transitions.len() {
        return Err(DatasetError::BadShots {
            requested: shots,
            available: transitions.len(),
        });
    }
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    Ok(rand::seq::index::sample(&mut rng, transitions.len(), shots)
        .into_iter()
        .map(|i| transitions[i].clone())
        .collect())
}

fn u16_at(bytes: &[u8], at: usize) -> u16 {
    u16::from_le_bytes([bytes[at], bytes[at + 1]])
}

fn u32_at(bytes: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(bytes[at..at + 4].try_into().expect("4 bytes"))
}

fn u64_at(bytes: &[u8], at: usize) -> u64 {
    u64::from_le_bytes(bytes[at..at + 8].try_into().expect("8 bytes"))
}
