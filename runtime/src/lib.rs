//! The processes of a run.
//!
//! - [`actor`], [`store`], [`evaluator`]: the actor, dataset store and evaluator processes.
//! - [`meta_learner`]: the meta-learner process; [`launch`]: `uavmeta launch`, the supervisor
//!   of a run's processes. Each is a folder with its loop and its metrics.

pub mod actor;
pub mod evaluator;
pub mod launch;
pub mod meta_learner;
pub mod store;
