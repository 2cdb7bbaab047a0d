//! MAML over a CQL or DQN inner loop: the paper's Algorithm 4 with eqs. 14-16, a meta-epoch being
//! one pass over the support shots (`meta.outer_steps_per_meta_epoch` = 1 is the literal reading).
//! The loop, its keys and why: docs/MODEL.md, section 5, "MAML over CQL" and "Epochs".
//!
//! With `meta.learn_inner_lr` (Meta-SGD, Li et al. 2017) eq. 14's step size is learned too: one
//! per weight, initialised to `eta_inner`, updated by the same outer Adam as `w0`. One shared
//! step size moves every task's weights by the same amount along its gradient; a task at the end
//! of the lambda range (lambda = 0, where power costs nothing) then adapts least well
//! (docs/EXPERIMENTS.md, C4), and per-weight steps let meta-training decide how far each weight
//! moves. The learned steps serve the adaptation (eq. 14, figure 4); meta-test fine-tunes `w0`
//! with CQL's Adam as before.
//!
//! `L` is eq. 8 (CQL-MAML) or eq. 7 (DQN-MAML) with the learner's TD options, so that MAML and
//! plain offline training optimise the same loss. `meta.huber` gives MAML alone the Huber TD
//! form: on a task whose values `w0` misjudges by far (lambda-0), squared TD errors otherwise
//! decide where the few inner steps go (docs/EXPERIMENTS.md, C6). Second-order MAML builds the
//! inner gradients with `create_graph`; first-order MAML (`meta.first_order`) treats them as
//! constants.
//!
//! # The target network Qhat
//!
//! Both losses bootstrap from a target network `Qhat` (eqs. 7-8). Here `Qhat` is a detached copy of
//! `w0`, refreshed at the start of every `meta.target_update_meta_epochs`-th meta-epoch, and one and the
//! same `Qhat` serves the inner loss (eq. 14) and the query loss (eq. 15) of every task of the
//! meta-epoch. Three reasons:
//!
//! 1. The inner loop rehearses meta-test. Fine-tuning (docs/MODEL.md section 5) starts with its
//!    target network equal to the initial weights `w0` and keeps it for
//!    `learner.target_update_every` gradient steps, far more than MAML's 1-5 inner steps. With
//!    `Qhat = w0` held constant through the inner steps, `w_i` is exactly what the first steps of
//!    fine-tuning would produce, so `w0` is trained for the adaptation it will actually get. Using
//!    the fast weights as their own target would rehearse a fine-tuning that does not exist.
//! 2. Eq. 16 stays a true gradient step. Between refreshes, the regression targets
//!    `r + gamma * max_a' Qhat(s', a')` are constants, so the meta-loss is an ordinary function of
//!    `w0` and the meta-gradient computed here is its exact derivative (`meta/tests/maml.rs`
//!    checks it against finite differences). Bootstrapping the query loss from `w_i` (or from `w0`
//!    with gradient) would make the objective depend on `w0` through the targets too, which the
//!    semi-gradient convention of eq. 7 deliberately ignores: the meta-gradient would then be the
//!    gradient of nothing, and differentiating through the targets instead (a residual gradient
//!    through a max) is known to learn worse values.
//! 3. Stability. A target that follows `w0` at every Adam step is DQN without a target network; a
//!    refresh interval above 1 is the usual cure, and is a config key for that reason. The default
//!    of 1 makes `Qhat` the `w0` the meta-epoch starts from, which matches point 1 exactly.
//!
//! The observation does not contain lambda, so `w0` is one Q-function for all tasks; its target is
//! a task-average value, and the per-task part of each `Q_{w_i}` comes from the adaptation.
//!
//! # Resuming
//!
//! Eq. 16's Adam is libtorch's fused kernel ([`FusedAdam`]) rather than `tch::nn::Optimizer`,
//! whose moments cannot be read or restored. [`Maml::save_state`] stores
//! the moments, the target network, the sampling stream and the epoch count beside a `w0`
//! checkpoint, and [`Maml::resume`] continues from them exactly as if never interrupted.

