//! Checkpoints: a Q-network's weights with enough metadata to rebuild and check it.
//!
//! A checkpoint named `P` is three files side by side:
//! - `P.safetensors`: the VarStore (`layer{i}.weight` [out, in], `layer{i}.bias` [out]);
//! - `P.json`: [`CheckpointMeta`] (algorithm, sizes, world hash, epoch, and the length and CRC32
//!   of the weights file, so truncation and corruption are caught before libtorch reads it);
//! - `P.toml`: the full config of the run that wrote it, to rebuild or reproduce it.
//!
//! Every file is written to a temporary name in the same directory, fsynced and renamed, so a
//! crash leaves either the old checkpoint or the new one, never a torn file under the real name.
//! The metadata goes last: a weights file without metadata is never taken for a checkpoint.
//!
//! A trainer that must continue exactly where it stopped (the meta-learner process) also saves
//! its **training state** beside `P` ([`save_state`]): `P.state.safetensors` (its tensors, such as
//! optimiser moments) and `P.state.json` (the trainer's own fields, and the length and CRC32 of
//! the tensors file), written the same way and before `P`'s metadata, so a complete checkpoint
//! always has its state.

use std::fs::File;
use std::path::{Path, PathBuf};

use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};
use tch::{TchError, Tensor};
use uavmeta_proto::config::Config;
use uavmeta_proto::method::{Method, Start};

use crate::algorithm;
use crate::qnet::{QNetwork, QNetworkConfig};
use uavmeta_proto::fs::FileError;

/// Version of the metadata layout; bumped when [`CheckpointMeta`] changes meaning.
pub const FORMAT_VERSION: u32 = 1;

/// What a checkpoint holds, stored as `P.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CheckpointMeta {
    pub format_version: u32,
    /// The method that trained the weights: `cql`, `dqn`, `cql-maml`, `dqn-online`, ...
    pub algorithm: String,
    /// Network input size, 2 + K.
    pub obs_len: usize,
    /// Network output size, 5K.
    pub actions: usize,
    pub hidden: Vec<usize>,
    /// Blocks of `actions` outputs (`QNetworkConfig::heads`); written only when not 1.
    #[serde(default = "one_head", skip_serializing_if = "is_one_head")]
    pub heads: usize,
    /// `Config::world_hash` of the world it was trained in.
    pub world_hash: u64,
    /// Epochs (or meta-epochs) of training behind these weights.
    pub epoch: usize,
    /// Length in bytes of `P.safetensors`.
    pub weights_len: u64,
    /// CRC32 of `P.safetensors`.
    pub weights_crc32: u32,
}

#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    #[error(transparent)]
    File(#[from] FileError),
    #[error("{}: not checkpoint metadata", path.display())]
    Meta {
        path: PathBuf,
        source: serde_json::Error,
    },
    #[error("{}: checkpoint format version {found}, this build reads version {FORMAT_VERSION}", path.display())]
    FormatVersion { path: PathBuf, found: u32 },
    #[error("{}: truncated: the file ends at offset {len}, its metadata records {expected} bytes", path.display())]
    Truncated {
        path: PathBuf,
        len: u64,
        expected: u64,
    },
    #[error("{}: corrupt: {len} bytes with CRC32 {found:#010x}, its metadata records {expected_len} bytes with CRC32 {expected:#010x}", path.display())]
    Corrupt {
        path: PathBuf,
        len: u64,
        found: u32,
        expected_len: u64,
        expected: u32,
    },
    #[error("{}: cannot {action} the weights", path.display())]
    Weights {
        path: PathBuf,
        /// "load" or "save": a full disk on save must not read as a damaged file.
        action: &'static str,
        source: TchError,
    },
    #[error("{}: `heads` = {found}, but a `{algorithm}` network has {expected} block(s) of outputs", path.display())]
    Heads {
        path: PathBuf,
        algorithm: String,
        found: usize,
        expected: usize,
    },
    #[error("{}: a context learner's model (`{algorithm}`): its network reads a task code after the observation, read from a task's shots; use it as `uavmeta meta-test --init`", path.display())]
    ContextModel { path: PathBuf, algorithm: String },
    /// `key` is the config key whose value differs from the checkpoint's; `detail` says how.
    #[error("{}: {detail}", path.display())]
    SizeMismatch {
        path: PathBuf,
        key: &'static str,
        detail: String,
    },
}

