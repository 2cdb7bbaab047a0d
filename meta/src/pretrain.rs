//! Multi-task pretraining (CQL-pretrain): the baseline a MAML init has to beat.
//!
//! One Q-network is trained with MAML's algorithm (`meta.inner_loss`: CQL, eq. 8, for CQL-MAML)
//! on the union of every meta-train task's shots (support and query sets alike), then fine-tuned
//! on the unseen task exactly as `w0` is. It gets MAML's budget: as many gradient steps as
//! meta-training makes outer steps (`meta.meta_epochs` times the outer steps of a meta-epoch), each
//! on a minibatch as large as the shots one outer step reads (tasks x (`meta.support_batch_size` +
//! `meta.query_batch_size`)). What separates the two inits is then only what they are optimised for: the
//! tasks' average loss here, the loss after one adaptation step in MAML. If MAML adds nothing, the
//! two score alike.

use uavmeta_learner::algorithm;
use uavmeta_learner::progress::OnStep;
use uavmeta_learner::qnet::{QNetwork, QNetworkConfig};
use uavmeta_learner::train::OfflineTrainer;
use uavmeta_learner::transitions::Transitions;
use uavmeta_proto::config::Config;

use crate::maml::{MamlConfig, MetaTask};

/// A network trained with `meta.inner_loss` on the union of `tasks`' shots, from the init of
/// `seed`. After each meta-epoch's worth of steps it asks `keep_going` (with the count done), and
/// returns `None` when told to stop; an error from `keep_going` ends the pretraining with that
/// error. `on_step` is called at every gradient step.
pub fn pretrain<E>(
    config: &Config,
    tasks: &[MetaTask],
    seed: u64,
    on_step: OnStep,
    keep_going: impl FnMut(usize) -> Result<bool, E>,
) -> Result<Option<QNetwork>, E> {
    let union = Transitions::concat(tasks.iter().flat_map(|t| [&t.support, &t.query]));
    let q = QNetworkConfig::for_world(&config.world, &config.learner.hidden).init(seed);
    train_multi_task(q, &union, config, tasks, seed, on_step, keep_going)
}

/// `q` trained with `meta.inner_loss` on `union`, the rows of `tasks` (as they are, or with
/// something appended to each observation), with MAML's budget for `tasks`; see [`pretrain`].
pub fn train_multi_task<E>(
    mut q: QNetwork,
    union: &Transitions,
    config: &Config,
    tasks: &[MetaTask],
    seed: u64,
    on_step: OnStep,
    mut keep_going: impl FnMut(usize) -> Result<bool, E>,
) -> Result<Option<QNetwork>, E> {
    let maml = MamlConfig::from_config(config);
    let mut budget = config.clone();
    budget.learner.batch_size =
        tasks.len() * (maml.meta.support_batch_size + maml.meta.query_batch_size);
    budget.learner.alpha = maml.meta.alpha;
    algorithm::prepare(&mut q, config.meta.inner_loss, &config.learner);
    let mut trainer = OfflineTrainer::new(&q, union.len(), config.meta.inner_loss, &budget, seed)
        .with_on_step(on_step);
    for epoch in 1..=config.meta.meta_epochs {
        for _ in 0..maml.outer_steps(tasks) {
            trainer.step(&mut q, union);
        }
        if !keep_going(epoch)? {
            return Ok(None);
        }
    }
    Ok(Some(q))
}
