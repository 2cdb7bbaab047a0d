//! Offline training of a population (issue #33): N runs of [`train`](crate::train::train) that
//! share a shape (loss, epochs, gradient steps per epoch, minibatch size, architecture) trained
//! in lockstep as one [`QPopulation`].
//!
//! Member i is the run `train` would make of its own init on its own data: the same minibatch
//! order (its own seed), the same hard target updates, its own value guard, its own evaluator
//! after every epoch. What the members share is the arithmetic: every gradient step is one
//! batched forward and backward pass over `[N, B, ..]` and one fused Adam step. The loss is the
//! sum over members of each member's own eq. 8 (or eq. 7), so member i's weights get exactly the
//! gradient of its own loss, and Adam, being elementwise, keeps each member's moments apart.
//!
//! A population of one is `train` bit for bit; of N, each member follows its separate run up to
//! float rounding (tests below). `uavmeta reproduce` trains a figure's fine-tuning runs this way
//! and the launch's meta-learner the methods of a meta-test task, up to `learner.population`
//! members at a time.

use std::path::Path;
use std::time::Instant;

use tch::{Device, Tensor};
use uavmeta_proto::config::{Config, Loss};

use crate::batch::Batch;
use crate::checkpoint;
use crate::cql::{conservative_rows, eq8};
use crate::dqn::TdConfig;
use crate::optim::FusedAdam;
use crate::population::QPopulation;
use crate::progress::{CsvLog, OnStep};
use crate::qnet::QNetwork;
use crate::train::{
    finish_epoch, steps_per_epoch, Average, EpochRow, EvaluatePolicy, MinibatchOrder, StepFigures,
    TrainError, ValueGuard, CSV_HEADER,
};

/// One run of a population.
pub struct Member<'a> {
    /// Its init: a random network, or a checkpoint to fine-tune.
    pub init: QNetwork,
    /// Its training set (every transition of its shots).
    pub data: &'a Batch,
    /// Seed of its minibatch order.
    pub seed: u64,
    /// Scores its greedy policy after every epoch.
    pub evaluator: &'a mut dyn EvaluatePolicy,
    /// Where its `train.csv` and `final` checkpoint go; `None` writes neither.
    pub out_dir: Option<&'a Path>,
}

/// The settings every member shares.
pub struct PopulationOptions<'a> {
    pub algorithm: Loss,
    /// `[learner]` drives training (as for `train`); the whole is saved beside checkpoints.
    pub config: &'a Config,
    /// Where the stacked networks live (`run.device`).
    pub device: Device,
    /// Called at every lockstep gradient step.
    pub on_step: OnStep,
}

/// What one member ends with: its network (the value guard's kept one if it stopped) and one row
/// per epoch, as `train` returns them.
pub struct Trained {
    pub q: QNetwork,
    pub rows: Vec<EpochRow>,
}

/// Trains every member of `members` in lockstep; results in member order.
pub fn train_population(
    members: Vec<Member>,
    opts: &PopulationOptions,
) -> Result<Vec<Trained>, TrainError> {
    let cfg = &opts.config.learner;
    let steps = check_shape(&members, opts.config)?;
    let started = Instant::now();
    let mut runs = members
        .into_iter()
        .map(|m| MemberRun::new(m, opts.config))
        .collect::<Result<Vec<_>, _>>()?;
    let networks: Vec<QNetwork> = runs.iter().map(|r| r.current.duplicate()).collect();
    let mut trainer = LockstepTrainer::new(&networks, opts);
    for epoch in 1..=cfg.epochs {
        let sums = trainer.epoch(&mut runs, steps);
        for (i, (run, sums)) in runs.iter_mut().zip(sums).enumerate() {
            run.end_epoch(epoch, &trainer, i, sums, started)?;
        }
    }
    runs.into_iter()
        .map(|run| run.finish(opts))
        .collect::<Result<Vec<_>, _>>()
}

