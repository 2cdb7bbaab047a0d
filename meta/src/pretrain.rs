//! CQL-pretrain: the multi-task baseline a MAML init has to beat.
//!
//! One Q-network is trained with plain CQL (eq. 8) on the union of every meta-train task's
//! shots (support and query sets alike), then fine-tuned on the unseen task exactly as a
//! CQL-MAML `w0` is. It gets MAML's budget: as many gradient steps as meta-training makes outer
//! steps (`meta.meta_epochs` times the outer steps of a meta-epoch), each on a minibatch as large
//! as the shots one outer step reads (tasks x (`meta.shots` + `meta.query_shots`)). What separates
//! the two inits is then only what they are optimised for: the tasks' average loss here, the loss
//! after one adaptation step in MAML. If MAML adds nothing, the two score alike.

use uavmeta_learner::batch::Batch;
use uavmeta_learner::progress::OnStep;
use uavmeta_learner::qnet::{QNetwork, QNetworkConfig};
use uavmeta_learner::train::OfflineTrainer;
use uavmeta_proto::config::{Config, Loss};

use crate::maml::{MamlConfig, MetaTask};

/// A network trained with CQL on the union of `tasks`' shots, from the init of `seed`. After each
/// meta-epoch's worth of steps it asks `keep_going` (with the count done), and returns `None`
/// when told to stop; an error from `keep_going` ends the pretraining with that error. `on_step`
/// is called at every gradient step.
pub fn pretrain<E>(
    config: &Config,
    tasks: &[MetaTask],
    seed: u64,
    on_step: OnStep,
    mut keep_going: impl FnMut(usize) -> Result<bool, E>,
) -> Result<Option<QNetwork>, E> {
    let union = Batch::concat(tasks.iter().flat_map(|t| [&t.support, &t.query]));
    let maml = MamlConfig::from_config(config);
    let mut budget = config.clone();
    budget.learner.batch = tasks.len() * (maml.meta.shots + maml.meta.query_shots);
    budget.learner.alpha = maml.meta.alpha;
    let w = &config.world;
    let mut q = QNetworkConfig::for_world(w, &config.learner.hidden).init(seed);
    let mut trainer =
        OfflineTrainer::new(&q, union.len(), Loss::Cql, &budget, seed).with_on_step(on_step);
    for epoch in 1..=config.meta.meta_epochs {
        for _ in 0..maml.outer_steps(tasks) {
            trainer.step(&mut q, &union);
        }
        if !keep_going(epoch)? {
            return Ok(None);
        }
    }
    Ok(Some(q))
}
