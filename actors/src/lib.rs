//! The UAV side of uavmeta: the world and the policies that act in it. The actor and evaluator
//! processes that run them in a run are `uavmeta-runtime`'s.
//!
//! - [`world`], [`rollout`]: re-exported from `uavmeta_world`, the libtorch-free crate that owns
//!   the environment, rollouts and evaluation.
//! - [`policy`]: the behaviour policies.
//!   - [`policy::heuristics`]: re-exported from `uavmeta_world`: random, stalest-first, greedy,
//!     epsilon-mixed and replayed policies, and the `PolicySpec` parser.
//!   - [`policy::dqn_online`]: the online DQN agent (epsilon-greedy, replay buffer, target
//!     network) whose replay buffer becomes the paper's datasets.
//!   - [`policy::q_policy`]: a `uavmeta_learner` Q-network's greedy policy, and the evaluator
//!     that scores it for `uavmeta_learner::train`.
//! - [`collect`]: one task's offline dataset (SPEC section 4) from a behaviour policy.
//!
//! ```
//! use uavmeta_actors::policy::heuristics::StalestPolicy;
//! use uavmeta_actors::rollout::evaluate;
//! use uavmeta_proto::config::{Config, TaskConfig};
//!
//! let config = Config::default();
//! let task = TaskConfig::one_off(300.0, None);
//! let metrics = evaluate(&config.world, &task, &mut StalestPolicy, 5, 0);
//! assert!(metrics.aoi.mean >= 1.0);
//! ```

pub mod collect;
pub mod policy;

pub use uavmeta_world::{rollout, world};
