//! What uavmeta's processes say to each other over iceoryx2, and where a run keeps its files.
//!
//! **Transitions** travel from actors to the store as a slice of fixed-layout
//! [`TransitionSlot`]s under one [`BatchHeader`] (`publish_subscribe::<[TransitionSlot]>()` with a
//! user header): an actor loans a batch of slots in shared memory, writes every step straight into
//! its slot ([`TransitionPublisher::loan`]) and sends it; the store reads it in place. Nothing is
//! serialised per transition. A slot's observation arrays have room for the largest K,
//! but only their first `obs_len` (= 2 + K, in the header) entries are written: **receivers must
//! never read past `obs_len`**; the rest holds whatever an earlier batch left in that memory.
//! There is one service per task, `uavmeta/<run>/transitions/<task>` ([`ServiceNames`]).
//!
//! **Delivery.** Safe overflow is off and publishers use `RetryUntilDelivered`: when the store's
//! buffer is full, an actor waits (backpressure) instead of overwriting a batch the store has not
//! read. An actor sends only while a store is subscribed ([`TransitionPublisher::subscribers`]),
//! holding its written batch until then, since iceoryx2 0.10 drops a batch sent to nobody. A send
//! can still report no recipient ([`Delivery::recipients`]) although the store is subscribed:
//! iceoryx2 connects a subscriber to a new publisher only when the subscriber next looks for data,
//! and a batch sent into its full queue before that is dropped. So an actor keeps a copy of what
//! it sent and sends it again under the same numbers when a send reaches nobody.
//!
//! **Acknowledgements.** A store that goes away loses the batches its queue held unwritten. So the
//! store acknowledges what it has appended ([`StoreAck`], one service per task,
//! `uavmeta/<run>/acks/<task>`): per actor, every sequence number below `next_seq` is in the
//! dataset file. An actor keeps what is not yet acknowledged and, when the store is replaced,
//! sends it again from the acknowledged number, in order; the new store drops what the dead one
//! had written as duplicates (see `actors::actor`, and `run.keep_until_stored` for the
//! cheaper choice of keeping a rollout's batches only until the store is proven connected:
//! more batches than its queue holds ([`TransitionPublisher::subscriber_buffer`]) delivered).
//! Acknowledgements are cumulative, so their service overwrites the oldest when an actor's buffer
//! is full rather than ever blocking the store.
//!
//! Transition services keep no history: in iceoryx2 0.10 a subscriber that joins a publisher with
//! history gets that history into its buffer and afterwards the blocking publisher silently loses
//! batches (measured: 39 296 of 43 456 transitions of one actor).
//!
//! **Control** messages ([`DatasetReady`], [`CheckpointReady`], [`Shutdown`]) each have their own
//! service under `uavmeta/<run>/control/`, with history, so a process that joins late (or
//! restarts) still hears what was announced before.
//!
//! **Schema version.** Every service is created with the attribute
//! `uavmeta.schema_version = SCHEMA_VERSION`, and every opener requires it. A process built with
//! another version therefore cannot open a run's services: it fails with
//! [`TransportError::SchemaMismatch`], which names the service and both versions. The version is
//! deliberately not in the service name: two versions would then share a run silently, each
//! waiting forever for the other's messages. The payload type names carry the version too, and
//! every header repeats it, so a mismatch can never be read as data.
//!
//! **Run directory** ([`RunDir`]): the config every process of the run reads, the datasets,
//! checkpoints, metrics port files and final metrics snapshots, logs and evaluation rows.

use std::fmt;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use iceoryx2::node::{Node, NodeWaitFailure};
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::port::{BackpressureAction, BackpressureInfo};
use iceoryx2::prelude::*;
use iceoryx2::service::port_factory::publish_subscribe::PortFactory as PubSubFactory;
use iceoryx2_bb_posix::signal::SignalHandler;

use crate::config::{Config, RunConfig, TaskConfig, MAX_DEVICES};
use crate::dataset::Transition;
use crate::method::Method;

/// The version of every payload below and of the service settings; bump it on any change.
pub const SCHEMA_VERSION: u32 = 3;

/// The service attribute that carries [`SCHEMA_VERSION`].
pub const SCHEMA_ATTRIBUTE: &str = "uavmeta.schema_version";

/// Entries of an observation array: 2 + the largest K a config admits.
pub const OBS_CAPACITY: usize = 2 + MAX_DEVICES;

/// Subscribers a transition service admits: the store, plus room for a benchmark or a monitor.
const TRANSITION_SUBSCRIBERS: usize = 4;

/// Acknowledgements an actor's subscriber holds: every actor of a task hears every one, and only
/// the newest of its own matters.
const ACK_BUFFER: usize = 16;

/// Processes besides the actors that open a control service: store, meta-learner, evaluator,
/// launcher, and room for a hand-started one of each.
const CONTROL_PEERS: usize = 8;

/// A control publisher blocked this long on one subscriber's full buffer gives up on that
/// subscriber: it is dead or stuck, and announcements must not stall the run.
const CONTROL_DELIVERY_TIMEOUT: Duration = Duration::from_secs(5);

/// Everything opening or using a service can fail on.
#[derive(Debug, thiserror::Error)]
pub enum TransportError {
    #[error(
        "service `{service}` belongs to schema version {theirs}, but this uavmeta build speaks \
         version {SCHEMA_VERSION}; run every process of a run from the same build"
    )]
    SchemaMismatch { service: String, theirs: String },
    #[error("service `{service}`: cannot {action}: {message}")]
    Service {
        service: String,
        action: &'static str,
        message: String,
    },
    #[error("iceoryx2: cannot {action}: {message}")]
    Receive {
        action: &'static str,
        message: String,
    },
    #[error("`{name}` is not a valid iceoryx2 service name: {message}")]
    ServiceName { name: String, message: String },
    #[error("{}: cannot {action}", path.display())]
    Io {
        path: PathBuf,
        action: &'static str,
        source: std::io::Error,
    },
    #[error(
        "batch from actor {actor} of task {task}: {problem}; the actor runs another config or \
         another run than this process"
    )]
    ForeignBatch {
        actor: u32,
        task: u32,
        problem: String,
    },
}

/// The header of one batch of transitions.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ZeroCopySend)]
#[type_name("uavmeta.BatchHeader.v3")]
#[repr(C)]
pub struct BatchHeader {
    pub schema_version: u32,
    /// The task's index in the config's `[[tasks]]`.
    pub task: u32,
    /// [`RunDir::hash`] of the run the actor joined.
    pub run: u64,
    /// `Config::world_hash` of the actor's world.
    pub world: u64,
    /// The actor that made the batch.
    pub actor: u32,
    /// Used entries of every observation array, 2 + K.
    pub obs_len: u32,
    /// Sequence number of the first slot; slot i has `first_seq + i`.
    pub first_seq: u64,
    /// Slots in the batch, equal to the slice length.
    pub count: u32,
    /// Explicit padding, so the layout has no uninitialised bytes.
    pub reserved: u32,
    /// Wall-clock send time in nanoseconds since the Unix epoch, for publish-to-receive latency
    /// (on one host both ends share the clock; from a remote actor host, through the tunnel, the
    /// figure is only as good as the two hosts' clock synchronisation).
    pub sent_unix_ns: u64,
}

impl Default for BatchHeader {
    fn default() -> Self {
        Self {
            schema_version: SCHEMA_VERSION,
            task: 0,
            run: 0,
            world: 0,
            actor: 0,
            obs_len: 0,
            first_seq: 0,
            count: 0,
            reserved: 0,
            sent_unix_ns: 0,
        }
    }
}

impl BatchHeader {
    /// Checks that a received batch belongs to this run, world and task, and that its count and
    /// observation length fit its slice.
    pub fn check(
        &self,
        run: u64,
        world: u64,
        task: u32,
        obs_len: usize,
        slots: usize,
    ) -> Result<(), TransportError> {
        let problem = if self.schema_version != SCHEMA_VERSION {
            Some(format!(
                "schema version {} (this build: {SCHEMA_VERSION})",
                self.schema_version
            ))
        } else if self.run != run {
            Some(format!(
                "run hash {:#018x} (this run: {run:#018x})",
                self.run
            ))
        } else if self.world != world {
            Some(format!(
                "world hash {:#018x} (this config: {world:#018x})",
                self.world
            ))
        } else if self.task != task {
            Some(format!(
                "task id {} on the service of task id {task}",
                self.task
            ))
        } else if self.obs_len as usize != obs_len {
            Some(format!(
                "observations of {} values (this config: {obs_len})",
                self.obs_len
            ))
        } else if self.count as usize != slots {
            Some(format!(
                "a header count of {} over {slots} slots",
                self.count
            ))
        } else {
            None
        };
        match problem {
            Some(problem) => Err(TransportError::ForeignBatch {
                actor: self.actor,
                task: self.task,
                problem,
            }),
            None => Ok(()),
        }
    }