use std::collections::HashMap;
use std::path::Path;

use rand::seq::{index, SliceRandom};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use tch::{Kind, Tensor};
use uavmeta_learner::algorithm::{self, Terms};
use uavmeta_learner::checkpoint::{self, CheckpointError};
use uavmeta_learner::dqn::TdConfig;
use uavmeta_learner::optim::FusedAdam;
use uavmeta_learner::progress::OnStep;
use uavmeta_learner::qnet::QNetwork;
use uavmeta_learner::transitions::Transitions;
use uavmeta_proto::config::{Config, LearnerConfig, MetaConfig};

use crate::MetaError;

/// The settings of Algorithm 4: the `[meta]` section itself, and the TD options of `[learner]`
/// its losses share with offline training.
#[derive(Debug, Clone, PartialEq)]
pub struct MamlConfig {
    /// `[meta]`: the loss (CQL-MAML or DQN-MAML), alpha, shots, steps and step sizes.
    pub meta: MetaConfig,
    /// Discount and TD options shared with offline training (`[learner]`), Huber also with
    /// `meta.huber`.
    pub td: TdConfig,
    /// `[learner]`, for the inner loss's own settings (`learner.bcq_threshold`).
    pub learner: LearnerConfig,
}

impl MamlConfig {
    pub fn from_config(config: &Config) -> Self {
        Self {
            meta: config.meta.clone(),
            td: TdConfig {
                huber: config.learner.huber || config.meta.huber,
                ..TdConfig::from(&config.learner)
            },
            learner: config.learner.clone(),
        }
    }

    /// Outer steps of one meta-epoch over `tasks`.
    pub fn outer_steps(&self, tasks: &[MetaTask]) -> usize {
        match self.meta.outer_steps_per_meta_epoch {
            0 => tasks
                .iter()
                .map(|t| t.support.len().div_ceil(self.meta.support_batch_size))
                .max()
                .unwrap_or(1),
            n => n,
        }
    }

    /// `L(w; batch)`: the loss of `meta.inner_loss` (eq. 8 for CQL-MAML) for the network with
    /// weights `params`, bootstrapping from the target network `target`, which no gradient reaches.
    /// Scalar.
    pub fn task_loss(&self, params: &[Tensor], target: &[Tensor], batch: &Transitions) -> Tensor {
        self.task_losses(params, target, &StackedShots::stack(&[batch]))
            .squeeze_dim(0)
    }

    /// `L(w_t; shots_t)` of every task t of `shots` at once, [T]: `params` are either stacked
    /// (one network per task, as [`QNetwork::forward_with`] takes them) or one network for all.
    pub fn task_losses(
        &self,
        params: &[Tensor],
        target: &[Tensor],
        shots: &StackedShots,
    ) -> Tensor {
        let batch = &shots.batch;
        // Q_w(s, .) [T, B, A], its graph back to params.
        let q = QNetwork::forward_with(params, &batch.obs);
        // Each task's mean over its own rows; padding rows weigh 0.
        let mean = |rows: Tensor| (rows * &shots.weight).sum_dim_intlist(-1, false, None::<Kind>);
        let algorithm = algorithm::of(self.meta.inner_loss);
        let td = mean(self.td.td_errors(
            (algorithm, &self.learner),
            &q,
            batch,
            |s| QNetwork::forward_with(target, s), // Qhat(s', .) [T, B, A]
            |s| QNetwork::forward_with(params, s),
        ));
        algorithm.loss(&Terms {
            q: &q,
            batch,
            td: &td,
            mean: &mean,
            alpha: self.meta.alpha,
            learner: &self.learner,
        })
    }

