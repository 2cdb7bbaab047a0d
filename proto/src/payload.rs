//! What uavmeta's processes say to each other: the payloads they exchange, the names of the
//! services that carry them, and the schema version they must agree on. How the payloads travel
//! (iceoryx2's services, backpressure, acknowledgements, clean-up) is `uavmeta_runtime::transport`.
//!
//! **Transitions** travel from actors to the store as a slice of fixed-layout
//! [`TransitionSlot`]s under one [`BatchHeader`] (`publish_subscribe::<[TransitionSlot]>()` with a
//! user header): an actor loans a batch of slots in shared memory, writes every step straight into
//! its slot and sends it; the store reads it in place. Nothing is serialised per transition. A
//! slot's observation arrays have room for the largest K, but only their first `obs_len`
//! (= 2 + K, in the header) entries are written: **receivers must never read past `obs_len`**;
//! the rest holds whatever an earlier batch left in that memory. There is one service per task,
//! `uavmeta/<run>/transitions/<task>` ([`ServiceNames`]).
//!
//! **Acknowledgements** ([`StoreAck`], one service per task, `uavmeta/<run>/acks/<task>`): per
//! actor, every sequence number below `next_seq` is in the dataset file. They are cumulative, so
//! a newer one makes every older one worthless.
//!
//! **Control** messages ([`DatasetReady`], [`CheckpointReady`], [`Shutdown`]) each have their own
//! service under `uavmeta/<run>/control/`, with history, so a process that joins late (or
//! restarts) still hears what was announced before.
//!
//! **Schema version.** Every service is created with the attribute
//! [`SCHEMA_ATTRIBUTE`]` = `[`SCHEMA_VERSION`], and every opener requires it, so a process built
//! with another version cannot open a run's services. The version is deliberately not in the
//! service name: two versions would then share a run silently, each waiting forever for the
//! other's messages. The payload type names carry the version too, and every header repeats it,
//! so a mismatch can never be read as data.
//!
//! With the feature `ipc` the payloads implement iceoryx2's `ZeroCopySend`, under the type names
//! above; without it they are plain `#[repr(C)]` structs and the crate builds no iceoryx2.

use std::time::{SystemTime, UNIX_EPOCH};

#[cfg(feature = "ipc")]
use iceoryx2::prelude::ZeroCopySend;

use crate::config::{TaskConfig, MAX_DEVICES};
use crate::dataset::Transition;

/// The version of every payload below and of the service settings; bump it on any change.
pub const SCHEMA_VERSION: u32 = 5;

/// The service attribute that carries [`SCHEMA_VERSION`].
pub const SCHEMA_ATTRIBUTE: &str = "uavmeta.schema_version";

/// Entries of an observation array: 2 + the largest K a config admits.
pub const OBS_CAPACITY: usize = 2 + MAX_DEVICES;

/// A received batch that belongs to another run, world, task or schema, or whose header does not
/// fit its slice ([`BatchHeader::check`]).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error(
    "batch from actor {actor} of task {task}: {problem}; the actor runs another config or another \
     run than this process"
)]
pub struct ForeignBatch {
    pub actor: u32,
    pub task: u32,
    pub problem: String,
}

/// The header of one batch of transitions.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(
    feature = "ipc",
    derive(ZeroCopySend),
    type_name("uavmeta.BatchHeader.v4")
)]
#[repr(C)]
pub struct BatchHeader {
    pub schema_version: u32,
    /// The task's index in the config's `[[tasks]]`.
    pub task: u32,
    /// The hash of the run the actor joined (`uavmeta_runtime::run_dir::RunDir::hash`).
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
    ) -> Result<(), ForeignBatch> {
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
            Some(problem) => Err(ForeignBatch {
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
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(
    feature = "ipc",
    derive(ZeroCopySend),
    type_name("uavmeta.TransitionSlot.v4")
)]
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
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(
    feature = "ipc",
    derive(ZeroCopySend),
    type_name("uavmeta.DatasetReady.v4")
)]
#[repr(C)]
pub struct DatasetReady {
    pub schema_version: u32,
    pub task: u32,
    pub transitions: u64,
}

/// The store has appended, and flushed to the operating system, every transition of `actor` on
/// `task` numbered below `next_seq` (or dropped it as surplus, the dataset being complete). Sent
/// after every batch; a killed store loses none of it, since the file survives the process.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(
    feature = "ipc",
    derive(ZeroCopySend),
    type_name("uavmeta.StoreAck.v4")
)]
#[repr(C)]
pub struct StoreAck {
    pub schema_version: u32,
    pub task: u32,
    pub actor: u32,
    /// Explicit padding, so the layout has no uninitialised bytes.
    pub reserved: u32,
    pub next_seq: u64,
}

