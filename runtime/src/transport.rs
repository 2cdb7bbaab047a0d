//! How uavmeta's processes reach each other over iceoryx2: the services that carry
//! `uavmeta_proto::payload`'s messages (whose layout, names and schema version are the contract),
//! their publishers and subscribers, and how a batch of transitions is delivered.
//!
//! **Transitions** travel from actors to the store as a slice of [`TransitionSlot`]s under one
//! [`BatchHeader`], one service per task: an actor loans a batch of slots in shared memory,
//! writes every step straight into its slot ([`TransitionPublisher::loan`]) and sends it; the
//! store reads it in place, never past the header's `obs_len`.
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
//! **Acknowledgements** ([`StoreAck`], one service per task) let an actor send again what a
//! replaced store lost (docs/ARCHITECTURE.md, "The multi-process run"; `crate::actor`): per
//! actor, every sequence number below `next_seq` is in the dataset file. They are cumulative, so
//! their service overwrites the oldest when an actor's buffer is full rather than block the store.
//!
//! Transition services keep no history: in iceoryx2 0.10 a subscriber that joins a publisher with
//! history gets that history into its buffer and afterwards the blocking publisher silently loses
//! batches (measured: 39 296 of 43 456 transitions of one actor).
//!
//! **Control** messages ([`DatasetReady`], [`CheckpointReady`], [`Shutdown`]) each have their own
//! service, with history, so a process that joins late (or restarts) still hears what was
//! announced before.
//!
//! **Schema version.** Every service is created with the attribute [`SCHEMA_ATTRIBUTE`] set to
//! [`SCHEMA_VERSION`], and every opener requires it. A process built with another version
//! therefore cannot open a run's services: it fails with [`TransportError::SchemaMismatch`],
//! which names the service and both versions.

use std::fmt;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use iceoryx2::node::Node;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::port::{BackpressureAction, BackpressureInfo};
use iceoryx2::prelude::*;
use iceoryx2::service::port_factory::publish_subscribe::PortFactory as PubSubFactory;
use uavmeta_proto::config::{Config, RunConfig};
use uavmeta_proto::payload::{
    unix_ns, BatchHeader, CheckpointReady, DatasetReady, ServiceNames, Shutdown, StoreAck,
    TransitionSlot, SCHEMA_ATTRIBUTE, SCHEMA_VERSION,
};

use crate::liveness::termination_requested;
use crate::run_dir::{FileError, RunDir};

/// Subscribers a transition service admits: the store, plus room for a benchmark or a monitor.
const TRANSITION_SUBSCRIBERS: usize = 4;

/// Acknowledgements an actor's subscriber holds: every actor of a task hears every one, and only
/// the newest of its own matters.
const ACK_BUFFER: usize = 16;

/// Processes besides the actors that open a control service: store, meta-learner, evaluator,
/// launcher, and room for a hand-started one of each.
const CONTROL_PEERS: usize = 8;
/// Announcements (dataset ready, checkpoint ready, shutdown) a control subscriber buffers; also the
/// history a process joining late receives: several times what a default launch announces (a
/// dataset per task and seed, a checkpoint per `meta.checkpoint_every`, the shutdown).
const CONTROL_HISTORY: usize = 256;

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
    #[error(transparent)]
    File(#[from] FileError),
}

/// The error of `action` on service `service`, for `map_err`.
pub(crate) fn service_error<E: fmt::Display>(
    service: impl Into<String>,
    action: &'static str,
) -> impl FnOnce(E) -> TransportError {
    let service = service.into();
    move |e| TransportError::Service {
        service,
        action,
        message: e.to_string(),
    }
}

/// [`service_error`] on the service named `name`.
fn port_error<E: fmt::Display>(
    name: &ServiceName,
    action: &'static str,
) -> impl FnOnce(E) -> TransportError {
    service_error(format!("{name:?}"), action)
}

/// The error of `name` (or a part of its service) that iceoryx2 refuses, for `map_err`.
fn invalid_name<E: fmt::Debug>(name: &str) -> impl FnOnce(E) -> TransportError {
    let name = name.to_string();
    move |e| TransportError::ServiceName {
        name,
        message: format!("{e:?}"),
    }
}

fn service_name(name: &str) -> Result<ServiceName, TransportError> {
    ServiceName::new(name).map_err(invalid_name(name))
}

