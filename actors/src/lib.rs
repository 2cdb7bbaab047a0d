//! The behaviour policies that need a Q-network, and data collection: what an actor runs beyond
//! the fixed heuristics. The world, rollouts, evaluation and the heuristics are `uavmeta_world`'s
//! (no libtorch); the actor and evaluator processes that run these in a run are
//! `uavmeta-runtime`'s.
//!
//! - [`policy`]: [`policy::build`] makes any behaviour policy from its spec, heuristics included.
//!   - [`policy::dqn_online`]: the online DQN agent (epsilon-greedy, replay buffer, target
//!     network) whose replay buffer becomes the paper's datasets.
//!   - [`policy::q_policy`]: a `uavmeta_learner` Q-network's greedy policy, and the evaluator
//!     that scores it for `uavmeta_learner::train`.
//! - [`collect`]: one task's offline dataset (docs/MODEL.md section 4) from a behaviour policy.
//!
//! ```
//! use uavmeta_actors::policy;
//! use uavmeta_proto::config::{Config, TaskConfig};
//! use uavmeta_world::heuristics::PolicySpec;
//! use uavmeta_world::rollout::evaluate;
//!
//! // A behaviour policy from its spec (`collect.policy`): stalest-first, 10% random actions.
//! let config = Config::default();
//! let spec: PolicySpec = "eps:0.1".parse().unwrap();
//! let mut behaviour = policy::build(&spec, &config, 0, None).unwrap();
//! let task = TaskConfig::one_off(300.0, None);
//! let metrics = evaluate(&config.world, &task, behaviour.as_mut(), 5, 0);
//! assert!(metrics.aoi.mean >= 1.0);
//! ```

pub mod collect;
pub mod policy;