    /// Seconds from this batch's send time to now, clamped at zero.
    pub fn age_seconds(&self) -> f64 {
        unix_ns().saturating_sub(self.sent_unix_ns) as f64 * 1e-9
    }
}

/// Nanoseconds since the Unix epoch.
pub fn unix_ns() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64)
}

/// One transition in shared memory: (s, a, r, s', truncated) with its episode and step. The
/// task, actor and sequence number are the batch's ([`BatchHeader`]).
///
/// Writers fill a slot in place with [`set_state`](Self::set_state) and
/// [`set_outcome`](Self::set_outcome) (or [`set_transition`](Self::set_transition)), which touch
/// only the header's `obs_len` entries of each array; readers use
/// [`to_transition`](Self::to_transition), which reads only those.
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("uavmeta.TransitionSlot.v3")]
#[repr(C)]
pub struct TransitionSlot {
    pub episode: u64,
    pub step: u32,
    pub reward: f32,
    pub action: u16,
    /// 1 when the step reached the horizon (a time limit, not a terminal state).
    pub truncated: u8,
    /// Explicit padding, never read.
    pub reserved: u8,
    /// s(t) in the first `obs_len` entries; the others are unspecified.
    pub obs: [u16; OBS_CAPACITY],
    /// s(t+1) in the first `obs_len` entries; the others are unspecified.
    pub next_obs: [u16; OBS_CAPACITY],
}

impl Default for TransitionSlot {
    fn default() -> Self {
        Self {
            episode: 0,
            step: 0,
            reward: 0.0,
            action: 0,
            truncated: 0,
            reserved: 0,
            obs: [0; OBS_CAPACITY],
            next_obs: [0; OBS_CAPACITY],
        }
    }
}

impl TransitionSlot {
    /// Copies what a writer wrote into `from`: every field and the first `obs_len` entries of
    /// each observation, about a quarter of the slot at K = 10.
    #[inline]
    pub fn copy_written(&mut self, from: &TransitionSlot, obs_len: usize) {
        self.episode = from.episode;
        self.step = from.step;
        self.reward = from.reward;
        self.action = from.action;
        self.truncated = from.truncated;
        self.obs[..obs_len].copy_from_slice(&from.obs[..obs_len]);
        self.next_obs[..obs_len].copy_from_slice(&from.next_obs[..obs_len]);
    }

    /// Writes the state half of a step: its episode, step index and s(t) (2 + K values,
    /// K <= `MAX_DEVICES`). Called before the step, since stepping overwrites the observation.
    #[inline]
    pub fn set_state(&mut self, episode: u64, step: u32, obs: &[u16]) {
        self.episode = episode;
        self.step = step;
        self.obs[..obs.len()].copy_from_slice(obs);
    }

    /// Writes the outcome half of a step: a, r, s(t+1) and whether the horizon was reached.
    #[inline]
    pub fn set_outcome(&mut self, action: u16, reward: f32, next_obs: &[u16], truncated: bool) {
        self.action = action;
        self.reward = reward;
        self.truncated = truncated as u8;
        self.next_obs[..next_obs.len()].copy_from_slice(next_obs);
    }

    /// Writes a dataset transition (its task, actor and seq go into the batch header).
    pub fn set_transition(&mut self, t: &Transition) {
        self.set_state(t.episode, t.step, &t.obs);
        self.set_outcome(t.action, t.reward, &t.next_obs, t.truncated);
    }

    /// Slot `index` of the batch under `header`, as a dataset transition. Reads only the
    /// header's `obs_len` entries of each array.
    pub fn to_transition(&self, header: &BatchHeader, index: usize) -> Transition {
        let len = header.obs_len as usize;
        Transition {
            task: header.task,
            actor: header.actor,
            episode: self.episode,
            step: self.step,
            seq: header.first_seq + index as u64,
            obs: self.obs[..len].to_vec(),
            action: self.action,
            reward: self.reward,
            next_obs: self.next_obs[..len].to_vec(),
            truncated: self.truncated != 0,
        }
    }
}

/// The store holds `transitions` transitions of `task`: its dataset file is complete and synced.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ZeroCopySend)]
#[type_name("uavmeta.DatasetReady.v3")]
#[repr(C)]
pub struct DatasetReady {
    pub schema_version: u32,
    pub task: u32,
    pub transitions: u64,
}

/// The store has appended, and flushed to the operating system, every transition of `actor` on
/// `task` numbered below `next_seq` (or dropped it as surplus, the dataset being complete). Sent
/// after every batch; a killed store loses none of it, since the file survives the process.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ZeroCopySend)]
#[type_name("uavmeta.StoreAck.v3")]
#[repr(C)]
pub struct StoreAck {
    pub schema_version: u32,
    pub task: u32,
    pub actor: u32,
    /// Explicit padding, so the layout has no uninitialised bytes.
    pub reserved: u32,
    pub next_seq: u64,
}

/// A checkpoint is on disk (written atomically) at [`RunDir::checkpoint`] of these fields.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ZeroCopySend)]
#[type_name("uavmeta.CheckpointReady.v3")]
#[repr(C)]
pub struct CheckpointReady {
    pub schema_version: u32,
    /// [`Method::code`].
    pub method: u32,
    /// The task it was trained for (meta-test) or is scored on; for [`Method::MetaInit`] the
    /// meta-test task whose zero-shot score it reports.
    pub task: u32,
    /// Epochs (meta-epochs for [`Method::MetaInit`]) behind it.
    pub epoch: u32,
}

/// Every process of the run finishes what it is doing and exits.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ZeroCopySend)]
#[type_name("uavmeta.Shutdown.v3")]
#[repr(C)]
pub struct Shutdown {
    pub schema_version: u32,
    pub reserved: u32,
}

/// The iceoryx2 service names of one run; the run id makes two runs on a host disjoint.
#[derive(Debug, Clone)]
pub struct ServiceNames {
    prefix: String,
}

impl ServiceNames {
    pub fn new(run: &RunDir) -> Self {
        Self {
            prefix: format!("uavmeta/{}", run.id()),
        }
    }

    pub fn transitions(&self, task: &str) -> String {
        format!("{}/transitions/{task}", self.prefix)
    }

    pub fn acks(&self, task: &str) -> String {
        format!("{}/acks/{task}", self.prefix)
    }

    pub fn dataset_ready(&self) -> String {
        format!("{}/control/dataset-ready", self.prefix)
    }

    pub fn checkpoint_ready(&self) -> String {
        format!("{}/control/checkpoint-ready", self.prefix)
    }

    pub fn shutdown(&self) -> String {
        format!("{}/control/shutdown", self.prefix)
    }

    /// The services a remote actor uses and which way each crosses a tunnel: the one
    /// declaration of what a remote host may send (its transitions) and what only the learner's
    /// host sends (acknowledgements, dataset announcements, the shutdown).
    pub fn tunnel_routes<'t>(
        &self,
        tasks: impl IntoIterator<Item = &'t TaskConfig>,
    ) -> Vec<(String, Crossing)> {
        let mut routes: Vec<(String, Crossing)> = tasks
            .into_iter()
            .flat_map(|t| {
                [
                    (self.transitions(&t.name), Crossing::ToLearner),
                    (self.acks(&t.name), Crossing::ToRemote),
                ]
            })
            .collect();
        routes.push((self.dataset_ready(), Crossing::ToRemote));
        routes.push((self.shutdown(), Crossing::ToRemote));
        routes
    }

    /// The copy of `service` that carries it to remote hosts, `uavmeta/<run>/to-remote/...`: no
    /// process of the learner's host reads it, so what a remote host publishes into it reaches
    /// none of them.
    pub fn to_remote(&self, service: &str) -> String {
        let rest = service
            .strip_prefix(&self.prefix)
            .unwrap_or(service)
            .trim_start_matches('/');
        format!("{}/to-remote/{rest}", self.prefix)
    }
}