    /// Eq. 14, `inner_steps` times: `w <- w - eta_inner * grad_w L(w; support)` from `w0`.
    ///
    /// Second order keeps the graph of every inner gradient, so the returned fast weights are
    /// differentiable functions of `w0` through the Hessian-vector terms; first order detaches the
    /// gradients, so `d w_i / d w0` is the identity.
    pub fn adapt(
        &self,
        w0: &[Tensor],
        step: StepSize,
        target: &[Tensor],
        support: &Transitions,
    ) -> Vec<Tensor> {
        self.adapt_stacked(w0, step, target, &StackedShots::stack(&[support]))
            .iter()
            .map(|w| w.squeeze_dim(0))
            .collect()
    }

    /// Eq. 14 for every task of `support` at once: stacked fast weights, one network per task.
    /// The tasks' losses are summed before differentiating; as task t's loss depends only on its
    /// own slice of the weights, the gradient of the sum is each task's own gradient.
    pub fn adapt_stacked(
        &self,
        w0: &[Tensor],
        step: StepSize,
        target: &[Tensor],
        support: &StackedShots,
    ) -> Vec<Tensor> {
        let tasks = support.tasks();
        let mut w: Vec<Tensor> = w0
            .iter()
            .map(|p| {
                let mut stacked = vec![tasks];
                stacked.extend(p.size());
                p.unsqueeze(0).expand(stacked, false)
            })
            .collect();
        let second_order = !self.meta.first_order;
        for _ in 0..self.meta.inner_steps {
            let loss = self.task_losses(&w, target, support).sum(None);
            // torch.autograd.grad(loss, w, retain_graph=create_graph=second_order)
            let grads = Tensor::run_backward(&[&loss], &w, second_order, second_order);
            w = match step {
                StepSize::Shared => w
                    .iter()
                    .zip(&grads)
                    .map(|(w, g)| w - g * self.meta.eta_inner)
                    .collect(),
                // [..] step sizes broadcast over the task dimension of [T, ..] weights.
                StepSize::PerWeight(lr) => w
                    .iter()
                    .zip(&grads)
                    .zip(lr)
                    .map(|((w, g), lr)| w - g * lr)
                    .collect(),
            };
        }
        w
    }

    /// Eq. 15 and its gradient: adapts to each task's support shots, evaluates `L(w_i; query)`,
    /// and accumulates `d L_meta / d w0` into the `.grad` of `w0` (which must be leaves that
    /// require grad), and Meta-SGD's `d L_meta / d lr` into the step sizes'. All tasks go through
    /// one stacked computation (batched matrix products instead of one small product per task).
    /// Returns each task's query loss.
    pub fn backward_meta_loss(
        &self,
        w0: &[Tensor],
        step: StepSize,
        target: &[Tensor],
        tasks: &[TaskShots],
    ) -> Vec<f64> {
        let support: Vec<&Transitions> = tasks.iter().map(|t| &t.support).collect();
        let query: Vec<&Transitions> = tasks.iter().map(|t| &t.query).collect();
        let query = StackedShots::stack(&query);
        let w = self.adapt_stacked(w0, step, target, &StackedShots::stack(&support)); // eq. 14
        let query_losses = self.task_losses(&w, target, &query); // eq. 15's terms
        self.with_w0_loss(query_losses.sum(None), w0, target, &query)
            .backward();
        Vec::<f64>::try_from(query_losses.detach().to_kind(Kind::Double))
            .expect("a [T] loss tensor")
    }

    /// `L_meta` plus `w0_loss_weight * sum_i L(w0; query shots of tau_i)`: the step-0 term of a
    /// multi-step meta-loss, which asks w0's own policy to fit every task's data. `w0` is one
    /// network for all tasks or one per task, as [`task_losses`](Self::task_losses) takes it.
    fn with_w0_loss(
        &self,
        meta_loss: Tensor,
        w0: &[Tensor],
        target: &[Tensor],
        query: &StackedShots,
    ) -> Tensor {
        let beta = self.meta.w0_loss_weight;
        if beta == 0.0 {
            return meta_loss;
        }
        meta_loss + self.task_losses(w0, target, query).sum(None) * beta
    }
}

