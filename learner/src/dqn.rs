//! The DQN loss, paper eq. 7:
//!
//! ```text
//! L_DQN(w) = mean_batch ( r + gamma * max_a' Qhat(s', a') - Q_w(s, a) )^2
//! ```
//!
//! `Qhat` is the target network, held fixed (no gradient flows through the target). The end of an
//! episode is a time limit, not a terminal state (docs/MODEL.md sections 1 and 5), so every
//! transition bootstraps: there is no `(1 - done)` factor.
//!
//! Two of d3rlpy's choices are options, both off by default so that the default is eq. 7 itself:
//! double DQN (the target network evaluates the online network's argmax) and a Huber TD loss.

use tch::{Reduction, Tensor};
use uavmeta_proto::config::LearnerConfig;

use crate::algorithm::{OfflineAlgorithm, Terms};
use crate::transitions::Transitions;

/// DQN on a fixed dataset, eq. 7 itself: the offline baseline that overestimates.
pub struct Dqn;

impl OfflineAlgorithm for Dqn {
    fn name(&self) -> &'static str {
        "dqn"
    }

    fn loss(&self, t: &Terms) -> Tensor {
        t.td.shallow_clone()
    }
}

/// Where eq. 7's bootstrap value `V(s')` comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Bootstrap {
    /// Eq. 7 as written: `max_a' Qhat(s', a')`.
    Max,
    /// Double DQN: the target network evaluates the online network's choice,
    /// `Qhat(s', argmax_a' Q(s', a'))`.
    Double,
}

impl Bootstrap {
    /// [`Bootstrap::Double`] when `double` is set (`learner.double_dqn`, `collect.dqn.double_dqn`).
    pub fn double_if(double: bool) -> Self {
        if double {
            Self::Double
        } else {
            Self::Max
        }
    }
}

/// How the temporal-difference loss is formed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TdConfig {
    /// Discount gamma.
    pub gamma: f64,
    pub bootstrap: Bootstrap,
    /// Huber (delta = 1) instead of the squared TD error.
    pub huber: bool,
}

impl TdConfig {
    /// Eq. 7 as written: max over the target network, squared error.
    pub fn eq7(gamma: f64) -> Self {
        Self {
            gamma,
            bootstrap: Bootstrap::Max,
            huber: false,
        }
    }

    /// Each transition's term of eq. 7 with these options and the bootstrap value of `algorithm`
    /// under `learner`'s settings, [B]
    /// (their mean is the loss): the whole target computation in one place, for offline
    /// training, the online DQN agent and MAML's inner and outer losses.
    ///
    /// `q` is the network's outputs on s, [B, heads * A], with its graph. `target` and `online`
    /// are the target network `Qhat` and the online network `Q_w` as functions of a batch of
    /// states; they are evaluated on `batch.next_obs` without a graph, `online` only where the
    /// bootstrap value needs it (double DQN, BCQ).
    pub fn td_errors(
        &self,
        (algorithm, learner): (&dyn OfflineAlgorithm, &LearnerConfig),
        q: &Tensor,
        batch: &Transitions,
        target: impl Fn(&Tensor) -> Tensor,
        online: impl Fn(&Tensor) -> Tensor,
    ) -> Tensor {
        let next_v = tch::no_grad(|| {
            let next_target = target(&batch.next_obs); // Qhat(s', .) [B, heads * A]
            algorithm.next_value(self, learner, &next_target, &|| online(&batch.next_obs))
        });
        td_errors(q, &next_v, batch, self.gamma, self.huber)
    }
}

impl From<&LearnerConfig> for TdConfig {
    fn from(cfg: &LearnerConfig) -> Self {
        Self {
            gamma: cfg.gamma,
            bootstrap: Bootstrap::double_if(cfg.double_dqn),
            huber: cfg.huber,
        }
    }
}

/// The bootstrap value of each next state, [B], without a graph.
///
/// `next_q_target` is `Qhat(s', .)` [B, A]; `next_q_online` gives `Q(s', .)` [B, A] and is called
/// only for [`Bootstrap::Double`]. Every function here also takes a leading task dimension
/// ([T, B, A] -> [T, B]), which is how MAML evaluates all its tasks in one pass.
pub fn next_value(
    bootstrap: Bootstrap,
    next_q_target: &Tensor,
    next_q_online: impl FnOnce() -> Tensor,
) -> Tensor {
    tch::no_grad(|| match bootstrap {
        Bootstrap::Max => next_q_target.amax(-1, false),
        Bootstrap::Double => {
            let a_star = next_q_online().argmax(-1, true); // [B, 1]
            next_q_target.gather(-1, &a_star, false).squeeze_dim(-1)
        }
    })
}

/// `Q(s, a_data)`: the Q-value of each transition's logged action. `q` [B, A] -> [B].
pub fn q_taken(q: &Tensor, batch: &Transitions) -> Tensor {
    q.gather(-1, &batch.actions.unsqueeze(-1), false)
        .squeeze_dim(-1)
}

/// Each transition's term of eq. 7 from a precomputed bootstrap value `next_v` [B] (see
/// [`next_value`]): `(y - Q(s, a))^2`, or its Huber form. `q` = `Q_w(s, .)` [B, A] carries the
/// graph; the result is [B], whose mean is the loss.
pub fn td_errors(
    q: &Tensor,
    next_v: &Tensor,
    batch: &Transitions,
    gamma: f64,
    huber: bool,
) -> Tensor {
    // y = r + gamma * V(s'), a constant of the optimisation (eq. 7's target term).
    let target = (&batch.rewards + next_v * gamma).detach();
    let q_sa = q_taken(q, batch); // [B]
    if huber {
        q_sa.huber_loss(&target, Reduction::None, 1.0)
    } else {
        (q_sa - target).square()
    }
}

/// Paper eq. 7: `mean (r + gamma * max_a' Qhat(s', a') - Q(s, a))^2`, a scalar.
///
/// `q` is `Q_w(s, .)` [B, A] (with its graph), `next_q_target` is `Qhat(s', .)` [B, A].
pub fn dqn_loss(q: &Tensor, next_q_target: &Tensor, batch: &Transitions, gamma: f64) -> Tensor {
    // mean_batch (y - Q(s, a))^2
    let next_v = next_value(Bootstrap::Max, next_q_target, || unreachable!("plain max"));
    td_errors(q, &next_v, batch, gamma, false).mean(None)
}