fn schema_verifier(service: &str) -> Result<AttributeVerifier, TransportError> {
    let key = SCHEMA_ATTRIBUTE.try_into().map_err(invalid_name(service))?;
    let value = SCHEMA_VERSION.to_string();
    let value = value.as_str().try_into().map_err(invalid_name(service))?;
    AttributeVerifier::new()
        .require(&key, &value)
        .map_err(|e| service_error(service, "require the schema attribute")(format!("{e:?}")))
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
    service_error(service, "open or create")(error)
}

/// Samples a subscriber may hold borrowed at once: iceoryx2 0.10's default, which the transition
/// service keeps.
const SUBSCRIBER_BORROWED: usize = 2;

/// Bytes of shared memory one actor's transition publisher maps: iceoryx2 sizes its data
/// segment for every sample that can be in flight (each subscriber's buffer and borrowed
/// samples, plus the one the actor loans), each a batch of `run.transitions_per_message` slots. The launcher
/// checks the run's total against /dev/shm before it starts anything.
pub fn actor_shared_memory(run: &RunConfig) -> u64 {
    let samples = TRANSITION_SUBSCRIBERS * (run.subscriber_buffer + SUBSCRIBER_BORROWED) + 1;
    let batch = std::mem::size_of::<TransitionSlot>() * run.transitions_per_message
        + std::mem::size_of::<BatchHeader>();
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
        .subscriber_max_buffer_size(CONTROL_HISTORY)
        .history_size(CONTROL_HISTORY)
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
) -> Result<Subscriber<ipc::Service, T, ()>, TransportError> {
    service
        .subscriber_builder()
        .history_request(CONTROL_HISTORY)
        .create()
        .map_err(port_error(service.name(), "create a subscriber"))
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
        .map_err(port_error(service.name(), "create a publisher"))
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
        .map_err(service_error("control", "connect new subscribers"))
}

/// Sends one control message by copy (they are a few bytes).
pub fn announce<T: fmt::Debug + ZeroCopySend>(
    publisher: &Publisher<ipc::Service, T, ()>,
    message: T,
) -> Result<usize, TransportError> {
    publisher
        .send_copy(message)
        .map_err(service_error("control", "send"))
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
        .map_err(port_error(service.name(), "create a subscriber"))
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
        .map_err(port_error(service.name(), "create a publisher"))
}

/// An actor's subscriber to its task's acknowledgements.
pub fn ack_subscriber(
    service: &AckService,
) -> Result<Subscriber<ipc::Service, StoreAck, ()>, TransportError> {
    service
        .subscriber_builder()
        .buffer_size(ACK_BUFFER)
        .create()
        .map_err(port_error(service.name(), "create a subscriber"))
}

/// Publishes one acknowledgement; never blocks (the service overwrites the oldest).
pub fn acknowledge(
    publisher: &Publisher<ipc::Service, StoreAck, ()>,
    ack: StoreAck,
) -> Result<(), TransportError> {
    publisher
        .send_copy(ack)
        .map(drop)
        .map_err(service_error("acks", "send an acknowledgement"))
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
    /// A publisher on `service` for `actor`'s batches of `run.transitions_per_message` transitions of task
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
            .initial_max_slice_len(config.run.transitions_per_message)
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
            .map_err(port_error(service.name(), "create a publisher"))?;
        let header = BatchHeader {
            task,
            run: run_dir.hash(),
            world: config.world_hash(),
            actor,
            obs_len: config.world.layout().observation_len() as u32,
            ..BatchHeader::default()
        };
        Ok(Self {
            service,
            publisher,
            blocked_ns,
            header,
            batch_size: config.run.transitions_per_message,
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
            .map_err(port_error(self.service.name(), "loan a batch"))?;
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
            .map_err(port_error(self.publisher.service.name(), "send a batch"))?;
        Ok(Delivery {
            recipients,
            backpressure: Duration::from_nanos(blocked.swap(0, Ordering::Relaxed)),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::domain::node;
    use crate::run_dir::tests::test_run;

    #[test]
    fn another_schema_version_is_refused_with_both_versions() {
        let (_dir, run) = test_run("schema");
        let names = ServiceNames::new(run.id());
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
        let names = ServiceNames::new(run.id());
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
}
