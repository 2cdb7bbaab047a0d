//! The UAV side of uavmeta: the world, the policies that act in it, and the processes that run
//! them.
//!
//! - [`world`]: [`world::World`], one task's environment (SPEC sections 1 and 3), built from
//!   `uavmeta_proto::config`'s `WorldConfig` and `TaskConfig`; a step allocates nothing.
//! - [`rollout`]: the [`rollout::Policy`] trait, single episodes with their
//!   `uavmeta_proto::stats::EpisodeMetrics`, and Monte-Carlo evaluation over fixed episode seeds.
//! - [`policy`]: the behaviour policies.
//!   - [`policy::heuristics`]: random, stalest-first, greedy, epsilon-mixed and replayed
//!     policies, and the `PolicySpec` parser behind `--policy` and `collect.policy`.
//!   - [`policy::dqn_online`]: the online DQN agent (epsilon-greedy, replay buffer, target
//!     network) whose replay buffer becomes the paper's datasets.
//!   - [`policy::q_policy`]: a `uavmeta_learner` Q-network's greedy policy, and the evaluator
//!     that scores it for `uavmeta_learner::train`.
//! - [`collect`]: one task's offline dataset (SPEC section 4) from a behaviour policy.
//! - [`actor`]: the actor process, behaviour policies publishing transitions to the store over
//!   iceoryx2; its folder holds its loop, its delivery and its metrics.
//! - [`evaluator`]: the evaluator process, greedy Q-policies of announced checkpoints scored in
//!   the true world; its folder holds its loop and its metrics.
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

pub mod actor;
pub mod collect;
pub mod evaluator;
pub mod policy;
pub mod rollout;
pub mod world;
