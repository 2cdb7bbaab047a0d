//! Dyna-CQL: CQL (eq. 8) on the shots plus rollouts of the policy being trained in the world the
//! shots identify, as Dyna and MBPO add model rollouts to the real data (docs/MODEL.md section 5,
//! "Dyna-CQL"). A model-based method of this project's own, not one of the paper's rows.
//!
//! It is told the world's form with no task in it: the grid and its moves, the AoI update, the
//! reward's form (the weighted AoI sum plus a power cost) and the channel law (a device's power
//! grows as h^2 + r^2 d^2 with its distance d). It learns from the shots each device's power cost
//! (the power weight lambda / K included) and whether the task has rain
//! (`uavmeta_world::identify`); where the shots show rain, or are no steps of this world, there
//! is no model and it trains on the shots alone, as `cql` does.
//!
//! Before each epoch, `learner.model_rows` steps of its own network, acting epsilon-greedily
//! (`learner.model_epsilon`) from the shots' own states, join the shots ([`crate::model_rows`]).
//! Both are read by the TD term; the conservative term averages over the batch with the model
//! rows weighing 0, so it anchors only to what the data did, as COMBO's regulariser rewards the
//! data's actions and not the model's. Averaged over the whole batch, that term acts at about
//! alpha times the logged rows' share of it (docs/EXPERIMENTS.md, D24).
//!
//! ```text
//! L(w) = 0.5 * L_DQN(w; shots + model rows) + alpha * sum_{shots} [ logsumexp_a Q_w(s, a) - Q_w(s, a_data) ] / B
//! ```

use tch::Tensor;

use crate::algorithm::{OfflineAlgorithm, Terms};
use crate::cql::Cql;

/// Dyna-CQL: CQL's loss over the shots and model rows.
pub struct DynaCql;

impl OfflineAlgorithm for DynaCql {
    fn name(&self) -> &'static str {
        "dyna-cql"
    }

    fn loss(&self, t: &Terms) -> Tensor {
        Cql.loss(t)
    }

    fn model_rows(&self) -> bool {
        true
    }
}
