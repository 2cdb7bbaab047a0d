//! The actor process (`uavmeta actor --run R --task T --policy P [--seed S]`): rolls a behaviour
//! policy out in one task's world and publishes its transitions to the store.
//!
//! Each step is written straight into its fixed-layout slot of a batch loaned in shared memory
//! (`proto::transport`), `run.batch_size` steps per batch, numbered 0, 1, 2, ... by a per-actor
//! sequence number, and the batch is sent without a further copy. When the store's buffer is full
//! the actor waits (backpressure); while no store is subscribed it holds its written batch and
//! sends it once one is; both waits are counted. A batch that iceoryx2 reports delivered to nobody
//! is sent again under the same numbers: from a copy the actor keeps until the store is proven
//! connected (`StoreLink`), or, for a replay sample, written again from the sample. With
//! `dqn-online` (the paper's behaviour policy) the actor first trains an online DQN agent and then
//! publishes `collect.transitions` transitions sampled from its replay buffer, after saving the
//! agent's network as the task's `online-dqn` checkpoint (the "online" reference); when the store
//! changes (a killed store replaced), it sends the whole sample again, since the dead store may
//! have taken part of it unwritten and a sample, unlike a rollout, has no more data to come.
//!
//! An actor's identity is a hash of its task, policy and seed: the same actor restarted (by the
//! launcher after a crash) makes the same transitions under the same numbers, and the store keeps
//! one copy. Two actors with different seeds add different data, so actors can be started and
//! stopped by hand at any time. An actor ends when its task's dataset is announced complete, when
//! a shutdown is announced, after `--transitions N`, or on SIGINT/SIGTERM.

use std::time::{Duration, Instant};

use iceoryx2::prelude::*;
use uavmeta_learner::checkpoint::{self, CheckpointError};
use uavmeta_learner::metrics::{MetricsError, MetricsServer};
use uavmeta_proto::config::{Config, ConfigError, TaskConfig};
use uavmeta_proto::dataset::Transition;
use uavmeta_proto::stats::EpisodeMetrics;
use uavmeta_proto::transport::{
    self, Method, RunDir, ServiceNames, SubscriberSet, TransitionPublisher, TransitionSlot,
    TransportError, SCHEMA_VERSION,
};

use crate::collect::{online_dqn_dataset, CollectError};
use crate::heuristics::{PolicyError, PolicySpec};
use crate::rollout::{episode_seed, EpisodeTally, Policy};
use crate::world::World;

/// How often an actor with nothing to send (no store yet, or its replay sample all sent) looks
/// for news.
const POLL: Duration = Duration::from_millis(10);

/// How often a publishing actor looks for signals and announcements.
const CONTROL_EVERY: Duration = Duration::from_millis(5);