/// A checkpoint is on disk (written atomically) at the run directory's path for these fields
/// (`uavmeta_runtime::run_dir::RunDir::checkpoint`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(
    feature = "ipc",
    derive(ZeroCopySend),
    type_name("uavmeta.CheckpointReady.v4")
)]
#[repr(C)]
pub struct CheckpointReady {
    pub schema_version: u32,
    /// [`Method::code`](crate::method::Method::code).
    pub method: u32,
    /// The task it was trained for (meta-test) or is scored on; for
    /// [`Method::MetaInit`](crate::method::Method::MetaInit) the meta-test task whose zero-shot
    /// score it reports.
    pub task: u32,
    /// Epochs (meta-epochs for `Method::MetaInit`) behind it.
    pub epoch: u32,
}

impl CheckpointReady {
    /// The announcement of `method`'s checkpoint of epoch `epoch` for task number `task`, at this
    /// build's schema.
    pub fn new(method: crate::method::Method, task: u32, epoch: u32) -> Self {
        Self {
            schema_version: SCHEMA_VERSION,
            method: method.code(),
            task,
            epoch,
        }
    }
}

/// Every process of the run finishes what it is doing and exits.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(
    feature = "ipc",
    derive(ZeroCopySend),
    type_name("uavmeta.Shutdown.v4")
)]
#[repr(C)]
pub struct Shutdown {
    pub schema_version: u32,
    pub reserved: u32,
}

/// The iceoryx2 service names of one run; the run id makes two runs on a host disjoint.
///
/// A remote host's actors publish their transitions and read their acknowledgements under names
/// of their own, `uavmeta/<run>/hosts/<host>/...` ([`ServiceNames::for_host`]): the learner
/// host's tunnel lets each host put only on its own (docs/SECURITY.md), so no remote host can
/// publish as the learner host's actors or another host's.
#[derive(Debug, Clone)]
pub struct ServiceNames {
    prefix: String,
    /// Where a task's transitions and acknowledgements are: the run's own services on the learner
    /// host, `hosts/<host>` under them for a remote host's.
    actors: String,
}

impl ServiceNames {
    /// The services of the run whose id is `run_id` (`uavmeta_runtime::run_dir::RunDir::id`),
    /// as the learner host's actors use them.
    pub fn new(run_id: &str) -> Self {
        let prefix = format!("uavmeta/{run_id}");
        Self {
            actors: prefix.clone(),
            prefix,
        }
    }

    /// The same run's services as remote host `host`'s actors use them.
    pub fn for_host(&self, host: &str) -> Self {
        Self {
            actors: format!("{}/hosts/{host}", self.prefix),
            prefix: self.prefix.clone(),
        }
    }

    pub fn transitions(&self, task: &str) -> String {
        format!("{}/transitions/{task}", self.actors)
    }

    pub fn acks(&self, task: &str) -> String {
        format!("{}/acks/{task}", self.actors)
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

    /// The services a remote host's actors use (names of [`Self::for_host`]) and which way each
    /// crosses a tunnel: the one declaration of what a remote host may send (its transitions of
    /// the tasks it serves) and what only the learner's host sends (acknowledgements, dataset
    /// announcements, the shutdown).
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
    fn two_runs_do_not_share_services() {
        assert_ne!(
            ServiceNames::new("run-a-00000001").transitions("t"),
            ServiceNames::new("run-b-00000002").transitions("t")
        );
    }

    #[test]
    fn each_remote_host_has_its_own_transitions_and_acks_and_shares_the_rest() {
        let run = ServiceNames::new("run-a-00000001");
        let (b, c) = (run.for_host("b"), run.for_host("c"));
        let names = [&run, &b, &c].map(|n| (n.transitions("t"), n.acks("t")));
        assert_eq!(names[1].0, "uavmeta/run-a-00000001/hosts/b/transitions/t");
        assert!(names[0] != names[1] && names[1] != names[2] && names[0] != names[2]);
        assert_eq!(b.shutdown(), run.shutdown());
        assert_eq!(b.dataset_ready(), run.dataset_ready());
        assert_eq!(
            b.to_remote(&b.acks("t")),
            "uavmeta/run-a-00000001/to-remote/hosts/b/acks/t"
        );
    }
}
