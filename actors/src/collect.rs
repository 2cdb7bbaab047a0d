//! Collecting one task's offline dataset (docs/MODEL.md section 4) with a behaviour policy.
//!
//! [`Collector`] rolls a policy out in the task's world and turns every step into a
//! `uavmeta_proto::dataset::Transition`; [`collect()`] drives it for `uavmeta collect`, writes the
//! dataset file in chunks of `run.transitions_per_message` transitions and saves the full config beside it
//! (`FILE.config.toml`), so a dataset always says which world, task, policy and seed made it.
//!
//! With `dqn-online`, the paper's behaviour policy, the dataset is instead sampled uniformly
//! without replacement from the replay buffer of an online DQN agent trained for
//! `collect.dqn.steps` steps, and written in the buffer's (time) order; the agent itself is saved
//! beside the file as a checkpoint ([`agent_path`]), the task's online reference.
//!
//! The i-th episode of a collector seeded S runs in the world of `episode_seed(S, i)`, as in
//! evaluation, so an episode's start cell and rain moves do not depend on what came before it.

use std::path::{Path, PathBuf};

use indicatif::ProgressBar;
use uavmeta_learner::checkpoint::{self, CheckpointError};
use uavmeta_learner::qnet::QNetwork;
use uavmeta_learner::transitions::TransitionsError;
use uavmeta_proto::config::{Config, ConfigError, TaskConfig, WorldConfig};
use uavmeta_proto::dataset::{
    sample_shots, DatasetError, DatasetHeader, DatasetWriter, Transition,
};
use uavmeta_proto::method::Method;

use crate::policy::dqn_online::OnlineDqn;
use uavmeta_world::heuristics::{PolicyError, PolicySpec};
use uavmeta_world::rollout::{episode_seed, record_step, Policy};
use uavmeta_world::world::World;

