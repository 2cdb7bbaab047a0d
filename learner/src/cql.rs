//! Conservative Q-learning, paper eq. 8 (CQL(H) for discrete actions):
//!
//! ```text
//! L_CQL(w) = 0.5 * L_DQN(w) + alpha * mean_batch [ log sum_a exp Q_w(s, a) - Q_w(s, a_data) ]
//! ```
//!
//! The second term pushes down a soft maximum over all actions and pushes up the actions the data
//! took, so actions the dataset never tried cannot look better than the logged ones; that is what
//! keeps offline Q-values from the overestimation plain DQN suffers. Its gradient with respect to
//! `Q(s, .)` is `(softmax(Q(s, .)) - onehot(a_data)) / B` per row.

use tch::Tensor;
use uavmeta_proto::config::LearnerConfig;

use crate::algorithm::{OfflineAlgorithm, Terms};
use crate::dqn::q_taken;
use crate::transitions::Transitions;

/// CQL, eq. 8.
pub struct Cql;

impl OfflineAlgorithm for Cql {
    fn name(&self) -> &'static str {
        "cql"
    }

    fn loss(&self, t: &Terms) -> Tensor {
        let conservative = (t.mean)(conservative_rows(t.q, t.batch));
        eq8(t.td, &conservative, t.alpha)
    }
}

/// Eq. 8 from its two terms, however they were averaged: `0.5 * td + alpha * conservative`.
pub fn eq8(td: &Tensor, conservative: &Tensor, alpha: f64) -> Tensor {
    td * 0.5 + conservative * alpha
}

/// `mean_batch [logsumexp_a Q(s, a) - Q(s, a_data)]`, scalar, from `q` [B, A].
pub fn conservative_term(q: &Tensor, batch: &Transitions) -> Tensor {
    conservative_rows(q, batch).mean(None)
}

/// Each transition's `logsumexp_a Q(s, a) - Q(s, a_data)`: `q` [B, A] -> [B] (or, with a
/// leading task dimension, [T, B, A] -> [T, B]).
pub fn conservative_rows(q: &Tensor, batch: &Transitions) -> Tensor {
    q.logsumexp([-1i64], false) - q_taken(q, batch)
}

/// Paper eq. 8 on one minibatch, a scalar with its graph: `q` is `Q_w(s, .)` [B, A],
/// `next_q_target` is `Qhat(s', .)` [B, A] (eq. 7's plain max and squared error).
pub fn cql_loss(
    q: &Tensor,
    next_q_target: &Tensor,
    batch: &Transitions,
    gamma: f64,
    alpha: f64,
) -> Tensor {
    let td = crate::dqn::dqn_loss(q, next_q_target, batch, gamma);
    let mean = |rows: Tensor| rows.mean(None);
    Cql.loss(&Terms {
        q,
        batch,
        td: &td,
        mean: &mean,
        alpha,
        learner: &LearnerConfig::default(),
    })
}
