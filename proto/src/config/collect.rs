//! `[collect]`: how each task's dataset is collected (docs/MODEL.md section 4), and
//! `[collect.dqn]`, the online DQN agent whose replay buffer is the paper's behaviour data. Read by
//! `uavmeta_actors` (the behaviour policies and the online agent), and by the launcher and
//! `uavmeta_reproduce` for the actors and agents they start.

use garde::Validate;
use serde::{Deserialize, Serialize};
use smart_default::SmartDefault;

use super::rules::{at_least, finite, positive, toml_seed, widths, within};

/// How each task's dataset is collected.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, SmartDefault, Validate)]
#[serde(deny_unknown_fields, default)]
#[garde(allow_unvalidated)]
pub struct CollectConfig {
    /// Behaviour policy: `dqn-online`, `random`, `stalest`, `greedy`, `eps:P` (stalest with
    /// probability 1-P, uniform random with probability P), `q:P:CHECKPOINT` (a saved Q-network's
    /// greedy policy, uniform random with probability P) or `actions:FILE`.
    #[default("dqn-online")]
    pub policy: String,
    /// Transitions kept per task (the paper's datasets hold 500).
    #[default(500)]
    #[garde(custom(at_least(1)))]
    pub transitions: usize,
    /// Actor processes per task in a launched run.
    #[default(1)]
    #[garde(custom(at_least(1)))]
    pub actors_per_task: usize,
    /// Base seed of the behaviour policies and their worlds.
    #[default(0)]
    #[garde(custom(toml_seed()))]
    pub seed: u64,
    /// The online DQN agent (`policy = "dqn-online"`).
    #[garde(dive)]
    pub dqn: OnlineDqnConfig,
}

/// `[collect.dqn]`: the online DQN agent (docs/MODEL.md section 5, "Online DQN"). The paper gives
/// no settings; these are the usual DQN stabilisers (CleanRL's and Dopamine's names where they
/// have one).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, SmartDefault, Validate)]
#[serde(deny_unknown_fields, default)]
#[garde(allow_unvalidated)]
pub struct OnlineDqnConfig {
    /// Environment steps it trains for before its replay buffer is sampled.
    #[default(30_000)]
    pub steps: usize,
    /// Replay buffer capacity.
    #[default(10_000)]
    #[garde(custom(at_least(1)))]
    pub replay_capacity: usize,
    /// Steps of uniform random actions before the first gradient step.
    #[default(1_000)]
    pub learning_starts: usize,
    /// Environment steps between gradient steps.
    #[default(1)]
    #[garde(custom(at_least(1)))]
    pub train_every: usize,
    /// Epsilon-greedy schedule: linear from `eps_start` to `eps_end` over `eps_decay_steps`;
    /// `eps_end` 0.01 as Rainbow and Dopamine (docs/EXPERIMENTS.md, section A).
    #[default(1.0)]
    #[garde(custom(within(0.0..=1.0, "a probability in [0, 1]")))]
    pub eps_start: f64,
    #[default(0.01)]
    #[garde(custom(within(0.0..=1.0, "a probability in [0, 1]")))]
    pub eps_end: f64,
    #[default(12_000)]
    pub eps_decay_steps: usize,
    /// Hidden layer widths of its Q-network (the offline learners' is `learner.hidden`).
    #[default(vec![256, 256])]
    #[garde(custom(widths()))]
    pub hidden: Vec<usize>,
    /// Adam learning rate (2e-4 brings every agent of the reproduction within 2% of the planner
    /// on the mean, docs/EXPERIMENTS.md A11; offline training's is `learner.lr`).
    #[default(2e-4)]
    #[garde(custom(positive("a finite rate > 0")))]
    pub lr: f64,
    /// The rate falls linearly from `lr` at `learning_starts` to `lr * lr_final_fraction` at
    /// `steps`; 1 keeps it constant.
    #[default(1.0)]
    #[garde(custom(within(0.0..=1.0, "a fraction in [0, 1] (1 = a constant rate)")))]
    pub lr_final_fraction: f64,
    /// Double DQN targets (van Hasselt et al.): the online network picks the next action, the
    /// target network values it.
    #[default(true)]
    pub double_dqn: bool,
    /// Huber (delta = 1) instead of the squared TD error.
    #[default(true)]
    pub huber: bool,
    /// Clip the gradient to this global L2 norm; 0 = no clipping.
    #[default(10.0)]
    #[garde(custom(finite(0.0.., "a finite norm >= 0 (0 = no clipping)")))]
    pub grad_clip_norm: f64,
    /// Gradient steps between hard target-network updates (docs/EXPERIMENTS.md, A2).
    #[default(2_000)]
    #[garde(custom(at_least(1)))]
    pub target_update_every: usize,
    /// Environment steps between exact evaluations of its greedy policy, from the step epsilon
    /// reaches `eps_end` to the last; the best of these snapshots is kept as its policy (as
    /// Stable-Baselines3's EvalCallback keeps the best model; docs/EXPERIMENTS.md, A5). Training,
    /// the buffer and the dataset are the same whatever this is; 0 = keep the last policy.
    #[default(0)]
    pub select_every: usize,
}

impl OnlineDqnConfig {
    /// How many of its last steps the dataset is sampled from: its final replay buffer,
    /// `min(steps, replay_capacity)` (the paper's "sampled from the replay buffer").
    pub fn sampled_window(&self) -> usize {
        self.steps.min(self.replay_capacity)
    }
}
