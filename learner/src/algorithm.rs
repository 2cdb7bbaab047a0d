//! The offline algorithms: each a loss over a minibatch, registered once.
//!
//! An algorithm is one file that implements [`OfflineAlgorithm`] (its loss, written as its paper
//! writes it) and one line in [`ALGORITHMS`], in the order and under the name of
//! `uavmeta_proto::method::ALGORITHMS`. Everything that trains picks it up from there: offline
//! training and fine-tuning (`train::OfflineTrainer`), MAML's inner and outer losses
//! (`uavmeta_meta::maml`), multi-task pretraining, `uavmeta train --algo`, the launch's table and
//! the reproduction's.

use tch::Tensor;
use uavmeta_proto::config::LearnerConfig;
use uavmeta_proto::method::Algo;

use crate::bc::Bc;
use crate::bcq::Bcq;
use crate::cql::Cql;
use crate::dqn::{next_value, Dqn, TdConfig};
use crate::dyna_cql::DynaCql;
use crate::qnet::{q_values, Acting, QNetwork};
use crate::transitions::Transitions;

/// What every loss is made from, for one minibatch, or for T tasks' shots at once (a leading
/// task dimension on every tensor, as MAML evaluates them).
pub struct Terms<'a> {
    /// The network's outputs on s, [B, heads * A] (or [T, ..]) with their graph back to the
    /// weights: `Q_w(s, .)` itself for a one-head algorithm.
    pub q: &'a Tensor,
    /// The transitions (normalised, rewards scaled).
    pub batch: &'a Transitions,
    /// Eq. 7 averaged over the transitions, with the run's TD options (target network, double
    /// DQN, Huber): a scalar, or [T], with its graph.
    pub td: &'a Tensor,
    /// Averages a per-transition term [.., B] over the transitions: [..]. MAML pads tasks to one
    /// length and weighs the padding 0; a model-based algorithm's model rows (`crate::model_rows`)
    /// weigh 0 too, so its own terms read only what the data did, while `td` reads every row.
    pub mean: &'a dyn Fn(Tensor) -> Tensor,
    /// The conservative weight alpha of eq. 8 for this run (`learner.alpha`, or `meta.alpha` in
    /// MAML and pretraining); algorithms without one ignore it.
    pub alpha: f64,
    /// The `[learner]` section, for an algorithm's own settings (`learner.bcq_threshold`).
    pub learner: &'a LearnerConfig,
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

    /// Whether it also trains on rollouts in the world its shots identify (`learner.model_rows`
    /// of them an epoch, [`crate::model_rows`]): a model-based algorithm.
    fn model_rows(&self) -> bool {
        false
    }

    /// Blocks of A outputs the network needs: the Q-values, then the algorithm's own.
    fn heads(&self) -> usize {
        1
    }

    /// Eq. 7's bootstrap value `V(s')` [.., B], without a graph, from the target network's
    /// outputs on s' and (called only if needed) the online network's: by default `max_a'
    /// Qhat(s', a')`, or double DQN's choice with `learner.double_dqn`.
    fn next_value(
        &self,
        td: &TdConfig,
        _learner: &LearnerConfig,
        next_target: &Tensor,
        next_online: &dyn Fn() -> Tensor,
    ) -> Tensor {
        let heads = self.heads();
        next_value(td.bootstrap, &q_values(next_target, heads), || {
            q_values(&next_online(), heads)
        })
    }

    /// How a network it trained acts, if not greedily on its Q-values: outputs [.., heads * A]
    /// to the values [.., A] whose argmax is the action.
    fn acting(&self, _learner: &LearnerConfig) -> Option<Acting> {
        None
    }
}

/// Every algorithm's loss, in the order of `uavmeta_proto::method::ALGORITHMS`.
pub const ALGORITHMS: &[&dyn OfflineAlgorithm] = &[&Cql, &Dqn, &Bc, &Bcq, &DynaCql];

/// The loss of `algo`.
pub fn of(algo: Algo) -> &'static dyn OfflineAlgorithm {
    ALGORITHMS[algo.index()]
}

/// Makes `q` a network `algo` trains and acts with: its heads (the Q-values kept) and its
/// acting rule under `learner`'s settings.
pub fn prepare(q: &mut QNetwork, algo: Algo, learner: &LearnerConfig) {
    let algorithm = of(algo);
    if q.config().heads != algorithm.heads() {
        *q = q.with_heads(algorithm.heads());
    }
    q.set_acting(algorithm.acting(learner));
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_registered_name_has_its_loss_in_the_same_place() {
        let names: Vec<&str> = ALGORITHMS.iter().map(|a| a.name()).collect();
        let registered: Vec<&str> = Algo::all().map(Algo::name).collect();
        assert_eq!(names, registered);
        for algo in Algo::all() {
            assert_eq!(of(algo).model_rows(), algo.model_based(), "{algo}");
        }
    }
}
