//! The dataset store process (`uavmeta store --run R`): subscribes to every task's transitions,
//! appends each task's dataset file, and announces a task's dataset once it is complete.
//!
//! **Exactly once, or counted.** Every actor numbers its transitions 0, 1, 2, ... and the store
//! remembers, per task, host and actor, the next number it expects. A transition below it is a
//! duplicate (an actor restarted with the same seed replays its episodes) and is dropped; a jump
//! above it is a gap, counted as missing. On start the store rebuilds these numbers from its own
//! files, so a store killed and restarted keeps one copy of everything and counts whatever the
//! crash lost (the batches in its buffer).
//!
//! **Durability.** Each received batch becomes one chunk of the crash-safe dataset format and is
//! flushed to the operating system before the next batch is read, and then acknowledged to the
//! task's actors ([`StoreAck`]: per actor, the next number not yet stored). Killing the store
//! loses only what its buffer held, and the actors send that again to its successor. A dataset is
//! fsynced before it is announced.
//!
//! **Size.** A task's file holds exactly `collect.transitions` transitions; later ones are dropped
//! as surplus. With one actor per task the file is therefore the same bytes for the same config
//! and seed, whatever the timing.
//!
//! **Hosts.** The learner host's actors publish on a task's own service, each remote host's on
//! services of its own (`ServiceNames::for_host`), which only that host can reach through the
//! tunnel; the store keeps sequence numbers per host, acknowledges each host on its own service,
//! tags every chunk with the host that made it (`uavmeta dataset inspect` counts them), and stores
//! at most `tunnel.max_host_share` of a dataset from any one remote host (the rest is surplus).
//!
//! **Validation.** Nothing a publisher sends is trusted: every batch is checked against the task's
//! world before its transitions are selected, its first sequence number within
//! [`sequence_window`] of what the store holds of that actor, and a batch that fails is dropped
//! whole (the checks and what a failure does: docs/SECURITY.md, "What is checked, where").
//!
//! Accounting, checked by the end-to-end tests: transitions the actors published = stored +
//! dropped (duplicate, surplus, foreign, invalid), and missing counts transitions that never
//! arrived.

use std::collections::HashMap;
use std::time::{Duration, Instant};

use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use iceoryx2::sample::Sample;
use uavmeta_proto::config::{Config, ConfigError, RunConfig};
use uavmeta_proto::dataset::{
    DatasetError, DatasetHeader, DatasetReader, DatasetWriter, Transition, LEARNER_HOST,
};
use uavmeta_proto::metrics::store::{
    DROPPED_REASONS, DUPLICATE, FOREIGN, INVALID, OTHER_ACTORS, REJECTION_ACTORS, SEQUENCE_WINDOW,
    SURPLUS,
};
use uavmeta_proto::payload::{
    BatchHeader, DatasetReady, ServiceNames, StoreAck, TransitionSlot, SCHEMA_VERSION,
};
use uavmeta_world::validate::{Claimed, Rejection, Validator};

use crate::metrics::MetricsError;
use crate::process::Process;
use crate::run_dir::RunDir;
use crate::transport::{self, TransportError};
use crate::{domain, liveness};

mod metrics;

/// The store's process name: its node, port file and metrics snapshot.
pub const PROCESS: &str = "store";

/// How long the loop sleeps when no batch arrived; bounds the added latency when idle. The
/// transport bench's receiver waits the same, to measure publish-to-store latency.
pub const IDLE_WAIT: Duration = Duration::from_micros(200);

/// Interval between repeats of every actor's acknowledgement (`TaskStore::acknowledge_all`). The
/// transport bench's receiver repeats its acknowledgements as often.
pub const ACK_REFRESH_EVERY: Duration = Duration::from_millis(100);

/// Interval between sweeps for dead processes' iceoryx2 resources: a dead subscriber of a control
/// service would otherwise hold a full buffer.
const CLEANUP_EVERY: Duration = Duration::from_secs(2);

