//! The actor process (`uavmeta actor --run R --task T --policy P [--seed S]`): rolls a behaviour
//! policy out in one task's world and publishes its transitions to the store.
//!
//! Each step is written straight into its fixed-layout slot of a batch loaned in shared memory
//! (`proto::transport`), `run.transitions_per_message` steps per batch, numbered 0, 1, 2, ... by a per-actor
//! sequence number, and the batch is sent without a further copy. When the store's buffer is full
//! the actor waits (backpressure); while no store is subscribed it holds its written batch and
//! sends it once one is; both waits are counted. The actor keeps what the store has not yet
//! acknowledged as appended and sends it again, in order, to a store that replaced a killed one
//! (`delivery`), so a store crash loses nothing. With `dqn-online` (the paper's behaviour policy)
//! the actor first trains an online DQN agent and then publishes `collect.transitions`
//! transitions sampled from its replay buffer, after saving the agent's network as the task's
//! `online-dqn` checkpoint (the "online" reference).
//!
//! An actor's identity is a hash of its task, policy and seed: the same actor restarted (by the
//! launcher after a crash) makes the same transitions under the same numbers, and the store keeps
//! one copy. Two actors with different seeds add different data, so actors can be started and
//! stopped by hand at any time. An actor ends when its task's dataset is announced complete, when
//! a shutdown is announced, after `--transitions N`, or on SIGINT/SIGTERM.

use std::time::{Duration, Instant};

use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use uavmeta_actors::collect::{online_dqn_dataset, CollectError};
use uavmeta_learner::checkpoint::{self, CheckpointError};
use uavmeta_proto::config::{Config, ConfigError, TaskConfig};
use uavmeta_proto::dataset::Transition;
use uavmeta_proto::method::Method;
use uavmeta_proto::payload::{DatasetReady, Shutdown, TransitionSlot, SCHEMA_VERSION};
use uavmeta_proto::stats::EpisodeMetrics;
use uavmeta_world::heuristics::{PolicyError, PolicySpec};
use uavmeta_world::rollout::{episode_seed, EpisodeTally, Policy};
use uavmeta_world::world::World;

use crate::liveness;
use crate::metrics::MetricsError;
use crate::process::Process;
use crate::run_dir::RunDir;
use crate::transport::{self, TransitionPublisher, TransportError};
use delivery::{write_sample, Sender, Sent};

mod delivery;
mod metrics;

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
    #[error(
        "the store acknowledged actor {actor:08x} of task {task} up to sequence number \
         {acknowledged}, but this actor has sent numbers below {sent} only: another publisher \
         sends under this actor's id (a second actor of the same task, policy and seed, or a \
         forged id), and the store would drop this actor's own transitions as duplicates"
    )]
    AckedBeyondSent {
        task: u32,
        actor: u32,
        acknowledged: u64,
        sent: u64,
    },
    #[error(
        "--task {task}: host `{host}` may not serve it; the learner host's tunnel.hosts lets it \
         serve {served:?}"
    )]
    NotServed {
        task: String,
        host: String,
        served: Vec<String>,
    },
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
        crate::run_dir::fnv1a(key.as_bytes()) as u32
    }

    /// The process name: node, port file and metrics snapshot.
    pub fn process_name(&self) -> String {
        format!("{PROCESS_PREFIX}{}-{:08x}", self.task, self.actor_id())
    }
}

/// How every actor's process name begins.
pub const PROCESS_PREFIX: &str = "actor-";

/// What an actor is doing, exported as `uavmeta_actor_phase{phase}` for the launcher's display
/// and dashboards.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Phase {
    /// Training its online DQN agent (`dqn-online` only), before it sends anything.
    Training,
    /// Sending transitions to the store.
    Sending,
    /// Everything sent; waiting for the store to acknowledge it or announce the dataset.
    Sent,
}

impl Phase {
    pub const ALL: [Phase; 3] = [Phase::Training, Phase::Sending, Phase::Sent];