/// The three files of checkpoint `path` (any extension of `path` is replaced).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CheckpointPaths {
    pub weights: PathBuf,
    pub meta: PathBuf,
    pub config: PathBuf,
}

impl CheckpointPaths {
    pub fn new(path: &Path) -> Self {
        Self {
            weights: path.with_extension("safetensors"),
            meta: path.with_extension("json"),
            config: path.with_extension("toml"),
        }
    }
}

/// Saves `q` as checkpoint `path` (see the module doc), trained by `algorithm` for `epoch`
/// epochs under `config`. Returns the metadata written.
pub fn save(
    path: &Path,
    q: &QNetwork,
    algorithm: &str,
    epoch: usize,
    config: &Config,
) -> Result<CheckpointMeta, CheckpointError> {
    let paths = CheckpointPaths::new(path);
    let dir = create_parent(&paths.weights)?;

    let (tmp_weights, bytes) = write_temp(&paths.weights, |tmp| q.vs.save(tmp))?;

    let meta = CheckpointMeta {
        format_version: FORMAT_VERSION,
        algorithm: algorithm.to_string(),
        obs_len: q.obs_len(),
        actions: q.actions(),
        hidden: q.hidden().to_vec(),
        heads: q.config().heads,
        world_hash: config.world_hash(),
        epoch,
        weights_len: bytes.len() as u64,
        weights_crc32: crc32fast::hash(&bytes),
    };
    let meta_text =
        serde_json::to_string_pretty(&meta).expect("checkpoint metadata always serialises");
    write_atomic(&paths.config, config.to_toml_string().as_bytes())?;
    rename(&tmp_weights, &paths.weights)?;
    write_atomic(&paths.meta, meta_text.as_bytes())?;
    // The renames are durable only once the directory entry is.
    sync_file(&dir)?;
    Ok(meta)
}

/// The metadata of a training state, stored as `P.state.json`.
#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct StateMeta<S> {
    format_version: u32,
    /// Length in bytes of `P.state.safetensors`.
    tensors_len: u64,
    /// CRC32 of `P.state.safetensors`.
    tensors_crc32: u32,
    /// The trainer's own fields.
    state: S,
}

/// The two files of the training state beside checkpoint `path`: tensors, then metadata.
pub fn state_paths(path: &Path) -> (PathBuf, PathBuf) {
    (
        path.with_extension("state.safetensors"),
        path.with_extension("state.json"),
    )
}

/// Saves a trainer's state beside checkpoint `path` (see the module doc): `tensors` bit for bit,
/// and `state` as JSON. Call it before [`save`], whose metadata marks the checkpoint complete.
pub fn save_state<S: Serialize>(
    path: &Path,
    tensors: &[(String, Tensor)],
    state: &S,
) -> Result<(), CheckpointError> {
    let (tensors_path, meta_path) = state_paths(path);
    let dir = create_parent(&tensors_path)?;
    let (tmp, bytes) = write_temp(&tensors_path, |tmp| Tensor::write_safetensors(tensors, tmp))?;
    let meta = StateMeta {
        format_version: FORMAT_VERSION,
        tensors_len: bytes.len() as u64,
        tensors_crc32: crc32fast::hash(&bytes),
        state,
    };
    let text = serde_json::to_string_pretty(&meta).map_err(|source| CheckpointError::Meta {
        path: meta_path.clone(),
        source,
    })?;
    rename(&tmp, &tensors_path)?;
    write_atomic(&meta_path, text.as_bytes())?;
    sync_file(&dir)
}

/// Loads the training state saved beside checkpoint `path`: its tensors, by name, and the
/// trainer's fields. A missing, truncated or corrupt file is an error naming it.
pub fn load_state<S: DeserializeOwned>(
    path: &Path,
) -> Result<(Vec<(String, Tensor)>, S), CheckpointError> {
    let (tensors_path, meta_path) = state_paths(path);
    let meta: StateMeta<S> = read_json(&meta_path, |m: &StateMeta<S>| m.format_version)?;
    verify(&tensors_path, meta.tensors_len, meta.tensors_crc32)?;
    let tensors =
        Tensor::read_safetensors(&tensors_path).map_err(weights_error(&tensors_path, "load"))?;
    Ok((tensors, meta.state))
}

