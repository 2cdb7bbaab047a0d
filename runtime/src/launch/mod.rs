//! `uavmeta launch`: one run on one host, supervised.
//!
//! The launcher makes the run directory (config, `prometheus.yml`), then starts, as children of
//! its own: the store, `collect.actors_per_task` actors per task, the meta-learner and the
//! evaluator. Each child runs the same `uavmeta` binary with `--run DIR`, in its own process group
//! (so a terminal's Ctrl-C reaches only the launcher, which then stops the children in order), with
//! `PR_SET_PDEATHSIG` so that it gets SIGTERM if the launcher dies (no orphans), and with its
//! output in `logs/<name>.log`.
//!
//! With `tunnel.listen` set it also starts `uavmeta tunnel serve` (after the store), through which
//! remote actor hosts publish into the run; what they announce lands in `remote-hosts/`, and
//! their processes join `prometheus-targets.json` under their own `host` label.
//!
//! Supervision: a child that exits with failure (or is killed) is restarted after a backoff of
//! 0.5 s, 1 s, 2 s, ... (at most 10 s), up to `run.max_restarts` times; the dead process's iceoryx2
//! resources are removed first, so survivors never wait on its buffers. A child that stops making
//! progress (SIGSTOP, a deadlock, a livelocked libtorch) is treated the same: each child beats
//! (`liveness::heartbeat`, the modification time of `heartbeats/<name>`, named in its
//! environment), and one silent for `run.hang_timeout_seconds` is killed (SIGKILL to its process
//! group), counted in `uavmeta_launcher_child_hangs_total`
//! (`uavmeta_proto::metrics::launcher::CHILD_HANGS`) and restarted. A child that exits successfully
//! is done: actors end when their task's dataset is complete, the meta-learner when it has
//! meta-tested. Then the launcher announces a shutdown, the evaluator finishes the checkpoints it
//! was told about, the store syncs its files, and the launcher prints a results table from the
//! evaluator's CSV.
//!
//! On SIGINT/SIGTERM it stops the children gracefully: actors first (so the store receives
//! everything they sent), then the meta-learner and the evaluator, then the store; a child still
//! running after a grace period is killed.
//!
//! Files: this one starts a run and reports it ([`launch`]); `plan.rs` the children of a run,
//! `supervise.rs` the supervision loop, `targets.rs` the Prometheus configuration, `remote.rs`
//! the remote actor hosts, `report.rs` the results table, `display.rs` the terminal rows,
//! `seeds.rs` a launch over several seeds, `reuse.rs` a run directory used again, `resources.rs`
//! whether the machine can hold the run.

use std::fs::OpenOptions;
use std::os::unix::process::CommandExt;
use std::path::PathBuf;
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant, SystemTime};

use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use indicatif::MultiProgress;
use uavmeta_proto::config::{Config, TaskRole};
use uavmeta_proto::payload::{
    CheckpointReady, DatasetReady, ServiceNames, Shutdown, SCHEMA_VERSION,
};
use uavmeta_world::heuristics::PolicySpec;

use crate::actor::ActorOptions;
use crate::metrics::{wait_for_port, MetricsError, MetricsServer};
use crate::run_dir::{write_atomic, FileError, RunDir};
use crate::transport::{self, TransportError};
use crate::{domain, evaluator, liveness, meta_learner, store};

mod display;
mod metrics;
mod plan;
mod remote;
mod report;
pub mod resources;
pub mod reuse;
pub mod seeds;
mod stall;
mod supervise;
mod targets;

use plan::{plan, Role, Supervised};
use remote::{wait_for_remote_hosts, TUNNEL_PROCESS};
use report::{latest_results, model_planner_rows, reference_rows};
pub use report::{results_table, LaunchReport};
pub use reuse::Reuse;
pub use seeds::{launch_seeds, SeedsReport};
pub use stall::Stall;
use supervise::{start_children, stop_all, supervise, Announcements, Supervisor, CLEANUP_WAIT};
use targets::{write_prometheus_yml, write_targets, Targets};

/// How often the run's `prometheus.yml` has Prometheus scrape every process; `uavmeta dashboard
/// render` takes it for the interval of its rates.
pub const SCRAPE_INTERVAL_SECONDS: u64 = 5;

/// The Grafana dashboard of a run's metrics, copied into every run directory beside
/// `prometheus.yml`; embedded so that the binary writes it from any working directory.
const DASHBOARD: &str = include_str!("../../../docs/grafana/uavmeta.json");

