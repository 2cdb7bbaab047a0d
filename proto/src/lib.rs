//! The contract between uavmeta's processes: what they read and write, what they send each
//! other and what they export, and nothing of how they run (that is `uavmeta-runtime`).
//!
//! - [`config`]: the experiment configuration (docs/MODEL.md section 7), read from TOML with every
//!   default, `--set` overrides and validation errors that name the file, key and value.
//! - [`dataset`]: the on-disk dataset format that collectors and the store write and learners read.
//! - [`layout`]: [`layout::Layout`], where the cell and each AoI sit in an observation and which
//!   move and device an action index means.
//! - [`fs`]: atomic file writes, for files other processes read while they change.
//! - [`method`]: [`method::Method`], which method made a checkpoint or a row: its name, label,
//!   loss and init.
//! - [`stats`]: episode metrics (docs/MODEL.md section 1) and their Monte-Carlo summaries.
//! - [`payload`]: the zero-copy payload types and iceoryx2 service names shared by the actor,
//!   store, meta-learner and evaluator processes, with the schema version they must agree on.
//! - [`resources`]: what a config will make a process allocate, checked against the memory and
//!   disk it may use before anything is allocated.
//! - [`metrics`]: every metric name and help text the processes export, so a renamed metric is a
//!   compile error in every reader.
//!
//! The feature `ipc` makes the payloads iceoryx2 zero-copy types; without it (as the readers of
//! datasets, the world and the Python package take this crate) no iceoryx2 is built.
//!
//! ```
//! use uavmeta_proto::config::Config;
//! let config = Config::from_toml_str("[world]\ndevices = 5", "example.toml", &["tasks.0.lambda=7".into()]).unwrap();
//! assert_eq!(config.world.layout().observation_len(), 7);
//! assert_eq!(config.tasks[0].lambda, 7.0);
//! ```

pub mod config;
pub mod dataset;
pub mod fs;
pub mod layout;
pub mod method;
pub mod metrics;
pub mod payload;
pub mod resources;
pub mod stats;
