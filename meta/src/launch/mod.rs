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
//! (`transport::heartbeat`, the modification time of `heartbeats/<name>`, named in its
//! environment), and one silent for `run.hang_timeout_seconds` is killed (SIGKILL to its process
//! group), counted in `uavmeta_launcher_child_hangs_total` (`uavmeta_proto::metrics::launcher::CHILD_HANGS`) and restarted. A child that exits
//! successfully is done: actors end when their task's dataset is complete, the meta-learner when
//! it has meta-tested. Then the launcher announces a shutdown, the evaluator finishes the
//! checkpoints it was told about, the store syncs its files, and the launcher prints a results
//! table from the evaluator's CSV.
//!
//! On SIGINT/SIGTERM it stops the children gracefully: actors first (so the store receives
//! everything they sent), then the meta-learner and the evaluator, then the store; a child still
//! running after a grace period is killed.

use std::fs::OpenOptions;
use std::os::unix::process::CommandExt;
use std::path::PathBuf;
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant, SystemTime};

use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use indicatif::MultiProgress;
use uavmeta_actors::actor::ActorOptions;
use uavmeta_actors::evaluator;
use uavmeta_actors::policy::heuristics::PolicySpec;
use uavmeta_learner::store;
use uavmeta_proto::config::{Config, TaskRole};
use uavmeta_proto::metrics::{wait_for_port, MetricsError, MetricsServer};
use uavmeta_proto::transport::{
    self, write_atomic, CheckpointReady, DatasetReady, RunDir, ServiceNames, Shutdown,
    TransportError, SCHEMA_VERSION,
};

use crate::meta_learner;

mod display;
mod metrics;
mod remote;
mod report;
pub mod resources;
pub mod reuse;
pub mod seeds;
mod targets;

use remote::{wait_for_remote_hosts, TUNNEL_PROCESS};
use report::{latest_results, reference_rows};
pub use report::{results_table, LaunchReport};
pub use reuse::Reuse;
pub use seeds::{launch_seeds, SeedsReport};
use targets::{write_prometheus_yml, write_targets};

/// How often the run's `prometheus.yml` has Prometheus scrape every process; `uavmeta dashboard
/// render` takes it for the interval of its rates.
pub const SCRAPE_INTERVAL_SECONDS: u64 = 5;

/// The Grafana dashboard of a run's metrics, copied into every run directory beside
/// `prometheus.yml`; embedded so that the binary writes it from any working directory.
const DASHBOARD: &str = include_str!("../../../docs/grafana/uavmeta.json");

/// How often the supervisor looks at its children and the run's announcements.
const TICK: Duration = Duration::from_millis(100);
/// How long the store may take to come up (its port file is the sign).
const STORE_START: Duration = Duration::from_secs(30);
/// How long a child may take to stop after SIGTERM (or, at the end, after the shutdown
/// announcement) before it is killed.
const GRACE: Duration = Duration::from_secs(20);
const BACKOFF_FIRST: Duration = Duration::from_millis(500);
/// How long a failed child's restart waits, past its backoff, for the sweep of its iceoryx2
/// resources (`transport::Cleaner`, on a thread of its own); then it restarts regardless.
const CLEANUP_WAIT: Duration = Duration::from_secs(15);
const BACKOFF_MAX: Duration = Duration::from_secs(10);