/// Reads and checks the metadata of checkpoint `path`.
pub fn read_meta(path: &Path) -> Result<CheckpointMeta, CheckpointError> {
    read_json(&CheckpointPaths::new(path).meta, |m: &CheckpointMeta| {
        m.format_version
    })
}

/// Reads a JSON metadata file and checks that `format_version` of it is the one this build writes.
fn read_json<T: DeserializeOwned>(
    path: &Path,
    format_version: impl Fn(&T) -> u32,
) -> Result<T, CheckpointError> {
    let text = read(path, "read")?;
    let meta: T = serde_json::from_slice(&text).map_err(|source| CheckpointError::Meta {
        path: path.to_path_buf(),
        source,
    })?;
    let found = format_version(&meta);
    if found != FORMAT_VERSION {
        return Err(CheckpointError::FormatVersion {
            path: path.to_path_buf(),
            found,
        });
    }
    Ok(meta)
}

/// Whether a checkpoint is the context learner's task-conditioned network, which reads a task
/// code after the observation (`uavmeta_meta::context`), rather than a network on the
/// observation alone (w0, or `cql-context`'s network after an epoch on a task's shots).
pub fn is_context_model(meta: &CheckpointMeta, config: &Config) -> bool {
    let method = Method::from_name(&meta.algorithm);
    method.and_then(Method::start) == Some(Start::Context)
        && meta.obs_len != config.world.layout().observation_len()
}

/// Loads checkpoint `path` into a new network sized by `config` (`world.devices`, and
/// `learner.hidden`, or `collect.dqn.hidden` for an online DQN agent's). Sizes that differ from the
/// checkpoint's, a truncated or corrupt weights file, or unreadable metadata are errors naming the
/// file.
pub fn load(path: &Path, config: &Config) -> Result<(QNetwork, CheckpointMeta), CheckpointError> {
    load_conditioned(path, config, 0)
}

/// [`load`] for a network that reads `code_len` values after the observation (the context
/// learner's task-conditioned Q-network, `uavmeta_meta::context`).
pub fn load_conditioned(
    path: &Path,
    config: &Config,
    code_len: usize,
) -> Result<(QNetwork, CheckpointMeta), CheckpointError> {
    let paths = CheckpointPaths::new(path);
    let meta = read_meta(path)?;
    let mismatch = |what: &str, checkpoint: String, config_value: String, key| {
        CheckpointError::SizeMismatch {
        path: paths.meta.clone(),
        key,
        detail: format!(
            "the checkpoint's network has {what} {checkpoint}, but {} gives {config_value} ({key}); \
             use the config it was trained with (saved beside it as {})",
            config.origin,
            paths.config.display()
        ),
    }
    };
    let obs_len = config.world.layout().observation_len() + code_len;
    if code_len == 0 && is_context_model(&meta, config) {
        return Err(CheckpointError::ContextModel {
            path: paths.meta.clone(),
            algorithm: meta.algorithm.clone(),
        });
    }
    let actions = config.world.layout().action_count();
    if meta.obs_len != obs_len {
        let what = match code_len {
            0 => "input size (2 + K)".to_string(),
            n => format!("input size (2 + K + a task code of {n})"),
        };
        return Err(mismatch(
            &what,
            meta.obs_len.to_string(),
            obs_len.to_string(),
            "world.devices",
        ));
    }
    if meta.actions != actions {
        return Err(mismatch(
            "output size (5K)",
            meta.actions.to_string(),
            actions.to_string(),
            "world.devices",
        ));
    }
    // The online DQN agent has a network of its own; every offline learner shares `learner`'s.
    let (hidden, hidden_key) = if meta.algorithm == Method::OnlineDqn.name() {
        (&config.collect.dqn.hidden, "collect.dqn.hidden")
    } else {
        (&config.learner.hidden, "learner.hidden")
    };
    if &meta.hidden != hidden {
        return Err(mismatch(
            "hidden widths",
            format!("{:?}", meta.hidden),
            format!("{hidden:?}"),
            hidden_key,
        ));
    }
    if meta.world_hash != config.world_hash() {
        tracing::warn!(
            checkpoint = %paths.weights.display(),
            "trained in a different world (hash {:#018x}) than {} ({:#018x}); the sizes match, so it loads",
            meta.world_hash,
            config.origin,
            config.world_hash()
        );
    }

    // The algorithm decides the heads; a forged count would size the network.
    let algorithm = Method::from_name(&meta.algorithm)
        .and_then(Method::algo)
        .map(algorithm::of);
    let heads = algorithm.as_ref().map_or(1, |a| a.heads());
    if meta.heads != heads {
        return Err(CheckpointError::Heads {
            path: paths.meta.clone(),
            algorithm: meta.algorithm.clone(),
            found: meta.heads,
            expected: heads,
        });
    }
    verify(&paths.weights, meta.weights_len, meta.weights_crc32)?;
    let mut q = QNetworkConfig {
        heads,
        ..QNetworkConfig::new(obs_len, actions, &meta.hidden)
    }
    .init(0);
    q.vs.load(&paths.weights)
        .map_err(weights_error(&paths.weights, "load"))?;
    // It acts as the algorithm that trained it does.
    if let Some(algorithm) = algorithm {
        q.set_acting(algorithm.acting(&config.learner));
    }
    Ok((q, meta))
}

