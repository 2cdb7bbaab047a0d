//! Behaviour cloning for discrete actions, as d3rlpy's `DiscreteBC`: the network's outputs are
//! read as the logits `f_w(s, .)` of a policy `softmax(f_w(s, .))`, fitted to the logged actions
//! by cross-entropy, with d3rlpy's penalty on the size of the log-probabilities (what
//! `Categorical(logits=f).logits` holds):
//!
//! ```text
//! L_BC(w) = mean_batch [ log sum_a exp f_w(s, a) - f_w(s, a_data) ]
//!         + beta * mean_batch mean_a (log_softmax f_w(s, .))_a^2
//! ```
//!
//! The first term is the negative log-likelihood of the data's action; it is eq. 8's conservative
//! term without its TD part. The second keeps the logits from growing without bound on actions
//! the data always takes (beta = 0.5, d3rlpy's default). Rewards play no part: BC is the level
//! any offline RL method has to beat on its own data. It acts through the same greedy policy as
//! the Q-learners (its most likely action), so every table and evaluation takes it as it is.

use tch::Tensor;

use crate::algorithm::{OfflineAlgorithm, Terms};
use crate::cql::conservative_rows;

/// d3rlpy's `DiscreteBCConfig.beta`: the weight of the penalty on the logits' size.
pub const BETA: f64 = 0.5;

/// Behaviour cloning.
pub struct Bc;

/// d3rlpy's penalty of a discrete imitation: `mean_a (log_softmax f)_a^2` of each row of
/// `logits` [.., B, A] -> [.., B].
pub fn log_prob_size(logits: &Tensor) -> Tensor {
    let log_probs = logits.log_softmax(-1, tch::Kind::Float);
    log_probs.square().mean_dim([-1i64].as_slice(), false, None)
}

impl OfflineAlgorithm for Bc {
    fn name(&self) -> &'static str {
        "bc"
    }

    fn loss(&self, t: &Terms) -> Tensor {
        // -log softmax(f_w(s, .))[a_data] of each transition [.., B].
        let nll = conservative_rows(t.q, t.batch);
        (t.mean)(nll) + (t.mean)(log_prob_size(t.q)) * BETA
    }

    /// Its outputs are logits, not returns.
    fn learns_values(&self) -> bool {
        false
    }
}