/// At most one log line per this interval for dropped batches of each kind (foreign, rejected);
/// the next line says how many it stands for.
const DROP_LOG_EVERY: Duration = Duration::from_secs(5);

/// How far ahead of the next number the store expects of an actor a batch may start, in
/// transitions: an actor keeps at most `2 * run.subscriber_buffer + 2` batches unacknowledged
/// (`crate::actor`), so a real actor's gap (batches lost with a killed store, or dropped
/// by a tunnel) stays within that many; four times it leaves room for all of them.
pub fn sequence_window(run: &RunConfig) -> u64 {
    4 * (2 * run.subscriber_buffer as u64 + 2) * run.transitions_per_message as u64
}

#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error(transparent)]
    Transport(#[from] TransportError),
    #[error(transparent)]
    Dataset(#[from] DatasetError),
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error(transparent)]
    Metrics(#[from] MetricsError),
}

/// One task's file and where its transitions come from.
struct TaskStore {
    name: String,
    id: u32,
    writer: DatasetWriter,
    /// The learner host's actors first, then each remote host that may serve the task.
    sources: Vec<Source>,
    announced: bool,
}

/// One host's actors of a task: their services and what the file holds of them.
struct Source {
    /// The chunks' host tag: `LEARNER_HOST`, or the remote host's name.
    host: String,
    subscriber: BatchSubscriber,
    /// Tells the host's actors what is stored, so that they send it again only if it is not.
    acks: Publisher<ipc::Service, StoreAck, ()>,
    /// Per actor, the next sequence number not yet stored.
    next_seq: HashMap<u32, u64>,
    /// The host's transitions in the file.
    stored: u64,
    /// The most of them the file may hold: the whole dataset for the learner's host,
    /// `tunnel.max_host_share` of it for a remote one.
    most: u64,
}

impl Source {
    /// Tells `actor` of task `task` that every number below `next_seq` is stored.
    fn acknowledge(&self, task: u32, actor: u32, next_seq: u64) -> Result<(), TransportError> {
        transport::acknowledge(
            &self.acks,
            StoreAck {
                schema_version: SCHEMA_VERSION,
                task,
                actor,
                reserved: 0,
                next_seq,
            },
        )
    }
}

impl TaskStore {
    /// Repeats every actor's acknowledgement: one an actor missed (its buffer overflowed) is
    /// made good, and a restarted store tells actors what its file already holds.
    fn acknowledge_all(&self) -> Result<(), TransportError> {
        self.sources.iter().try_for_each(|source| {
            (source.next_seq.iter())
                .try_for_each(|(&actor, &next)| source.acknowledge(self.id, actor, next))
        })
    }
}

/// What a store run did, for its log line.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub struct StoreSummary {
    pub stored: u64,
    pub dropped: u64,
    pub missing: u64,
}

/// Runs the store of `run` until SIGINT/SIGTERM or a shutdown announcement.
pub fn run(run: &RunDir, config: &Config) -> Result<StoreSummary, StoreError> {
    let process = Process::start(run, config, PROCESS)?;
    let node = &process.node;
    // A predecessor killed mid-run left its ports in every service; without this sweep the actors
    // stay blocked on its full buffer.
    let cleaned = domain::cleanup_dead_nodes(node);
    if cleaned > 0 {
        tracing::info!(cleaned, "removed iceoryx2 resources of dead processes");
    }
    let mut store = Store::open(run, config, &process)?;
    // The port file is the launcher's sign that the store is ready, so it comes after the
    // subscribers: actors started then find a connected store.
    let _server = process.serve_metrics(run, config, store.metrics.registry.clone())?;
    tracing::info!(run = run.id(), tasks = store.tasks.len(), "store ready");

    let cleaner = domain::Cleaner::start(&format!("{}-{PROCESS}", run.id()), &config.run);
    let mut idle = false;
    let mut last_cleanup = Instant::now();
    let mut last_ack_refresh = Instant::now();
    while liveness::keep_running(node, if idle { IDLE_WAIT } else { Duration::ZERO }) {
        transport::serve_history(&store.ready)?;
        if transport::shutdown_requested(&process.shutdown)? {
            tracing::info!("shutdown announced");
            break;
        }
        idle = store.drain()? == 0;
        if last_ack_refresh.elapsed() >= ACK_REFRESH_EVERY {
            store
                .tasks
                .iter()
                .try_for_each(TaskStore::acknowledge_all)?;
            last_ack_refresh = Instant::now();
        }
        if last_cleanup.elapsed() >= CLEANUP_EVERY {
            cleaner.request();
            last_cleanup = Instant::now();
        }
    }
    // Batches already delivered are written before exiting: actors stop first in an orderly
    // shutdown, so this empties the buffers.
    while store.drain()? > 0 {}
    for task in store.tasks.iter_mut() {
        task.writer.sync()?;
    }
    let summary = store.summary;
    tracing::info!(
        stored = summary.stored,
        dropped = summary.dropped,
        missing = summary.missing,
        "store stopped"
    );
    Ok(summary)
}

