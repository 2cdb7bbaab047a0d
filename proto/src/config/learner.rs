//! `[learner]`: SPEC section 5's Q-network and the DQN / CQL settings every method shares. Read by
//! `uavmeta_learner` (offline training and fine-tuning) and by the evaluators (`eval_episodes`,
//! `eval_seed`).

use std::fmt;

use garde::Validate;
use serde::{Deserialize, Serialize};
use smart_default::SmartDefault;

use super::rules::{at_least, finite, positive, toml_seed, widths, within, Broken};

/// SPEC section 5: the Q-network and the DQN / CQL training settings shared by every method.
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
    /// Minibatch size.
    #[default(64)]
    #[garde(custom(at_least(1)))]
    pub batch: usize,
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
    /// Guard against late collapse, from the offline data alone: training stops, keeping the
    /// previous epoch's network, once the mean Q of the data's own actions falls below
    /// `V_data - value_guard * |V_data|`, `V_data` = the shots' mean reward / (1 - gamma) (see
    /// `learner/src/train.rs`). 0 = no guard.
    #[default(0.5)]
    #[garde(custom(finite(0.0.., "a finite margin >= 0 (0 = no guard)")))]
    pub value_guard: f64,
    /// Averaging of the trained network's weights over epochs: the published network is the
    /// exponential moving average of the networks after each epoch (that the value guard let
    /// through), over about the last 1 / (1 - decay) epochs, bias-corrected so the init has no
    /// weight (`learner/src/train.rs`, `Average`). Evaluations, the returned network and the
    /// `final` checkpoint are the average; the gradient steps keep training Q itself. 0 = off
    /// (SPEC): the last epoch's network, whose return moves by up to several percent between
    /// epochs on 500 shots (docs/EXPERIMENTS.md, B3).
    #[default(0.0)]
    #[garde(custom(within(0.0..1.0, "a decay in [0, 1): 0 = no averaging")))]
    pub average_decay: f64,
    /// L2-SP (Li, Grandvalet & Davoine 2018): `init_penalty / 2 * ||w - w_init||^2` added to the
    /// loss of every offline training and fine-tuning run (`uavmeta train`, meta-test, a
    /// launch's fine-tunings; not multi-task pretraining), `w_init` the run's init, so where the
    /// shots are silent the network stays near it. 0 = off (SPEC): 0.03 fixed CQL-pretrain's late
    /// drift on lambda-300 and nothing on held-out tasks (docs/EXPERIMENTS.md, D5).
    #[default(0.0)]
    #[garde(custom(finite(0.0.., "a finite number >= 0 (0 = off)")))]
    pub init_penalty: f64,
    /// Offline selection of the published network by fitted Q evaluation on the shots
    /// (`learner/src/fqe.rs`): at the start, every this many epochs and at the last epoch the
    /// network a run would publish is scored by FQE, and from then on the run publishes the
    /// best-scoring one so far, the init included (its rows' returns and its `final` checkpoint
    /// are that network's). The scores go to `select.csv` beside the measured return of each
    /// candidate. 0 = off (SPEC): on 500 shots FQE does not rank this world's policies (Kendall
    /// tau 0.04 among fine-tuned epochs): it catches a drift of 20% and more, and costs as much
    /// elsewhere (docs/EXPERIMENTS.md, D4).
    #[default(0)]
    pub select_every: usize,
    /// Gradient steps of each FQE estimate (`learner.select_every`). More is not better on 500
    /// shots: at 10 000 the fit diverges (docs/EXPERIMENTS.md, D4).
    #[default(3000)]
    #[garde(custom(at_least(1)))]
    pub fqe_steps: usize,
    /// Gradient steps between FQE's hard target updates: a backup every this many steps, so
    /// `fqe_steps / fqe_target_update_every` backups reach that many steps into the future.
    #[default(10)]
    #[garde(custom(at_least(1)))]
    pub fqe_target_update_every: usize,
    /// Adam learning rate of FQE's fit, its own so that a run's rate does not change its judge.
    #[default(1e-3)]
    #[garde(custom(positive("a learning rate > 0")))]
    pub fqe_lr: f64,
    /// Conservative weight of FQE's own fit (eq. 8's term on `F`): pushes `F` down on actions the
    /// shots never took, so a policy that leaves the data is not valued by extrapolation. Plain
    /// FQE (0) valued inits that leave the data far above what they return and chose worse than
    /// the last epoch on 12 of 20 runs (4 of 6 with these backups); with 1, 9 better and 6 worse
    /// (docs/EXPERIMENTS.md, D4).
    #[default(1.0)]
    #[garde(custom(finite(0.0.., "a finite number >= 0")))]
    pub fqe_alpha: f64,
    /// Where a command fine-tunes several runs of one shape (the fine-tuning runs of
    /// `uavmeta reproduce`'s figures, the methods the launch's meta-learner fine-tunes on a task),
    /// up to this many train as one population: stacked networks updated as one computation
    /// (`learner::train_population`). A population of one is the single run bit for bit; larger
    /// ones give each member its separate run up to float rounding. 1 is the fastest on CPU
    /// (docs/BENCHMARKS.md, "Populations"); stacking is for accelerators (`run.device`).
    #[default(1)]
    #[garde(custom(at_least(1)))]
    pub population: usize,
    /// Monte-Carlo episodes of each evaluation of a greedy policy.
    #[default(20)]
    pub eval_episodes: usize,
    /// Seed of the evaluation episodes, the same for every method and epoch.
    #[default(12345)]
    #[garde(custom(toml_seed()))]
    pub eval_seed: u64,
}

/// A Q-learning loss: MAML's inner loss (`meta.inner_loss`), offline training's (`uavmeta train
/// --algo`) and each fine-tuned method's.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Loss {
    /// Paper eq. 8.
    Cql,
    /// Paper eq. 7 on a fixed dataset: the baseline that overestimates.
    Dqn,
}

impl LearnerConfig {
    /// The selection by FQE and the init penalty run in single runs only: a population's
    /// lockstep has neither.
    pub(super) fn check_single_run_keys(&self) -> Result<(), Broken> {
        if self.population == 1 {
            return Ok(());
        }
        let expected = format!(
            "0 while learner.population = {} (single runs only: set learner.population = 1)",
            self.population
        );
        if self.select_every != 0 {
            return Err(Broken::new(
                "learner.select_every",
                &self.select_every,
                expected,
            ));
        }
        if self.init_penalty != 0.0 {
            return Err(Broken::new(
                "learner.init_penalty",
                &self.init_penalty,
                expected,
            ));
        }
        Ok(())
    }
}

impl fmt::Display for Loss {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Loss::Cql => "cql",
            Loss::Dqn => "dqn",
        })
    }
}

impl std::str::FromStr for Loss {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "cql" => Ok(Loss::Cql),
            "dqn" => Ok(Loss::Dqn),
            _ => Err(format!("`{s}`: expected `cql` or `dqn`")),
        }
    }
}
