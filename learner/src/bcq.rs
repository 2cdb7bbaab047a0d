//! Discrete batch-constrained Q-learning (Fujimoto, Conti, Ghavamzadeh and Pineau 2019,
//! "Benchmarking batch deep reinforcement learning algorithms"), as d3rlpy's `DiscreteBCQ`: a
//! Q-network that may only choose actions the data supports, judged by an imitation model of the
//! data's policy on the same hidden layers (the network's second head, logits `g_w(s, .)`):
//!
//! ```text
//! G_w(a | s) = softmax(g_w(s, .))[a]                                  the data's policy
//! A_tau(s)   = { a : G_w(a | s) / max_a' G_w(a' | s) > tau }          the supported actions
//! a*(s')     = argmax_{a in A_tau(s')} Q_w(s', a)
//! L_BCQ(w)   = mean_batch ( r + gamma * Qhat(s', a*(s')) - Q_w(s, a) )^2
//!            + mean_batch [ log sum_a exp g_w(s, a) - g_w(s, a_data) ]
//!            + beta * mean_batch mean_a g_w(s, a)^2
//! pi(s)      = argmax_{a in A_tau(s)} Q_w(s, a)
//! ```
//!
//! The first term is eq. 7 with the bootstrap action restricted to `A_tau`, chosen by the online
//! network and valued by the target network (BCQ's double-DQN target); the second and third are
//! behaviour cloning's loss on the imitation head (`crate::bc`, d3rlpy's beta = 0.5). `tau` is
//! `learner.bcq_threshold` (0.3, the paper's and d3rlpy's `action_flexibility`): tau = 0 is DQN
//! with double-DQN targets, tau = 1 behaviour cloning's most likely action.

use std::sync::Arc;

use tch::Tensor;
use uavmeta_proto::config::LearnerConfig;

use crate::algorithm::{OfflineAlgorithm, Terms};
use crate::bc::{log_prob_size, BETA};
use crate::cql::conservative_rows;
use crate::dqn::TdConfig;
use crate::qnet::{head, q_values, Acting};

/// Discrete BCQ.
pub struct Bcq;

impl OfflineAlgorithm for Bcq {
    fn name(&self) -> &'static str {
        "bcq"
    }

    /// The Q-values, then the imitation logits `g_w(s, .)`.
    fn heads(&self) -> usize {
        2
    }

    fn loss(&self, t: &Terms) -> Tensor {
        let logits = imitation_logits(t.q);
        // -log G_w(a_data | s) of each transition [.., B].
        let nll = conservative_rows(&logits, t.batch);
        t.td + (t.mean)(nll) + (t.mean)(log_prob_size(&logits)) * BETA
    }

    /// `Qhat(s', a*(s'))`, `a*` the online network's best supported action.
    fn next_value(
        &self,
        _td: &TdConfig,
        learner: &LearnerConfig,
        next_target: &Tensor,
        next_online: &dyn Fn() -> Tensor,
    ) -> Tensor {
        let a_star = supported_values(&next_online(), learner.bcq_threshold).argmax(-1, true);
        q_values(next_target, 2)
            .gather(-1, &a_star, false)
            .squeeze_dim(-1)
    }

    fn acting(&self, learner: &LearnerConfig) -> Option<Acting> {
        let threshold = learner.bcq_threshold;
        Some(Arc::new(move |outputs| {
            supported_values(outputs, threshold)
        }))
    }
}

/// The imitation head's logits `g_w(s, .)`: the second block of the outputs [.., 2A].
fn imitation_logits(outputs: &Tensor) -> Tensor {
    head(outputs, 2, 1)
}

/// The Q-values of the supported actions `A_tau(s)` shifted to be positive, and 0 elsewhere, from
/// the outputs [.., 2A]: their argmax is the best supported action (d3rlpy's rule; the shift
/// keeps an unsupported action from winning when every supported Q is negative). The ratio
/// `G_w(a | s) / max_a' G_w(a' | s)` is `exp(g_w(s, a) - max_a' g_w(s, a'))`: the softmax's
/// normaliser cancels.
pub fn supported_values(outputs: &Tensor, threshold: f64) -> Tensor {
    let logits = imitation_logits(outputs);
    let log_ratio = &logits - logits.amax([-1i64].as_slice(), true);
    let supported = log_ratio.ge(threshold.ln());
    let q = q_values(outputs, 2);
    let shifted = &q - q.amin([-1i64].as_slice(), true) + 1e-5;
    shifted * supported
}