/// Eq. 14's step size.
#[derive(Debug, Clone, Copy)]
pub enum StepSize<'a> {
    /// MAML: `eta_inner` for every weight.
    Shared,
    /// Meta-SGD: one step size per weight, shaped like the weights (in their order).
    PerWeight(&'a [Tensor]),
}

/// The shots of T tasks as one [`Transitions`] with a leading task dimension ([T, B, ..]), each task's
/// rows padded to the longest task's B with rows that weigh 0.
pub struct StackedShots {
    pub batch: Transitions,
    /// [T, B]: 1 / (task t's row count) on its rows, 0 on its padding; a task's loss is the
    /// weighted sum of its rows' terms, the mean over its own rows.
    pub weight: Tensor,
}

impl StackedShots {
    /// Stacks `parts` (at least one).
    pub fn stack(parts: &[&Transitions]) -> StackedShots {
        let rows = parts.iter().map(|b| b.len()).max().unwrap_or(0) as i64;
        let pad = |t: &Tensor| {
            let missing = rows - t.size()[0];
            if missing == 0 {
                return t.shallow_clone();
            }
            let mut shape = t.size();
            shape[0] = missing;
            Tensor::cat(
                &[
                    t.shallow_clone(),
                    t.new_zeros(shape.as_slice(), (t.kind(), t.device())),
                ],
                0,
            )
        };
        let column = |pick: fn(&Transitions) -> &Tensor| {
            Tensor::stack(&parts.iter().map(|b| pad(pick(b))).collect::<Vec<_>>(), 0)
        };
        let weight: Vec<Tensor> = parts
            .iter()
            .map(|b| {
                let n = b.len() as i64;
                let ones = b.rewards.ones_like() / n as f64;
                pad(&ones)
            })
            .collect();
        StackedShots {
            batch: Transitions {
                obs: column(|b| &b.obs),
                actions: column(|b| &b.actions),
                rewards: column(|b| &b.rewards),
                next_obs: column(|b| &b.next_obs),
            },
            weight: Tensor::stack(&weight, 0),
        }
    }

    /// T.
    pub fn tasks(&self) -> i64 {
        self.weight.size()[0]
    }
}

/// One meta-train task's data: its support set (inner loop) and query set (meta-loss), each
/// encoded once; the shots of a meta-epoch are row selections of them.
pub struct MetaTask {
    pub name: String,
    pub support: Transitions,
    pub query: Transitions,
}

/// The shots one task contributes to one meta-epoch.
pub struct TaskShots {
    /// k shots of the support set.
    pub support: Transitions,
    /// Shots of the query set.
    pub query: Transitions,
}

impl MetaTask {
    /// `shots` support rows and `query_batch_size` query rows drawn without replacement (all rows of a
    /// set smaller than asked for).
    pub fn sample(&self, shots: usize, query_batch_size: usize, rng: &mut ChaCha8Rng) -> TaskShots {
        TaskShots {
            support: sample_rows(&self.support, shots, rng),
            query: sample_rows(&self.query, query_batch_size, rng),
        }
    }
}

/// One meta-epoch's pass over a task's support set: consecutive slices of a seeded permutation,
/// reshuffled when spent, so that a pass adapts to every support shot once.
struct SupportPass {
    order: Vec<i64>,
    next: usize,
}

impl SupportPass {
    fn new(len: usize, rng: &mut ChaCha8Rng) -> Self {
        let mut pass = Self {
            order: (0..len as i64).collect(),
            next: len,
        };
        pass.reshuffle_if_spent(rng);
        pass
    }

    fn reshuffle_if_spent(&mut self, rng: &mut ChaCha8Rng) {
        if self.next >= self.order.len() {
            self.order.shuffle(rng);
            self.next = 0;
        }
    }