type BatchSubscriber = Subscriber<ipc::Service, [TransitionSlot], BatchHeader>;
type BatchSample = Sample<ipc::Service, [TransitionSlot], BatchHeader>;

/// A store run's state: every task's file and subscriber, what a batch is checked against, and
/// what the run has counted.
struct Store<'a> {
    run: &'a RunDir,
    /// Transitions a complete dataset holds (`collect.transitions`).
    target: u64,
    obs_len: usize,
    world_hash: u64,
    metrics: metrics::StoreMetrics,
    ready: Publisher<ipc::Service, DatasetReady, ()>,
    /// In task order.
    tasks: Vec<TaskStore>,
    /// The transitions of the batch being stored, kept to reuse its allocation.
    buffer: Vec<Transition>,
    /// In task order: every transition is checked against its task's world.
    validators: Vec<Validator>,
    /// [`sequence_window`] of the run.
    seq_window: u64,
    /// Actor ids the rejection metric labels by their own id (at most [`REJECTION_ACTORS`]).
    labelled_actors: std::collections::HashSet<u32>,
    foreign_log: LogLimit,
    rejection_log: LogLimit,
    summary: StoreSummary,
}

/// A log line at most every [`DROP_LOG_EVERY`]; the lines in between are counted, not written.
#[derive(Default)]
struct LogLimit {
    last: Option<Instant>,
    suppressed: u64,
}

impl LogLimit {
    /// Whether to write a line now; if so, how many were suppressed since the last one.
    fn allow(&mut self) -> Option<u64> {
        if self.last.is_some_and(|at| at.elapsed() < DROP_LOG_EVERY) {
            self.suppressed += 1;
            return None;
        }
        self.last = Some(Instant::now());
        Some(std::mem::take(&mut self.suppressed))
    }
}

impl<'a> Store<'a> {
    /// Opens every task's file and services, and announces the datasets already complete.
    fn open(run: &'a RunDir, config: &Config, process: &Process) -> Result<Self, StoreError> {
        let (node, names) = (&process.node, &process.names);
        let metrics = metrics::StoreMetrics::new();
        let mut tasks = Vec::with_capacity(config.tasks.len());
        for (id, task) in config.tasks.iter().enumerate() {
            let sources = sources(node, names, config, &task.name)?;
            tasks.push(open_task(
                run, config, &task.name, id as u32, sources, &metrics,
            )?);
        }
        let ready =
            transport::control_publisher(&transport::dataset_ready_service(node, names, config)?)?;
        let mut store = Store {
            run,
            target: config.collect.transitions as u64,
            obs_len: config.world.layout().observation_len(),
            world_hash: config.world_hash(),
            metrics,
            ready,
            tasks,
            buffer: Vec::with_capacity(config.run.transitions_per_message),
            validators: Validator::for_tasks(&config.world, &config.tasks),
            seq_window: sequence_window(&config.run),
            labelled_actors: Default::default(),
            foreign_log: LogLimit::default(),
            rejection_log: LogLimit::default(),
            summary: StoreSummary::default(),
        };
        for i in 0..store.tasks.len() {
            store.announce_if_complete(i)?;
        }
        Ok(store)
    }

