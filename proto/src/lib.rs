//! The contract between uavmeta's processes (what they read and write, what they send each other,
//! what they export) and the start-up they all share.
//!
//! - [`config`]: the experiment configuration (SPEC section 7), read from TOML with every SPEC
//!   default, `--set` overrides and validation errors that name the file, key and value.
//! - [`dataset`]: the on-disk dataset format that collectors and the store write and learners read.
//! - [`method`]: [`method::Method`], which method made a checkpoint or a row: its name, label,
//!   loss and init.
//! - [`stats`]: episode metrics (SPEC section 1) and their Monte-Carlo summaries.
//! - [`transport`]: the zero-copy payload types and iceoryx2 service names shared by the actor,
//!   store, meta-learner and evaluator processes, with the schema version they must agree on,
//!   and the run directory's layout.
//! - [`process`]: the start-up every process shares (node, services, /metrics, shutdown).
//! - [`metrics`]: every metric name and help text the processes export (so a renamed metric is a
//!   compile error in every reader), the /metrics endpoint they serve and the client that reads it.
//!
//! `transport`, `process` and `metrics` are the default feature `ipc`; without it (as
//! `uavmeta-world` and the Python package take this crate) neither iceoryx2 nor Prometheus is built.
//!
//! ```
//! use uavmeta_proto::config::Config;
//! let config = Config::from_toml_str("[world]\ndevices = 5", "example.toml", &["tasks.0.lambda=7".into()]).unwrap();
//! assert_eq!(config.world.observation_len(), 7);
//! assert_eq!(config.tasks[0].lambda, 7.0);
//! ```

pub mod config;
pub mod dataset;
pub mod method;
#[cfg(feature = "ipc")]
pub mod metrics;
#[cfg(feature = "ipc")]
pub mod process;
pub mod stats;
#[cfg(feature = "ipc")]
pub mod transport;
