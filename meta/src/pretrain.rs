//! CQL-pretrain: the multi-task baseline a MAML init has to beat.
//!
//! One Q-network is trained with plain CQL (eq. 8) on the union of every meta-train task's
//! shots (support and query sets alike), then fine-tuned on the unseen task exactly as a
//! CQL-MAML `w0` is. It sees the same data as MAML and the same number of passes over it
//! (`meta.meta_epochs` epochs of the union in minibatches of `learner.batch`), so what separates
//! the two is only how the init is optimised: for the tasks' average loss here, for the loss
//! after one adaptation step in MAML. If MAML adds nothing, the two inits score alike.

use uavmeta_learner::batch::Batch;
use uavmeta_learner::qnet::QNetwork;
use uavmeta_learner::train::{steps_per_epoch, Algorithm, OfflineTrainer};
use uavmeta_proto::config::Config;

use crate::maml::MetaTask;

/// The checkpoint algorithm name of a pretrained init; it is fine-tuned with CQL.
pub const ALGORITHM: &str = "cql-pretrain";

/// A network trained with CQL on the union of `tasks`' shots, from the init of `seed`, reporting
/// each finished epoch to `progress`.
pub fn pretrain(
    config: &Config,
    tasks: &[MetaTask],
    seed: u64,
    mut progress: impl FnMut(usize),
) -> QNetwork {
    let union = Batch::concat(tasks.iter().flat_map(|t| [&t.support, &t.query]));
    let w = &config.world;
    let mut q = QNetwork::new(
        w.observation_len(),
        w.action_count(),
        &config.learner.hidden,
        seed,
    );
    let mut trainer = OfflineTrainer::new(&q, union.len(), Algorithm::Cql, config, seed);
    let steps = steps_per_epoch(&config.learner, union.len());
    for epoch in 1..=config.meta.meta_epochs {
        for _ in 0..steps {
            trainer.step(&mut q, &union);
        }
        progress(epoch);
    }
    q
}
