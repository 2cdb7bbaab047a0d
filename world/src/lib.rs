//! The world every uavmeta process and user steps, and the fixed policies that act in it; it
//! links no libtorch, so the Python package and the tools that only simulate can use it.
//!
//! - [`world`]: [`world::World`], one task's environment (docs/MODEL.md sections 1 and 3), built
//!   from `uavmeta_proto::config`'s `WorldConfig` and `TaskConfig`; a step allocates nothing.
//! - [`rollout`]: the [`rollout::Policy`] trait, single episodes with their
//!   `uavmeta_proto::stats::EpisodeMetrics`, and evaluation: exact over every start cell where
//!   the world is deterministic, Monte-Carlo over fixed episode seeds where the rain moves.
//! - [`planner`]: the planner reference, a beam search that knows the world (docs/MODEL.md section
//!   9), the measure of what is achievable; [`schedule`] improves its plan by local search over
//!   the device schedule, each schedule flown by its exact cheapest path.
//! - [`heuristics`]: random, stalest-first, greedy, epsilon-mixed and replayed policies, and the
//!   `PolicySpec` parser behind `--policy` and `collect.policy`.
//! - [`identify`]: the world as a fine-tuning run's own shots identify it, where the run scores
//!   the networks it may keep (docs/MODEL.md section 5).
//! - [`validate`]: whether a transition is one the world makes ([`validate::Validator`]), which
//!   the store checks before it appends a batch and `uavmeta dataset inspect` checks in a file.

pub mod heuristics;
pub mod identify;
pub mod planner;
pub mod rollout;
pub mod schedule;
mod team_planner;
pub mod validate;
pub mod world;