/// Which way a service crosses a tunnel ([`ServiceNames::tunnel_routes`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Crossing {
    /// Remote hosts publish into it, under its own name, and the learner's host reads it.
    ToLearner,
    /// Only the learner's host publishes: its tunnel copies the service into
    /// [`ServiceNames::to_remote`], which crosses, and a remote host's tunnel copies that into its
    /// own service; nothing crosses back into the original.
    ToRemote,
}

/// A run's directory and the layout of everything in it.
#[derive(Debug, Clone)]
pub struct RunDir {
    root: PathBuf,
    id: String,
    hash: u64,
}

impl RunDir {
    /// Opens `path`, creating it and its subdirectories when missing. The run id is the
    /// directory's name plus a hash of its absolute path: readable in service names, and
    /// distinct for two runs whose directories share a name.
    pub fn create(path: &Path) -> Result<Self, TransportError> {
        std::fs::create_dir_all(path).map_err(|source| TransportError::Io {
            path: path.to_path_buf(),
            action: "create the run directory",
            source,
        })?;
        let run = Self::open(path)?;
        for sub in ["datasets", "checkpoints", "ports", "metrics", "logs"] {
            let dir = run.root.join(sub);
            std::fs::create_dir_all(&dir).map_err(|source| TransportError::Io {
                path: dir.clone(),
                action: "create",
                source,
            })?;
        }
        Ok(run)
    }

    /// The existing run directory `path`, with the id [`RunDir::create`] gives it; nothing is
    /// created.
    pub fn open(path: &Path) -> Result<Self, TransportError> {
        let root = path.canonicalize().map_err(|source| TransportError::Io {
            path: path.to_path_buf(),
            action: "resolve the run directory",
            source,
        })?;
        let hash = fnv1a(root.to_string_lossy().as_bytes());
        let name: String = root
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| "root".into())
            .chars()
            .map(|c| {
                if c.is_ascii_alphanumeric() || c == '-' || c == '_' {
                    c
                } else {
                    '_'
                }
            })
            .take(64)
            .collect();
        let local = Self {
            id: format!("{name}-{:08x}", hash as u32),
            root,
            hash,
        };
        local
            .remote_identity()
            .map(|remote| remote.unwrap_or(local))
    }

    /// Makes `path` the directory of run `id` (hash `hash`) of another host, on a remote actor
    /// host (`uavmeta tunnel join`): the processes started in it join that run, since id and
    /// hash, which come from the learner host's path, are read from [`REMOTE_RUN_FILE`].
    pub fn create_remote(path: &Path, id: &str, hash: u64) -> Result<Self, TransportError> {
        let local = Self::create(path)?;
        let file = local.root.join(REMOTE_RUN_FILE);
        write_atomic(&file, format!("{id}\n{hash:016x}\n").as_bytes())?;
        Self::create(path)
    }

    /// The id and hash of the remote run this directory stands for, if it does.
    fn remote_identity(&self) -> Result<Option<Self>, TransportError> {
        let file = self.root.join(REMOTE_RUN_FILE);
        let text = match std::fs::read_to_string(&file) {
            Ok(text) => text,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(source) => {
                return Err(TransportError::Io {
                    path: file,
                    action: "read",
                    source,
                })
            }
        };
        let mut lines = text.lines();
        let parsed = lines
            .next()
            .zip(lines.next().and_then(|h| u64::from_str_radix(h, 16).ok()));
        let Some((id, hash)) = parsed else {
            return Err(TransportError::Io {
                path: file,
                action: "parse (expected a run id and a hexadecimal hash)",
                source: std::io::ErrorKind::InvalidData.into(),
            });
        };
        Ok(Some(Self {
            root: self.root.clone(),
            id: id.to_string(),
            hash,
        }))
    }

    /// Where the learner host's tunnel keeps what remote hosts announced: one file per host.
    pub fn remote_hosts_dir(&self) -> PathBuf {
        self.root.join("remote-hosts")
    }

    pub fn root(&self) -> &Path {
        &self.root
    }

    /// The run's name in service names: `<dir name>-<hash>`.
    pub fn id(&self) -> &str {
        &self.id
    }

    /// A 64-bit fingerprint of the run's absolute path, carried by every batch.
    pub fn hash(&self) -> u64 {
        self.hash
    }

    /// The config every process of the run uses, written by the first process to start.
    pub fn config_file(&self) -> PathBuf {
        self.root.join("config.toml")
    }

    /// Task `task`'s dataset file, appended by the store.
    pub fn dataset(&self, task: &TaskConfig) -> PathBuf {
        self.root
            .join("datasets")
            .join(format!("{}.{}", task.name, crate::dataset::FILE_EXTENSION))
    }

    /// The checkpoint (in `uavmeta_learner::checkpoint`'s naming) of `method` on `task` after
    /// `epoch` epochs; [`Method::MetaInit`] checkpoints belong to no task and ignore it.
    pub fn checkpoint(&self, method: Method, task: &TaskConfig, epoch: u32) -> PathBuf {
        let dir = self.root.join("checkpoints").join(method.name());
        let dir = if method == Method::MetaInit {
            dir
        } else {
            dir.join(&task.name)
        };
        dir.join(format!("epoch-{epoch:05}"))
    }

    /// Where process `process` writes the port of its /metrics endpoint.
    pub fn port_file(&self, process: &str) -> PathBuf {
        self.ports_dir().join(format!("{process}.port"))
    }

    /// Every process's port file ([`RunDir::port_file`]).
    pub fn ports_dir(&self) -> PathBuf {
        self.root.join("ports")
    }

    /// Where process `process` writes its last metrics when it exits.
    pub fn metrics_snapshot(&self, process: &str) -> PathBuf {
        self.root.join("metrics").join(format!("{process}.prom"))
    }

    /// The log file of a child process started by the launcher.
    pub fn log_file(&self, process: &str) -> PathBuf {
        self.root.join("logs").join(format!("{process}.log"))
    }

    /// The file whose modification time a launched process moves while it makes progress
    /// ([`heartbeat`]).
    pub fn heartbeat_file(&self, process: &str) -> PathBuf {
        self.root.join("heartbeats").join(process)
    }

    /// The evaluator's rows, one per evaluated checkpoint.
    pub fn evaluations_csv(&self) -> PathBuf {
        self.root.join("evaluations.csv")
    }

    /// A Prometheus config that scrapes this run.
    pub fn prometheus_yml(&self) -> PathBuf {
        self.root.join("prometheus.yml")
    }

    /// The scrape targets (Prometheus file service discovery), rewritten as processes start.
    pub fn prometheus_targets(&self) -> PathBuf {
        self.root.join("prometheus-targets.json")
    }

    /// The Grafana dashboard of the run's metrics (a copy of `docs/grafana/uavmeta.json`), to
    /// import beside a Prometheus that reads [`RunDir::prometheus_yml`].
    pub fn grafana_dashboard(&self) -> PathBuf {
        self.root.join("grafana-dashboard.json")
    }

    /// Reads the run's config, or, on the run's first start, writes `fallback` as the run's config
    /// (atomically, so two processes starting together agree) and returns it.
    pub fn load_or_init_config(
        &self,
        fallback: impl FnOnce() -> Result<Config, crate::config::ConfigError>,
    ) -> Result<Config, RunConfigError> {
        let path = self.config_file();
        if path.exists() {
            return Ok(Config::load(&path, &[])?);
        }
        let config = fallback()?;
        write_atomic(&path, config.to_toml_string().as_bytes())?;
        Ok(Config::load(&path, &[])?)
    }
}

/// Reading or writing a run's config.
#[derive(Debug, thiserror::Error)]
pub enum RunConfigError {
    #[error(transparent)]
    Config(#[from] crate::config::ConfigError),
    #[error(transparent)]
    Transport(#[from] TransportError),
}

/// Writes `bytes` to `path` through a temporary file in the same directory, fsynced and renamed,
/// so readers see the old content or the new, never a torn file. A failure (a full disk) removes
/// the temporary file.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), TransportError> {
    use std::io::Write;
    let io = |path: &Path, action, source| TransportError::Io {
        path: path.to_path_buf(),
        action,
        source,
    };
    let tmp = path.with_extension(format!("tmp.{}", std::process::id()));
    let mut file = std::fs::File::create(&tmp).map_err(|e| io(&tmp, "create", e))?;
    let written = file
        .write_all(bytes)
        .map_err(|e| io(&tmp, "write", e))
        .and_then(|()| file.sync_all().map_err(|e| io(&tmp, "sync", e)))
        .and_then(|()| std::fs::rename(&tmp, path).map_err(|e| io(path, "rename into place", e)));
    if written.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    written
}

fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, b| {
        (h ^ *b as u64).wrapping_mul(0x100_0000_01b3)
    })
}