    /// Receives and stores everything waiting on every task's services; returns the batches
    /// handled.
    fn drain(&mut self) -> Result<usize, StoreError> {
        let mut batches = 0;
        for i in 0..self.tasks.len() {
            for s in 0..self.tasks[i].sources.len() {
                while let Some(sample) = self.tasks[i].sources[s]
                    .subscriber
                    .receive()
                    .map_err(transport::receive_failed("receive a batch"))?
                {
                    batches += 1;
                    self.store_batch(i, s, sample)?;
                }
            }
        }
        Ok(batches)
    }

    /// Checks a batch of task `i` from source `s`, appends what its file lacks, and
    /// acknowledges it.
    fn store_batch(&mut self, i: usize, s: usize, sample: BatchSample) -> Result<(), StoreError> {
        let name = self.tasks[i].name.clone();
        let name = name.as_str();
        let header = *sample.user_header();
        let slots = sample.payload();
        let metrics = &self.metrics;
        metrics.batches_received.with_label_values(&[name]).inc();
        metrics
            .transitions_received
            .with_label_values(&[name])
            .inc_by(slots.len() as u64);
        metrics.batch_latency.observe(header.age_seconds());
        let task_id = self.tasks[i].id;
        if let Err(error) = header.check(
            self.run.hash(),
            self.world_hash,
            task_id,
            self.obs_len,
            slots.len(),
        ) {
            if let Some(suppressed) = self.foreign_log.allow() {
                tracing::warn!(suppressed, "dropped a batch: {error}");
            }
            metrics
                .transitions_dropped
                .with_label_values(&[name, FOREIGN])
                .inc_by(slots.len() as u64);
            self.summary.dropped += slots.len() as u64;
            return Ok(());
        }
        if let Err(rejection) = self.validate(i, s, &header, slots) {
            self.reject(i, &header, slots.len() as u64, &rejection);
            return Ok(());
        }
        let acknowledged = self.select(i, s, &header, slots);
        drop(sample);
        self.append(i, s)?;
        let task = &self.tasks[i];
        task.sources[s].acknowledge(task.id, header.actor, acknowledged)?;
        self.announce_if_complete(i)
    }

    /// Checks a batch of task `i` from source `s` whose header passed: its first sequence
    /// number within the actor's window, and every transition one the task's world makes.
    fn validate(
        &mut self,
        i: usize,
        s: usize,
        header: &BatchHeader,
        slots: &[TransitionSlot],
    ) -> Result<(), Rejection> {
        let next = self.tasks[i].sources[s]
            .next_seq
            .get(&header.actor)
            .copied()
            .unwrap_or(0);
        if header.first_seq > next.saturating_add(self.seq_window) {
            return Err(Rejection {
                reason: SEQUENCE_WINDOW,
                detail: format!(
                    "first sequence number {}, but the store holds this actor's numbers below \
                     {next} and admits at most {} ahead",
                    header.first_seq, self.seq_window
                ),
            });
        }
        let validator = &mut self.validators[i];
        for (index, slot) in slots.iter().enumerate() {
            validator
                .check(Claimed::from_slot(slot, self.obs_len))
                .map_err(|r| Rejection {
                    detail: format!(
                        "transition {index} (sequence number {}): {}",
                        header.first_seq + index as u64,
                        r.detail
                    ),
                    ..r
                })?;
        }
        Ok(())
    }

