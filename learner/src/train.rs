//! Offline training of a Q-network on a fixed set of transitions, with any registered algorithm.
//!
//! One run: Adam(`learner.lr`) on the network, `learner.epochs` epochs of `learner.steps_per_epoch`
//! gradient steps (0 = one pass, ceil(N / batch)), each on a minibatch drawn from the N shots by a
//! seeded shuffle, and a hard target-network update every `learner.target_update_every` gradient
//! steps. After every epoch the greedy policy is evaluated through [`EvaluatePolicy`] (the world
//! lives in `uavmeta-actors`, which implements it) and one row is written: to a table on stderr,
//! to `train.csv` in the output directory, and to the returned list. The run reports its last
//! epoch's network, as d3rlpy and CORL do; nothing that picks or trains it reads the evaluation.
//! Two options that read only the shots: weight averaging (`learner.average_decay`, [`Average`])
//! and a guard against late collapse (`learner.value_guard`, [`ValueGuard`]). A model-based
//! algorithm (`dyna-cql`) adds rollouts in the world its shots identify to each epoch's shots
//! ([`crate::model_rows`]).

use std::path::Path;
use std::time::Instant;

use indicatif::ProgressBar;
use rand::seq::SliceRandom;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use tch::Tensor;
use uavmeta_proto::config::{Config, LearnerConfig};
use uavmeta_proto::dataset::Transition;
use uavmeta_proto::method::Algo;
use uavmeta_proto::stats::PolicyMetrics;

use crate::algorithm::{self, OfflineAlgorithm, Terms};
use crate::checkpoint::{self, CheckpointError};
use crate::cql::conservative_term;
use crate::dqn::{q_taken, TdConfig};
use crate::model_rows::ModelRows;
use crate::optim::FusedAdam;
use crate::progress::{progress_bar, CsvLog, OnStep};
use crate::qnet::{q_values, QNetwork};
use crate::transitions::Transitions;

/// Measures the greedy policy of a Q-network on the true environment.
///
/// `train` calls [`EvaluatePolicy::evaluate`] once per epoch with the network the run publishes
/// after it, each a new network (after a value-guard stop no call is made), so an evaluator may
/// count epochs or checkpoint what it is given (the launch's does).
pub trait EvaluatePolicy {
    fn evaluate(&mut self, q: &QNetwork) -> PolicyMetrics;

    /// About `ask.rows` steps of `q`'s policy in the world the run's shots identify (never the
    /// true world), from the shots' own states, acting uniformly at random with probability
    /// `ask.epsilon` (draws seeded `ask.seed`) and greedily otherwise: every step as a
    /// transition, rewards from the model. What a model-based algorithm adds to the shots
    /// ([`crate::model_rows`]). `None` where the shots identify no world. Required, so that a
    /// wrapper cannot drop its inner evaluator's model by forgetting it.
    fn rollouts(&mut self, q: &QNetwork, ask: Rollouts) -> Option<Vec<Transition>>;
}

/// What [`EvaluatePolicy::rollouts`] is asked for.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Rollouts {
    /// About how many steps.
    pub rows: usize,
    /// How often an action is uniformly random rather than greedy.
    pub epsilon: f64,
    /// Seed of those draws.
    pub seed: u64,
}

#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    #[error(transparent)]
    Csv(#[from] uavmeta_proto::fs::FileError),
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
}

/// One run's settings beyond the config's `[learner]` section.
pub struct TrainOptions<'a> {
    pub algorithm: Algo,
    /// The run's config: `[learner]` drives training, the whole is saved beside checkpoints.
    pub config: &'a Config,
    /// Seed of the minibatch order.
    pub seed: u64,
    /// Where `train.csv` and the `final` checkpoint go; `None` writes neither.
    pub out_dir: Option<&'a Path>,
    /// Draw a progress bar on stderr (when it is a terminal) and print the per-epoch table there;
    /// off for runs inside a larger job (`uavmeta reproduce` fine-tunes hundreds of them).
    pub progress: bool,
    /// Called at every gradient step.
    pub on_step: OnStep,
}