/// What a remote actor host announces to the learner's host (as JSON), which keeps the latest in
/// [`RunDir::remote_hosts_dir`] for the launcher's Prometheus targets and progress.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RemoteHost {
    /// The host's name: the `host` label of its processes' metrics.
    pub host: String,
    pub processes: Vec<RemoteProcess>,
}

/// One process of a remote actor host.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RemoteProcess {
    pub name: String,
    /// Where its /metrics answers, `address:port`.
    pub metrics: String,
}

/// The file in a remote actor host's run directory that names the learner host's run.
pub const REMOTE_RUN_FILE: &str = "remote-run";

/// The iceoryx2 config of `run.domain`: iceoryx2's defaults, with the domain's own prefix and
/// root path, so that nodes, services and shared memory of two domains never meet. This is how
/// iceoryx2's own examples and tests isolate systems on one machine.
pub fn iceoryx_config(run: &RunConfig) -> Result<iceoryx2::config::Config, TransportError> {
    let mut config = iceoryx2::config::Config::global_config().clone();
    if run.domain.is_empty() {
        return Ok(config);
    }
    let invalid = |message: String| TransportError::ServiceName {
        name: run.domain.clone(),
        message,
    };
    let prefix = format!("iox2_{}_", run.domain);
    config.global.prefix = iceoryx2::prelude::FileName::new(prefix.as_bytes())
        .map_err(|e| invalid(format!("run.domain as an iceoryx2 prefix: {e:?}")))?;
    let root = format!("/tmp/iceoryx2/{}/", run.domain);
    let root = iceoryx2::prelude::Path::new(root.as_bytes())
        .map_err(|e| invalid(format!("run.domain as an iceoryx2 root path: {e:?}")))?;
    config.global.set_root_path(&root);
    Ok(config)
}

/// Removes what iceoryx2 keeps of `run.domain` after its last process has gone: the domain's
/// global management segment in /dev/shm and its root directory. For a domain made for one test
/// or benchmark, once none of its processes runs; the default domain (empty) is left alone.
pub fn remove_domain(run: &RunConfig) -> Result<(), TransportError> {
    if run.domain.is_empty() {
        return Ok(());
    }
    let config = iceoryx_config(run)?;
    let gone = |path: PathBuf, removed: std::io::Result<()>| match removed {
        Err(source) if source.kind() != std::io::ErrorKind::NotFound => Err(TransportError::Io {
            path,
            action: "remove",
            source,
        }),
        _ => Ok(()),
    };
    let root = PathBuf::from(config.global.root_path().to_string());
    gone(root.clone(), std::fs::remove_dir_all(&root))?;
    let prefix = config.global.prefix.to_string();
    for entry in std::fs::read_dir("/dev/shm")
        .into_iter()
        .flatten()
        .flatten()
    {
        if entry.file_name().to_string_lossy().starts_with(&prefix) {
            gone(entry.path(), std::fs::remove_file(entry.path()))?;
        }
    }
    Ok(())
}

/// The iceoryx2 node of a process in `run.domain`, named after the process so `iox2 node list`
/// shows who is who.
pub fn node(process: &str, run: &RunConfig) -> Result<Node<ipc::Service>, TransportError> {
    // iceoryx2 warns on every start that it runs on its built-in defaults, which uavmeta means
    // to; its own errors still show (IOX2_LOG_LEVEL overrides).
    set_log_level_from_env_or(LogLevel::Error);
    let service_error = |message: String| TransportError::Service {
        service: process.into(),
        action: "create the node",
        message,
    };
    let name = NodeName::new(process).map_err(|e| service_error(format!("{e:?}")))?;
    let config = iceoryx_config(run)?;
    // Creating a node sweeps dead nodes' resources.
    remove_unfinished_segments(&config);
    let node = NodeBuilder::new()
        .name(&name)
        .config(&config)
        .create::<ipc::Service>()
        .map_err(|e| service_error(e.to_string()))?;
    // The first wait registers iceoryx2's SIGINT/SIGTERM handler, so a termination request that
    // arrives while a publisher is blocked on backpressure is seen by `termination_requested`.
    let _ = node.wait(Duration::ZERO);
    Ok(node)
}

/// Removes the resources of dead processes from every service (their ports would otherwise block
/// the living on full buffers); the number of dead nodes cleaned up.
pub fn cleanup_dead_nodes(node: &Node<ipc::Service>) -> u64 {
    remove_unfinished_segments(node.config());
    node.try_cleanup_dead_nodes().cleanups
}

/// A segment at size zero older than this is no creation in progress (that takes microseconds).
const UNFINISHED_SEGMENT_AGE: Duration = Duration::from_secs(10);

/// Longest that [`remove_unfinished_segments`] waits in all, however many segments it meets: a
/// segment that keeps being truncated to size zero (by another user: iceoryx2's files are
/// world-writable) would otherwise stay young, and waited for, for ever.
const UNFINISHED_SEGMENTS_BOUND: Duration = Duration::from_secs(12);

