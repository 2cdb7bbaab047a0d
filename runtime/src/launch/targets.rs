//! The run's Prometheus configuration: `prometheus.yml`, and the targets file rewritten as
//! processes (here and on remote hosts) come and go.

use std::collections::HashMap;
use std::time::{Duration, Instant};

use super::{LaunchError, Supervised, PROCESS, SCRAPE_INTERVAL_SECONDS};
use crate::run_dir::{write_atomic, RemoteHost, RunDir};

pub(super) fn write_prometheus_yml(run: &RunDir) -> Result<(), LaunchError> {
    // honor_labels: the launcher's restart and hang counters name the child in their `process`
    // label, which must win over the target's `process` (the launcher) rather than be renamed
    // `exported_process`.
    let text = format!(
        "# Scrapes every process of uavmeta run {id}. Ports are ephemeral; the launcher rewrites\n\
         # the targets file as processes (re)start: prometheus --config.file={yml}\n\
         # Grafana: import {dashboard} (docs/DASHBOARD.md).\n\
         global:\n  scrape_interval: {SCRAPE_INTERVAL_SECONDS}s\nscrape_configs:\n  - job_name: uavmeta\n    honor_labels: true\n    file_sd_configs:\n      - files: ['{targets}']\n",
        id = run.id(),
        yml = run.prometheus_yml().display(),
        dashboard = run.grafana_dashboard().display(),
        targets = run.prometheus_targets().display(),
    );
    Ok(write_atomic(&run.prometheus_yml(), text.as_bytes())?)
}

/// A remote host's processes are logged when they change, at most once per this interval, so
/// that a host whose processes (or a hostile one whose announcements) change every second cannot
/// flood the launcher's log: at most `tunnel.max_hosts` lines a minute, each under 1 KB.
const LOG_HOST_EVERY: Duration = Duration::from_secs(60);
/// Process names a log line lists at most; it counts them all.
const LOG_NAMES: usize = 8;

/// The targets file's last text, and each remote host's processes as last logged, and when.
#[derive(Default)]
pub(super) struct Targets {
    text: String,
    logged: HashMap<String, (Instant, Vec<String>)>,
}

/// Rewrites the Prometheus targets file when the set of live ports changed. Every target has a
/// `host` label: this host's name, or the remote host's that announced it (which the tunnel
/// checked against the host's certificate, at the address it reaches the tunnel from).
pub(super) fn write_targets(
    run: &RunDir,
    children: &[Supervised],
    last: &mut Targets,
) -> Result<(), LaunchError> {
    let here = std::fs::read_to_string("/proc/sys/kernel/hostname")
        .map(|h| h.trim().to_string())
        .unwrap_or_else(|_| "localhost".into());
    let mut targets = Vec::new();
    for name in std::iter::once(PROCESS).chain(children.iter().map(|c| c.name.as_str())) {
        if let Ok(port) = std::fs::read_to_string(run.port_file(name)) {
            targets.push(serde_json::json!({
                "targets": [format!("127.0.0.1:{}", port.trim())],
                "labels": { "process": name, "run": run.id(), "host": here },
            }));
        }
    }
    let hosts = run.remote_hosts();
    for host in &hosts {
        for process in &host.processes {
            targets.push(serde_json::json!({
                "targets": [process.metrics],
                "labels": { "process": process.name, "run": run.id(), "host": host.host },
            }));
        }
    }
    let text = serde_json::to_string_pretty(&targets).expect("JSON values always serialise");
    if text != last.text {
        // Scrape targets are a convenience: a full disk must not end the run for them.
        if let Err(error) = write_atomic(&run.prometheus_targets(), text.as_bytes()) {
            tracing::warn!(%error, "cannot rewrite the Prometheus targets; trying again");
            return Ok(());
        }
        last.text = text;
        hosts.iter().for_each(|host| last.log(host));
    }
    Ok(())
}

impl Targets {
    /// Logs `host`'s processes if they changed since its last line, at most every
    /// [`LOG_HOST_EVERY`].
    fn log(&mut self, host: &RemoteHost) {
        let mut names: Vec<String> = host.processes.iter().map(|p| p.name.clone()).collect();
        names.sort();
        let due = match self.logged.get(&host.host) {
            None => true,
            Some((at, logged)) => *logged != names && at.elapsed() >= LOG_HOST_EVERY,
        };
        if !due {
            return;
        }
        let shown = &names[..names.len().min(LOG_NAMES)];
        let more = names.len() - shown.len();
        tracing::info!(host = %host.host, processes = names.len(), ?shown, more, "remote actor host");
        self.logged
            .insert(host.host.clone(), (Instant::now(), names));
    }
}