/// One epoch's figures.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct EpochRow {
    pub epoch: usize,
    /// Gradient steps so far.
    pub steps: usize,
    /// Mean over the epoch's steps of the TD loss (eq. 7, on scaled rewards).
    pub td_loss: f64,
    /// Mean over the epoch's steps of `mean(logsumexp_a Q - Q(s, a_data))` (eq. 8's term, before
    /// alpha); reported for DQN too, where it shows how far unseen actions drift above seen ones.
    pub conservative_loss: f64,
    /// Mean over the epoch's minibatch states of `max_a Q(s, a)`, in unscaled reward units: the
    /// value the greedy policy believes it gets, comparable to its measured return.
    pub mean_q: f64,
    /// The greedy policy on the true environment after the epoch.
    pub policy: PolicyMetrics,
    /// Wall-clock seconds since training started.
    pub seconds: f64,
    /// The epoch whose network `policy` scores (0 = the start): `epoch` itself, but from a
    /// value-guard stop on, where training stopped and the previous epoch's network stands.
    pub network_epoch: usize,
}

const CSV_HEADER: &str = "epoch,steps,td_loss,conservative_loss,mean_q,return,return_ci95,aoi,aoi_ci95,power_mw,power_mw_ci95,outages,outages_ci95,episodes,seconds,network_epoch";

impl EpochRow {
    /// The row of a trained epoch, its policy not yet scored.
    fn trained(
        epoch: usize,
        network_epoch: usize,
        steps: usize,
        means: &StepFigures,
        cfg: &LearnerConfig,
    ) -> Self {
        EpochRow {
            epoch,
            steps,
            td_loss: means.td_loss,
            conservative_loss: means.conservative_loss,
            mean_q: means.max_q / cfg.reward_scale,
            policy: PolicyMetrics::default(),
            seconds: 0.0,
            network_epoch,
        }
    }

    /// Which network the row scores, in words: "epoch 100", or "epoch 100, keeping epoch 57's
    /// network" after a value-guard stop (the start's is epoch 0's).
    pub fn kept(&self) -> String {
        match self.network_epoch == self.epoch {
            true => format!("epoch {}", self.epoch),
            false => format!(
                "epoch {}, keeping epoch {}'s network (the value guard stopped training)",
                self.epoch, self.network_epoch
            ),
        }
    }

    fn csv(&self) -> String {
        let (epoch, steps, td_loss) = (self.epoch, self.steps, self.td_loss);
        let (conservative_loss, mean_q) = (self.conservative_loss, self.mean_q);
        let (policy, episodes) = (self.policy.csv(), self.policy.episodes);
        format!(
            "{epoch},{steps},{td_loss},{conservative_loss},{mean_q},{policy},{episodes},{:.3},{}",
            self.seconds, self.network_epoch
        )
    }

    fn table_header() -> String {
        format!(
            "{:>5} {:>7} {:>10} {:>10} {:>10} {:>22} {:>14} {:>14} {:>12}",
            "epoch",
            "steps",
            "td_loss",
            "cons_loss",
            "mean_q",
            "return",
            "aoi",
            "power_mw",
            "outages"
        )
    }

    fn table_line(&self) -> String {
        let p = &self.policy;
        format!(
            "{:>5} {:>7} {:>10.4} {:>10.4} {:>10.1} {:>22} {:>14} {:>14} {:>12}",
            self.epoch,
            self.steps,
            self.td_loss,
            self.conservative_loss,
            self.mean_q,
            format!("{:.1}", p.ret),
            format!("{:.2}", p.aoi),
            format!("{:.3}", p.power_mw),
            format!("{:.1}", p.outages)
        )
    }
}

/// The loss figures of one gradient step, or their means over an epoch.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepFigures {
    /// Eq. 7 on the minibatch (scaled rewards).
    pub td_loss: f64,
    /// `mean(logsumexp_a Q - Q(s, a_data))`, before alpha.
    pub conservative_loss: f64,
    /// Mean over the minibatch of `max_a Q(s, a)`, scaled.
    pub max_q: f64,
}

/// Offline gradient steps on one network: Adam(`learner.lr`), minibatches of a seeded shuffle of
/// the data, a hard target update every `learner.target_update_every` steps. [`train`] drives
/// it epoch by epoch; multi-task pretraining drives it on the union of tasks' shots.
pub struct OfflineTrainer {
    algorithm: &'static dyn OfflineAlgorithm,
    learner: LearnerConfig,
    td: TdConfig,
    target_update_every: usize,
    opt: FusedAdam,
    target: QNetwork,
    order: MinibatchOrder,
    steps: usize,
    on_step: OnStep,
    /// Rows from this index on are a model-based algorithm's model rows
    /// ([`crate::model_rows`]): its own per-transition terms weigh them 0.
    model_from: Option<usize>,
}

