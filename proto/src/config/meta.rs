//! `[meta]`: docs/MODEL.md section 5's MAML over CQL (Algorithm 4). Read by `uavmeta_meta` (`maml`,
//! `meta_train`, `pretrain`).

use std::ops::Bound::Excluded;

use garde::Validate;
use serde::{Deserialize, Serialize};
use smart_default::SmartDefault;

use super::rules::{at_least, finite, positive, within};
use crate::method::Algo;

/// docs/MODEL.md section 5: MAML over CQL (Algorithm 4).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, SmartDefault, Validate)]
#[serde(deny_unknown_fields, default)]
#[garde(allow_unvalidated)]
pub struct MetaConfig {
    /// Meta-epochs E_meta.
    #[default(150)]
    pub meta_epochs: usize,
    /// Outer (eq. 16) steps per meta-epoch; 0 = one pass over the tasks' support sets, i.e.
    /// ceil(support set / `support_batch_size`) steps, each task's support transitions drawn
    /// without replacement within the pass (docs/MODEL.md section 5, "Epochs"). 1 = Algorithm 4 read literally.
    #[default(0)]
    pub outer_steps_per_meta_epoch: usize,
    /// Tasks sampled per meta-epoch; 0 means every meta-train task.
    #[default(0)]
    pub tasks_per_meta_epoch: usize,
    /// k, the paper's "k shots": the minibatch of transitions drawn from a task's support set for
    /// its inner steps (every inner step uses the same k, as in MAML). A minibatch, as
    /// `learner.batch_size` is; `learner.shots` is the whole few-shot set N.
    #[default(64)]
    #[garde(custom(at_least(1)))]
    pub support_batch_size: usize,
    /// The minibatch of transitions drawn from a task's query set per meta-loss evaluation.
    #[default(64)]
    #[garde(custom(at_least(1)))]
    pub query_batch_size: usize,
    /// Share of each task's dataset that forms its support set; the rest is its query set.
    #[default(0.5)]
    #[garde(custom(within((Excluded(0.0), Excluded(1.0)), "a share strictly between 0 and 1")))]
    pub support_fraction: f64,
    /// SGD steps of the inner loop.
    #[default(1)]
    #[garde(custom(at_least(1)))]
    pub inner_steps: usize,
    #[default(1e-2)]
    #[garde(custom(positive("a learning rate > 0")))]
    pub eta_inner: f64,
    #[default(1e-3)]
    #[garde(custom(positive("a learning rate > 0")))]
    pub eta_outer: f64,
    /// First-order MAML: do not differentiate through the inner steps.
    #[default(false)]
    pub first_order: bool,
    /// Meta-SGD (Li et al., 2017): learn eq. 14's step size, one per weight, initialised to
    /// `eta_inner` and updated by eq. 16's Adam together with w0; false is MAML's one fixed
    /// `eta_inner`.
    #[default(false)]
    pub learn_inner_lr: bool,
    /// The algorithm of MAML's inner and outer losses and of pretraining: `cql` (CQL-MAML, the
    /// paper's method), `dqn` (DQN-MAML, its ablation) or any registered one.
    #[default(Algo::CQL)]
    pub inner_loss: Algo,
    /// Eq. 8's conservative weight alpha in MAML's losses (eqs. 14-15) and in CQL-pretrain's
    /// multi-task training, the two inits; `learner.alpha` is the weight of the offline training
    /// and fine-tuning on a task's shots. The paper's alpha = 1 for both.
    #[default(1.0)]
    #[garde(custom(finite(0.0.., "a finite number >= 0")))]
    pub alpha: f64,
    /// Huber instead of squared TD error in MAML's losses (eqs. 14-15) even when fine-tuning keeps
    /// the square; `learner.huber` turns it on for both. Off to match eq. 7.
    #[default(false)]
    pub huber: bool,
    /// Meta-epochs between w0 checkpoints.
    #[default(10)]
    #[garde(custom(within(1.., "at least 1 meta-epoch")))]
    pub checkpoint_every: usize,
    /// Meta-epochs between refreshes of the target network Qhat from w0; Qhat is held constant
    /// through the inner and outer losses in between (see `meta/src/maml.rs`).
    #[default(1)]
    #[garde(custom(within(1.., "at least 1 meta-epoch")))]
    pub target_update_meta_epochs: usize,
    /// Meta-epochs between evaluations of each task's adapted greedy policy on its environment
    /// (costly: `learner.eval_episodes` episodes per task); 0 evaluates only after the last.
    #[default(10)]
    pub eval_every: usize,
    /// Polyak averaging of the meta-iterates: after every outer step the published init becomes
    /// `decay * init + (1 - decay) * w0`, an exponential moving average of w0 over the last
    /// 1 / (1 - decay) outer steps; checkpoints, evaluations and the meta-test use it, while eq.
    /// 16 keeps updating w0 itself. 0 = off: the init is the last iterate, whose return swung by
    /// up to 2.4k between neighbouring meta-epochs (docs/EXPERIMENTS.md, C7).
    #[default(0.0)]
    #[garde(custom(within(0.0..1.0, "a decay in [0, 1): 0 = no averaging")))]
    pub average_decay_per_outer_step: f64,
    /// beta: the meta-loss adds `beta * L(w0; query shots)` per task to eq. 15's
    /// `L(w_i; query shots)`, the loss of w0 before any inner step (the step-0 term of MAML++'s
    /// multi-step loss, Antoniou et al. 2019). Eq. 15 alone never asks w0's own greedy policy to
    /// be good, and its zero-shot return wanders by 10-15% over the meta-epochs
    /// (docs/EXPERIMENTS.md, C8-C10). 0 = eq. 15 as written.
    #[default(0.0)]
    #[garde(custom(finite(0.0.., "a finite number >= 0 (0 = eq. 15 as written)")))]
    pub w0_loss_weight: f64,
    /// Independent adaptations (each on fresh `shots` support shots) per task and evaluation;
    /// the reported return is their mean, so that a figure-4 point measures the adapted return
    /// rather than sampling one adaptation of it.
    #[default(1)]
    #[garde(custom(within(1.., "at least 1 adaptation per evaluation")))]
    pub eval_adaptations: usize,
}