#[derive(Debug, thiserror::Error)]
pub enum ActorError {
    #[error(transparent)]
    Transport(#[from] TransportError),
    #[error(transparent)]
    Metrics(#[from] MetricsError),
    #[error("--policy {spec}: {error}")]
    Policy { spec: String, error: PolicyError },
    #[error(transparent)]
    Collect(#[from] CollectError),
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
}

/// What to run: the flags of `uavmeta actor`.
#[derive(Debug, Clone)]
pub struct ActorOptions {
    pub task: String,
    pub policy: PolicySpec,
    /// Seeds the episodes' worlds and the policy's random stream.
    pub seed: u64,
    /// Stop after publishing this many transitions; `None` runs until the dataset is complete.
    pub transitions: Option<u64>,
}

impl ActorOptions {
    /// The actor's id: an FNV-1a hash of task, policy and seed, so a restarted actor keeps its id.
    pub fn actor_id(&self) -> u32 {
        let key = format!("{}\0{}\0{}", self.task, self.policy, self.seed);
        key.bytes().fold(0x811c_9dc5u32, |h, b| {
            (h ^ b as u32).wrapping_mul(0x0100_0193)
        })
    }

    /// The process name: node, port file and metrics snapshot.
    pub fn process_name(&self) -> String {
        format!("actor-{}-{:08x}", self.task, self.actor_id())
    }
}

/// What an actor run did.
#[derive(Debug, Default, Clone, Copy, PartialEq)]
pub struct ActorSummary {
    pub actor: u32,
    pub steps: u64,
    pub published: u64,
    pub episodes: u64,
    pub backpressure: Duration,
}

/// The actor's metrics: every name it exports, in one place. The registry labels them all with
/// the actor's task and id.
mod metrics {
    use std::collections::HashMap;

    use prometheus::{Counter, Gauge, Histogram, IntCounter, Opts, Registry};

    use uavmeta_learner::metrics::{counter, latency_histogram, register};

    pub struct ActorMetrics {
        pub registry: Registry,
        pub steps: IntCounter,
        pub transitions_published: IntCounter,
        pub batches_resent: IntCounter,
        pub samples_resent: IntCounter,
        pub transitions_lost: IntCounter,
        pub batches_published: IntCounter,
        pub episodes: IntCounter,
        pub episode_return: Gauge,
        pub episode_aoi: Gauge,
        pub episode_power: Gauge,
        pub episode_outages: Gauge,
        pub backpressure_wait: Counter,
        pub batch_duration: Histogram,
    }

    impl ActorMetrics {
        pub fn new(task: &str, actor: u32) -> Self {
            let labels = HashMap::from([
                ("task".to_string(), task.to_string()),
                ("actor".to_string(), format!("{actor:08x}")),
            ]);
            let registry = Registry::new_custom(Some("uavmeta".into()), Some(labels))
                .expect("valid prefix and labels");
            let gauge = |name: &str, help: &str| {
                register(
                    &registry,
                    Gauge::with_opts(Opts::new(name, help)).expect("valid gauge"),
                )
            };
            Self {
                steps: counter(&registry, "actor_steps_total", "Environment steps taken (for dqn-online, training steps included)."),
                transitions_published: counter(&registry, "actor_transitions_published_total", "Transitions delivered to the store's service."),
                batches_resent: counter(&registry, "actor_batches_resent_total", "Batches sent again because iceoryx2 reported them delivered to no store."),
                samples_resent: counter(&registry, "actor_samples_resent_total", "Times the replay sample (dqn-online) was sent again from its start because the store changed."),
                transitions_lost: counter(&registry, "actor_transitions_lost_total", "Transitions delivered to no store because the connected store went away during the send; the restarted store counts them as missing."),
                batches_published: counter(&registry, "actor_batches_published_total", "Batches sent to the store's service."),
                episodes: counter(&registry, "actor_episodes_total", "Episodes finished by the behaviour policy."),
                episode_return: gauge("actor_episode_return", "Return of the last finished episode."),
                episode_aoi: gauge("actor_episode_aoi", "Mean AoI over steps and devices of the last finished episode."),
                episode_power: gauge("actor_episode_power_watts", "Mean transmit power per step of the last finished episode, in watts."),
                episode_outages: gauge("actor_episode_outages", "Steps in outage of the last finished episode."),
                backpressure_wait: register(
                    &registry,
                    Counter::with_opts(Opts::new(
                        "actor_backpressure_wait_seconds_total",
                        "Time blocked because the store's buffer was full or no store was connected.",
                    ))
                    .expect("valid counter"),
                ),
                batch_duration: latency_histogram(&registry, "actor_batch_duration_seconds", "Time to roll out and send one batch."),
                registry,
            }
        }
    }
}

/// A behaviour policy rolled out episode after episode, each step written into a slot: the whole
/// of an actor's work besides sending (the transport benchmark times it alone too).
pub struct Rollout {
    world: World,
    policy: Box<dyn Policy>,
    seed: u64,
    episode: u64,
    in_episode: bool,
    /// The episode in progress.
    tally: EpisodeTally,
    finished: Vec<EpisodeMetrics>,
}

impl Rollout {
    pub fn new(config: &Config, task: &TaskConfig, policy: Box<dyn Policy>, seed: u64) -> Self {
        Self {
            world: World::new(&config.world, task, seed),
            policy,
            seed,
            episode: 0,
            in_episode: false,
            tally: EpisodeTally::default(),
            finished: Vec::new(),
        }
    }

    /// Takes one step, writing it into `slot` in place. The i-th episode runs in the world of
    /// `episode_seed(seed, i)`, as in `collect` and evaluation.
    #[inline]
    pub fn write_step(&mut self, slot: &mut TransitionSlot) {
        if !self.in_episode {
            self.world
                .reseed(episode_seed(self.seed, self.episode as usize));
            self.world.reset();
            self.in_episode = true;
        }
        slot.set_state(self.episode, self.world.t(), self.world.observation());
        let action = self.policy.act(&self.world);
        let step = self.world.step(action);
        // Below 5K <= 5 * MAX_DEVICES, checked by the world's step.
        slot.set_outcome(
            action as u16,
            step.reward as f32,
            self.world.observation(),
            step.truncated,
        );
        self.tally.add(&step);
        if step.truncated {
            self.finished.push(std::mem::take(&mut self.tally).finish());
            self.episode += 1;
            self.in_episode = false;
        }
    }

    /// The episodes finished since the last call.
    pub fn drain_finished(&mut self) -> impl Iterator<Item = EpisodeMetrics> + '_ {
        self.finished.drain(..)
    }
}

/// Where the actor's transitions come from.
enum Source {
    Rollout(Box<Rollout>),
    /// A fixed list (the online DQN agent's replay sample), published in order once.
    Fixed(Vec<Transition>),
}

/// Runs an actor of `run` until its task's dataset is complete, a shutdown, its transition limit,
/// or SIGINT/SIGTERM.
pub fn run(
    run: &RunDir,
    config: &Config,
    options: &ActorOptions,
) -> Result<ActorSummary, ActorError> {
    let task = config.task(&options.task)?.clone();
    let task_id = config.task_id(&task.name)? as u32;
    let actor = options.actor_id();
    let process = options.process_name();
    let node = transport::node(&format!("{}-{process}", run.id()))?;
    let names = ServiceNames::new(run);
    let metrics = metrics::ActorMetrics::new(&task.name, actor);
    let _server = MetricsServer::start(
        metrics.registry.clone(),
        &config.run.metrics_host,
        0,
        run,
        &process,
    )?;
    let service = transport::transition_service(&node, &names, &task.name, &config.run)?;
    let publisher = TransitionPublisher::new(&service, run, config, task_id, actor)?;
    let ready = transport::control_subscriber(
        &transport::dataset_ready_service(&node, &names, config)?,
        config,
    )?;
    let shutdown = transport::control_subscriber(
        &transport::shutdown_service(&node, &names, config)?,
        config,
    )?;
    let mut summary = ActorSummary {
        actor,
        ..ActorSummary::default()
    };
    tracing::info!(task = %task.name, actor = format!("{actor:08x}"), policy = %options.policy, seed = options.seed, "actor started");

    let mut source = match &options.policy {
        PolicySpec::DqnOnline => {
            let trained = online_dqn_dataset(config, &task, task_id, actor, options.seed, |n| {
                metrics.steps.inc_by(n as u64);
                transport::keep_running(&node, Duration::ZERO)
            });
            match trained {
                Ok((sample, agent)) => {
                    summary.steps = agent.steps() as u64;
                    // The reference the meta-learner announces once the dataset is stored.
                    checkpoint::save(
                        &run.checkpoint(Method::OnlineDqn, &task, 1),
                        agent.q_network(),
                        Method::OnlineDqn.name(),
                        1,
                        config,
                    )?;
                    Source::Fixed(sample)
                }
                Err(CollectError::Interrupted { steps }) => {
                    tracing::info!(steps, "stopped while training the online DQN agent");
                    return Ok(summary);
                }
                Err(error) => return Err(error.into()),
            }
        }
        spec => {
            let policy = spec
                .build(config.world.action_count(), options.seed, usize::MAX)
                .map_err(|error| ActorError::Policy {
                    spec: spec.to_string(),
                    error,
                })?;
            Source::Rollout(Box::new(Rollout::new(config, &task, policy, options.seed)))
        }
    };

    let limit = options.transitions.unwrap_or(u64::MAX);
    let mut seq = 0u64;
    let mut link = StoreLink::new(publisher.subscriber_buffer());
    let mut outbox: Vec<TransitionSlot> = Vec::with_capacity(publisher.batch_size());
    let mut next_look = Instant::now();
    'publishing: loop {
        // Signals and announcements are looked at every CONTROL_EVERY, not every batch: a look
        // costs a syscall and two receives, a batch of 64 steps a few microseconds.
        if Instant::now() >= next_look {
            if !transport::keep_running(&node, Duration::ZERO)
                || announced(&ready, &shutdown, task_id)?
            {
                break;
            }
            next_look = Instant::now() + CONTROL_EVERY;
        }
        if let Source::Fixed(_) = &source {
            // A replay sample can be sent again, and must be: a store that went away took what it
            // held unwritten with it, and no actor will ever send those transitions otherwise.
            // Its successor keeps what it lacks and drops the rest as duplicates.
            let subscribers = publisher.subscribers();
            if seq > 0 && link.replaced(subscribers) {
                tracing::warn!(
                    sent = seq,
                    "the store changed; sending the replay sample again"
                );
                metrics.samples_resent.inc();
                link.observe(subscribers);
                seq = 0;
            }
        }
        let left = match &source {
            Source::Rollout(_) => limit - seq,
            Source::Fixed(list) => limit.min(list.len() as u64).saturating_sub(seq),
        };
        let count = left.min(publisher.batch_size() as u64) as usize;
        if count == 0 {
            if seq >= limit {
                tracing::info!(published = seq, "published the requested transitions");
                break;
            }
            // Everything sampled is sent; stay until the store announces the dataset.
            transport::keep_running(&node, POLL);
            continue;
        }
        let start = Instant::now();
        let mut batch = publisher.loan(seq, count)?;
        // A rollout cannot be replayed: while the store may not be connected yet, keep a copy of
        // the batch to send again if iceoryx2 drops it (below).
        let keep = !link.confirmed();
        match &mut source {
            Source::Rollout(rollout) => {
                for slot in batch.slots_mut() {
                    rollout.write_step(slot);
                }
                if keep {
                    outbox.clear();
                    outbox.extend_from_slice(batch.slots_mut());
                }
            }
            Source::Fixed(list) => write_sample(batch.slots_mut(), list, seq),
        }
        let mut waited = Duration::ZERO;
        let delivered = loop {
            // Sent while no store is subscribed, the batch would be lost: hold it until one is.
            let subscribers = loop {
                let subscribers = publisher.subscribers();
                if !subscribers.is_empty() {
                    break subscribers;
                }
                let pause = Instant::now();
                let alive = transport::keep_running(&node, POLL);
                waited += pause.elapsed();
                if !alive || announced(&ready, &shutdown, task_id)? {
                    break 'publishing;
                }
            };
            link.observe(subscribers);
            let delivery = match batch.send() {
                Ok(delivery) => delivery,
                Err(_) if transport::termination_requested() => break 'publishing,
                Err(error) => return Err(error.into()),
            };
            waited += delivery.backpressure;
            if delivery.recipients > 0 {
                link.delivered();
                break true;
            }
            if !keep && matches!(source, Source::Rollout(_)) {
                // The connected store went away during the send: what its queue held is lost
                // with it, and so is this batch; the restarted store counts both as missing.
                break false;
            }
            // Not yet connected (or the store died): send it again under the same numbers.
            metrics.batches_resent.inc();
            batch = publisher.loan(seq, count)?;
            match &source {
                Source::Rollout(_) => batch.slots_mut().copy_from_slice(&outbox),
                Source::Fixed(list) => write_sample(batch.slots_mut(), list, seq),
            }
        };
        summary.backpressure += waited;
        metrics.backpressure_wait.inc_by(waited.as_secs_f64());
        if delivered {
            summary.published += count as u64;
            metrics.transitions_published.inc_by(count as u64);
            metrics.batches_published.inc();
        } else {
            metrics.transitions_lost.inc_by(count as u64);
        }
        metrics
            .batch_duration
            .observe(start.elapsed().as_secs_f64());
        seq += count as u64;
        if let Source::Rollout(rollout) = &mut source {
            summary.steps += count as u64;
            metrics.steps.inc_by(count as u64);
            for episode in rollout.drain_finished() {
                summary.episodes += 1;
                metrics.episodes.inc();
                metrics.episode_return.set(episode.ret);
                metrics.episode_aoi.set(episode.aoi);
                metrics.episode_power.set(episode.power_mw * 1e-3);
                metrics.episode_outages.set(episode.outages as f64);
            }
        }
    }
    tracing::info!(
        published = summary.published,
        steps = summary.steps,
        episodes = summary.episodes,
        "actor stopped"
    );
    Ok(summary)
}

/// What the actor knows of its connection to the store. iceoryx2 0.10 connects a subscriber to a
/// new publisher only when the subscriber next looks for data; until then a batch sent into its
/// full queue is dropped (0 recipients). A subscriber that has received more batches than its
/// queue holds has taken some, so it is connected, and stays so until it goes away.
#[derive(Debug)]
struct StoreLink {
    /// The subscriber's queue length: more batches than this delivered prove the connection.
    queue: usize,
    /// Subscribers attached when the last batch was sent.
    subscribers: SubscriberSet,
    /// Batches delivered since that set last changed.
    delivered: usize,
}

impl StoreLink {
    fn new(queue: usize) -> Self {
        Self {
            queue,
            subscribers: SubscriberSet::default(),
            delivered: 0,
        }
    }