/// Why a dataset could not be collected.
#[derive(Debug, thiserror::Error)]
pub enum CollectError {
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error("{origin}: key `collect.policy`: {error}")]
    Policy { origin: String, error: PolicyError },
    #[error(transparent)]
    Dataset(#[from] DatasetError),
    #[error("{}: cannot write the dataset's config", path.display())]
    WriteConfig {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{}: cannot remove the online agent of the collection before", path.display())]
    RemoveAgent {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("online DQN training: {0}")]
    Train(#[from] TransitionsError),
    #[error("saving the online DQN agent")]
    Agent(#[from] CheckpointError),
    #[error(
        "{origin}: collect.transitions = {wanted}, but the online DQN agent's replay buffer will hold only \
         {available} transitions to sample from (the smaller of collect.dqn.steps and collect.dqn.replay_capacity): \
         raise both to at least {wanted}"
    )]
    ReplayTooSmall {
        origin: String,
        wanted: usize,
        available: usize,
    },
    #[error("stopped after {steps} online DQN steps: termination requested before the agent finished training")]
    Interrupted { steps: usize },
}

/// Rolls a behaviour policy out in one task's world, episode after episode, as transitions.
pub struct Collector {
    world: World,
    policy: Box<dyn Policy>,
    task: u32,
    actor: u32,
    seed: u64,
    /// The episode in progress (or the next one, between episodes).
    episode: u64,
    in_episode: bool,
    seq: u64,
}

impl Collector {
    /// Transitions of task `task_id` (`task` under `world`) made by `policy` as actor `actor`;
    /// `seed` fixes the episodes' worlds.
    pub fn new(
        world: &WorldConfig,
        task: &TaskConfig,
        task_id: u32,
        actor: u32,
        policy: Box<dyn Policy>,
        seed: u64,
    ) -> Self {
        Self {
            world: World::new(world, task, seed),
            policy,
            task: task_id,
            actor,
            seed,
            episode: 0,
            in_episode: false,
            seq: 0,
        }
    }

    /// Appends the next `n` transitions to `out`, continuing the episode in progress; an episode
    /// ends at the horizon with a `truncated` transition and the next one starts on demand.
    pub fn fill(&mut self, n: usize, out: &mut Vec<Transition>) {
        out.reserve(n);
        for _ in 0..n {
            if !self.in_episode {
                self.world
                    .reseed(episode_seed(self.seed, self.episode as usize));
                self.world.reset();
                self.in_episode = true;
            }
            let action = self.policy.act(&self.world);
            let t = Transition {
                task: self.task,
                actor: self.actor,
                episode: self.episode,
                seq: self.seq,
                ..record_step(&mut self.world, action)
            };
            self.seq += 1;
            if t.truncated {
                self.episode += 1;
                self.in_episode = false;
            }
            out.push(t);
        }
    }
}

/// What [`collect()`] wrote.
#[derive(Debug, Clone)]
pub struct CollectSummary {
    pub dataset: PathBuf,
    pub config: PathBuf,
    pub transitions: u64,
    /// Environment steps the behaviour policy took: the transitions themselves, or the online DQN
    /// agent's training steps whose replay buffer they were sampled from.
    pub steps: u64,
    pub bytes: u64,
}

/// Online DQN steps between progress updates.
const DQN_PROGRESS_STEPS: usize = 500;

/// The paper's dataset of one task: an online DQN agent (actor `actor`, seeded `seed`) trains for
/// `collect.dqn.steps` steps, reporting each block of training steps (and the agent, for its
/// exploration rate and returns) to `progress`, and
/// `collect.transitions` transitions are sampled from its final replay buffer, in time order. Also
/// returns the trained agent, the task's online reference. Training stops early with
/// [`CollectError::Interrupted`] when `progress` returns false.
pub fn online_dqn_dataset(
    config: &Config,
    task: &TaskConfig,
    task_id: u32,
    actor: u32,
    seed: u64,
    mut progress: impl FnMut(usize, &OnlineDqn) -> bool,
) -> Result<(Vec<Transition>, OnlineDqn), CollectError> {
    let mut agent = OnlineDqn::new(config, task, task_id, actor, seed);
    let mut left = config.collect.dqn.steps;
    while left > 0 {
        let n = left.min(DQN_PROGRESS_STEPS);
        agent.train_steps(n)?;
        if !progress(n, &agent) {
            return Err(CollectError::Interrupted {
                steps: agent.steps(),
            });
        }
        left -= n;
    }
    let sampled = replay_sample(config, &agent, seed)?;
    Ok((sampled, agent))
}

/// Logs which snapshot an agent kept, and samples its dataset: `collect.transitions` transitions
/// drawn from its final replay buffer, in time order.
fn replay_sample(
    config: &Config,
    agent: &OnlineDqn,
    seed: u64,
) -> Result<Vec<Transition>, CollectError> {
    if let (Some((step, ret)), Some(&(_, last))) =
        (agent.selected(), agent.selection_evaluations().last())
    {
        let (task, actor) = agent.task_and_actor();
        tracing::info!(
            task,
            actor,
            step,
            ret,
            last,
            "online DQN: kept the best snapshot"
        );
    }
    let buffer: Vec<Transition> = agent.replay_buffer().iter().cloned().collect();
    // A seed no collection episode uses, so the draw is independent of the agent's own.
    let mut sampled = sample_shots(
        &buffer,
        config.collect.transitions,
        episode_seed(seed, usize::MAX),
    )?;
    sampled.sort_unstable_by_key(|t| t.seq);
    Ok(sampled)
}

/// Where the config of dataset `out` is saved: `out` with `.config.toml` appended.
pub fn config_path(out: &Path) -> PathBuf {
    let mut name = out.as_os_str().to_owned();
    name.push(".config.toml");
    PathBuf::from(name)
}

/// Where the online DQN agent behind dataset `out` is saved, as a checkpoint: `online-dqn` in the
/// directory `out` with `.agent` appended (a directory, since task names may hold dots that a
/// checkpoint's extension would cut).
pub fn agent_path(out: &Path) -> PathBuf {
    let mut dir = out.as_os_str().to_owned();
    dir.push(".agent");
    PathBuf::from(dir).join(Method::OnlineDqn.name())
}

/// Collects task `task_name`'s dataset into `out` as `config.collect` says (policy, transitions,
/// seed) and saves `config` beside it. `progress` counts transitions, or the online DQN agent's
/// training steps.
pub fn collect(
    config: &Config,
    task_name: &str,
    out: &Path,
    progress: &ProgressBar,
) -> Result<CollectSummary, CollectError> {
    let policy_error = |error| CollectError::Policy {
        origin: config.origin.clone(),
        error,
    };
    let spec: PolicySpec = config.collect.policy.parse().map_err(policy_error)?;
    let task = config.task(task_name)?;
    let header = DatasetHeader::for_task(config, task_name)?;
    let wanted = config.collect.transitions;
    let seed = config.collect.seed;
    // Everything that can be refused is checked before a file is written.
    let rollout_policy = match &spec {
        PolicySpec::DqnOnline => {
            check_replay_window(config)?;
            None
        }
        spec => Some(crate::policy::build(spec, config, seed, Some(wanted)).map_err(policy_error)?),
    };

    // The agent an earlier collection saved last marks that dataset complete: it goes first, so a
    // kill from here on leaves nothing a reader takes for a finished dataset of this config.
    let agent_dir = agent_path(out).parent().map(Path::to_path_buf);
    if let Some(dir) = agent_dir.filter(|d| d.exists()) {
        std::fs::remove_dir_all(&dir).map_err(|source| CollectError::RemoveAgent {
            path: dir.clone(),
            source,
        })?;
    }
    let config_file = config_path(out);
    uavmeta_proto::fs::write_atomic(&config_file, config.to_toml_string().as_bytes()).map_err(
        |e| CollectError::WriteConfig {
            path: config_file.clone(),
            source: e.source,
        },
    )?;
    let mut writer = DatasetWriter::create(out, header)?;

    let steps = match rollout_policy {
        None => write_replay_sample(config, task, out, &mut writer, progress)?,
        Some(policy) => write_rollout(config, task, policy, &mut writer, progress)?,
    };
    writer.sync()?;
    Ok(CollectSummary {
        dataset: out.to_path_buf(),
        config: config_file,
        transitions: writer.transitions(),
        steps,
        bytes: writer.len_bytes(),
    })
}

/// Refuses a config whose online agent's replay buffer holds fewer transitions than its dataset
/// is to sample.
fn check_replay_window(config: &Config) -> Result<(), CollectError> {
    let (wanted, available) = (
        config.collect.transitions,
        config.collect.dqn.sampled_window(),
    );
    if available < wanted {
        return Err(CollectError::ReplayTooSmall {
            origin: config.origin.clone(),
            wanted,
            available,
        });
    }
    Ok(())
}

/// Trains the online DQN agent, writes the sample of its replay buffer and saves the agent beside
/// dataset `out`; returns its environment steps.
fn write_replay_sample(
    config: &Config,
    task: &TaskConfig,
    out: &Path,
    writer: &mut DatasetWriter,
    progress: &ProgressBar,
) -> Result<u64, CollectError> {
    progress.set_length(config.collect.dqn.steps as u64);
    let task_id = writer.header().task;
    let (sampled, agent) =
        online_dqn_dataset(config, task, task_id, 0, config.collect.seed, |n, _| {
            progress.inc(n as u64);
            true
        })?;
    write_sample(config, out, writer, &sampled, agent.q_network())?;
    Ok(agent.steps() as u64)
}

/// Writes a replay sample into `writer`, `run.transitions_per_message` transitions a chunk, and saves the
/// agent `q` that made it beside dataset `out`.
fn write_sample(
    config: &Config,
    out: &Path,
    writer: &mut DatasetWriter,
    sampled: &[Transition],
    q: &QNetwork,
) -> Result<(), CollectError> {
    for chunk in sampled.chunks(config.run.transitions_per_message) {
        writer.append(chunk)?;
    }
    checkpoint::save(&agent_path(out), q, &Method::OnlineDqn.name(), 1, config)?;
    Ok(())
}

/// Rolls `policy` out into `writer`, `run.transitions_per_message` transitions a chunk; returns the steps
/// taken.
fn write_rollout(
    config: &Config,
    task: &TaskConfig,
    policy: Box<dyn Policy>,
    writer: &mut DatasetWriter,
    progress: &ProgressBar,
) -> Result<u64, CollectError> {
    let wanted = config.collect.transitions;
    progress.set_length(wanted as u64);
    let task_id = writer.header().task;
    let mut collector =
        Collector::new(&config.world, task, task_id, 0, policy, config.collect.seed);
    let mut chunk = Vec::with_capacity(config.run.transitions_per_message);
    let mut left = wanted;
    while left > 0 {
        let n = left.min(config.run.transitions_per_message);
        chunk.clear();
        collector.fill(n, &mut chunk);
        writer.append(&chunk)?;
        progress.inc(n as u64);
        left -= n;
    }
    Ok(collector.seq)
}

#[cfg(test)]
mod tests {
    use uavmeta_proto::dataset::DatasetReader;

    use super::*;
    use uavmeta_world::heuristics::RandomPolicy;

    fn small_config(policy: &str) -> Config {
        let text = format!("[world]\ndevices = 4\nhorizon = 7\n[collect]\npolicy = \"{policy}\"\ntransitions = 30\nseed = 5\n[run]\ntransitions_per_message = 8");
        Config::from_toml_str(&text, "small.toml", &[]).unwrap()
    }

    #[test]
    fn transitions_chain_within_episodes_and_truncate_at_the_horizon() {
        let config = small_config("random");
        let task = &config.tasks[2];
        let mut collector =
            Collector::new(&config.world, task, 2, 1, Box::new(RandomPolicy::new(3)), 9);
        let mut data = Vec::new();
        // Two calls that split an episode: the second continues it.
        collector.fill(10, &mut data);
        collector.fill(11, &mut data);
        assert_eq!(data.len(), 21);
        for (i, t) in data.iter().enumerate() {
            assert_eq!((t.task, t.actor, t.seq), (2, 1, i as u64));
            assert_eq!((t.episode, t.step), ((i / 7) as u64, (i % 7) as u32));
            assert_eq!(t.truncated, i % 7 == 6);
            assert_eq!(t.obs.len(), 6);
            // AoI: each device ages by one or restarts at 1.
            for (before, after) in t.obs[2..].iter().zip(&t.next_obs[2..]) {
                assert!(*after == before + 1 || *after == 1, "{t:?}");
            }
        }
        for pair in data.windows(2) {
            if !pair[0].truncated {
                assert_eq!(
                    pair[0].next_obs, pair[1].obs,
                    "a step starts where the last one ended"
                );
            } else {
                assert!(
                    pair[1].obs[2..].iter().all(|&a| a == 1),
                    "a new episode starts with every AoI at 1"
                );
            }
        }
    }

    #[test]
    fn collect_writes_a_readable_reproducible_dataset_and_its_config() {
        let dir = tempfile::tempdir().unwrap();
        let config = small_config("eps:0.5");
        let (a, b) = (dir.path().join("a.uavds"), dir.path().join("b.uavds"));
        let summary = collect(&config, "lambda-300", &a, &ProgressBar::hidden()).unwrap();
        assert_eq!((summary.transitions, summary.steps), (30, 30));
        assert_eq!(summary.bytes, std::fs::metadata(&a).unwrap().len());

        let reader = DatasetReader::open(&a).unwrap();
        reader.check_world(&config).unwrap();
        assert_eq!(reader.header().task_name, "lambda-300");
        assert_eq!(reader.transitions().len(), 30);
        assert!(reader.transitions().iter().all(|t| t.task == 8));

        // The saved config alone reproduces the file byte for byte.
        let saved = Config::load(&config_path(&a), &[]).unwrap();
        assert_eq!(saved.collect, config.collect);
        collect(&saved, "lambda-300", &b, &ProgressBar::hidden()).unwrap();
        assert_eq!(std::fs::read(&a).unwrap(), std::fs::read(&b).unwrap());
    }

    #[test]
    fn a_replay_buffer_smaller_than_the_dataset_is_refused_before_writing() {
        let dir = tempfile::tempdir().unwrap();
        let mut config = small_config("dqn-online");
        config.collect.dqn.steps = 20;
        let out = dir.path().join("d.uavds");
        let error = collect(&config, "lambda-300", &out, &ProgressBar::hidden()).unwrap_err();
        assert!(
            matches!(
                error,
                CollectError::ReplayTooSmall {
                    wanted: 30,
                    available: 20,
                    ..
                }
            ),
            "{error}"
        );
        assert!(!out.exists());
    }

    #[test]
    fn dqn_online_datasets_are_distinct_replay_transitions_in_time_order() {
        let dir = tempfile::tempdir().unwrap();
        let mut config = small_config("dqn-online");
        config.collect.dqn.steps = 60;
        config.collect.dqn.replay_capacity = 50;
        config.collect.dqn.learning_starts = 10;
        config.learner.hidden = vec![8];
        config.learner.batch_size = 8;
        let (a, b) = (dir.path().join("a.uavds"), dir.path().join("b.uavds"));
        let summary = collect(&config, "lambda-300", &a, &ProgressBar::hidden()).unwrap();
        assert_eq!((summary.transitions, summary.steps), (30, 60));
        let data = DatasetReader::open(&a).unwrap().into_transitions();
        // From the buffer, which holds the last 50 of the 60 steps, strictly in time order.
        assert!(
            data.iter().all(|t| (10..60).contains(&t.seq)),
            "{:?}",
            data.iter().map(|t| t.seq).collect::<Vec<_>>()
        );
        assert!(data.windows(2).all(|w| w[0].seq < w[1].seq));
        assert!(data
            .iter()
            .all(|t| t.episode == t.seq / 7 && t.step as u64 == t.seq % 7));
        collect(&config, "lambda-300", &b, &ProgressBar::hidden()).unwrap();
        assert_eq!(std::fs::read(&a).unwrap(), std::fs::read(&b).unwrap());
    }
}
