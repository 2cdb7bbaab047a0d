//! The run's Prometheus configuration: `prometheus.yml`, and the targets file rewritten as
//! processes (here and on remote hosts) come and go.

use super::remote::remote_hosts;
use super::{LaunchError, Supervised, PROCESS, SCRAPE_INTERVAL_SECONDS};
use crate::run_dir::{write_atomic, RunDir};

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

/// Rewrites the Prometheus targets file when the set of live ports changed; returns its text.
/// Every target has a `host` label: this host's name, or the remote host's that announced it.
pub(super) fn write_targets(
    run: &RunDir,
    children: &[Supervised],
    last: String,
) -> Result<String, LaunchError> {
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
    for host in remote_hosts(run) {
        for process in &host.processes {
            targets.push(serde_json::json!({
                "targets": [process.metrics],
                "labels": { "process": process.name, "run": run.id(), "host": host.host },
            }));
        }
    }
    let text = serde_json::to_string_pretty(&targets).expect("JSON values always serialise");
    if text != last {
        // Scrape targets are a convenience: a full disk must not end the run for them.
        if let Err(error) = write_atomic(&run.prometheus_targets(), text.as_bytes()) {
            tracing::warn!(%error, "cannot rewrite the Prometheus targets; trying again");
            return Ok(last);
        }
        for host in remote_hosts(run) {
            let names: Vec<&str> = host.processes.iter().map(|p| p.name.as_str()).collect();
            tracing::info!(host = %host.host, processes = ?names, "remote actor host");
        }
    }
    Ok(text)
}