impl OfflineTrainer {
    /// A trainer of `q` on `rows` transitions with `config`'s `[learner]` settings.
    pub fn new(q: &QNetwork, rows: usize, algorithm: Algo, config: &Config, seed: u64) -> Self {
        let cfg = &config.learner;
        Self {
            algorithm: algorithm::of(algorithm),
            learner: cfg.clone(),
            td: TdConfig::from(cfg),
            target_update_every: cfg.target_update_every,
            opt: FusedAdam::new(q.parameters(), cfg.lr),
            target: q.duplicate(),
            order: MinibatchOrder::new(rows, cfg.batch_size.min(rows), seed),
            steps: 0,
            on_step: OnStep::default(),
            model_from: None,
        }
    }

    /// The trainer of data whose rows from `shots` on are model rows.
    fn with_model_rows_from(self, shots: usize) -> Self {
        Self {
            model_from: Some(shots),
            ..self
        }
    }

    /// The trainer with `on_step` called at every gradient step.
    pub fn with_on_step(self, on_step: OnStep) -> Self {
        Self { on_step, ..self }
    }

    /// ALGO: one Adam step on the algorithm's loss over the next minibatch of `data`.
    pub fn step(&mut self, q: &mut QNetwork, data: &Transitions) -> StepFigures {
        self.on_step.step();
        let index = self.order.next_indices();
        let mb = data.select(&index);
        // 1 for a logged row, 0 for a model row: [b].
        let logged = self
            .model_from
            .map(|shots| index.lt(shots as i64).to_kind(tch::Kind::Float));
        // Q_w(s, .) with its graph; Qhat(s', .) from the frozen target network.
        let q_all = q.forward(&mb.obs); // [b, A]
        let td_loss = self
            .td
            .td_errors(
                (self.algorithm, &self.learner),
                &q_all,
                &mb,
                |s| self.target.forward(s),
                |s| q.forward(s),
            )
            .mean(None); // eq. 7
        let mean = |rows: Tensor| match &logged {
            Some(logged) => (rows * logged).sum(None) / logged.numel() as f64,
            None => rows.mean(None),
        };
        let loss = self.algorithm.loss(&Terms {
            q: &q_all,
            batch: &mb,
            td: &td_loss,
            mean: &mean,
            alpha: self.learner.alpha,
            learner: &self.learner,
        });
        self.opt.backward_step(&loss);
        // Eq. 8's term, before alpha, for every algorithm: how far unseen actions drift above
        // the data's.
        let q_values = q_values(&q_all, self.algorithm.heads());
        let conservative = tch::no_grad(|| conservative_term(&q_values, &mb));
        self.steps += 1;
        if self.steps.is_multiple_of(self.target_update_every) {
            self.target.copy_from(q);
        }
        StepFigures {
            td_loss: td_loss.double_value(&[]),
            conservative_loss: conservative.double_value(&[]),
            max_q: tch::no_grad(|| q_values.amax(-1, false).mean(None)).double_value(&[]),
        }
    }

    /// `steps` gradient steps, each a tick of `bar`; returns their figures' means.
    fn epoch(
        &mut self,
        q: &mut QNetwork,
        data: &Transitions,
        steps: usize,
        bar: &ProgressBar,
    ) -> StepFigures {
        let (mut td_sum, mut cons_sum, mut q_sum) = (0.0, 0.0, 0.0);
        for _ in 0..steps {
            let step = self.step(q, data);
            td_sum += step.td_loss;
            cons_sum += step.conservative_loss;
            q_sum += step.max_q;
            bar.inc(1);
        }
        let k = steps as f64;
        StepFigures {
            td_loss: td_sum / k,
            conservative_loss: cons_sum / k,
            max_q: q_sum / k,
        }
    }

    /// Gradient steps so far.
    pub fn steps(&self) -> usize {
        self.steps
    }
}