/// Checks that `path` holds `expected_len` bytes with CRC32 `expected_crc`.
fn verify(path: &Path, expected_len: u64, expected_crc: u32) -> Result<(), CheckpointError> {
    let bytes = read(path, "read")?;
    let len = bytes.len() as u64;
    if len < expected_len {
        return Err(CheckpointError::Truncated {
            path: path.to_path_buf(),
            len,
            expected: expected_len,
        });
    }
    let crc = crc32fast::hash(&bytes);
    if len != expected_len || crc != expected_crc {
        return Err(CheckpointError::Corrupt {
            path: path.to_path_buf(),
            len,
            found: crc,
            expected_len,
            expected: expected_crc,
        });
    }
    Ok(())
}

/// Writes tensors with `write` to a synced temporary file beside `path`: its name and its bytes.
fn write_temp(
    path: &Path,
    write: impl FnOnce(&Path) -> Result<(), TchError>,
) -> Result<(PathBuf, Vec<u8>), CheckpointError> {
    // VarStore::save picks the format from the extension, so the temporary name keeps it.
    let tmp = temp_name(path, "safetensors");
    write(&tmp).map_err(weights_error(&tmp, "save"))?;
    let bytes = read(&tmp, "read back")?;
    sync_file(&tmp)?;
    Ok((tmp, bytes))
}

/// The error of `action` ("load" or "save") on the weights file `path`, for `map_err`.
fn weights_error(path: &Path, action: &'static str) -> impl FnOnce(TchError) -> CheckpointError {
    let path = path.to_path_buf();
    move |source| CheckpointError::Weights {
        path,
        action,
        source,
    }
}

fn read(path: &Path, action: &'static str) -> Result<Vec<u8>, CheckpointError> {
    std::fs::read(path)
        .map_err(FileError::at(path, action))
        .map_err(CheckpointError::from)
}

/// Creates the directory `path` goes into, and returns it.
fn create_parent(path: &Path) -> Result<PathBuf, CheckpointError> {
    let dir = path
        .parent()
        .filter(|d| !d.as_os_str().is_empty())
        .unwrap_or(Path::new("."))
        .to_path_buf();
    std::fs::create_dir_all(&dir).map_err(FileError::at(&dir, "create the directory"))?;
    Ok(dir)
}

/// `dir/.name.tmp-PID.ext`: hidden, unique per process, same directory (so rename is atomic).
fn temp_name(path: &Path, ext: &str) -> PathBuf {
    let stem = path
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    path.with_file_name(format!(".{stem}.tmp-{}.{ext}", std::process::id()))
}

fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), CheckpointError> {
    Ok(uavmeta_proto::fs::write_atomic(path, bytes)?)
}

fn sync_file(path: &Path) -> Result<(), CheckpointError> {
    File::open(path)
        .and_then(|f| f.sync_all())
        .map_err(FileError::at(path, "fsync"))
        .map_err(CheckpointError::from)
}

fn rename(from: &Path, to: &Path) -> Result<(), CheckpointError> {
    std::fs::rename(from, to)
        .map_err(FileError::at(to, "rename into place"))
        .map_err(CheckpointError::from)
}

fn one_head() -> usize {
    1
}

fn is_one_head(heads: &usize) -> bool {
    *heads == 1
}
