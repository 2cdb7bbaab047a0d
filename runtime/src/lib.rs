//! The processes of a run.
//!
//! - [`store`]: the dataset store process.
//! - [`meta_learner`]: the meta-learner process; [`launch`]: `uavmeta launch`, the supervisor
//!   of a run's processes. Each is a folder with its loop and its metrics.

pub mod launch;
pub mod meta_learner;
pub mod store;