    /// The next (at most) `shots` rows of `support`.
    fn take(&mut self, support: &Transitions, shots: usize, rng: &mut ChaCha8Rng) -> Transitions {
        let end = (self.next + shots).min(self.order.len());
        let rows = Tensor::from_slice(&self.order[self.next..end]);
        self.next = end;
        self.reshuffle_if_spent(rng);
        support.select(&rows)
    }
}

fn sample_rows(batch: &Transitions, amount: usize, rng: &mut ChaCha8Rng) -> Transitions {
    let rows: Vec<i64> = index::sample(rng, batch.len(), amount.min(batch.len()))
        .into_iter()
        .map(|i| i as i64)
        .collect();
    batch.select(&Tensor::from_slice(&rows))
}

/// One meta-learner's draws through one meta-epoch (every one from its own `rng`, in this
/// order: the support passes, then at each outer step the tasks and their shots) and the losses
/// they gave.
struct EpochDraws {
    passes: Vec<SupportPass>,
    loss_sums: Vec<(f64, usize)>,
    meta_loss: f64,
    steps: usize,
}

impl EpochDraws {
    fn new(tasks: &[MetaTask], rng: &mut ChaCha8Rng) -> Self {
        Self {
            passes: (tasks.iter())
                .map(|t| SupportPass::new(t.support.len(), rng))
                .collect(),
            loss_sums: vec![(0.0, 0); tasks.len()],
            meta_loss: 0.0,
            steps: 0,
        }
    }

    /// The next outer step's task indices (ascending; all of them when `tasks_per_meta_epoch`
    /// is 0), each with the next k support shots of its pass and fresh query shots.
    fn next(
        &mut self,
        meta: &MetaConfig,
        tasks: &[MetaTask],
        rng: &mut ChaCha8Rng,
    ) -> (Vec<usize>, Vec<TaskShots>) {
        let count = match meta.tasks_per_meta_epoch {
            0 => tasks.len(),
            n => n.min(tasks.len()),
        };
        let mut picked = index::sample(rng, tasks.len(), count).into_vec();
        picked.sort_unstable();
        let shots = picked
            .iter()
            .map(|&i| TaskShots {
                support: self.passes[i].take(&tasks[i].support, meta.support_batch_size, rng),
                query: sample_rows(&tasks[i].query, meta.query_batch_size, rng),
            })
            .collect();
        (picked, shots)
    }

    /// The query losses of the tasks `picked` at one outer step.
    fn record(&mut self, picked: Vec<usize>, losses: Vec<f64>) {
        self.meta_loss += losses.iter().sum::<f64>();
        self.steps += 1;
        for (i, loss) in picked.into_iter().zip(losses) {
            self.loss_sums[i].0 += loss;
            self.loss_sums[i].1 += 1;
        }
    }

    /// The meta-epoch's figures, as meta-epoch `epoch` (counting from 1).
    fn finish(self, epoch: usize) -> MetaEpoch {
        MetaEpoch {
            epoch,
            outer_steps: self.steps,
            meta_loss: self.meta_loss / self.steps as f64,
            task_losses: (self.loss_sums.into_iter().enumerate())
                .filter(|(_, (_, n))| *n > 0)
                .map(|(i, (sum, n))| (i, sum / n as f64))
                .collect(),
        }
    }
}

/// What one meta-epoch did.
#[derive(Debug, Clone, PartialEq)]
pub struct MetaEpoch {
    /// The meta-epoch, counting from 1.
    pub epoch: usize,
    /// Outer steps it made.
    pub outer_steps: usize,
    /// `L_meta` of eq. 15, the mean over the epoch's outer steps (each at the `w0` it started
    /// from).
    pub meta_loss: f64,
    /// `(task index, mean L(w_i; query))` of each task sampled in the epoch, in task order.
    pub task_losses: Vec<(usize, f64)>,
}