/// Trains `q` in place on `data` (every transition of the N shots) and returns one row per epoch.
pub fn train(
    q: &mut QNetwork,
    data: &Transitions,
    opts: &TrainOptions,
    evaluator: &mut dyn EvaluatePolicy,
) -> Result<Vec<EpochRow>, TrainError> {
    let cfg = &opts.config.learner;
    algorithm::prepare(q, opts.algorithm, cfg);
    let mut model = ModelRows::new(opts, q, evaluator);
    let rows_per_epoch = data.len() + model.as_ref().map_or(0, ModelRows::rows);
    let steps_per_epoch = steps_per_epoch(cfg, rows_per_epoch);
    let mut csv = match opts.out_dir {
        Some(dir) => Some(CsvLog::create(&dir.join("train.csv"), CSV_HEADER)?),
        None => None,
    };
    let bar = progress_bar(
        opts.progress,
        (cfg.epochs * steps_per_epoch) as u64,
        "{bar:40} {pos}/{len} steps {per_sec} eta {eta}",
    );
    if opts.progress {
        bar.suspend(|| eprintln!("{}", EpochRow::table_header()));
    }
    let mut trainer =
        OfflineTrainer::new(q, rows_per_epoch, opts.algorithm, opts.config, opts.seed)
            .with_on_step(opts.on_step.clone());
    if model.is_some() {
        trainer = trainer.with_model_rows_from(data.len());
    }
    let started = Instant::now();
    let mut rows: Vec<EpochRow> = Vec::new();
    let mut guard = Guarded::new(cfg, q, data, opts.algorithm);
    let mut average = Average::new(cfg);
    let mut stopped = false;
    for epoch in 1..=cfg.epochs {
        let mut row = match (stopped, rows.last()) {
            // Stopped by the value guard: the network stays as it is.
            (true, Some(last)) => {
                bar.inc(steps_per_epoch as u64);
                EpochRow { epoch, ..*last }
            }
            _ => {
                let with_model = model
                    .as_mut()
                    .map(|model| model.epoch_data(epoch, q, data, evaluator));
                let epoch_data = with_model.as_ref().unwrap_or(data);
                let means = trainer.epoch(q, epoch_data, steps_per_epoch, &bar);
                stopped = guard
                    .as_mut()
                    .is_some_and(|g| g.tripped(epoch, q, data, cfg));
                if !stopped {
                    average.update(q);
                }
                let network_epoch = epoch - usize::from(stopped);
                let mut row = EpochRow::trained(epoch, network_epoch, trainer.steps(), &means, cfg);
                // The previous epoch's network, scored already, unless it is the start's.
                row.policy = match (stopped, rows.last()) {
                    (true, Some(last)) => last.policy,
                    _ => evaluator.evaluate(average.published(q)),
                };
                row
            }
        };
        row.seconds = started.elapsed().as_secs_f64();
        finish_epoch(&row, opts.progress, &bar, csv.as_mut())?;
        rows.push(row);
    }
    bar.finish_and_clear();
    average.publish_into(q);
    if let Some(dir) = opts.out_dir {
        checkpoint::save(
            &dir.join("final"),
            q,
            &opts.algorithm.to_string(),
            cfg.epochs,
            opts.config,
        )?;
    }
    Ok(rows)
}

/// Shows and logs one epoch's row.
fn finish_epoch(
    row: &EpochRow,
    progress: bool,
    bar: &ProgressBar,
    csv: Option<&mut CsvLog>,
) -> Result<(), TrainError> {
    if progress {
        bar.suspend(|| eprintln!("{}", row.table_line()));
    }
    match csv {
        Some(csv) => Ok(csv.line(&row.csv())?),
        None => Ok(()),
    }
}

/// The value guard of a run that has one, with the network it restores.
struct Guarded {
    guard: ValueGuard,
    last_good: QNetwork,
}

impl Guarded {
    /// The guard of a run of `algorithm` starting from `q`, if `learner.value_guard` asks for one
    /// and the algorithm learns values.
    fn new(cfg: &LearnerConfig, q: &QNetwork, data: &Transitions, algorithm: Algo) -> Option<Self> {
        let guard = ValueGuard::new(cfg, q, data)?;
        algorithm::of(algorithm).learns_values().then(|| Self {
            guard,
            last_good: q.duplicate(),
        })
    }

    /// After epoch `epoch`: whether the guard tripped, `q` then back at the previous epoch's.
    fn tripped(
        &mut self,
        epoch: usize,
        q: &mut QNetwork,
        data: &Transitions,
        cfg: &LearnerConfig,
    ) -> bool {
        let tripped = self.guard.restore_if_tripped(q, &mut self.last_good, data);
        if tripped {
            tracing::info!(
                epoch,
                v_data = self.guard.v_data / cfg.reward_scale,
                "the value guard stopped training; the previous epoch's network is kept"
            );
        }
        tripped
    }
}