    /// Counts a batch of task `i` that failed validation as dropped, and says so at most every
    /// [`DROP_LOG_EVERY`].
    fn reject(&mut self, i: usize, header: &BatchHeader, count: u64, rejection: &Rejection) {
        let name = self.tasks[i].name.as_str();
        let actor = if self.labelled_actors.contains(&header.actor)
            || self.labelled_actors.len() < REJECTION_ACTORS
        {
            self.labelled_actors.insert(header.actor);
            header.actor.to_string()
        } else {
            OTHER_ACTORS.to_string()
        };
        let metrics = &self.metrics;
        metrics
            .transitions_rejected
            .with_label_values(&[name, &actor, rejection.reason])
            .inc_by(count);
        metrics
            .transitions_dropped
            .with_label_values(&[name, INVALID])
            .inc_by(count);
        self.summary.dropped += count;
        if let Some(suppressed) = self.rejection_log.allow() {
            tracing::warn!(
                task = name,
                actor = header.actor,
                transitions = count,
                suppressed,
                "dropped a batch that failed validation: {rejection}"
            );
        }
    }

    /// Fills the buffer with the batch's transitions that task `i`'s file lacks of source `s`,
    /// counting duplicates, surplus (beyond the file's size or the source's share) and gaps;
    /// returns the actor's next sequence number.
    fn select(
        &mut self,
        i: usize,
        s: usize,
        header: &BatchHeader,
        slots: &[TransitionSlot],
    ) -> u64 {
        let task = &mut self.tasks[i];
        let name = task.name.as_str();
        let source = &mut task.sources[s];
        let room = (self.target.saturating_sub(task.writer.transitions()))
            .min(source.most.saturating_sub(source.stored));
        let next = source.next_seq.entry(header.actor).or_default();
        self.buffer.clear();
        let (mut duplicates, mut surplus) = (0u64, 0u64);
        for (index, slot) in slots.iter().enumerate() {
            let seq = header.first_seq + index as u64;
            if seq < *next {
                duplicates += 1;
                continue;
            }
            if seq > *next {
                let gap = seq - *next;
                tracing::warn!(
                    task = name,
                    actor = header.actor,
                    from = *next,
                    to = seq,
                    "sequence gap: {gap} transitions missing"
                );
                self.metrics
                    .transitions_missing
                    .with_label_values(&[name])
                    .inc_by(gap);
                self.summary.missing += gap;
            }
            *next = seq + 1;
            if self.buffer.len() as u64 >= room {
                surplus += 1;
            } else {
                self.buffer.push(slot.to_transition(header, index));
            }
        }
        let dropped = &self.metrics.transitions_dropped;
        dropped
            .with_label_values(&[name, DUPLICATE])
            .inc_by(duplicates);
        dropped.with_label_values(&[name, SURPLUS]).inc_by(surplus);
        self.summary.dropped += duplicates + surplus;
        *next
    }

    /// Appends the buffer, made by source `s`, to task `i`'s file and flushes it.
    fn append(&mut self, i: usize, s: usize) -> Result<(), StoreError> {
        if self.buffer.is_empty() {
            return Ok(());
        }
        let task = &mut self.tasks[i];
        let source = &mut task.sources[s];
        let start = Instant::now();
        task.writer.append_from(&source.host, &self.buffer)?;
        task.writer.flush()?;
        source.stored += self.buffer.len() as u64;
        let metrics = &self.metrics;
        metrics
            .append_duration
            .observe(start.elapsed().as_secs_f64());
        metrics
            .transitions_stored
            .with_label_values(&[&task.name])
            .inc_by(self.buffer.len() as u64);
        metrics
            .dataset_transitions
            .with_label_values(&[&task.name])
            .set(task.writer.transitions() as i64);
        self.summary.stored += self.buffer.len() as u64;
        Ok(())
    }

    /// Syncs and announces task `i`'s dataset the first time it holds `target` transitions.
    fn announce_if_complete(&mut self, i: usize) -> Result<(), StoreError> {
        let task = &mut self.tasks[i];
        if task.announced || task.writer.transitions() < self.target {
            return Ok(());
        }
        task.writer.sync()?;
        transport::announce(
            &self.ready,
            DatasetReady {
                schema_version: SCHEMA_VERSION,
                task: task.id,
                transitions: task.writer.transitions(),
            },
        )?;
        self.metrics
            .dataset_ready
            .with_label_values(&[&task.name])
            .set(1);
        task.announced = true;
        tracing::info!(task = %task.name, transitions = task.writer.transitions(), file = %task.writer.path().display(), "dataset ready");
        Ok(())
    }
}