/// The launcher's process name: node, port file, metrics snapshot.
pub const PROCESS: &str = "launcher";
#[derive(Debug, thiserror::Error)]
pub enum LaunchError {
    #[error(transparent)]
    Transport(#[from] TransportError),
    #[error(transparent)]
    Metrics(#[from] MetricsError),
    #[error("{}: cannot {action}", path.display())]
    Io {
        path: PathBuf,
        action: &'static str,
        source: std::io::Error,
    },
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

/// What kind of child a process is: decides the stop order and when the run is done.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
enum Role {
    Actor,
    MetaLearner,
    Evaluator,
    /// The run's end of the tunnel to remote actor hosts (`tunnel.listen`).
    Tunnel,
    Store,
}

struct Supervised {
    name: String,
    role: Role,
    /// An actor's task.
    task: Option<String>,
    args: Vec<String>,
    child: Option<Child>,
    /// Failures so far; each one is followed by a restart until `run.max_restarts`.
    failures: u32,
    restart_at: Option<Instant>,
    /// Exited successfully: not restarted.
    done: bool,
    /// The sweep of its resources requested when it last failed.
    cleanup: Option<u64>,
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
    resources::check_here(config)?;
    reuse::prepare(config, reuse)?;
    let run = RunDir::create(&config.run.dir)?;
    write_atomic(&run.config_file(), config.to_toml_string().as_bytes())?;
    write_prometheus_yml(&run)?;
    write_atomic(&run.grafana_dashboard(), DASHBOARD.as_bytes())?;
    let node = transport::node(&format!("{}-{PROCESS}", run.id()), &config.run)?;
    transport::cleanup_dead_nodes(&node);
    let names = ServiceNames::new(&run);
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
    let actors = children
        .iter()
        .filter_map(|c| Some((c.name.clone(), c.task.clone()?)));
    let display = terminal.map(|t| display::Display::start(t, &run, config, actors.collect()));
    let supervisor = Supervisor {
        exe,
        run: run.clone(),
        max_restarts: config.run.max_restarts,
        hang_timeout: Duration::from_secs_f64(config.run.hang_timeout_seconds),
        metrics: &launcher_metrics,
        cleaner: transport::Cleaner::start(&format!("{}-{PROCESS}", run.id()), &config.run),
    };

    start_children(&supervisor, &mut children, config, &node)?;
    tracing::info!(run = %run.root().display(), children = children.len(), "launched");

    let outcome = supervise(
        &supervisor,
        &mut children,
        &node,
        &announcements,
        config.tasks.len(),
    );
    stop_all(&mut children);
    supervisor.cleaner.sweep_within(CLEANUP_WAIT);
    if let Some(display) = display {
        display.finish();
    }
    outcome?;
    let results = latest_results(&run)?;
    Ok(LaunchReport {
        run: run.root().to_path_buf(),
        restarts: children.iter().map(|c| c.failures).sum(),
        results,
        references: reference_rows(config),
    })
}

/// The announcements the launcher hears (datasets and checkpoints ready) and makes (the
/// shutdown).
struct Announcements {
    dataset_ready: Subscriber<ipc::Service, DatasetReady, ()>,
    checkpoint_ready: Subscriber<ipc::Service, CheckpointReady, ()>,
    shutdown: Publisher<ipc::Service, Shutdown, ()>,
    /// Every shutdown announced, to tell one the launcher did not make.
    shutdowns: Subscriber<ipc::Service, Shutdown, ()>,
}

impl Announcements {
    fn open(
        node: &Node<ipc::Service>,
        names: &ServiceNames,
        config: &Config,
    ) -> Result<Self, LaunchError> {
        let shutdown = transport::shutdown_service(node, names, config)?;
        Ok(Self {
            dataset_ready: transport::control_subscriber(
                &transport::dataset_ready_service(node, names, config)?,
                config,
            )?,
            checkpoint_ready: transport::control_subscriber(
                &transport::checkpoint_ready_service(node, names, config)?,
                config,
            )?,
            shutdown: transport::control_publisher(&shutdown)?,
            shutdowns: transport::control_subscriber(&shutdown, config)?,
        })
    }
}

/// Supervises the children until they have all finished after the shutdown (announced once
/// meta-learning is done and every one of the `tasks` datasets is ready), or SIGINT/SIGTERM.
fn supervise(
    supervisor: &Supervisor,
    children: &mut [Supervised],
    node: &Node<ipc::Service>,
    announcements: &Announcements,
    tasks: usize,
) -> Result<(), LaunchError> {
    let metrics = supervisor.metrics;
    let mut ready_tasks = vec![false; tasks];
    let mut shutdown_sent = false;
    let mut shutdown_at = Instant::now();
    let mut last_targets = String::new();
    loop {
        if !transport::keep_running(node, TICK) {
            return Err(LaunchError::Interrupted);
        }
        supervisor.poll(children)?;
        // Before its own, any shutdown is another process's: the children stop on it, and the
        // run must not end as if its work were done.
        if !shutdown_sent && transport::shutdown_requested(&announcements.shutdowns)? {
            return Err(LaunchError::ForeignShutdown);
        }
        count_announcements(
            &announcements.dataset_ready,
            &announcements.checkpoint_ready,
            &mut ready_tasks,
            metrics,
        )?;
        last_targets = write_targets(&supervisor.run, children, last_targets)?;
        metrics
            .children_running
            .set(children.iter().filter(|c| c.child.is_some()).count() as i64);

        if !shutdown_sent && work_done(children, &ready_tasks) {
            tracing::info!("meta-learning finished; announcing the shutdown");
            transport::announce(
                &announcements.shutdown,
                Shutdown {
                    schema_version: SCHEMA_VERSION,
                    reserved: 0,
                },
            )?;
            shutdown_sent = true;
            shutdown_at = Instant::now();
        }
        if shutdown_sent && all_exited(children) {
            return Ok(());
        }
        if !shutdown_sent && all_exited(children) {
            return Err(LaunchError::EndedEarly {
                ready: ready_tasks.iter().filter(|r| **r).count(),
                tasks,
                learning: match children
                    .iter()
                    .any(|c| c.role == Role::MetaLearner && !c.done)
                {
                    true => "unfinished",
                    false => "finished",
                },
            });
        }
        if shutdown_sent && shutdown_at.elapsed() > GRACE {
            tracing::warn!("children still running {GRACE:?} after the shutdown; stopping them");
            return Ok(());
        }
    }
}

/// Whether no child runs or waits for a restart: a forged shutdown ends every one of them.
fn all_exited(children: &[Supervised]) -> bool {
    children
        .iter()
        .all(|c| c.child.is_none() && c.restart_at.is_none())
}

/// Whether the run's work is done: the meta-learner finished and every task's dataset is ready,
/// its actors finished or gone.
fn work_done(children: &[Supervised], ready_tasks: &[bool]) -> bool {
    let learning_done = children
        .iter()
        .filter(|c| c.role == Role::MetaLearner)
        .all(|c| c.done);
    let collecting_done = ready_tasks.iter().all(|r| *r)
        && children
            .iter()
            .filter(|c| c.role == Role::Actor)
            .all(|c| c.done || c.child.is_none());
    learning_done && collecting_done
}

/// Starts the children in their order: the store first, and ready, so the actors' first batches
/// have a subscriber; then the tunnel, and the remote hosts the config waits for; then the local
/// actors, the meta-learner and the evaluator.
fn start_children(
    supervisor: &Supervisor,
    children: &mut [Supervised],
    config: &Config,
    node: &Node<ipc::Service>,
) -> Result<(), LaunchError> {
    let run = &supervisor.run;
    let store_index = children
        .iter()
        .position(|c| c.role == Role::Store)
        .expect("the plan has a store");
    supervisor.start(&mut children[store_index])?;
    wait_for_store(run, &mut children[store_index])?;
    for child in children.iter_mut().filter(|c| c.role == Role::Tunnel) {
        supervisor.start(child)?;
        // What an actor host needs to join (docs/REMOTE.md).
        tracing::info!(
            endpoint = %config.tunnel.listen,
            "remote actor hosts join with `uavmeta tunnel join --connect <this host's address for \
             the endpoint> --run-id {}`",
            run.id()
        );
    }
    wait_for_remote_hosts(run, config, node)?;
    for child in children
        .iter_mut()
        .filter(|c| !matches!(c.role, Role::Store | Role::Tunnel))
    {
        supervisor.start(child)?;
    }
    Ok(())
}

/// Waits for the store's port file, at most [`STORE_START`]; a store that exits first is named
/// with its exit status and the last line of its log (a damaged dataset file, say), not left to
/// a timeout.
fn wait_for_store(run: &RunDir, store: &mut Supervised) -> Result<(), LaunchError> {
    let start = Instant::now();
    while start.elapsed() < STORE_START {
        if run.port_file(store::PROCESS).exists() {
            wait_for_port(run, store::PROCESS, STORE_START)?;
            return Ok(());
        }
        let exited = store
            .child
            .as_mut()
            .and_then(|c| c.try_wait().ok().flatten());
        if let Some(status) = exited {
            let log = run.log_file(&store.name);
            let text = std::fs::read_to_string(&log).unwrap_or_default();
            return Err(LaunchError::StoreFailed {
                status: describe(status),
                cause: text
                    .lines()
                    .rev()
                    .find(|l| !l.trim().is_empty())
                    .unwrap_or("")
                    .to_string(),
                log,
            });
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    Ok(wait_for_port(run, store::PROCESS, Duration::ZERO).map(drop)?)
}

/// Reads the store's dataset and the meta-learner's checkpoint announcements into `ready_tasks`
/// and the launcher's metrics.
fn count_announcements(
    dataset_ready: &Subscriber<ipc::Service, DatasetReady, ()>,
    checkpoint_ready: &Subscriber<ipc::Service, CheckpointReady, ()>,
    ready_tasks: &mut [bool],
    metrics: &metrics::LauncherMetrics,
) -> Result<(), LaunchError> {
    while let Some(m) = dataset_ready
        .receive()
        .map_err(transport::receive_failed("receive a dataset announcement"))?
    {
        if m.schema_version == SCHEMA_VERSION {
            if let Some(ready) = ready_tasks.get_mut(m.task as usize) {
                *ready = true;
            }
        }
    }
    metrics
        .datasets_ready
        .set(ready_tasks.iter().filter(|r| **r).count() as i64);
    while checkpoint_ready
        .receive()
        .map_err(transport::receive_failed(
            "receive a checkpoint announcement",
        ))?
        .is_some()
    {
        metrics.checkpoints_announced.inc();
    }
    Ok(())
}

/// Orderly stop of whatever still runs: actors, then learners, then the store.
fn stop_all(children: &mut [Supervised]) {
    for role in [
        Role::Actor,
        Role::MetaLearner,
        Role::Evaluator,
        Role::Tunnel,
        Role::Store,
    ] {
        stop_role(children, role);
    }
}

/// The children of a run: store, actors, meta-learner, evaluator.
fn plan(run: &RunDir, config: &Config) -> Result<Vec<Supervised>, LaunchError> {
    let policy: PolicySpec = config.collect.policy.parse().map_err(
        |e: uavmeta_actors::policy::heuristics::PolicyError| LaunchError::Policy {
            origin: config.origin.clone(),
            message: e.to_string(),
        },
    )?;
    let run_arg = run.root().display().to_string();
    let child = |name: String, role: Role, args: Vec<String>| Supervised {
        name,
        role,
        task: None,
        args,
        child: None,
        failures: 0,
        restart_at: None,
        done: false,
        cleanup: None,
    };
    let mut children = vec![child(
        store::PROCESS.into(),
        Role::Store,
        vec!["store".into(), "--run".into(), run_arg.clone()],
    )];
    for task in &config.tasks {
        for i in 0..config.collect.actors_per_task {
            let seed = config.collect.seed.wrapping_add(i as u64);
            let options = ActorOptions {
                task: task.name.clone(),
                policy: policy.clone(),
                seed,
                transitions: None,
            };
            let args = vec![
                "actor".into(),
                "--run".into(),
                run_arg.clone(),
                "--task".into(),
                task.name.clone(),
                "--seed".into(),
                seed.to_string(),
            ];
            children.push(Supervised {
                task: Some(task.name.clone()),
                ..child(options.process_name(), Role::Actor, args)
            });
        }
    }
    if !config.tunnel.listen.is_empty() {
        children.push(child(
            TUNNEL_PROCESS.into(),
            Role::Tunnel,
            vec![
                "tunnel".into(),
                "serve".into(),
                "--run".into(),
                run_arg.clone(),
            ],
        ));
    }
    if config.tasks_with_role(TaskRole::MetaTrain).next().is_some()
        && config.tasks_with_role(TaskRole::MetaTest).next().is_some()
    {
        children.push(child(
            meta_learner::PROCESS.into(),
            Role::MetaLearner,
            vec!["meta-learner".into(), "--run".into(), run_arg.clone()],
        ));
        children.push(child(
            evaluator::PROCESS.into(),
            Role::Evaluator,
            vec!["evaluator".into(), "--run".into(), run_arg],
        ));
    }
    Ok(children)
}

struct Supervisor<'a> {
    exe: PathBuf,
    run: RunDir,
    max_restarts: u32,
    /// Zero: never taken for hung.
    hang_timeout: Duration,
    metrics: &'a metrics::LauncherMetrics,
    /// Sweeps dead children's iceoryx2 resources off the supervision loop.
    cleaner: transport::Cleaner,
}

impl Supervisor<'_> {
    fn start(&self, child: &mut Supervised) -> Result<(), LaunchError> {
        let log_path = self.run.log_file(&child.name);
        let log = OpenOptions::new()
            .create(true)
            .append(true)
            .open(&log_path)
            .map_err(|source| LaunchError::Io {
                path: log_path.clone(),
                action: "open the log",
                source,
            })?;
        let err_log = log.try_clone().map_err(|source| LaunchError::Io {
            path: log_path.clone(),
            action: "open the log",
            source,
        })?;
        // A new file: its modification time is the start, the child's first beat.
        let heartbeat = self.run.heartbeat_file(&child.name);
        std::fs::create_dir_all(self.run.root().join("heartbeats"))
            .and_then(|()| std::fs::File::create(&heartbeat))
            .map_err(|source| LaunchError::Io {
                path: heartbeat.clone(),
                action: "create the heartbeat file",
                source,
            })?;
        let parent = std::process::id() as libc::pid_t;
        let mut command = Command::new(&self.exe);
        command
            .env(transport::HEARTBEAT_FILE_ENV, &heartbeat)
            .args(&child.args)
            .stdin(Stdio::null())
            .stdout(log)
            .stderr(err_log)
            .process_group(0);
        // SAFETY: the closure runs in the child between fork and exec and calls only
        // async-signal-safe functions (prctl, getppid).
        unsafe {
            command.pre_exec(move || {
                // The child gets SIGTERM when the launcher dies, however it dies.
                if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM) != 0 {
                    return Err(std::io::Error::last_os_error());
                }
                // The launcher may have died before prctl took effect.
                if libc::getppid() != parent {
                    return Err(std::io::Error::other(
                        "the launcher exited while starting this child",
                    ));
                }
                Ok(())
            });
        }
        let process = command.spawn().map_err(|source| LaunchError::Spawn {
            name: child.name.clone(),
            exe: self.exe.clone(),
            source,
        })?;
        tracing::debug!(name = %child.name, pid = process.id(), "started");
        child.child = Some(process);
        child.restart_at = None;
        Ok(())
    }

    /// Reaps exited children, schedules restarts of failed ones and starts those that are due.
    fn poll(&self, children: &mut [Supervised]) -> Result<(), LaunchError> {
        for c in children.iter_mut() {
            let Some(process) = c.child.as_mut() else {
                if self.restart_due(c) {
                    self.metrics.restarts.with_label_values(&[&c.name]).inc();
                    tracing::warn!(name = %c.name, attempt = c.failures, "restarting");
                    self.start(c)?;
                }
                continue;
            };
            let waited = match process.try_wait() {
                Ok(Some(status)) => Ok(status),
                Err(e) => Err(e),
                Ok(None) => match self.silent_for(&c.name) {
                    Some(silent) => {
                        tracing::warn!(name = %c.name, ?silent, "no heartbeat: taken for hung, killed");
                        self.metrics.hangs.with_label_values(&[&c.name]).inc();
                        // The whole group, and SIGKILL, which a stopped process cannot defer.
                        // SAFETY: kill(2) on our own child's process group.
                        unsafe { libc::kill(-(process.id() as libc::pid_t), libc::SIGKILL) };
                        process.wait()
                    }
                    None => continue,
                },
            };
            let status = waited.map_err(|source| LaunchError::Io {
                path: self.run.log_file(&c.name),
                action: "wait for a child",
                source,
            })?;
            c.child = None;
            if status.success() {
                tracing::info!(name = %c.name, "finished");
                c.done = true;
                continue;
            }
            c.failures += 1;
            // The dead child's ports still sit in the services; remove them before anyone
            // (its successor included) waits on them.
            c.cleanup = Some(self.cleaner.request());
            if c.failures > self.max_restarts {
                return Err(LaunchError::GaveUp {
                    name: c.name.clone(),
                    failures: c.failures,
                    status: describe(status),
                    max: self.max_restarts,
                    log: self.run.log_file(&c.name),
                });
            }
            let backoff = (BACKOFF_FIRST * 2u32.saturating_pow(c.failures - 1)).min(BACKOFF_MAX);
            tracing::warn!(name = %c.name, status = %describe(status), ?backoff, "child failed");
            c.restart_at = Some(Instant::now() + backoff);
        }
        Ok(())
    }
}

impl Supervisor<'_> {
    /// Whether a failed child's backoff is over and the sweep of its resources has ended (or
    /// [`CLEANUP_WAIT`] more has passed: the sweep is stuck, and the child restarts regardless).
    fn restart_due(&self, c: &Supervised) -> bool {
        let Some(at) = c.restart_at else {
            return false;
        };
        let now = Instant::now();
        let swept = c.cleanup.is_none_or(|ticket| self.cleaner.finished(ticket));
        if !swept && now >= at + CLEANUP_WAIT {
            tracing::warn!(name = %c.name, "the iceoryx2 clean-up is stuck; restarting without it");
            return true;
        }
        now >= at && swept
    }

    /// How long child `name`'s heartbeat has not moved, if longer than the hang timeout.
    fn silent_for(&self, name: &str) -> Option<Duration> {
        if self.hang_timeout.is_zero() {
            return None;
        }
        let beat = std::fs::metadata(self.run.heartbeat_file(name))
            .and_then(|m| m.modified())
            .ok()?;
        let silent = SystemTime::now().duration_since(beat).ok()?;
        (silent > self.hang_timeout).then_some(silent)
    }
}

fn describe(status: ExitStatus) -> String {
    use std::os::unix::process::ExitStatusExt;
    match (status.code(), status.signal()) {
        (Some(code), _) => format!("exit code {code}"),
        (None, Some(signal)) => format!("killed by signal {signal}"),
        _ => status.to_string(),
    }
}

/// SIGTERM to every running child of `role` (its whole process group), then waits up to
/// [`GRACE`], then SIGKILL.
fn stop_role(children: &mut [Supervised], role: Role) {
    let group: Vec<&mut Supervised> = children.iter_mut().filter(|c| c.role == role).collect();
    for c in group {
        c.restart_at = None;
        let Some(mut process) = c.child.take() else {
            continue;
        };
        let pid = process.id() as libc::pid_t;
        // SAFETY: plain syscalls on the child's own process group (its pid, set by
        // process_group(0)).
        unsafe { libc::killpg(pid, libc::SIGTERM) };
        let start = Instant::now();
        loop {
            match process.try_wait() {
                Ok(Some(_)) | Err(_) => break,
                Ok(None) if start.elapsed() > GRACE => {
                    tracing::warn!(name = %c.name, "did not stop within {GRACE:?}; killing it");
                    unsafe { libc::killpg(pid, libc::SIGKILL) };
                    let _ = process.wait();
                    break;
                }
                Ok(None) => std::thread::sleep(Duration::from_millis(20)),
            }
        }
    }
}