/// Gradient steps per epoch, the same for every member, or which member differs and how.
fn check_shape(members: &[Member], config: &Config) -> Result<usize, TrainError> {
    let cfg = &config.learner;
    let shape = |m: &Member| {
        (
            steps_per_epoch(cfg, m.data.len()),
            cfg.batch.min(m.data.len()),
            m.init.config().clone(),
        )
    };
    let first = members
        .first()
        .map(shape)
        .ok_or(TrainError::EmptyPopulation)?;
    for (i, m) in members.iter().enumerate() {
        let (steps, batch, net) = shape(m);
        if (steps, batch, &net) != (first.0, first.1, &first.2) {
            return Err(TrainError::PopulationShape {
                member: i,
                got: format!("{steps} steps per epoch of {batch} rows, network {net:?}"),
                expected: format!(
                    "{} steps per epoch of {} rows, network {:?} (member 0's)",
                    first.0, first.1, first.2
                ),
            });
        }
    }
    Ok(first.0)
}

/// ALGO: the lockstep gradient steps: eq. 8 (CQL) or eq. 7 (DQN) of each member on its own
/// minibatch, summed, one fused Adam step, a hard target update every `target_update_every`.
struct LockstepTrainer {
    algorithm: Loss,
    alpha: f64,
    td: TdConfig,
    target_update_every: usize,
    /// `learner.reward_scale`, to report Q in reward units.
    reward_scale: f64,
    q: QPopulation,
    target: QPopulation,
    opt: FusedAdam,
    steps: usize,
    on_step: OnStep,
}

impl LockstepTrainer {
    fn new(networks: &[QNetwork], opts: &PopulationOptions) -> Self {
        let cfg = &opts.config.learner;
        let q = QPopulation::from_networks(networks, opts.device);
        Self {
            algorithm: opts.algorithm,
            alpha: cfg.alpha,
            td: TdConfig::from(cfg),
            target_update_every: cfg.target_update_every,
            reward_scale: cfg.reward_scale,
            target: q.duplicate(),
            opt: FusedAdam::new(q.parameters(), cfg.lr),
            q,
            steps: 0,
            on_step: opts.on_step.clone(),
        }
    }

    /// One lockstep step; each member's figures, as `OfflineTrainer::step` reports them.
    fn step(&mut self, runs: &mut [MemberRun]) -> Vec<StepFigures> {
        self.on_step.step();
        let minibatches: Vec<Batch> = runs
            .iter_mut()
            .map(|r| r.data.select(&r.order.next_indices()))
            .collect();
        let mb = Batch::stack(&minibatches, self.q.device()); // [N, B, ..]
        let q_all = self.q.forward(&mb.obs); // Q_w(s, .) [N, B, A]
        let mean = |rows: Tensor| rows.mean_dim([-1].as_slice(), false, None); // [N, B] -> [N]
        let td = mean(self.td.td_errors(
            &q_all,
            &mb,
            |s| self.target.forward(s),
            |s| self.q.forward(s),
        )); // eq. 7, each member's
        let (loss, conservative) = match self.algorithm {
            Loss::Cql => {
                let conservative = mean(conservative_rows(&q_all, &mb));
                (eq8(&td, &conservative, self.alpha), conservative) // eq. 8, each member's
            }
            Loss::Dqn => (
                td.shallow_clone(),
                tch::no_grad(|| mean(conservative_rows(&q_all, &mb))),
            ),
        };
        // Summed: member i's weights get exactly the gradient of its own loss.
        self.opt.backward_step(&loss.sum(None));
        self.steps += 1;
        if self.steps.is_multiple_of(self.target_update_every) {
            self.target.copy_from(&self.q);
        }
        let max_q = tch::no_grad(|| mean(q_all.amax(-1, false)));
        let [td, conservative, max_q] = [td, conservative, max_q].map(|t| {
            Vec::<f32>::try_from(t.detach().to_device(Device::Cpu))
                .expect("a figure per member is a float vector")
        });
        (0..runs.len())
            .map(|i| StepFigures {
                td_loss: f64::from(td[i]),
                conservative_loss: f64::from(conservative[i]),
                max_q: f64::from(max_q[i]),
            })
            .collect()
    }