/// The meta-learner: `w0`, Meta-SGD's step sizes, the target network and the outer Adam
/// optimiser.
pub struct Maml {
    config: MamlConfig,
    /// The iterate eq. 16 updates.
    w0: QNetwork,
    /// The moving average of `w0` published as the init, when `meta.average_decay_per_outer_step` > 0.
    average: Option<QNetwork>,
    /// Meta-SGD's per-weight step sizes (leaves that require grad), when `learn_inner_lr`.
    inner_lr: Option<Vec<Tensor>>,
    target: QNetwork,
    optimizer: FusedAdam,
    rng: ChaCha8Rng,
    epochs_done: usize,
    /// Called at every outer step.
    on_step: OnStep,
}

/// What eq. 16 updates: `w0`'s parameters, then Meta-SGD's step sizes if learned.
fn meta_parameters(weights: Vec<Tensor>, inner_lr: &Option<Vec<Tensor>>) -> Vec<Tensor> {
    let mut params = weights;
    params.extend(inner_lr.iter().flatten().map(Tensor::shallow_clone));
    params
}

/// Meta-SGD's starting step sizes (`meta.eta_inner` in a leaf of each weight's shape, when
/// `meta.learn_inner_lr`) and the outer Adam over `weights` and them (eq. 16).
fn outer_optimizer(weights: Vec<Tensor>, config: &MamlConfig) -> (Option<Vec<Tensor>>, FusedAdam) {
    let inner_lr: Option<Vec<Tensor>> = config.meta.learn_inner_lr.then(|| {
        (weights.iter())
            .map(|p| {
                p.full_like(config.meta.eta_inner)
                    .detach()
                    .set_requires_grad(true)
            })
            .collect()
    });
    let optimizer = FusedAdam::new(meta_parameters(weights, &inner_lr), config.meta.eta_outer);
    (inner_lr, optimizer)
}

/// What [`Maml::save_state`] stores besides tensors: the counters and the sampling stream's
/// position (ChaCha8's seed, stream and word position).
#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct MamlProgress {
    epochs_done: usize,
    adam_steps: u64,
    rng_seed: [u8; 32],
    rng_stream: u64,
    rng_word_pos: u128,
}

impl Maml {
    /// Meta-trains `w0` (its current weights are the starting point); task and shot sampling
    /// draw from `seed` alone.
    pub fn new(w0: QNetwork, config: MamlConfig, seed: u64) -> Result<Self, MetaError> {
        let (inner_lr, optimizer) = outer_optimizer(w0.parameters(), &config);
        let target = w0.duplicate();
        let average = (config.meta.average_decay_per_outer_step > 0.0).then(|| w0.duplicate());
        Ok(Self {
            config,
            w0,
            average,
            inner_lr,
            target,
            optimizer,
            rng: ChaCha8Rng::seed_from_u64(seed),
            epochs_done: 0,
            on_step: OnStep::default(),
        })
    }

