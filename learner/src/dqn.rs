//! The DQN loss, paper eq. 7:
//!
//! ```text
//! L_DQN(w) = mean_batch ( r + gamma * max_a' Qhat(s', a') - Q_w(s, a) )^2
//! ```
//!
//! `Qhat` is the target network, held fixed (no gradient flows through the target). The end of an
//! episode is a time limit, not a terminal state (SPEC sections 1 and 5), so every transition
//! bootstraps: there is no `(1 - done)` factor.
//!
//! Two of d3rlpy's choices are options, both off by default so that the default is eq. 7 itself:
//! double DQN (the target network evaluates the online network's argmax) and a Huber TD loss.

use tch::{Reduction, Tensor};
use uavmeta_proto::config::LearnerConfig;

use crate::batch::Batch;

/// How the temporal-difference loss is formed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TdConfig {
    /// Discount gamma.
    pub gamma: f64,
    /// Bootstrap with `Qhat(s', argmax_a' Q(s', a'))` instead of `max_a' Qhat(s', a')`.
    pub double_dqn: bool,
    /// Huber (delta = 1) instead of the squared TD error.
    pub huber: bool,
}

impl TdConfig {
    /// Eq. 7 as written: max over the target network, squared error.
    pub fn eq7(gamma: f64) -> Self {
        Self {
            gamma,
            double_dqn: false,
            huber: false,
        }
    }
}

impl From<&LearnerConfig> for TdConfig {
    fn from(cfg: &LearnerConfig) -> Self {
        Self {
            gamma: cfg.gamma,
            double_dqn: cfg.double_dqn,
            huber: cfg.huber,
        }
    }
}

/// The bootstrap value of each next state, [B], without a graph.
///
/// `next_q_target` is `Qhat(s', .)` [B, A]. With `next_q_online = Some(Q(s', .))` [B, A] this is
/// double DQN's `Qhat(s', argmax_a' Q(s', a'))`, otherwise eq. 7's `max_a' Qhat(s', a')`.
/// Every function here also takes a leading task dimension ([T, B, A] -> [T, B]), which is how
/// MAML evaluates all its tasks in one pass.
pub fn next_value(next_q_target: &Tensor, next_q_online: Option<&Tensor>) -> Tensor {
    tch::no_grad(|| match next_q_online {
        None => next_q_target.amax(-1, false),
        Some(online) => {
            let a_star = online.argmax(-1, true); // [B, 1]
            next_q_target.gather(-1, &a_star, false).squeeze_dim(-1)
        }
    })
}

/// `Q(s, a_data)`: the Q-value of each transition's logged action. `q` [B, A] -> [B].
pub fn q_taken(q: &Tensor, batch: &Batch) -> Tensor {
    q.gather(-1, &batch.actions.unsqueeze(-1), false)
        .squeeze_dim(-1)
}

/// Each transition's term of eq. 7 from a precomputed bootstrap value `next_v` [B] (see
/// [`next_value`]): `(y - Q(s, a))^2`, or its Huber form. `q` = `Q_w(s, .)` [B, A] carries the
/// graph; the result is [B], whose mean is the loss.
pub fn td_errors(q: &Tensor, next_v: &Tensor, batch: &Batch, gamma: f64, huber: bool) -> Tensor {
    // y = r + gamma * V(s'), a constant of the optimisation (eq. 7's target term).
    let target = (&batch.rewards + next_v * gamma).detach();
    let q_sa = q_taken(q, batch); // [B]
    if huber {
        q_sa.huber_loss(&target, Reduction::None, 1.0)
    } else {
        (q_sa - target).square()
    }
}

/// The TD loss of eq. 7 from a precomputed bootstrap value: the mean of [`td_errors`], a scalar.
pub fn td_loss(q: &Tensor, next_v: &Tensor, batch: &Batch, gamma: f64, huber: bool) -> Tensor {
    // mean_batch (y - Q(s, a))^2
    td_errors(q, next_v, batch, gamma, huber).mean(None)
}

/// Each transition's term of eq. 7 with the options of `td`, [B] (their mean is the loss);
/// `next_q_online` is needed (and only used) for double DQN.
///
/// # Panics
/// If `td.double_dqn` is set and `next_q_online` is `None`: the caller chose double DQN and must
/// evaluate the online network on `s'`.
pub fn td_errors_with(
    q: &Tensor,
    next_q_target: &Tensor,
    next_q_online: Option<&Tensor>,
    batch: &Batch,
    td: &TdConfig,
) -> Tensor {
    let online = if td.double_dqn {
        Some(next_q_online.expect("double DQN needs Q(s', .) of the online network"))
    } else {
        None
    };
    td_errors(
        q,
        &next_value(next_q_target, online),
        batch,
        td.gamma,
        td.huber,
    )
}

/// Paper eq. 7: `mean (r + gamma * max_a' Qhat(s', a') - Q(s, a))^2`, a scalar.
///
/// `q` is `Q_w(s, .)` [B, A] (with its graph), `next_q_target` is `Qhat(s', .)` [B, A].
pub fn dqn_loss(q: &Tensor, next_q_target: &Tensor, batch: &Batch, gamma: f64) -> Tensor {
    td_loss(q, &next_value(next_q_target, None), batch, gamma, false)
}
