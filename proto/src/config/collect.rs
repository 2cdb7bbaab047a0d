//! `[collect]`: SPEC section 4's dataset collection and the online DQN behaviour policy. Read by
//! `uavmeta_actors` (the behaviour policies and the online agent), and by the launcher and
//! `uavmeta_reproduce` for the actors and agents they start.

use garde::Validate;
use serde::{Deserialize, Serialize};
use smart_default::SmartDefault;

use super::rules::{at_least, finite, positive, toml_seed, widths, within, Broken};

/// SPEC section 4: how each task's dataset is collected, and the online DQN behaviour policy.
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
    /// Environment steps the online DQN agent trains for before its replay buffer is sampled.
    #[default(30_000)]
    pub dqn_steps: usize,
    /// Replay buffer capacity of the online DQN agent.
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
    /// Epsilon-greedy schedule: linear from `eps_start` to `eps_end` over `eps_decay_steps`.
    /// `eps_end` 0.01 (Rainbow's and Dopamine's value): at 0.05 the agents of the AoI-dominated
    /// tasks (lambda 0 and 100) ended up to 7% below the heuristics on their worst seed, at 0.01
    /// within 1.7% (docs/EXPERIMENTS.md, section A).
    #[default(1.0)]
    #[garde(custom(within(0.0..=1.0, "a probability in [0, 1]")))]
    pub eps_start: f64,
    #[default(0.01)]
    #[garde(custom(within(0.0..=1.0, "a probability in [0, 1]")))]
    pub eps_end: f64,
    #[default(12_000)]
    pub eps_decay_steps: usize,
    /// Hidden layer widths of the online agent's Q-network (SPEC section 5's [256, 256]; the
    /// offline learners' network is `learner.hidden`).
    #[default(vec![256, 256])]
    #[garde(custom(widths()))]
    pub dqn_hidden: Vec<usize>,
    /// Adam learning rate of the online agent. Lower than offline training's: the agent takes
    /// tens of thousands of steps on a buffer that keeps changing, and at 1e-3 its greedy policy
    /// swings by a fifth of its return from one evaluation to the next.
    #[default(1e-4)]
    #[garde(custom(positive("a finite rate > 0")))]
    pub dqn_lr: f64,
    /// Double DQN targets for the online agent (van Hasselt et al.): the online network picks
    /// the next action, the target network values it.
    #[default(true)]
    pub dqn_double: bool,
    /// Huber (delta = 1) instead of the squared TD error for the online agent.
    #[default(true)]
    pub dqn_huber: bool,
    /// Clip the online agent's gradient to this global L2 norm; 0 = no clipping.
    #[default(10.0)]
    #[garde(custom(finite(0.0.., "a finite norm >= 0 (0 = no clipping)")))]
    pub dqn_grad_clip_norm: f64,
    /// Gradient steps between the online agent's hard target-network updates. Slower than the
    /// usual 500: at lambda = 0 the best and second-best actions differ by a fraction of a percent
    /// of Q, and a target refreshed every 500 steps moves more than that (docs/EXPERIMENTS.md, A2).
    #[default(2_000)]
    #[garde(custom(at_least(1)))]
    pub dqn_target_update_every: usize,
    /// Steps in the online agent's bootstrapped return: the target of a transition is
    /// `sum_{k<n} gamma^k r_{t+k} + gamma^n V(s_{t+n})`, cut short at the episode's end (the
    /// horizon, which still bootstraps) and at the newest transition of the buffer. 1 is eq. 7.
    /// The dataset stays one-step transitions whatever this is.
    #[default(1)]
    pub dqn_n_step: usize,
    /// The online agent's learning rate falls linearly from `dqn_lr` at `learning_starts` to
    /// `dqn_lr * dqn_lr_final_fraction` at `dqn_steps`; 1 keeps it constant.
    #[default(1.0)]
    #[garde(custom(within(0.0..=1.0, "a fraction in [0, 1] (1 = a constant rate)")))]
    pub dqn_lr_final_fraction: f64,
    /// Environment steps between exact evaluations of the online agent's greedy policy (over
    /// every start cell; `learner.eval_episodes` Monte-Carlo episodes of its own seed where the
    /// rain moves), from the step epsilon reaches `eps_end` to `dqn_steps`, the last step always
    /// among them. The agent's policy, saved as the task's online reference, is the best of those
    /// snapshots rather than the last, as an online learner with a simulator may choose
    /// (Stable-Baselines3's EvalCallback): the last iterate's return moves by 1-3% between
    /// neighbouring evaluations (docs/EXPERIMENTS.md, A5). Training, and so the replay buffer and
    /// the dataset sampled from it, is the same whatever this is. 0 = keep the last policy.
    #[default(0)]
    pub dqn_select_every: usize,
    /// The dataset is sampled from the newest this many transitions of the agent's final replay
    /// buffer; 0 = the whole buffer (the paper's "sampled from the replay buffer").
    #[default(0)]
    pub sample_newest: usize,
    /// Where a command trains several online agents (`uavmeta reproduce`'s datasets), up to this
    /// many train as one population: stacked networks stepped and updated as one computation
    /// (`actors::policy::dqn_population`). A population of one is the single agent bit for bit;
    /// larger ones give each member its separate run up to float rounding. 1 (one at a time) is
    /// the fastest on CPU, where a [256, 256] step already runs at 60-70% of its matrix
    /// products' floor; stacking is for accelerators (docs/BENCHMARKS.md, "Populations").
    #[default(1)]
    #[garde(custom(at_least(1)))]
    pub population: usize,
}

impl CollectConfig {
    /// How many of the online agent's last steps its dataset is sampled from: the final replay
    /// buffer (`min(dqn_steps, replay_capacity)`), cut to its newest `sample_newest` when set.
    pub fn sampled_window(&self) -> usize {
        let held = self.dqn_steps.min(self.replay_capacity);
        match self.sample_newest {
            0 => held,
            n => held.min(n),
        }
    }

    /// The online agent's return looks at most one episode of `horizon` steps ahead.
    pub(super) fn check_n_step(&self, horizon: u32) -> Result<(), Broken> {
        match (1..=horizon as usize).contains(&self.dqn_n_step) {
            true => Ok(()),
            false => Err(Broken::new(
                "collect.dqn_n_step",
                &self.dqn_n_step,
                format!("a step count in [1, world.horizon = {horizon}]"),
            )),
        }
    }
}