    /// Eq. 14's step size for this run.
    fn step_size(&self) -> StepSize<'_> {
        match &self.inner_lr {
            Some(lr) => StepSize::PerWeight(lr),
            None => StepSize::Shared,
        }
    }

    /// Saves everything besides `w0` that the next meta-epochs depend on (Adam's moments, the
    /// target network, the sampling stream, the epoch count) beside the `w0` checkpoint `path`,
    /// before `w0` itself is saved there.
    pub fn save_state(&self, path: &Path) -> Result<(), CheckpointError> {
        let mut tensors = Vec::new();
        for (i, (m, v)) in self.optimizer.moments().enumerate() {
            tensors.push((format!("adam.m.{i}"), m.shallow_clone()));
            tensors.push((format!("adam.v.{i}"), v.shallow_clone()));
        }
        for (i, target) in self.target.parameters().into_iter().enumerate() {
            tensors.push((format!("target.{i}"), target));
        }
        for (i, lr) in self.inner_lr.iter().flatten().enumerate() {
            tensors.push((format!("inner_lr.{i}"), lr.detach()));
        }
        // With averaging the checkpoint holds the average, so the iterate goes here.
        if self.average.is_some() {
            for (i, p) in self.w0.parameters().into_iter().enumerate() {
                tensors.push((format!("iterate.{i}"), p.detach()));
            }
        }
        let progress = MamlProgress {
            epochs_done: self.epochs_done,
            adam_steps: self.optimizer.steps(),
            rng_seed: self.rng.get_seed(),
            rng_stream: self.rng.get_stream(),
            rng_word_pos: self.rng.get_word_pos(),
        };
        checkpoint::save_state(path, &tensors, &progress)
    }

    /// Continues a meta-training from `w0` (loaded from checkpoint `path`: the published init,
    /// the average when averaging) and the state saved beside it by
    /// [`save_state`](Self::save_state), under `config`.
    pub fn resume(w0: QNetwork, config: MamlConfig, path: &Path) -> Result<Self, MetaError> {
        let (tensors, progress): (_, MamlProgress) = checkpoint::load_state(path)?;
        let params = w0.parameters();
        let mut named: HashMap<String, Tensor> = tensors.into_iter().collect();
        // The tensors passed the CRC check, so a missing or misshapen one was saved for another
        // network than the checkpoint beside it.
        let mut take = |name: String, like: &Tensor| -> Result<Tensor, CheckpointError> {
            let mismatch = |detail| CheckpointError::SizeMismatch {
                path: checkpoint::state_paths(path).0,
                key: match name.starts_with("inner_lr") {
                    true => "meta.learn_inner_lr",
                    false => "learner.hidden",
                },
                detail,
            };
            let t = named
                .remove(&name)
                .ok_or_else(|| mismatch(format!("no tensor `{name}` in the training state")))?;
            if t.size() != like.size() {
                return Err(mismatch(format!(
                    "`{name}` has shape {:?}, the network's parameter {:?}",
                    t.size(),
                    like.size()
                )));
            }
            Ok(t.to_kind(like.kind()))
        };
        let target = w0.duplicate();
        for (i, (p, mut t)) in params.iter().zip(target.parameters()).enumerate() {
            let saved = take(format!("target.{i}"), p)?;
            tch::no_grad(|| t.copy_(&saved));
        }
        let average = match config.meta.average_decay_per_outer_step > 0.0 {
            true => {
                let average = w0.duplicate();
                for (i, (p, mut dst)) in params.iter().zip(w0.parameters()).enumerate() {
                    let saved = take(format!("iterate.{i}"), p)?;
                    tch::no_grad(|| dst.copy_(&saved));
                }
                Some(average)
            }
            false => None,
        };
        let inner_lr = match config.meta.learn_inner_lr {
            true => Some(
                (params.iter().enumerate())
                    .map(|(i, p)| Ok(take(format!("inner_lr.{i}"), p)?.set_requires_grad(true)))
                    .collect::<Result<Vec<_>, CheckpointError>>()?,
            ),
            false => None,
        };
        let meta_params = meta_parameters(w0.parameters(), &inner_lr);
        let moments = (meta_params.iter().enumerate())
            .map(|(i, p)| {
                Ok((
                    take(format!("adam.m.{i}"), p)?,
                    take(format!("adam.v.{i}"), p)?,
                ))
            })
            .collect::<Result<Vec<_>, CheckpointError>>()?;
        let mut optimizer = FusedAdam::new(meta_params, config.meta.eta_outer);
        optimizer.restore(moments, progress.adam_steps);
        let mut rng = ChaCha8Rng::from_seed(progress.rng_seed);
        rng.set_stream(progress.rng_stream);
        rng.set_word_pos(progress.rng_word_pos);
        Ok(Self {
            config,
            w0,
            average,
            inner_lr,
            target,
            optimizer,
            rng,
            epochs_done: progress.epochs_done,
            on_step: OnStep::default(),
        })
    }

    pub fn config(&self) -> &MamlConfig {
        &self.config
    }

    /// The meta-learner with `on_step` called at every outer step.
    pub fn with_on_step(self, on_step: OnStep) -> Self {
        Self { on_step, ..self }
    }

    /// The meta-learned initial weights: the moving average of the iterates when
    /// `meta.average_decay_per_outer_step` > 0, else the last iterate.
    pub fn w0(&self) -> &QNetwork {
        self.average.as_ref().unwrap_or(&self.w0)
    }

    /// Polyak averaging: init <- decay * init + (1 - decay) * w0.
    fn update_average(&mut self) {
        if let Some(average) = &mut self.average {
            average.average_toward(&self.w0, self.config.meta.average_decay_per_outer_step);
        }
    }

    /// Meta-epochs run so far.
    pub fn epochs_done(&self) -> usize {
        self.epochs_done
    }

    /// One meta-epoch of Algorithm 4 over `tasks`: `outer_steps` updates of w0.
    pub fn meta_epoch(&mut self, tasks: &[MetaTask]) -> Result<MetaEpoch, MetaError> {
        if tasks.is_empty() {
            return Err(MetaError::NoTasks);
        }
        if self
            .epochs_done
            .is_multiple_of(self.config.meta.target_update_meta_epochs)
        {
            self.target.copy_from(&self.w0); // Qhat <- w0, constant until the next refresh
        }
        let steps = self.config.outer_steps(tasks);
        let mut draws = EpochDraws::new(tasks, &mut self.rng);
        for _ in 0..steps {
            self.on_step.step();
            let (picked, shots) = draws.next(&self.config.meta, tasks, &mut self.rng);
            // Eqs. 14-15, with the meta-gradient accumulated into w0's (and the step sizes')
            // gradients.
            self.optimizer.zero_grad();
            let target = self.target.parameters();
            let losses = self.config.backward_meta_loss(
                &self.w0.parameters(),
                self.step_size(),
                &target,
                &shots,
            );
            // Eq. 16: Adam(eta_outer) on w0 (and the step sizes).
            self.optimizer.step();
            self.update_average();
            draws.record(picked, losses);
        }
        self.epochs_done += 1;
        Ok(draws.finish(self.epochs_done))
    }

    /// `L_meta` (eq. 15) of `w0` on the given shots, without changing anything: the adaptation
    /// runs as in training, but no gradient reaches `w0`.
    pub fn meta_loss(&self, shots: &[TaskShots]) -> f64 {
        let w0 = self.w0.parameters();
        let target = self.target.parameters();
        shots
            .iter()
            .map(|task| {
                let w_i = self.adapt_detached(&w0, &target, &task.support);
                tch::no_grad(|| {
                    self.config
                        .task_loss(&w_i, &target, &task.query)
                        .double_value(&[])
                })
            })
            .sum()
    }

    /// The network `w0` adapts to on `support` (eq. 14 with the meta-epoch's target), as a plain
    /// Q-network: what meta-train evaluates on each task's environment.
    pub fn adapted(&self, support: &Transitions) -> QNetwork {
        let w0 = self.w0.parameters();
        let target = self.target.parameters();
        let w_i = self.adapt_detached(&w0, &target, support);
        let network = self.w0.duplicate();
        tch::no_grad(|| {
            for (dst, src) in network.parameters().iter_mut().zip(&w_i) {
                dst.copy_(src);
            }
        });
        network
    }

    /// Eq. 14 with first-order gradients: the same fast weights, without keeping graphs.
    fn adapt_detached(
        &self,
        w0: &[Tensor],
        target: &[Tensor],
        support: &Transitions,
    ) -> Vec<Tensor> {
        let mut first_order = self.config.clone();
        first_order.meta.first_order = true;
        first_order
            .adapt(w0, self.step_size(), target, support)
            .into_iter()
            .map(|w| w.detach())
            .collect()
    }
}