/// Removes iceoryx2 shared-memory segments that a process killed between creating and sizing them
/// left at size zero. iceoryx2 0.10's dead-node sweep waits, without a timeout, for such a segment
/// to be initialised (`posix_shared_memory::open_impl` on `MappingSizeIsZero`), so one such
/// leftover would hang every later sweep in the domain. Found by the chaos test. A zero-size
/// segment younger than [`UNFINISHED_SEGMENT_AGE`] may be a creation in progress, or the leftover
/// of a process killed a moment ago and restarted at once (a tunnel restarted after kill -9 hung
/// here in tests/remote.rs), so it is waited for: sized, gone, or old enough to remove; all of it
/// within [`UNFINISHED_SEGMENTS_BOUND`], after which what is left is given up on with a warning.
fn remove_unfinished_segments(config: &iceoryx2::config::Config) {
    remove_unfinished_service_files(config);
    let prefix = config.global.prefix.to_string();
    let Ok(entries) = std::fs::read_dir("/dev/shm") else {
        return;
    };
    let zero_sized = entries
        .flatten()
        .filter(|e| e.file_name().to_string_lossy().starts_with(&prefix))
        .filter(|e| e.metadata().is_ok_and(|m| m.len() == 0))
        .map(|e| e.path());
    let start = std::time::Instant::now();
    for path in zero_sized.collect::<Vec<_>>() {
        while let Ok(metadata) = std::fs::metadata(&path) {
            if metadata.len() > 0 {
                break;
            }
            let age = metadata.modified().ok().and_then(|at| at.elapsed().ok());
            if age.is_some_and(|age| age > UNFINISHED_SEGMENT_AGE) {
                if std::fs::remove_file(&path).is_ok() {
                    tracing::warn!(path = %path.display(), "removed an iceoryx2 segment a killed process left unfinished");
                }
                break;
            }
            if start.elapsed() > UNFINISHED_SEGMENTS_BOUND {
                tracing::warn!(path = %path.display(), waited = ?start.elapsed(), "gave up on an iceoryx2 segment that stays at size zero (truncated again and again?)");
                return;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }
}

/// The permission iceoryx2's file-based static storage (a service's static config) keeps while
/// its creator writes it; the creator makes it read-only once complete.
const UNFINISHED_SERVICE_FILE_MODE: u32 = 0o600;

/// Removes a service's static config file that a process killed while creating the service left
/// unfinished (still at [`UNFINISHED_SERVICE_FILE_MODE`]) and older than
/// [`UNFINISHED_SEGMENT_AGE`]: iceoryx2 0.10 takes such a file for a creation in progress for
/// ever, so every later open or create of that service fails with `HangsInCreation`, and a store
/// killed at that moment could never be restarted (found by the chaos test: the launcher
/// restarted it every 11 s until it gave up). A younger one may be a creation in progress and is
/// left for a later sweep.
fn remove_unfinished_service_files(config: &iceoryx2::config::Config) {
    use std::os::unix::fs::PermissionsExt;
    let prefix = config.global.prefix.to_string();
    let dir = PathBuf::from(config.global.service_dir().to_string());
    let Ok(entries) = std::fs::read_dir(&dir) else {
        return;
    };
    for entry in entries.flatten() {
        let Ok(metadata) = entry.metadata() else {
            continue;
        };
        let unfinished = metadata.is_file()
            && entry.file_name().to_string_lossy().starts_with(&prefix)
            && metadata.permissions().mode() & 0o777 == UNFINISHED_SERVICE_FILE_MODE;
        let age = metadata.modified().ok().and_then(|at| at.elapsed().ok());
        if unfinished
            && age.is_some_and(|age| age > UNFINISHED_SEGMENT_AGE)
            && std::fs::remove_file(entry.path()).is_ok()
        {
            tracing::warn!(path = %entry.path().display(), "removed an iceoryx2 service file a killed process left unfinished");
        }
    }
}

/// Sweeps for dead processes' iceoryx2 resources on a thread of its own, with a node of its own,
/// so that a sweep that waits (on a segment left unfinished, or one another user truncates) never
/// stops the loop that asked for it. [`Cleaner::request`] returns a ticket at once;
/// [`Cleaner::finished`] tells when a sweep that started after it has ended.
pub struct Cleaner {
    shared: Arc<CleanerState>,
}

#[derive(Default)]
struct CleanerState {
    /// Sweeps requested so far, and whether the owner has gone.
    requested: std::sync::Mutex<(u64, bool)>,
    wake: std::sync::Condvar,
    /// Requests served: every ticket up to this one has had a whole sweep after it.
    done: AtomicU64,
}

impl Cleaner {
    /// Starts the thread; its node is `<process>-cleaner` in `run.domain`.
    pub fn start(process: &str, run: &RunConfig) -> Self {
        let shared = Arc::new(CleanerState::default());
        let state = Arc::clone(&shared);
        let (name, run) = (format!("{process}-cleaner"), run.clone());
        let spawned = std::thread::Builder::new()
            .name("iceoryx2-cleaner".into())
            .spawn(move || state.serve(&name, &run));
        if let Err(error) = spawned {
            tracing::warn!(%error, "cannot start the iceoryx2 cleaner thread; dead processes' resources stay");
        }
        Self { shared }
    }

    /// Asks for a sweep; returns its ticket.
    pub fn request(&self) -> u64 {
        let mut requested = self.shared.lock();
        requested.0 += 1;
        self.shared.wake.notify_one();
        requested.0
    }

    /// Whether a sweep has ended since `ticket` was requested.
    pub fn finished(&self, ticket: u64) -> bool {
        self.shared.done.load(Ordering::Acquire) >= ticket
    }

    /// Asks for a sweep and waits for it, at most `bound`; whether it ended in time.
    pub fn sweep_within(&self, bound: Duration) -> bool {
        let ticket = self.request();
        let start = std::time::Instant::now();
        while !self.finished(ticket) {
            if start.elapsed() > bound {
                tracing::warn!(
                    ?bound,
                    "the iceoryx2 clean-up did not finish in time; going on without it"
                );
                return false;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        true
    }
}

impl Drop for Cleaner {
    fn drop(&mut self) {
        self.shared.lock().1 = true;
        self.shared.wake.notify_one();
    }
}

impl CleanerState {
    fn lock(&self) -> std::sync::MutexGuard<'_, (u64, bool)> {
        self.requested.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The thread: one sweep per wake-up that found new requests, until the owner goes.
    fn serve(&self, name: &str, run: &RunConfig) {
        let node = match node(name, run) {
            Ok(node) => node,
            Err(error) => {
                tracing::warn!(%error, "the iceoryx2 cleaner has no node; dead processes' resources stay");
                return;
            }
        };
        loop {
            let ticket = {
                let mut requested = self.lock();
                while requested.0 == self.done.load(Ordering::Acquire) && !requested.1 {
                    requested = self.wake.wait(requested).unwrap_or_else(|e| e.into_inner());
                }
                if requested.1 {
                    return;
                }
                requested.0
            };
            let cleaned = cleanup_dead_nodes(&node);
            if cleaned > 0 {
                tracing::info!(cleaned, "removed iceoryx2 resources of dead processes");
            }
            self.done.store(ticket, Ordering::Release);
        }
    }
}

/// Set once a termination request was seen: iceoryx2's signal state forgets a signal once read.
static TERMINATING: AtomicBool = AtomicBool::new(false);

/// True once SIGINT or SIGTERM arrived (iceoryx2's handler records it), for good.
pub fn termination_requested() -> bool {
    if TERMINATING.load(Ordering::Relaxed) {
        return true;
    }
    let requested = SignalHandler::termination_requested();
    if requested {
        TERMINATING.store(true, Ordering::Relaxed);
    }
    requested
}

/// Sleeps `cycle` on `node`; false once the process should stop. `Node::wait` also fails when any
/// other signal iceoryx2 catches (SIGCONT after a stop, SIGURG, ...) interrupts its sleep, which is
/// no reason to end a process, so only a termination request counts.
pub fn keep_running(node: &Node<ipc::Service>, cycle: Duration) -> bool {
    heartbeat();
    match node.wait(cycle) {
        Err(NodeWaitFailure::TerminationRequest) => {
            TERMINATING.store(true, Ordering::Relaxed);
            false
        }
        _ => !termination_requested(),
    }
}

/// The variable through which the launcher tells a child which file to beat on.
pub const HEARTBEAT_FILE_ENV: &str = "UAVMETA_HEARTBEAT_FILE";

/// At most this often a beat touches the file; the launcher's `run.hang_timeout_seconds` is many
/// times longer.
const HEARTBEAT_EVERY: Duration = Duration::from_millis(500);

/// Tells the launcher that this process's loop is making progress, by moving the modification
/// time of the file named in [`HEARTBEAT_FILE_ENV`]. A stopped, deadlocked or livelocked process
/// stops moving it, and the launcher kills and restarts it. Every loop that polls its node beats
/// through [`keep_running`]; long computations call this between their steps. A process started by
/// hand has no such file, and beats go nowhere.
pub fn heartbeat() {
    struct Beat {
        file: std::fs::File,
        last: std::sync::Mutex<Option<std::time::Instant>>,
    }
    static BEAT: std::sync::OnceLock<Option<Beat>> = std::sync::OnceLock::new();
    let beat = BEAT.get_or_init(|| {
        let path = std::env::var_os(HEARTBEAT_FILE_ENV)?;
        match std::fs::OpenOptions::new().write(true).create(true).truncate(false).open(&path) {
            Ok(file) => Some(Beat {
                file,
                last: std::sync::Mutex::new(None),
            }),
            Err(e) => {
                tracing::warn!(path = %Path::new(&path).display(), error = %e, "cannot open the heartbeat file; the launcher will take this process for hung");
                None
            }
        }
    });
    let Some(beat) = beat else { return };
    let mut last = beat.last.lock().unwrap_or_else(|e| e.into_inner());
    if last.is_none_or(|at| at.elapsed() >= HEARTBEAT_EVERY) {
        // A failed touch looks like a missed beat; the next one tries again.
        let _ = beat.file.set_modified(SystemTime::now());
        *last = Some(std::time::Instant::now());
    }
}

fn service_name(name: &str) -> Result<ServiceName, TransportError> {
    ServiceName::new(name).map_err(|e| TransportError::ServiceName {
        name: name.into(),
        message: format!("{e:?}"),
    })
}

fn schema_verifier(service: &str) -> Result<AttributeVerifier, TransportError> {
    let key = SCHEMA_ATTRIBUTE
        .try_into()
        .map_err(|e| TransportError::ServiceName {
            name: service.into(),
            message: format!("{e:?}"),
        })?;
    let value = SCHEMA_VERSION.to_string();
    let value = value
        .as_str()
        .try_into()
        .map_err(|e| TransportError::ServiceName {
            name: service.into(),
            message: format!("{e:?}"),
        })?;
    AttributeVerifier::new()
        .require(&key, &value)
        .map_err(|e| TransportError::Service {
            service: service.into(),
            action: "require the schema attribute",
            message: format!("{e:?}"),
        })
}

/// Turns an open-or-create failure into an error, reading the existing service's schema version
/// when the attributes were the problem.
fn open_error(
    config: &iceoryx2::config::Config,
    name: &ServiceName,
    service: &str,
    error: impl fmt::Debug + fmt::Display,
) -> TransportError {
    if format!("{error:?}").contains("IncompatibleAttributes") {
        let theirs = <ipc::Service as iceoryx2::service::Service>::details(
            name,
            config,
            MessagingPattern::PublishSubscribe,
        )
        .ok()
        .flatten()
        .and_then(|details| {
            let key = SCHEMA_ATTRIBUTE.try_into().ok()?;
            details
                .static_details
                .attributes()
                .key_value(&key, 0)
                .map(|v| v.to_string())
        })
        .unwrap_or_else(|| "<none>".into());
        return TransportError::SchemaMismatch {
            service: service.into(),
            theirs,
        };
    }
    TransportError::Service {
        service: service.into(),
        action: "open or create",
        message: error.to_string(),
    }
}

/// Samples a subscriber may hold borrowed at once: iceoryx2 0.10's default, which the transition
/// service keeps.
const SUBSCRIBER_BORROWED: usize = 2;

/// Bytes of shared memory one actor's transition publisher maps: iceoryx2 sizes its data
/// segment for every sample that can be in flight (each subscriber's buffer and borrowed
/// samples, plus the one the actor loans), each a batch of `run.batch_size` slots. The launcher
/// checks the run's total against /dev/shm before it starts anything.
pub fn actor_shared_memory(run: &RunConfig) -> u64 {
    let samples = TRANSITION_SUBSCRIBERS * (run.subscriber_buffer + SUBSCRIBER_BORROWED) + 1;
    let batch =
        std::mem::size_of::<TransitionSlot>() * run.batch_size + std::mem::size_of::<BatchHeader>();
    samples as u64 * batch as u64
}

/// A task's transition service.
pub type TransitionService = PubSubFactory<ipc::Service, [TransitionSlot], BatchHeader>;
/// A control service carrying `T`.
pub type ControlService<T> = PubSubFactory<ipc::Service, T, ()>;

/// Opens (or creates) the transition service of `task`, with capacities from `[run]`.
pub fn transition_service(
    node: &Node<ipc::Service>,
    names: &ServiceNames,
    task: &str,
    run: &RunConfig,
) -> Result<TransitionService, TransportError> {
    let service = names.transitions(task);
    let name = service_name(&service)?;
    node.service_builder(&name)
        .publish_subscribe::<[TransitionSlot]>()
        .user_header::<BatchHeader>()
        // A full store buffer must make actors wait, never overwrite an unread batch.
        .enable_safe_overflow(false)
        .subscriber_max_buffer_size(run.subscriber_buffer)
        .max_publishers(run.max_publishers)
        .max_subscribers(TRANSITION_SUBSCRIBERS)
        .max_nodes(run.max_publishers + TRANSITION_SUBSCRIBERS)
        .open_or_create_with_attributes(&schema_verifier(&service)?)
        .map_err(|e| open_error(node.config(), &name, &service, e))
}

/// Opens (or creates) the control service `service`, whose history lets late joiners catch up.
pub fn control_service<T: fmt::Debug + ZeroCopySend + 'static>(
    node: &Node<ipc::Service>,
    service: String,
    config: &Config,
) -> Result<ControlService<T>, TransportError> {
    let name = service_name(&service)?;
    let peers = config.tasks.len() * config.collect.actors_per_task
        + config.run.max_publishers
        + CONTROL_PEERS;
    node.service_builder(&name)
        .publish_subscribe::<T>()
        // Announcements must reach everyone; a stuck subscriber is skipped after a timeout.
        .enable_safe_overflow(false)
        .subscriber_max_buffer_size(config.run.control_buffer)
        .history_size(config.run.control_buffer)
        .max_publishers(CONTROL_PEERS)
        .max_subscribers(peers)
        .max_nodes(peers + CONTROL_PEERS)
        .open_or_create_with_attributes(&schema_verifier(&service)?)
        .map_err(|e| open_error(node.config(), &name, &service, e))
}

pub fn dataset_ready_service(
    node: &Node<ipc::Service>,
    names: &ServiceNames,
    config: &Config,
) -> Result<ControlService<DatasetReady>, TransportError> {
    control_service(node, names.dataset_ready(), config)
}

pub fn checkpoint_ready_service(
    node: &Node<ipc::Service>,
    names: &ServiceNames,
    config: &Config,
) -> Result<ControlService<CheckpointReady>, TransportError> {
    control_service(node, names.checkpoint_ready(), config)
}

pub fn shutdown_service(
    node: &Node<ipc::Service>,
    names: &ServiceNames,
    config: &Config,
) -> Result<ControlService<Shutdown>, TransportError> {
    control_service(node, names.shutdown(), config)
}

/// Maps a failed receive to a [`TransportError`] that says what was being received.
pub fn receive_failed(
    action: &'static str,
) -> impl Fn(iceoryx2::port::ReceiveError) -> TransportError {
    move |e| TransportError::Receive {
        action,
        message: e.to_string(),
    }
}

/// Drains the shutdown service: true if this build's run was told to stop. A shutdown from a
/// build of another schema version is not addressed to this run's processes.
pub fn shutdown_requested(
    shutdown: &iceoryx2::port::subscriber::Subscriber<ipc::Service, Shutdown, ()>,
) -> Result<bool, TransportError> {
    let mut requested = false;
    while let Some(message) = shutdown
        .receive()
        .map_err(receive_failed("receive a shutdown"))?
    {
        requested |= message.schema_version == SCHEMA_VERSION;
    }
    Ok(requested)
}

/// A subscriber that also receives the service's history.
pub fn control_subscriber<T: fmt::Debug + ZeroCopySend>(
    service: &ControlService<T>,
    config: &Config,
) -> Result<Subscriber<ipc::Service, T, ()>, TransportError> {
    service
        .subscriber_builder()
        .history_request(config.run.control_buffer)
        .create()
        .map_err(|e| TransportError::Service {
            service: format!("{:?}", service.name()),
            action: "create a subscriber",
            message: e.to_string(),
        })
}

/// A control publisher that skips a subscriber stuck for [`CONTROL_DELIVERY_TIMEOUT`].
pub fn control_publisher<T: fmt::Debug + ZeroCopySend>(
    service: &ControlService<T>,
) -> Result<Publisher<ipc::Service, T, ()>, TransportError> {
    service
        .publisher_builder()
        .backpressure_strategy(BackpressureStrategy::RetryUntilDelivered)
        .set_backpressure_handler(|info: &BackpressureInfo| {
            if info.elapsed_time >= CONTROL_DELIVERY_TIMEOUT || termination_requested() {
                BackpressureAction::DiscardData
            } else {
                BackpressureAction::Retry
            }
        })
        .create()
        .map_err(|e| TransportError::Service {
            service: format!("{:?}", service.name()),
            action: "create a publisher",
            message: e.to_string(),
        })
}

/// Connects subscribers that joined since the last send and hands them the service's history.
/// iceoryx2 does this only inside `send`, so a process whose announcements are all made must
/// call this in its loop, or a process joining later never hears them.
pub fn serve_history<T: fmt::Debug + ZeroCopySend>(
    publisher: &Publisher<ipc::Service, T, ()>,
) -> Result<(), TransportError> {
    use iceoryx2::port::update_connections::UpdateConnections;
    publisher
        .update_connections()
        .map_err(|e| TransportError::Service {
            service: "control".into(),
            action: "connect new subscribers",
            message: e.to_string(),
        })
}

/// Sends one control message by copy (they are a few bytes).
pub fn announce<T: fmt::Debug + ZeroCopySend>(
    publisher: &Publisher<ipc::Service, T, ()>,
    message: T,
) -> Result<usize, TransportError> {
    publisher
        .send_copy(message)
        .map_err(|e| TransportError::Service {
            service: "control".into(),
            action: "send",
            message: e.to_string(),
        })
}

/// The store's subscriber on a task's transition service.
pub fn transition_subscriber(
    service: &TransitionService,
    run: &RunConfig,
) -> Result<Subscriber<ipc::Service, [TransitionSlot], BatchHeader>, TransportError> {
    service
        .subscriber_builder()
        .buffer_size(run.subscriber_buffer)
        .create()
        .map_err(|e| TransportError::Service {
            service: format!("{:?}", service.name()),
            action: "create a subscriber",
            message: e.to_string(),
        })
}

/// A task's acknowledgement service ([`StoreAck`]).
pub type AckService = PubSubFactory<ipc::Service, StoreAck, ()>;

/// Opens (or creates) the acknowledgement service of `task`: the store publishes, the task's
/// actors subscribe.
pub fn ack_service(
    node: &Node<ipc::Service>,
    names: &ServiceNames,
    task: &str,
    run: &RunConfig,
) -> Result<AckService, TransportError> {
    ack_service_at(node, names.acks(task), run)
}

/// Opens (or creates) an acknowledgement service named `service` (a task's, or its tunnel copy).
pub fn ack_service_at(
    node: &Node<ipc::Service>,
    service: String,
    run: &RunConfig,
) -> Result<AckService, TransportError> {
    let name = service_name(&service)?;
    node.service_builder(&name)
        .publish_subscribe::<StoreAck>()
        // Cumulative: a newer acknowledgement makes an overwritten one worthless, and the store
        // must never wait on an actor.
        .enable_safe_overflow(true)
        .subscriber_max_buffer_size(ACK_BUFFER)
        .max_publishers(TRANSITION_SUBSCRIBERS)
        .max_subscribers(run.max_publishers)
        .max_nodes(run.max_publishers + TRANSITION_SUBSCRIBERS)
        .open_or_create_with_attributes(&schema_verifier(&service)?)
        .map_err(|e| open_error(node.config(), &name, &service, e))
}

/// The store's publisher of one task's acknowledgements.
pub fn ack_publisher(
    service: &AckService,
) -> Result<Publisher<ipc::Service, StoreAck, ()>, TransportError> {
    service
        .publisher_builder()
        .create()
        .map_err(|e| TransportError::Service {
            service: format!("{:?}", service.name()),
            action: "create a publisher",
            message: e.to_string(),
        })
}

/// An actor's subscriber to its task's acknowledgements.
pub fn ack_subscriber(
    service: &AckService,
) -> Result<Subscriber<ipc::Service, StoreAck, ()>, TransportError> {
    service
        .subscriber_builder()
        .buffer_size(ACK_BUFFER)
        .create()
        .map_err(|e| TransportError::Service {
            service: format!("{:?}", service.name()),
            action: "create a subscriber",
            message: e.to_string(),
        })
}

/// Publishes one acknowledgement; never blocks (the service overwrites the oldest).
pub fn acknowledge(
    publisher: &Publisher<ipc::Service, StoreAck, ()>,
    ack: StoreAck,
) -> Result<(), TransportError> {
    publisher
        .send_copy(ack)
        .map(drop)
        .map_err(|e| TransportError::Service {
            service: "acks".into(),
            action: "send an acknowledgement",
            message: e.to_string(),
        })
}

/// The highest acknowledged `next_seq` of `actor` among the acknowledgements waiting, if any.
pub fn latest_ack(
    acks: &Subscriber<ipc::Service, StoreAck, ()>,
    task: u32,
    actor: u32,
) -> Result<Option<u64>, TransportError> {
    let mut latest = None;
    while let Some(ack) = acks
        .receive()
        .map_err(receive_failed("receive an acknowledgement"))?
    {
        if ack.schema_version == SCHEMA_VERSION && ack.task == task && ack.actor == actor {
            latest = latest.max(Some(ack.next_seq));
        }
    }
    Ok(latest)
}

/// The identities of the subscribers attached to a service, folded into one value that changes
/// whenever one joins or leaves.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SubscriberSet {
    count: usize,
    /// XOR of the identities' hashes, so the order iceoryx2 lists them in does not matter.
    fingerprint: u64,
}

impl SubscriberSet {
    fn add(&mut self, id: &impl std::hash::Hash) {
        use std::hash::{BuildHasher, BuildHasherDefault, DefaultHasher};
        self.count += 1;
        self.fingerprint ^= BuildHasherDefault::<DefaultHasher>::default().hash_one(id);
    }

    /// True when no subscriber is attached.
    pub fn is_empty(&self) -> bool {
        self.count == 0
    }
}

/// What one publish cost and reached.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Delivery {
    /// Subscribers the batch reached. 0 means the batch is lost and must be sent again: the store
    /// went away during the send, or iceoryx2 0.10 dropped it (see the module doc).
    pub recipients: usize,
    /// Time spent blocked on a full subscriber buffer.
    pub backpressure: Duration,
}

/// An actor's publisher: blocking backpressure, and the blocked time measured.
pub struct TransitionPublisher<'s> {
    service: &'s TransitionService,
    publisher: Publisher<ipc::Service, [TransitionSlot], BatchHeader>,
    /// Longest `elapsed_time` the backpressure handler saw during the current send, in ns.
    blocked_ns: Arc<AtomicU64>,
    header: BatchHeader,
    batch_size: usize,
    subscriber_buffer: usize,
}

