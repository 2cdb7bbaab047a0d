//! Transitions as tensors: the normalised `(s, a, r, s')` columns every loss reads.
//!
//! A training set is turned into one [`Transitions`] once; minibatches are row selections of it
//! ([`Transitions::select`]), so sampling costs one `index_select` per column instead of re-encoding
//! transitions every step. There is no `done` column: an episode ends by a time limit, which is
//! never terminal, so every transition bootstraps (docs/MODEL.md section 5).

use std::borrow::Borrow;
use std::path::{Path, PathBuf};

use tch::Tensor;
use uavmeta_proto::config::{Config, TaskConfig, WorldConfig};
use uavmeta_proto::dataset::{DatasetError, DatasetReader, Transition};

/// A transition that does not fit the world the network is built for.
#[derive(Debug, thiserror::Error)]
pub enum TransitionsError {
    #[error("transition {index} (task {task}, actor {actor}, episode {episode}, step {step}): {what} has {got} values, expected {expected} (2 + world.devices)")]
    ObservationLength {
        index: usize,
        task: u32,
        actor: u32,
        episode: u64,
        step: u32,
        what: &'static str,
        got: usize,
        expected: usize,
    },
    #[error("transition {index} (task {task}, actor {actor}, episode {episode}, step {step}): action {action} is out of range, expected below {actions} (5 * world.devices)")]
    Action {
        index: usize,
        task: u32,
        actor: u32,
        episode: u64,
        step: u32,
        action: u16,
        actions: usize,
    },
    #[error("an empty set of transitions cannot form a batch")]
    Empty,
}

/// Why a task's shots could not be loaded from its dataset file.
#[derive(Debug, thiserror::Error)]
pub enum ShotsError {
    #[error(transparent)]
    Dataset(#[from] DatasetError),
    // The source is not in the message: `{:#}` prints the cause chain after it.
    #[error("{}", path.display())]
    Transitions {
        path: PathBuf,
        source: TransitionsError,
    },
}

/// A task's shots: as the dataset holds them, and encoded for the networks.
pub struct Shots {
    /// The raw transitions, from which the world is identified (`uavmeta_world::identify`).
    pub rows: Vec<Transition>,
    /// What the losses read.
    pub data: Transitions,
}

/// `shots` transitions of `task` drawn (seeded) from the dataset file `path`, encoded for the
/// config's world: what every offline learner trains on. The file must come from this world and
/// this task.
pub fn load_shots(
    config: &Config,
    task: &TaskConfig,
    path: &Path,
    shots: usize,
    seed: u64,
) -> Result<Shots, ShotsError> {
    let rows = DatasetReader::open_task(path, config, &task.name)?.shots(shots, seed)?;
    let data =
        Transitions::new(&rows, &config.world, config.learner.reward_scale).map_err(|source| {
            ShotsError::Transitions {
                path: path.to_path_buf(),
                source,
            }
        })?;
    Ok(Shots { rows, data })
}

/// Transitions as tensors on the CPU, one row each.
pub struct Transitions {
    /// `s`, normalised (x/(L-1), y/(L-1), A/aoi_max): [B, D] f32.
    pub obs: Tensor,
    /// `a`: [B] i64.
    pub actions: Tensor,
    /// `r * reward_scale`: [B] f32.
    pub rewards: Tensor,
    /// `s'`, normalised like `obs`: [B, D] f32.
    pub next_obs: Tensor,
}

impl Transitions {
    /// Encodes `transitions` for `world`, multiplying rewards by `reward_scale`
    /// (`learner.reward_scale`). Every transition is checked against the world's sizes first.
    /// Takes owned transitions or references (a replay buffer's sampled rows).
    pub fn new<T: Borrow<Transition>>(
        transitions: &[T],
        world: &WorldConfig,
        reward_scale: f64,
    ) -> Result<Transitions, TransitionsError> {
        if transitions.is_empty() {
            return Err(TransitionsError::Empty);
        }
        let d = world.layout().observation_len();
        let actions_n = world.layout().action_count();
        let scale = world.observation_scale();
        let rows = transitions.len();
        let mut obs = Vec::with_capacity(rows * d);
        let mut next_obs = Vec::with_capacity(rows * d);
        let mut actions = Vec::with_capacity(rows);
        let mut rewards = Vec::with_capacity(rows);
        for (index, t) in transitions.iter().enumerate() {
            let t: &Transition = t.borrow();
            for (what, values) in [("obs", &t.obs), ("next_obs", &t.next_obs)] {
                if values.len() != d {
                    return Err(TransitionsError::ObservationLength {
                        index,
                        task: t.task,
                        actor: t.actor,
                        episode: t.episode,
                        step: t.step,
                        what,
                        got: values.len(),
                        expected: d,
                    });
                }
            }
            if usize::from(t.action) >= actions_n {
                return Err(TransitionsError::Action {
                    index,
                    task: t.task,
                    actor: t.actor,
                    episode: t.episode,
                    step: t.step,
                    action: t.action,
                    actions: actions_n,
                });
            }
            obs.extend(t.obs.iter().zip(&scale).map(|(&v, &s)| f32::from(v) / s));
            next_obs.extend(
                t.next_obs
                    .iter()
                    .zip(&scale)
                    .map(|(&v, &s)| f32::from(v) / s),
            );
            actions.push(i64::from(t.action));
            rewards.push((f64::from(t.reward) * reward_scale) as f32);
        }
        let shape = [rows as i64, d as i64];
        Ok(Transitions {
            obs: Tensor::from_slice(&obs).view(shape),
            actions: Tensor::from_slice(&actions),
            rewards: Tensor::from_slice(&rewards),
            next_obs: Tensor::from_slice(&next_obs).view(shape),
        })
    }

    /// The data's value scale, `V_data = mean(r) / (1 - gamma)` (scaled rewards): the value of
    /// the behaviour policy's average step, were it repeated forever. `gamma` < 1.
    pub fn value_scale(&self, gamma: f64) -> f64 {
        self.rewards.mean(None).double_value(&[]) / (1.0 - gamma)
    }

    /// Number of transitions, B.
    pub fn len(&self) -> usize {
        self.actions.size()[0] as usize
    }

    /// Never true: [`Transitions::new`] refuses an empty set.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The rows of every batch in `parts`, one after the other: the union of several tasks'
    /// shots. `parts` must not be empty.
    pub fn concat<'a>(parts: impl IntoIterator<Item = &'a Transitions>) -> Transitions {
        let parts: Vec<&Transitions> = parts.into_iter().collect();
        let column = |pick: fn(&Transitions) -> &Tensor| {
            Tensor::cat(&parts.iter().map(|b| pick(b)).collect::<Vec<_>>(), 0)
        };
        Transitions {
            obs: column(|b| &b.obs),
            actions: column(|b| &b.actions),
            rewards: column(|b| &b.rewards),
            next_obs: column(|b| &b.next_obs),
        }
    }

    /// The rows `index` ([M] i64) of every column: a minibatch.
    pub fn select(&self, index: &Tensor) -> Transitions {
        Transitions {
            obs: self.obs.index_select(0, index),
            actions: self.actions.index_select(0, index),
            rewards: self.rewards.index_select(0, index),
            next_obs: self.next_obs.index_select(0, index),
        }
    }
}