/// The guard against late collapse (`learner.value_guard`), from the offline data alone.
///
/// The shots come from one behaviour policy, so their mean reward over (1 - gamma) is the scale
/// of its value, `V_data`, and a Q-function trained on them should value the data's own actions
/// near it. From its init, `mean Q(s, a_data)` travels towards `V_data` (here, with costs as
/// rewards, it falls from about 0); once it has gone past `V_data` by more than
/// `value_guard * |V_data|`, Q is drifting beyond any value the data supports (the late collapse
/// of a long CQL run), so training stops and the previous epoch's network is kept. A stop shows
/// in `train.csv` as `steps` no longer growing.
struct ValueGuard {
    v_data: f64,
    /// +1 when Q has to rise to reach `V_data`, -1 when it has to fall.
    direction: f64,
    margin: f64,
}

impl ValueGuard {
    fn new(cfg: &LearnerConfig, q: &QNetwork, data: &Transitions) -> Option<Self> {
        if cfg.value_guard == 0.0 || cfg.gamma >= 1.0 {
            return None;
        }
        let v_data = data.value_scale(cfg.gamma);
        Some(Self {
            v_data,
            direction: (v_data - Self::mean_q(q, data)).signum(),
            margin: cfg.value_guard * v_data.abs(),
        })
    }

    /// `mean Q(s, a_data)` over the data, scaled.
    fn mean_q(q: &QNetwork, data: &Transitions) -> f64 {
        tch::no_grad(|| q_taken(&q.forward(&data.obs), data).mean(None)).double_value(&[])
    }

    fn tripped(&self, q: &QNetwork, data: &Transitions) -> bool {
        self.direction * (Self::mean_q(q, data) - self.v_data) > self.margin
    }

    /// After an epoch: puts `last_good` back into `q` if the guard tripped, else keeps `q` as the
    /// new `last_good`; returns whether it tripped.
    fn restore_if_tripped(
        &self,
        q: &mut QNetwork,
        last_good: &mut QNetwork,
        data: &Transitions,
    ) -> bool {
        let tripped = self.tripped(q, data);
        if tripped {
            q.copy_from(last_good);
        } else {
            last_good.copy_from(q);
        }
        tripped
    }
}

/// The network a run publishes (`learner.average_decay`): the trained Q itself, or its
/// exponential moving average over the epochs, bias-corrected as Adam's moments are, so the init
/// has no weight in it: after t epochs, sum_k decay^(t-k) Q_k / sum_k decay^(t-k), k = 1..t.
struct Average {
    decay: f64,
    /// The average, made at the first epoch averaged; `None` before it and when not averaging.
    average: Option<QNetwork>,
    /// Epochs averaged so far.
    epochs: i32,
}

impl Average {
    fn new(cfg: &LearnerConfig) -> Self {
        Self {
            decay: cfg.average_decay,
            average: None,
            epochs: 0,
        }
    }

    /// After an epoch the value guard let through: Q joins the average with the weight
    /// (1 - decay) / (1 - decay^t) (1 at the first epoch, so the init has no weight).
    fn update(&mut self, q: &QNetwork) {
        if self.decay == 0.0 {
            return;
        }
        self.epochs += 1;
        let weight = (1.0 - self.decay) / (1.0 - self.decay.powi(self.epochs));
        match &mut self.average {
            Some(average) => average.average_toward(q, 1.0 - weight),
            None => self.average = Some(q.duplicate()),
        }
    }

    /// The network to evaluate and keep: the average once there is one, else `q`.
    fn published<'a>(&'a self, q: &'a QNetwork) -> &'a QNetwork {
        self.average.as_ref().unwrap_or(q)
    }

    /// At the end: `q` becomes the published network.
    fn publish_into(&self, q: &mut QNetwork) {
        if let Some(average) = &self.average {
            q.copy_from(average);
        }
    }
}

/// Gradient steps of one epoch on `rows` transitions: `learner.steps_per_epoch`, or one pass,
/// ceil(rows / batch), when that is 0.
pub fn steps_per_epoch(cfg: &LearnerConfig, rows: usize) -> usize {
    match cfg.steps_per_epoch {
        0 => rows.div_ceil(cfg.batch_size.min(rows).max(1)),
        n => n,
    }
}

/// Minibatch indices: consecutive slices of a seeded permutation of the N rows, reshuffled each
/// time it runs out, so every row is seen once per pass whatever the steps per epoch.
struct MinibatchOrder {
    perm: Vec<i64>,
    pos: usize,
    batch: usize,
    rng: ChaCha8Rng,
}