    /// The `phase` label value.
    pub fn name(self) -> &'static str {
        match self {
            Phase::Training => "training",
            Phase::Sending => "sending",
            Phase::Sent => "sent",
        }
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

/// The transitions an actor publishes at most: `--transitions`, else a replayed action list's
/// share of the dataset (`collect.transitions`: the list must hold that many, and the actor stops
/// there rather than run past its end), else no limit.
fn transition_limit(options: &ActorOptions, config: &Config) -> u64 {
    match (options.transitions, &options.policy) {
        (Some(n), _) => n,
        (None, PolicySpec::Actions(_)) => config.collect.transitions as u64,
        (None, _) => u64::MAX,
    }
}

/// On a remote host, `task` must be one the learner host lets it serve (`tunnel.hosts`, which
/// `uavmeta tunnel join` copies from the handshake): its transitions would reach no one.
fn check_served(run: &RunDir, config: &Config, task: &str) -> Result<(), ActorError> {
    let Some(host) = run.host() else {
        return Ok(());
    };
    let served: Vec<String> = (config.tunnel.tasks_of(host, &config.tasks).iter())
        .map(|t| t.name.clone())
        .collect();
    match served.iter().any(|t| t == task) {
        true => Ok(()),
        false => Err(ActorError::NotServed {
            task: task.into(),
            host: host.into(),
            served,
        }),
    }
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
    check_served(run, config, &task.name)?;
    let actor = options.actor_id();
    let process = Process::start(run, config, &options.process_name())?;
    let (node, names) = (&process.node, &process.names);
    let metrics = metrics::ActorMetrics::new(&task.name, actor);
    let _server = process.serve_metrics(run, config, metrics.registry.clone())?;
    let service = transport::transition_service(node, names, &task.name, &config.run)?;
    let publisher = TransitionPublisher::new(&service, run, config, task_id, actor)?;
    let ready =
        transport::control_subscriber(&transport::dataset_ready_service(node, names, config)?)?;
    let mut summary = ActorSummary {
        actor,
        ..ActorSummary::default()
    };
    tracing::info!(task = %task.name, actor = format!("{actor:08x}"), policy = %options.policy, seed = options.seed, "actor started");

    let control = Control {
        process: &process,
        ready,
        task: task_id,
    };
    let Some(source) = start_source(
        run,
        config,
        options,
        &task,
        &metrics,
        &control,
        &mut summary,
    )?
    else {
        return Ok(summary);
    };

    let acks = transport::ack_subscriber(&transport::ack_service(
        node,
        names,
        &task.name,
        &config.run,
    )?)?;
    let mut feed = Feed {
        source,
        publisher: &publisher,
        sender: Sender::new(&publisher, acks, (task_id, actor), &metrics),
        metrics: &metrics,
        seq: 0,
        limit: transition_limit(options, config),
        summary,
    };
    feed.send_all(&control)?;
    let mut summary = feed.summary;
    summary.published = feed.sender.published();
    tracing::info!(
        published = summary.published,
        steps = summary.steps,
        episodes = summary.episodes,
        "actor stopped"
    );
    Ok(summary)
}

/// The actor's sending loop: where its transitions come from, the sender they go through, and
/// how far it got.
struct Feed<'a, 's> {
    source: Source,
    publisher: &'a TransitionPublisher<'s>,
    sender: Sender<'a, 's>,
    metrics: &'a metrics::ActorMetrics,
    /// The number of the next transition to send.
    seq: u64,
    /// Stop after this many transitions (`--transitions`).
    limit: u64,
    summary: ActorSummary,
}

impl<'a, 's> Feed<'a, 's> {
    /// Sends batch after batch until a stop is requested, or the limit is reached and stored.
    fn send_all(&mut self, control: &Control) -> Result<(), ActorError> {
        let mut next_look = Instant::now();
        let mut phase = Phase::Sending;
        self.metrics.set_phase(phase);
        loop {
            // Signals and announcements are looked at every CONTROL_EVERY, not every batch: a
            // look costs a syscall and two receives, a batch of 64 steps a few microseconds.
            if Instant::now() >= next_look {
                if control.stop_requested(Duration::ZERO)? {
                    return Ok(());
                }
                next_look = Instant::now() + CONTROL_EVERY;
            }
            self.sender.read_acks()?;
            if let Source::Fixed(_) = &self.source {
                // A store that went away took what it held unwritten with it, and a replay
                // sample, unlike a rollout, has no more data to come: send it again from what is
                // stored.
                if let Some(to) = self.sender.rewind_if_store_changed() {
                    self.seq = to;
                }
            }
            let count = self.next_count();
            let now = if count == 0 {
                Phase::Sent
            } else {
                Phase::Sending
            };
            if now != phase {
                phase = now;
                self.metrics.set_phase(phase);
            }
            if count == 0 {
                if self.seq >= self.limit {
                    tracing::info!(published = self.seq, "published the requested transitions");
                    if self.sender.wait_until_stored(control)? {
                        tracing::info!("the store has acknowledged them all");
                    }
                    return Ok(());
                }
                // Everything sampled is sent; stay until the store announces the dataset.
                liveness::keep_running(&control.process.node, POLL);
                continue;
            }
            let start = Instant::now();
            let sent = self.send_batch(count, control)?;
            let waited = self.sender.take_waited();
            self.summary.backpressure += waited;
            self.metrics.backpressure_wait.inc_by(waited.as_secs_f64());
            match sent {
                Sent::Delivered => {}
                Sent::Rewind(to) => {
                    self.seq = to;
                    continue;
                }
                Sent::Stopped => return Ok(()),
            }
            self.metrics
                .batch_duration
                .observe(start.elapsed().as_secs_f64());
            self.seq += count as u64;
            self.count_steps(count);
        }
    }

