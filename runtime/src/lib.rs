//! The processes of a run, and what they share at run time. `uavmeta-proto` is the contract they
//! agree on (config, dataset format, payloads, service names, schema version, metric names); this
//! crate is how they live: it owns the run directory, the iceoryx2 transport, start-up, signals,
//! heartbeats and the /metrics endpoint, and the loop of every process kind. The libraries it
//! runs (`uavmeta-actors`, `uavmeta-learner`, `uavmeta-meta`) know nothing of processes; the
//! `uavmeta` binary's process subcommands call in here.
//!
//! What the processes share:
//! - [`run_dir`]: the run directory's layout ([`run_dir::RunDir`]: config, datasets,
//!   checkpoints, ports, metrics snapshots, logs, heartbeats, Prometheus and Grafana files),
//!   atomic writes into it, and a remote actor host's stand-in for the learner host's run.
//! - [`transport`]: iceoryx2 services for `uavmeta_proto::payload`'s messages, with the schema
//!   check, and the actors' transition publisher with backpressure.
//! - [`domain`]: an iceoryx2 domain's config and nodes, and the removal of what dead processes
//!   left in it (on a thread of its own: [`domain::Cleaner`]).
//! - [`liveness`]: termination requests (SIGINT, SIGTERM) and the heartbeat file a launched
//!   process beats while it makes progress.
//! - [`metrics`]: the /metrics endpoint, registries built from `uavmeta_proto::metrics`'s
//!   declarations, and the client that scrapes and reads an endpoint.
//! - [`process`]: the start-up every process shares, and the question its loop asks.
//!
//! The processes, one folder each with its loop and its metrics:
//! - [`actor`]: behaviour policies publishing transitions to the store.
//! - [`store`]: the dataset store, appending each task's transitions to its dataset file.
//! - [`meta_learner`]: MAML over the run's datasets as the store announces them, then meta-test.
//! - [`evaluator`]: every announced checkpoint's greedy policy scored in the true world.
//! - [`launch`]: `uavmeta launch`, the supervisor that starts, watches and stops the others.

pub mod actor;
pub mod domain;
pub mod evaluator;
pub mod launch;
pub mod liveness;
pub mod meta_learner;
pub mod metrics;
pub mod process;
pub mod run_dir;
pub mod store;
pub mod transport;