impl<'s> TransitionPublisher<'s> {
    /// A publisher on `service` for `actor`'s batches of `run.batch_size` transitions of task
    /// `task` (its index) in a world with `obs_len` observation entries.
    pub fn new(
        service: &'s TransitionService,
        run_dir: &RunDir,
        config: &Config,
        task: u32,
        actor: u32,
    ) -> Result<Self, TransportError> {
        let blocked_ns = Arc::new(AtomicU64::new(0));
        let handler_blocked = Arc::clone(&blocked_ns);
        let publisher = service
            .publisher_builder()
            .initial_max_slice_len(config.run.batch_size)
            .max_loaned_samples(1)
            // Backpressure: wait for the store instead of dropping or overwriting.
            .backpressure_strategy(BackpressureStrategy::RetryUntilDelivered)
            .set_backpressure_handler(move |info: &BackpressureInfo| {
                handler_blocked.fetch_max(info.elapsed_time.as_nanos() as u64, Ordering::Relaxed);
                // SIGINT/SIGTERM must end an actor even while the store is gone or stuck.
                if termination_requested() {
                    BackpressureAction::DiscardDataAndFail
                } else {
                    BackpressureAction::Retry
                }
            })
            .create()
            .map_err(|e| TransportError::Service {
                service: format!("{:?}", service.name()),
                action: "create a publisher",
                message: e.to_string(),
            })?;
        let header = BatchHeader {
            task,
            run: run_dir.hash(),
            world: config.world_hash(),
            actor,
            obs_len: config.world.observation_len() as u32,
            ..BatchHeader::default()
        };
        Ok(Self {
            service,
            publisher,
            blocked_ns,
            header,
            batch_size: config.run.batch_size,
            subscriber_buffer: config.run.subscriber_buffer,
        })
    }