impl MinibatchOrder {
    fn new(n: usize, batch: usize, seed: u64) -> Self {
        let mut order = Self {
            perm: (0..n as i64).collect(),
            pos: n,
            batch,
            rng: ChaCha8Rng::seed_from_u64(seed),
        };
        order.reshuffle_if_spent();
        order
    }

    fn reshuffle_if_spent(&mut self) {
        if self.pos + self.batch > self.perm.len() {
            self.perm.shuffle(&mut self.rng);
            self.pos = 0;
        }
    }

    /// [batch] i64 row indices.
    fn next_indices(&mut self) -> Tensor {
        let index = Tensor::from_slice(&self.perm[self.pos..self.pos + self.batch]);
        self.pos += self.batch;
        self.reshuffle_if_spent();
        index
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::qnet::QNetworkConfig;

    /// A network whose every Q-value is `value`.
    fn constant_q(value: f32) -> QNetwork {
        QNetworkConfig::new(2, 3, &[4]).constant(&[value; 3])
    }

    #[test]
    fn the_value_guard_trips_only_past_the_data_value_in_the_direction_q_travels() {
        // Rewards averaging -1 with gamma 0.5: V_data = -2; margin 0.5 * 2 = 1.
        let data = Transitions {
            obs: Tensor::zeros([4, 2], (tch::Kind::Float, tch::Device::Cpu)),
            actions: Tensor::from_slice(&[0i64, 1, 2, 0]),
            rewards: Tensor::from_slice(&[-0.5f32, -1.5, -1.0, -1.0]),
            next_obs: Tensor::zeros([4, 2], (tch::Kind::Float, tch::Device::Cpu)),
        };
        let mut cfg = LearnerConfig {
            gamma: 0.5,
            value_guard: 0.5,
            ..LearnerConfig::default()
        };
        // Q starts at 0, above V_data: it has to fall, and may fall to -3 but not below.
        let guard = ValueGuard::new(&cfg, &constant_q(0.0), &data).unwrap();
        assert!(!guard.tripped(&constant_q(-1.0), &data));
        assert!(!guard.tripped(&constant_q(-2.9), &data));
        assert!(guard.tripped(&constant_q(-3.1), &data));
        // Rising past V_data from below is a drift the other way round.
        let guard = ValueGuard::new(&cfg, &constant_q(-10.0), &data).unwrap();
        assert!(!guard.tripped(&constant_q(-1.1), &data));
        assert!(guard.tripped(&constant_q(-0.9), &data));
        // 0 turns the guard off.
        cfg.value_guard = 0.0;
        assert!(ValueGuard::new(&cfg, &constant_q(0.0), &data).is_none());
    }

    /// Model rows weigh 0 in the algorithm's own terms: on rows whose TD error is 0, CQL's
    /// conservative term alone would move Q, and it does not read model rows.
    #[test]
    fn the_conservative_term_reads_no_model_row() {
        tch::set_num_threads(1);
        // gamma 0 and rewards equal to every Q-value: the TD term is 0.
        let data = Transitions {
            obs: Tensor::zeros([4, 2], (tch::Kind::Float, tch::Device::Cpu)),
            actions: Tensor::from_slice(&[0i64, 0, 0, 0]),
            rewards: Tensor::from_slice(&[-1.0f32; 4]),
            next_obs: Tensor::zeros([4, 2], (tch::Kind::Float, tch::Device::Cpu)),
        };
        let mut config = Config::default();
        config.learner.gamma = 0.0;
        config.learner.batch_size = 4;
        config.learner.alpha = 10.0;
        let probe = Tensor::zeros([1, 2], (tch::Kind::Float, tch::Device::Cpu));
        let after_a_step = |model_from: Option<usize>| {
            let mut q = constant_q(-1.0);
            let mut trainer = OfflineTrainer::new(&q, 4, Algo::CQL, &config, 0);
            if let Some(shots) = model_from {
                trainer = trainer.with_model_rows_from(shots);
            }
            trainer.step(&mut q, &data);
            q.forward(&probe)
        };
        let unmoved = constant_q(-1.0).forward(&probe);
        // Every row a model row: nothing moves Q. Every row logged: the term lifts action 0.
        assert!(after_a_step(Some(0)).allclose(&unmoved, 0.0, 0.0, false));
        for logged in [None, Some(4), Some(2)] {
            let moved = after_a_step(logged);
            assert!(moved.double_value(&[0, 0]) > -1.0, "{logged:?}: {moved}");
        }
    }
}