    /// Transitions the next batch holds: 0 once everything there is to send is sent.
    fn next_count(&self) -> usize {
        let left = match &self.source {
            Source::Rollout(_) => self.limit - self.seq,
            Source::Fixed(list) => (self.limit.min(list.len() as u64)).saturating_sub(self.seq),
        };
        left.min(self.publisher.batch_size() as u64) as usize
    }

    /// Loans a batch of `count` slots from `seq` on, writes the source's transitions into it and
    /// sends it.
    fn send_batch(&mut self, count: usize, control: &Control) -> Result<Sent, ActorError> {
        let publisher: &'a TransitionPublisher<'s> = self.publisher;
        let mut batch = publisher.loan(self.seq, count)?;
        match &mut self.source {
            Source::Rollout(rollout) => {
                for slot in batch.slots_mut() {
                    rollout.write_step(slot);
                }
                self.sender.send_rollout(batch, control)
            }
            Source::Fixed(list) => {
                write_sample(batch.slots_mut(), list, self.seq);
                self.sender.send_sample(batch, list, control)
            }
        }
    }

    /// After a rollout's batch is sent: counts its steps and the episodes it finished.
    fn count_steps(&mut self, count: usize) {
        if let Source::Rollout(rollout) = &mut self.source {
            self.summary.steps += count as u64;
            self.metrics.steps.inc_by(count as u64);
            for episode in rollout.drain_finished() {
                self.summary.episodes += 1;
                self.metrics.observe_episode(&episode);
            }
        }
    }
}

/// What the actor sends: a rollout of its behaviour policy, or for `dqn-online` the replay
/// sample of an online DQN agent it trains first (saving the agent as the task's reference).
/// `None` if stopped while training.
fn start_source(
    run: &RunDir,
    config: &Config,
    options: &ActorOptions,
    task: &TaskConfig,
    metrics: &metrics::ActorMetrics,
    control: &Control,
    summary: &mut ActorSummary,
) -> Result<Option<Source>, ActorError> {
    let task_id = config.task_id(&task.name)? as u32;
    let actor = options.actor_id();
    let source = match &options.policy {
        PolicySpec::DqnOnline => {
            metrics.set_phase(Phase::Training);
            let dqn = metrics::OnlineDqnMetrics::new(&metrics.registry);
            // A dataset already complete (a resumed launch, or another actor's) ends training
            // too: the agent would only make transitions the store no longer takes.
            let mut stop = Ok(false);
            let trained =
                online_dqn_dataset(config, task, task_id, actor, options.seed, |n, agent| {
                    metrics.steps.inc_by(n as u64);
                    dqn.observe(agent);
                    stop = control.stop_requested(Duration::ZERO);
                    matches!(stop, Ok(false))
                });
            stop?;
            match trained {
                Ok((sample, agent)) => {
                    summary.steps = agent.steps() as u64;
                    // The reference the meta-learner announces once the dataset is stored.
                    checkpoint::save(
                        &run.checkpoint(Method::OnlineDqn, task, 1),
                        agent.q_network(),
                        &Method::OnlineDqn.name(),
                        1,
                        config,
                    )?;
                    Source::Fixed(sample)
                }
                Err(CollectError::Interrupted { steps }) => {
                    tracing::info!(steps, "stopped while training the online DQN agent");
                    return Ok(None);
                }
                Err(error) => return Err(error.into()),
            }
        }
        spec => {
            // A replayed list must hold the transitions the actor will publish, when bounded.
            let limit = usize::try_from(transition_limit(options, config))
                .ok()
                .filter(|&n| n != usize::MAX);
            let policy = uavmeta_actors::policy::build(spec, config, options.seed, limit).map_err(
                |error| ActorError::Policy {
                    spec: spec.to_string(),
                    error,
                },
            )?;
            Source::Rollout(Box::new(Rollout::new(config, task, policy, options.seed)))
        }
    };
    Ok(Some(source))
}

/// The actor's way of hearing that it should stop: signals, its task's dataset announced
/// complete, or a shutdown.
struct Control<'p> {
    process: &'p Process,
    ready: Subscriber<ipc::Service, DatasetReady, ()>,
    task: u32,
}

impl Control<'_> {
    /// Waits up to `cycle` for a signal, then reads the announcements; true if the actor should
    /// stop.
    fn stop_requested(&self, cycle: Duration) -> Result<bool, ActorError> {
        Ok(!liveness::keep_running(&self.process.node, cycle)
            || announced(&self.ready, &self.process.shutdown, self.task)?)
    }
}

/// True once the task's dataset is announced complete or a shutdown is announced.
fn announced(
    ready: &Subscriber<ipc::Service, DatasetReady, ()>,
    shutdown: &Subscriber<ipc::Service, Shutdown, ()>,
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