    pub fn batch_size(&self) -> usize {
        self.batch_size
    }

    /// Entries of each observation array a slot uses (2 + K).
    pub fn obs_len(&self) -> usize {
        self.header.obs_len as usize
    }

    /// Which subscribers are attached to the service, a dead store's included until it is cleaned
    /// up: while the set is empty a batch sent now reaches nobody. Compared by identity, not
    /// count: a restarted store that replaced a dead one is new.
    pub fn subscribers(&self) -> SubscriberSet {
        let mut set = SubscriberSet::default();
        self.service.dynamic_config().list_subscribers(|details| {
            set.add(&details.subscriber_id);
            CallbackProgression::Continue
        });
        set
    }

    /// Batches a subscriber's queue holds ([`RunConfig::subscriber_buffer`]): once more than this
    /// many sent batches have reached one subscriber, it has taken some, so it is connected and
    /// no later batch can be dropped as sent to an unconnected subscriber (see the module doc).
    pub fn subscriber_buffer(&self) -> usize {
        self.subscriber_buffer
    }

    /// Loans `count` slots of shared memory for sequence numbers `first_seq..first_seq + count`,
    /// to be written in place and sent with [`LoanedBatch::send`]. Dropping the batch unsent
    /// returns the memory and sends nothing.
    pub fn loan(
        &self,
        first_seq: u64,
        count: usize,
    ) -> Result<LoanedBatch<'_, 's>, TransportError> {
        let sample = self
            .publisher
            .loan_slice_uninit(count)
            .map_err(|e| self.error("loan a batch", e.to_string()))?;
        // SAFETY: every byte of the loaned memory is initialised: iceoryx2 zero-fills a data
        // segment when it creates it, and its chunks only ever hold earlier batches' slots.
        // TransitionSlot is plain integers and a float, for which every bit pattern is valid, so
        // the stale slots are valid values; writers overwrite what receivers read.
        let mut sample = unsafe { sample.assume_init() };
        *sample.user_header_mut() = BatchHeader {
            first_seq,
            count: count as u32,
            ..self.header
        };
        Ok(LoanedBatch {
            sample,
            publisher: self,
        })
    }