/// The services of task `task`'s sources, in the order [`TaskStore::sources`] keeps them: the
/// learner host's, then those of every remote host `tunnel.hosts` lets serve it, with no
/// transition counted yet.
fn sources(
    node: &Node<ipc::Service>,
    names: &ServiceNames,
    config: &Config,
    task: &str,
) -> Result<Vec<Source>, StoreError> {
    let target = config.collect.transitions as u64;
    let share = (target as f64 * config.tunnel.max_host_share).floor() as u64;
    let remote = (config.tunnel.hosts.keys())
        .filter(|host| (config.tunnel.tasks_of(host, &config.tasks).iter()).any(|t| t.name == task))
        .map(|host| (host.as_str(), names.for_host(host), share));
    let learner = std::iter::once((LEARNER_HOST, names.clone(), target));
    learner
        .chain(remote)
        .map(|(host, names, most)| {
            let service = transport::transition_service(node, &names, task, &config.run)?;
            let acks = transport::ack_service(node, &names, task, &config.run)?;
            Ok(Source {
                host: host.to_string(),
                subscriber: transport::transition_subscriber(&service, &config.run)?,
                acks: transport::ack_publisher(&acks)?,
                next_seq: HashMap::new(),
                stored: 0,
                most,
            })
        })
        .collect()
}

/// Opens (or creates) a task's file and rebuilds its sources' sequence numbers and counts from
/// it.
fn open_task(
    run: &RunDir,
    config: &Config,
    name: &str,
    id: u32,
    mut sources: Vec<Source>,
    metrics: &metrics::StoreMetrics,
) -> Result<TaskStore, StoreError> {
    let path = run.dataset(config.task(name)?);
    let header = DatasetHeader::for_task(config, name)?;
    let (writer, recovery) = DatasetWriter::open_or_create(&path, header)?;
    if let Some(r) = recovery {
        tracing::warn!(file = %path.display(), cut_bytes = r.cut_bytes, offset = r.offset, reason = %r.reason, "cut a torn tail left by a crash");
    }
    let mut held: HashMap<(usize, u32), u64> = HashMap::new();
    if writer.transitions() > 0 {
        let reader = DatasetReader::open(&path)?;
        for (host, t) in reader.with_hosts() {
            // A host no longer allowed to serve the task keeps its transitions, not its numbers.
            let Some(s) = sources.iter().position(|s| s.host == host) else {
                continue;
            };
            let next = sources[s].next_seq.entry(t.actor).or_default();
            *next = (*next).max(t.seq + 1);
            sources[s].stored += 1;
            *held.entry((s, t.actor)).or_default() += 1;
        }
    }
    // Sequence numbers start at 0, so what an actor's file lacks below its highest is missing.
    let missing: u64 = (sources.iter().enumerate())
        .flat_map(|(s, source)| source.next_seq.iter().map(move |(a, next)| (s, *a, *next)))
        .map(|(s, actor, next)| next - held[&(s, actor)])
        .sum();
    metrics
        .transitions_missing
        .with_label_values(&[name])
        .inc_by(missing);
    metrics
        .dataset_transitions
        .with_label_values(&[name])
        .set(writer.transitions() as i64);
    metrics.dataset_ready.with_label_values(&[name]).set(0);
    for reason in DROPPED_REASONS {
        metrics
            .transitions_dropped
            .with_label_values(&[name, reason]);
    }
    for family in [
        &metrics.batches_received,
        &metrics.transitions_received,
        &metrics.transitions_stored,
    ] {
        family.with_label_values(&[name]);
    }
    if writer.transitions() > 0 {
        tracing::info!(
            task = name,
            transitions = writer.transitions(),
            actors = sources.iter().map(|s| s.next_seq.len()).sum::<usize>(),
            missing,
            "resuming the dataset"
        );
    }
    Ok(TaskStore {
        name: name.to_string(),
        id,
        writer,
        sources,
        announced: false,
    })
}