    /// `steps` lockstep steps; each member's figures summed over them.
    fn epoch(&mut self, runs: &mut [MemberRun], steps: usize) -> Vec<StepFigures> {
        let zero = StepFigures {
            td_loss: 0.0,
            conservative_loss: 0.0,
            max_q: 0.0,
        };
        let mut sums = vec![zero; runs.len()];
        for _ in 0..steps {
            for (sum, step) in sums.iter_mut().zip(self.step(runs)) {
                sum.td_loss += step.td_loss;
                sum.conservative_loss += step.conservative_loss;
                sum.max_q += step.max_q;
            }
        }
        let k = steps as f64;
        sums.into_iter()
            .map(|s| StepFigures {
                td_loss: s.td_loss / k,
                conservative_loss: s.conservative_loss / k,
                max_q: s.max_q / k,
            })
            .collect()
    }
}

/// One member's run around the lockstep steps: its data and minibatch order, its value guard,
/// its evaluator, its rows.
struct MemberRun<'a> {
    data: &'a Batch,
    order: MinibatchOrder,
    /// Its network after the last epoch: the population's member, or the kept one once the
    /// value guard stopped it.
    current: QNetwork,
    guard: Option<ValueGuard>,
    stopped: bool,
    /// What it publishes: `current`, or its average over epochs (`learner.average_decay`).
    average: Average,
    evaluator: &'a mut dyn EvaluatePolicy,
    out_dir: Option<&'a Path>,
    csv: Option<CsvLog>,
    rows: Vec<EpochRow>,
}

impl<'a> MemberRun<'a> {
    fn new(m: Member<'a>, config: &Config) -> Result<Self, TrainError> {
        let cfg = &config.learner;
        let rows = m.data.len();
        Ok(Self {
            order: MinibatchOrder::new(rows, cfg.batch.min(rows), m.seed),
            guard: ValueGuard::new(cfg, &m.init, m.data),
            average: Average::new(cfg),
            csv: match m.out_dir {
                Some(dir) => Some(CsvLog::create(&dir.join("train.csv"), CSV_HEADER)?),
                None => None,
            },
            data: m.data,
            current: m.init,
            stopped: false,
            evaluator: m.evaluator,
            out_dir: m.out_dir,
            rows: Vec::with_capacity(cfg.epochs),
        })
    }

    /// After epoch `epoch`: the value guard's check, the evaluation and the row, as `train`
    /// makes them; a stopped member repeats its last row.
    fn end_epoch(
        &mut self,
        epoch: usize,
        trainer: &LockstepTrainer,
        member: usize,
        means: StepFigures,
        started: Instant,
    ) -> Result<(), TrainError> {
        let seconds = started.elapsed().as_secs_f64();
        let row = match (self.stopped, self.rows.last()) {
            (true, Some(last)) => EpochRow {
                epoch,
                seconds,
                ..*last
            },
            _ => {
                let trained = trainer.q.member(member);
                match &self.guard {
                    Some(guard) if guard.tripped(&trained, self.data) => {
                        // The previous epoch's network (`current`) is kept.
                        self.stopped = true;
                        tracing::info!(epoch, member, "the value guard stopped training");
                    }
                    _ => {
                        self.current = trained;
                        self.average.update(&self.current);
                    }
                }
                EpochRow {
                    epoch,
                    steps: trainer.steps,
                    td_loss: means.td_loss,
                    conservative_loss: means.conservative_loss,
                    mean_q: means.max_q / trainer.reward_scale,
                    policy: self
                        .evaluator
                        .evaluate(self.average.published(&self.current)),
                    seconds,
                }
            }
        };
        finish_epoch(
            &row,
            false,
            &indicatif::ProgressBar::hidden(),
            self.csv.as_mut(),
        )?;
        self.rows.push(row);
        Ok(())
    }

    fn finish(mut self, opts: &PopulationOptions) -> Result<Trained, TrainError> {
        self.average.publish_into(&mut self.current);
        if let Some(dir) = self.out_dir {
            checkpoint::save(
                &dir.join("final"),
                &self.current,
                &opts.algorithm.to_string(),
                opts.config.learner.epochs,
                opts.config,
            )?;
        }
        Ok(Trained {
            q: self.current,
            rows: self.rows,
        })
    }
}