    fn error(&self, action: &'static str, message: String) -> TransportError {
        TransportError::Service {
            service: format!("{:?}", self.service.name()),
            action,
            message,
        }
    }
}

/// A batch of slots in shared memory, loaned by [`TransitionPublisher::loan`].
pub struct LoanedBatch<'p, 's> {
    sample: iceoryx2::sample_mut::SampleMut<ipc::Service, [TransitionSlot], BatchHeader>,
    publisher: &'p TransitionPublisher<'s>,
}

impl LoanedBatch<'_, '_> {
    /// The sequence number of the first slot.
    pub fn first_seq(&self) -> u64 {
        self.sample.user_header().first_seq
    }

    /// The slots; each holds stale data until written (see [`TransitionSlot`]).
    pub fn slots(&self) -> &[TransitionSlot] {
        self.sample.payload()
    }

    /// The slots to write in place; each holds stale data until written (see [`TransitionSlot`]).
    pub fn slots_mut(&mut self) -> &mut [TransitionSlot] {
        self.sample.payload_mut()
    }

    /// Stamps the send time and sends the batch without copying it. Blocks while the store's
    /// buffer is full; fails if termination is requested meanwhile. Check
    /// [`Delivery::recipients`].
    pub fn send(mut self) -> Result<Delivery, TransportError> {
        self.sample.user_header_mut().sent_unix_ns = unix_ns();
        let blocked = &self.publisher.blocked_ns;
        blocked.store(0, Ordering::Relaxed);
        let recipients = self
            .sample
            .send()
            .map_err(|e| self.publisher.error("send a batch", e.to_string()))?;
        Ok(Delivery {
            recipients,
            backpressure: Duration::from_nanos(blocked.swap(0, Ordering::Relaxed)),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn transition() -> Transition {
        Transition {
            task: 3,
            actor: 9,
            episode: 12,
            step: 99,
            seq: 1_000_001,
            obs: vec![1, 2, 3, 4, 5],
            action: 14,
            reward: -12.5,
            next_obs: vec![2, 2, 1, 5, 6],
            truncated: true,
        }
    }

    /// A slot as shared memory may hand it out: every entry left over from an earlier batch.
    fn stale_slot() -> TransitionSlot {
        TransitionSlot {
            episode: u64::MAX,
            step: u32::MAX,
            reward: f32::NAN,
            action: u16::MAX,
            truncated: 1,
            reserved: u8::MAX,
            obs: [u16::MAX; OBS_CAPACITY],
            next_obs: [u16::MAX; OBS_CAPACITY],
        }
    }

    #[test]
    fn slot_round_trips_a_transition_over_stale_memory() {
        let t = transition();
        let header = BatchHeader {
            task: 3,
            actor: 9,
            obs_len: 5,
            first_seq: 1_000_000,
            count: 2,
            ..BatchHeader::default()
        };
        let mut slot = stale_slot();
        slot.set_transition(&t);
        // Only the used entries are written; what lies past them is never read back.
        assert_eq!(slot.obs[5..], [u16::MAX; OBS_CAPACITY - 5]);
        assert_eq!(slot.to_transition(&header, 1), t);
        assert_ne!(slot.to_transition(&header, 0), t);
        let untruncated = Transition {
            truncated: false,
            ..t.clone()
        };
        slot.set_transition(&untruncated);
        assert_eq!(slot.to_transition(&header, 1), untruncated);
    }

    #[test]
    fn header_check_names_the_mismatch() {
        let header = BatchHeader {
            task: 1,
            run: 7,
            world: 8,
            actor: 2,
            obs_len: 12,
            count: 4,
            ..BatchHeader::default()
        };
        assert!(header.check(7, 8, 1, 12, 4).is_ok());
        let err = header.check(7, 9, 1, 12, 4).unwrap_err().to_string();
        assert!(err.contains("world hash"), "{err}");
        let err = header.check(7, 8, 1, 12, 3).unwrap_err().to_string();
        assert!(err.contains("count"), "{err}");
        let old = BatchHeader {
            schema_version: SCHEMA_VERSION + 1,
            ..header
        };
        let err = old.check(7, 8, 1, 12, 4).unwrap_err().to_string();
        assert!(err.contains("schema version"), "{err}");
    }

    #[test]
    fn method_codes_round_trip() {
        for m in Method::ALL {
            assert_eq!(Method::from_code(m.code()), Some(m));
        }
        assert_eq!(Method::from_code(99), None);
    }

    fn test_run(name: &str) -> (tempfile::TempDir, RunDir) {
        let dir = tempfile::Builder::new()
            .prefix(name)
            .tempdir()
            .expect("temp dir");
        let run = RunDir::create(dir.path()).expect("run dir");
        (dir, run)
    }

    #[test]
    fn another_schema_version_is_refused_with_both_versions() {
        let (_dir, run) = test_run("schema");
        let names = ServiceNames::new(&run);
        let config = Config::default();
        let node = node("schema-test", &config.run).expect("node");
        // A "future build": the same service created with the next schema version.
        let service = names.transitions("t");
        let foreign = (SCHEMA_VERSION + 1).to_string();
        let _theirs = node
            .service_builder(&service_name(&service).unwrap())
            .publish_subscribe::<[TransitionSlot]>()
            .user_header::<BatchHeader>()
            .create_with_attributes(
                &AttributeSpecifier::new()
                    .define(
                        &SCHEMA_ATTRIBUTE.try_into().unwrap(),
                        &foreign.as_str().try_into().unwrap(),
                    )
                    .unwrap(),
            )
            .expect("create the foreign service");
        let err = transition_service(&node, &names, "t", &config.run).expect_err("must refuse");
        match &err {
            TransportError::SchemaMismatch { theirs, .. } => assert_eq!(theirs, &foreign),
            other => panic!("expected a schema mismatch, got {other}"),
        }
        assert!(
            err.to_string()
                .contains(&format!("version {SCHEMA_VERSION}")),
            "{err}"
        );
    }

    #[test]
    fn batches_written_in_place_arrive_with_their_header() {
        let (_dir, run) = test_run("batches");
        let names = ServiceNames::new(&run);
        let mut config = Config::default();
        config.world.devices = 3;
        let node = node("batch-test", &config.run).expect("node");
        let service = transition_service(&node, &names, "t", &config.run).expect("service");
        let publisher = TransitionPublisher::new(&service, &run, &config, 0, 5).expect("publisher");
        assert!(publisher.subscribers().is_empty(), "no subscriber yet");
        let subscriber = transition_subscriber(&service, &config.run).expect("subscriber");
        assert!(!publisher.subscribers().is_empty());
        // Two batches, so the second may reuse the first one's memory.
        for (first_seq, count) in [(40u64, 3usize), (43, 2)] {
            let mut batch = publisher.loan(first_seq, count).expect("loan");
            for (i, slot) in batch.slots_mut().iter_mut().enumerate() {
                let seq = first_seq as u16 + i as u16;
                slot.set_state(1, seq as u32, &[seq, 2, 3, 4, 5]);
                slot.set_outcome(seq, -1.0, &[5, 4, 3, 2, seq], false);
            }
            let delivery = batch.send().expect("send");
            assert_eq!(delivery.recipients, 1);
            let sample = subscriber.receive().expect("receive").expect("a batch");
            let header = *sample.user_header();
            header
                .check(
                    run.hash(),
                    config.world_hash(),
                    0,
                    5,
                    sample.payload().len(),
                )
                .expect("own batch");
            for (i, slot) in sample.payload().iter().enumerate() {
                let t = slot.to_transition(&header, i);
                let seq = first_seq as u16 + i as u16;
                assert_eq!(t.seq, seq as u64);
                assert_eq!((t.action, t.step), (seq, seq as u32));
                assert_eq!(t.obs, [seq, 2, 3, 4, 5]);
                assert_eq!(t.next_obs, [5, 4, 3, 2, seq]);
            }
        }
    }

    #[test]
    fn two_runs_do_not_share_services() {
        let (_a, run_a) = test_run("run-a");
        let (_b, run_b) = test_run("run-b");
        assert_ne!(
            ServiceNames::new(&run_a).transitions("t"),
            ServiceNames::new(&run_b).transitions("t")
        );
        assert_ne!(run_a.hash(), run_b.hash());
    }
}
