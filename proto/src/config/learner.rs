//! `[learner]`: docs/MODEL.md section 5's Q-network and the DQN / CQL settings every method shares.
//! Read by `uavmeta_learner` (offline training and fine-tuning) and by the evaluators
//! (`eval_episodes`, `eval_seed`).

use garde::Validate;
use serde::{Deserialize, Serialize};
use smart_default::SmartDefault;

use super::rules::{at_least, finite, positive, toml_seed, widths, within};
use crate::method::Algo;

/// docs/MODEL.md section 5: the Q-network and the DQN / CQL training settings shared by every
/// method.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, SmartDefault, Validate)]
#[serde(deny_unknown_fields, default)]
#[garde(allow_unvalidated)]
pub struct LearnerConfig {
    /// Hidden layer widths of the Q-network MLP.
    #[default(vec![256, 256])]
    #[garde(custom(widths()))]
    pub hidden: Vec<usize>,
    /// Discount factor gamma.
    #[default(0.99)]
    #[garde(custom(within(0.0..=1.0, "a discount in [0, 1]")))]
    pub gamma: f64,
    /// Rewards are multiplied by this before any loss sees them. A step costs around 100 (the
    /// AoI sum alone is K times the mean AoI), so unscaled Q-values reach -10^4 and Adam at
    /// lr = 1e-3 needs tens of thousands of steps just to move the output that far; 0.01 is the
    /// paper's own plotting scale (reward / 100). Reported Q-values are divided back.
    #[default(0.01)]
    #[garde(custom(positive("a finite number > 0")))]
    pub reward_scale: f64,
    /// CQL conservative weight alpha (eq. 8) of offline training and fine-tuning on a task's shots;
    /// MAML's losses and CQL-pretrain take `meta.alpha`.
    #[default(1.0)]
    #[garde(custom(finite(0.0.., "a finite number >= 0")))]
    pub alpha: f64,
    /// Offline algorithms a launch and the reproduction fine-tune on each unseen task beside
    /// `meta.inner_loss`, each from w0 and from a random init (`<algo>-w0`, `<algo>`); by default
    /// every algorithm registered as a baseline (`uavmeta_proto::method::ALGORITHMS`).
    #[default(Algo::baselines())]
    pub baselines: Vec<Algo>,
    /// Minibatch size.
    #[default(64)]
    #[garde(custom(at_least(1)))]
    pub batch_size: usize,
    /// Adam learning rate of offline training and fine-tuning (eta_outer, so every method
    /// shares the meta-learner's optimiser settings).
    #[default(1e-3)]
    #[garde(custom(positive("a learning rate > 0")))]
    pub lr: f64,
    /// Shots N of a launch's fine-tuning runs (the meta-learner's meta-tests and their
    /// baselines), drawn from the task's dataset with the run's seed; 0 = the whole dataset,
    /// `collect.transitions`. A larger `collect.transitions` with `shots = 500` gives the
    /// meta-train tasks more data while the unseen task keeps the paper's 500 shots
    /// (docs/EXPERIMENTS.md, C15). A launch refuses more than `collect.transitions`
    /// ([`super::Config::validate_launch`]); the one-shot commands take `--shots` instead.
    #[default(0)]
    pub shots: usize,
    /// Training epochs E.
    #[default(100)]
    pub epochs: usize,
    /// Gradient steps per epoch; 0 means one pass over the dataset, ceil(N / batch).
    #[default(0)]
    pub steps_per_epoch: usize,
    /// Gradient steps between hard target-network updates.
    #[default(100)]
    #[garde(custom(at_least(1)))]
    pub target_update_every: usize,
    /// Double DQN targets (d3rlpy's choice); off to match eq. 7.
    #[default(false)]
    pub double_dqn: bool,
    /// Huber instead of squared TD error (d3rlpy's choice); off to match eq. 7.
    #[default(false)]
    pub huber: bool,
    /// Discrete BCQ's tau (`--algo bcq`): an action is supported where its imitation
    /// probability is at least tau times the most likely action's (learner/src/bcq.rs).
    #[default(0.3)]
    #[garde(custom(within(0.0..=1.0, "a share in [0, 1]")))]
    pub bcq_threshold: f64,
    /// Guard against late collapse, from the offline data alone: training stops, keeping the
    /// previous epoch's network, once the mean Q of the data's own actions falls below
    /// `V_data - value_guard * |V_data|`, `V_data` = the shots' mean reward / (1 - gamma) (see
    /// `learner/src/train.rs`). 0 = no guard (the default: no algorithm's paper has one;
    /// docs/MODEL.md's departures).
    #[default(0.0)]
    #[garde(custom(finite(0.0.., "a finite margin >= 0 (0 = no guard)")))]
    pub value_guard: f64,
    /// Averaging of the trained network's weights over epochs, per epoch: the published network
    /// is the exponential moving average of the networks after each epoch (that the value guard
    /// let through), over about the last 1 / (1 - decay) epochs, bias-corrected so the init has
    /// no weight (`learner/src/train.rs`, `Average`). Evaluations, the returned network and the
    /// `final` checkpoint are the average; the gradient steps keep training Q itself. 0 = off
    /// (the default): the last epoch's network, whose return moves by up to several percent
    /// between epochs on 500 shots (docs/EXPERIMENTS.md, B3).
    #[default(0.0)]
    #[garde(custom(within(0.0..1.0, "a decay in [0, 1): 0 = no averaging")))]
    pub average_decay: f64,
    /// Model rows per epoch of a model-based algorithm (`dyna-cql`; `learner/src/model_rows.rs`):
    /// steps of its own policy rolled out in the world its shots identify, from the shots' own
    /// states, added to the shots, read by the TD term and weighing 0 in the conservative term.
    /// 2 000 is 4 model rows for each of the paper's 500 shots; at 10 000 its Q-values diverged
    /// on every seed of lambda-300 (docs/EXPERIMENTS.md, D24). No other algorithm reads it.
    #[default(2000)]
    #[garde(custom(at_least(1)))]
    pub model_rows: usize,
    /// How often a model-based algorithm's rollouts act at random rather than greedily.
    #[default(0.1)]
    #[garde(custom(within(0.0..=1.0, "a probability in [0, 1]")))]
    pub model_epsilon: f64,
    /// Monte-Carlo episodes of each evaluation of a greedy policy.
    #[default(20)]
    pub eval_episodes: usize,
    /// Seed of the evaluation episodes, the same for every method and epoch.
    #[default(12345)]
    #[garde(custom(toml_seed()))]
    pub eval_seed: u64,
}