/// The launcher's process name: node, port file, metrics snapshot.
pub const PROCESS: &str = "launcher";
#[derive(Debug, thiserror::Error)]
pub enum LaunchError {
    #[error(transparent)]
    Transport(#[from] TransportError),
    #[error(transparent)]
    File(#[from] FileError),
    #[error(transparent)]
    Metrics(#[from] MetricsError),
    #[error("cannot start `{name}` ({exe})", exe = exe.display())]
    Spawn {
        name: String,
        exe: PathBuf,
        source: std::io::Error,
    },
    #[error("`{name}` failed {failures} times (last: {status}); giving up after run.max_restarts = {max}; its log: {}", log.display())]
    GaveUp {
        name: String,
        failures: u32,
        status: String,
        max: u32,
        log: PathBuf,
    },
    #[error("{origin}: key `collect.policy`: {message}")]
    Policy { origin: String, message: String },
    #[error(transparent)]
    Config(#[from] uavmeta_proto::config::ConfigError),
    #[error("stopped by a termination request")]
    Interrupted,
    #[error("the store exited ({status}) before it was ready: {cause} (its log: {})", log.display())]
    StoreFailed {
        status: String,
        cause: String,
        log: PathBuf,
    },
    #[error(
        "every process of the run has exited, but its work is not done ({ready} of {tasks} \
         datasets announced, meta-learning {learning}) and the launcher announced no shutdown: \
         was one announced from outside? The run stays as it is; launch again to continue it"
    )]
    EndedEarly {
        ready: usize,
        tasks: usize,
        learning: &'static str,
    },
    #[error(
        "a shutdown was announced on the run's services by another process than this launcher, \
         before the run's work was done; its processes stop, so the run ends here unfinished \
         (launch again to continue it)"
    )]
    ForeignShutdown,
    #[error(
        "the dataset of task `{}` has held {} of its {} transitions for {:.0} s \
         (run.hang_timeout_seconds) while its actors went on: {}; {}. The run stays as it is; \
         launch again to continue it",
        .0.task, .0.stored, .0.target, .0.seconds, .0.actors, .0.cause
    )]
    DatasetStalled(Box<stall::Stall>),
    #[error("run directory {}: {message}", dir.display())]
    Reuse { dir: PathBuf, message: String },
    #[error("this machine cannot hold the run: {message}")]
    Resources { message: String },
    #[error(
        "tunnel.wait_for_hosts: after {seconds} s (tunnel.wait_seconds), hosts {missing} have \
         announced no actor and the store has {stored} transitions; is `uavmeta tunnel join \
         --connect <this host's address for {endpoint}>` running there, with actors?"
    )]
    RemoteHosts {
        missing: String,
        stored: f64,
        endpoint: String,
        seconds: f64,
    },
}

/// Runs `config` as one supervised run in `config.run.dir`, children started from `exe` (the
/// `uavmeta` binary). With a `terminal`, it shows what every process is doing there (`display`);
/// whatever else writes to that terminal meanwhile (the log lines) must go through its
/// `suspend`. A directory that holds a run already is used as `reuse` says ([`reuse::prepare`]).
pub fn launch(
    exe: PathBuf,
    config: &Config,
    reuse: Reuse,
    terminal: Option<&MultiProgress>,
) -> Result<LaunchReport, LaunchError> {
    config.validate_launch()?;
    resources::check_here(config)?;
    reuse::prepare(config, reuse)?;
    let run = RunDir::create(&config.run.dir)?;
    write_atomic(&run.config_file(), config.to_toml_string().as_bytes())?;
    write_prometheus_yml(&run)?;
    write_atomic(&run.grafana_dashboard(), DASHBOARD.as_bytes())?;
    let node = domain::node(&format!("{}-{PROCESS}", run.id()), &config.run)?;
    domain::cleanup_dead_nodes(&node);
    let names = ServiceNames::new(run.id());
    let launcher_metrics = metrics::LauncherMetrics::new();
    let _server = MetricsServer::start(
        launcher_metrics.registry.clone(),
        &config.run.metrics_host,
        config.run.metrics_port,
        &run,
        PROCESS,
    )?;
    let announcements = Announcements::open(&node, &names, config)?;

    let mut children = plan(&run, config)?;
    for child in &children {
        launcher_metrics.restarts.with_label_values(&[&child.name]);
        launcher_metrics.hangs.with_label_values(&[&child.name]);
    }
    let actors: Vec<(String, String)> = children
        .iter()
        .filter_map(|c| Some((c.name.clone(), c.task.clone()?)))
        .collect();
    let display = terminal.map(|t| display::Display::start(t, &run, config, actors.clone()));
    let supervisor = Supervisor {
        exe,
        run: run.clone(),
        max_restarts: config.run.max_restarts,
        hang_timeout: Duration::from_secs_f64(config.run.hang_timeout_seconds),
        metrics: &launcher_metrics,
        cleaner: domain::Cleaner::start(&format!("{}-{PROCESS}", run.id()), &config.run),
    };

    start_children(&supervisor, &mut children, config, &node)?;
    tracing::info!(run = %run.root().display(), children = children.len(), "launched");

    let stalls = stall::StallWatch::start(&run, config, actors);
    let outcome = supervise(
        &supervisor,
        &mut children,
        &node,
        &announcements,
        config.tasks.len(),
        stalls.as_ref(),
    );
    stop_all(&mut children);
    supervisor.cleaner.sweep_within(CLEANUP_WAIT);
    if let Some(display) = display {
        display.finish();
    }
    outcome?;
    let mut results = latest_results(&run)?;
    if let [seed] = config.run.seeds[..] {
        results.extend(model_planner_rows(config, &run, seed));
    }
    Ok(LaunchReport {
        run: run.root().to_path_buf(),
        restarts: children.iter().map(|c| c.failures).sum(),
        results,
        references: reference_rows(config),
        bounds: report::bounds(config),
    })
}
