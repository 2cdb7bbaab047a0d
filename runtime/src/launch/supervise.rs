//! Supervision: starting the children in order, restarting a crashed or hung one with backoff,
//! hearing the run's announcements, and stopping everything in order at the end.

use super::stall::StallWatch;
use super::*;
use uavmeta_proto::fs::FileError;

pub(super) const TICK: Duration = Duration::from_millis(100);
/// How long the store may take to come up (its port file is the sign).
pub(super) const STORE_START: Duration = Duration::from_secs(30);
/// How long a child may take to stop after SIGTERM (or, at the end, after the shutdown
/// announcement) before it is killed.
pub(super) const GRACE: Duration = Duration::from_secs(20);
pub(super) const BACKOFF_FIRST: Duration = Duration::from_millis(500);
/// How long a failed child's restart waits, past its backoff, for the sweep of its iceoryx2
/// resources (`domain::Cleaner`, on a thread of its own); then it restarts regardless.
pub(super) const CLEANUP_WAIT: Duration = Duration::from_secs(15);
pub(super) const BACKOFF_MAX: Duration = Duration::from_secs(10);

/// The announcements the launcher hears (datasets and checkpoints ready) and makes (the
/// shutdown).
pub(super) struct Announcements {
    pub(super) dataset_ready: Subscriber<ipc::Service, DatasetReady, ()>,
    pub(super) checkpoint_ready: Subscriber<ipc::Service, CheckpointReady, ()>,
    pub(super) shutdown: Publisher<ipc::Service, Shutdown, ()>,
    /// Every shutdown announced, to tell one the launcher did not make.
    pub(super) shutdowns: Subscriber<ipc::Service, Shutdown, ()>,
}

impl Announcements {
    pub(super) fn open(
        node: &Node<ipc::Service>,
        names: &ServiceNames,
        config: &Config,
    ) -> Result<Self, LaunchError> {
        let shutdown = transport::shutdown_service(node, names, config)?;
        Ok(Self {
            dataset_ready: transport::control_subscriber(&transport::dataset_ready_service(
                node, names, config,
            )?)?,
            checkpoint_ready: transport::control_subscriber(&transport::checkpoint_ready_service(
                node, names, config,
            )?)?,
            shutdown: transport::control_publisher(&shutdown)?,
            shutdowns: transport::control_subscriber(&shutdown)?,
        })
    }
}

/// Supervises the children until they have all finished after the shutdown (announced once
/// meta-learning is done and every one of the `tasks` datasets is ready), SIGINT/SIGTERM, or a
/// dataset that `stalls` reports stopped growing.
pub(super) fn supervise(
    supervisor: &Supervisor,
    children: &mut [Supervised],
    node: &Node<ipc::Service>,
    announcements: &Announcements,
    tasks: usize,
    stalls: Option<&StallWatch>,
) -> Result<(), LaunchError> {
    let metrics = supervisor.metrics;
    let mut ready_tasks = vec![false; tasks];
    let mut shutdown_sent = false;
    let mut shutdown_at = Instant::now();
    let mut targets = Targets::default();
    loop {
        if !liveness::keep_running(node, TICK) {
            return Err(LaunchError::Interrupted);
        }
        supervisor.poll(children)?;
        if let Some(stall) = stalls.and_then(|s| s.stalled.try_recv().ok()) {
            return Err(LaunchError::DatasetStalled(Box::new(stall)));
        }
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
        write_targets(&supervisor.run, children, &mut targets)?;
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
pub(super) fn all_exited(children: &[Supervised]) -> bool {
    children
        .iter()
        .all(|c| c.child.is_none() && c.restart_at.is_none())
}

/// Whether the run's work is done: the meta-learner finished and every task's dataset is ready,
/// its actors finished or gone.
pub(super) fn work_done(children: &[Supervised], ready_tasks: &[bool]) -> bool {
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
pub(super) fn start_children(
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
pub(super) fn wait_for_store(run: &RunDir, store: &mut Supervised) -> Result<(), LaunchError> {
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
            return Err(LaunchError::StoreFailed {
                status: describe(status),
                cause: last_line(&log),
                log,
            });
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    Ok(wait_for_port(run, store::PROCESS, Duration::ZERO).map(drop)?)
}

/// Reads the store's dataset and the meta-learner's checkpoint announcements into `ready_tasks`
/// and the launcher's metrics.
pub(super) fn count_announcements(
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
pub(super) fn stop_all(children: &mut [Supervised]) {
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

pub(super) struct Supervisor<'a> {
    pub(super) exe: PathBuf,
    pub(super) run: RunDir,
    pub(super) max_restarts: u32,
    /// Zero: never taken for hung.
    pub(super) hang_timeout: Duration,
    pub(super) metrics: &'a metrics::LauncherMetrics,
    /// Sweeps dead children's iceoryx2 resources off the supervision loop.
    pub(super) cleaner: domain::Cleaner,
}

impl Supervisor<'_> {
    pub(super) fn start(&self, child: &mut Supervised) -> Result<(), LaunchError> {
        let log_path = self.run.log_file(&child.name);
        let log = OpenOptions::new()
            .create(true)
            .append(true)
            .open(&log_path)
            .map_err(FileError::at(&log_path, "open the log"))?;
        let err_log = log
            .try_clone()
            .map_err(FileError::at(&log_path, "open the log"))?;
        // A new file: its modification time is the start, the child's first beat.
        let heartbeat = self.run.heartbeat_file(&child.name);
        std::fs::create_dir_all(self.run.root().join("heartbeats"))
            .and_then(|()| std::fs::File::create(&heartbeat))
            .map_err(FileError::at(&heartbeat, "create the heartbeat file"))?;
        let parent = std::process::id() as libc::pid_t;
        let mut command = Command::new(&self.exe);
        command
            .env(liveness::HEARTBEAT_FILE_ENV, &heartbeat)
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
    pub(super) fn poll(&self, children: &mut [Supervised]) -> Result<(), LaunchError> {
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
            let status = waited.map_err(FileError::at(
                &self.run.log_file(&c.name),
                "wait for a child",
            ))?;
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
            // A child that returned an error said why as its last words; one killed said nothing.
            let cause = (status.code())
                .map(|_| last_line(&self.run.log_file(&c.name)))
                .unwrap_or_default();
            tracing::warn!(name = %c.name, status = %describe(status), %cause, ?backoff, "child failed");
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

/// The last non-empty line of the log at `path` (a child's error), or nothing.
fn last_line(path: &std::path::Path) -> String {
    let text = std::fs::read_to_string(path).unwrap_or_default();
    let line = text.lines().rev().find(|l| !l.trim().is_empty());
    line.unwrap_or("").to_string()
}

pub(super) fn describe(status: ExitStatus) -> String {
    use std::os::unix::process::ExitStatusExt;
    match (status.code(), status.signal()) {
        (Some(code), _) => format!("exit code {code}"),
        (None, Some(signal)) => format!("killed by signal {signal}"),
        _ => status.to_string(),
    }
}

/// SIGTERM to every running child of `role` (its whole process group), then waits up to
/// [`GRACE`], then SIGKILL.
pub(super) fn stop_role(children: &mut [Supervised], role: Role) {
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
