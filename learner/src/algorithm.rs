//! The offline algorithms: each a loss over a minibatch, registered once.
//!
//! An algorithm is one file that implements [`OfflineAlgorithm`] (its loss, written as its paper
//! writes it) and one line in [`ALGORITHMS`], in the order and under the name of
//! `uavmeta_proto::method::ALGORITHMS`. Everything that trains picks it up from there: offline
//! training and fine-tuning (`train::OfflineTrainer`), MAML's inner and outer losses
//! (`uavmeta_meta::maml`), multi-task pretraining, `uavmeta train --algo`, the launch's table and
//! the reproduction's.

use tch::Tensor;
use uavmeta_proto::method::Algo;

use crate::bc::Bc;
use crate::cql::Cql;
use crate::dqn::Dqn;
use crate::transitions::Transitions;

/// What every loss is made from, for one minibatch, or for T tasks' shots at once (a leading
/// task dimension on every tensor, as MAML evaluates them).
pub struct Terms<'a> {
    /// `Q_w(s, .)`: [B, A], or [T, B, A], with its graph back to the weights.
    pub q: &'a Tensor,
    /// The transitions (normalised, rewards scaled).
    pub batch: &'a Transitions,
    /// Eq. 7 averaged over the transitions, with the run's TD options (target network, double
    /// DQN, Huber): a scalar, or [T], with its graph.
    pub td: &'a Tensor,
    /// Averages a per-transition term [.., B] over the transitions the way `td` was: [..]. MAML
    /// pads tasks to one length and weighs the padding 0.
    pub mean: &'a dyn Fn(Tensor) -> Tensor,
    /// The conservative weight alpha of eq. 8 for this run (`learner.alpha`, or `meta.alpha` in
    /// MAML and pretraining); algorithms without one ignore it.
    pub alpha: f64,
}

/// An offline learning algorithm: the loss a Q-network minimises on logged transitions.
pub trait OfflineAlgorithm: Sync {
    /// Its name, as `uavmeta_proto::method::ALGORITHMS` registers it.
    fn name(&self) -> &'static str;

    /// The loss of `terms`' transitions, averaged with `terms.mean`: a scalar, or [T].
    fn loss(&self, terms: &Terms) -> Tensor;

    /// Whether the network's outputs estimate returns, so that the value guard
    /// (`learner.value_guard`) can judge them; an imitation loss, whose outputs are logits,
    /// says no.
    fn learns_values(&self) -> bool {
        true
    }
}

/// Every algorithm's loss, in the order of `uavmeta_proto::method::ALGORITHMS`.
pub const ALGORITHMS: &[&dyn OfflineAlgorithm] = &[&Cql, &Dqn, &Bc];

/// The loss of `algo`.
pub fn of(algo: Algo) -> &'static dyn OfflineAlgorithm {
    ALGORITHMS[algo.index()]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_registered_name_has_its_loss_in_the_same_place() {
        let names: Vec<&str> = ALGORITHMS.iter().map(|a| a.name()).collect();
        let registered: Vec<&str> = Algo::all().map(Algo::name).collect();
        assert_eq!(names, registered);
    }
}