    /// A new store (or a dead one cleaned up) changes the set: its connection is unproven.
    fn observe(&mut self, subscribers: SubscriberSet) {
        if subscribers != self.subscribers {
            self.subscribers = subscribers;
            self.delivered = 0;
        }
    }

    fn delivered(&mut self) {
        self.delivered = self.delivered.saturating_add(1);
    }

    /// True when a store is subscribed but the set differs from the one the last batch was sent
    /// to: a store that held batches may have died and been replaced.
    fn replaced(&self, now: SubscriberSet) -> bool {
        !self.subscribers.is_empty() && !now.is_empty() && now != self.subscribers
    }

    /// True once the store has provably taken batches from this publisher's queue.
    fn confirmed(&self) -> bool {
        !self.subscribers.is_empty() && self.delivered > self.queue
    }
}

/// Writes the replay sample's transitions `first_seq..` into `slots`.
fn write_sample(slots: &mut [TransitionSlot], sample: &[Transition], first_seq: u64) {
    let range = first_seq as usize..first_seq as usize + slots.len();
    for (slot, t) in slots.iter_mut().zip(&sample[range]) {
        slot.set_transition(t);
    }
}

/// True once the task's dataset is announced complete or a shutdown is announced.
fn announced(
    ready: &iceoryx2::port::subscriber::Subscriber<ipc::Service, transport::DatasetReady, ()>,
    shutdown: &iceoryx2::port::subscriber::Subscriber<ipc::Service, transport::Shutdown, ()>,
    task: u32,
) -> Result<bool, ActorError> {
    let mut done = false;
    while let Some(message) = ready
        .receive()
        .map_err(transport::receive_failed("receive a dataset announcement"))?
    {
        if message.schema_version == SCHEMA_VERSION && message.task == task {
            tracing::info!(
                transitions = message.transitions,
                "the task's dataset is complete"
            );
            done = true;
        }
    }
    Ok(transport::shutdown_requested(shutdown)? || done)
}
