//! Remote actor hosts: which have announced themselves through the tunnel, and the wait for
//! those `tunnel.wait_for_hosts` names before the local processes start.

use std::time::{Duration, Instant};

use iceoryx2::prelude::*;
use uavmeta_proto::config::Config;
use uavmeta_proto::metrics::store::TRANSITIONS_STORED;

use crate::metrics::{scrape_process, sum};
use crate::run_dir::{RemoteHost, RunDir};
use crate::{actor, liveness, store};

use super::supervise::TICK;
use super::targets::{write_targets, Targets};
use super::LaunchError;

/// The tunnel child's name (`uavmeta tunnel serve`; the tunnel crate is not linked here).
pub(super) const TUNNEL_PROCESS: &str = "tunnel";

/// Waits until every host of `tunnel.wait_for_hosts` has announced itself with its actors and
/// the store has stored a transition (only remote actors run yet, so it came through the tunnel).
/// A host's first announcement can come before its actors have started: waiting for one that
/// lists them puts them in the Prometheus targets however soon they finish (the tunnel records a
/// host's announcement at most once a second).
pub(super) fn wait_for_remote_hosts(
    run: &RunDir,
    config: &Config,
    node: &Node<ipc::Service>,
) -> Result<(), LaunchError> {
    let wanted = &config.tunnel.wait_for_hosts;
    if wanted.is_empty() {
        return Ok(());
    }
    tracing::info!(hosts = ?wanted, endpoint = %config.tunnel.listen, "waiting for remote actor hosts");
    let deadline = Instant::now() + Duration::from_secs_f64(config.tunnel.wait_seconds);
    let mut targets = Targets::default();
    loop {
        // Prometheus sees the remote actors from the start, however short-lived they are.
        write_targets(run, &[], &mut targets)?;
        let hosts = run.remote_hosts();
        let missing: Vec<&String> = wanted
            .iter()
            .filter(|w| !hosts.iter().any(|h| &h.host == *w && announces_actors(h)))
            .collect();
        let stored = scrape_process(run, &config.run.metrics_host, store::PROCESS)
            .map_or(0.0, |samples| sum(&samples, TRANSITIONS_STORED, &[]));
        if missing.is_empty() && stored > 0.0 {
            tracing::info!(hosts = ?wanted, "remote actor hosts are publishing");
            return Ok(());
        }
        if !liveness::keep_running(node, TICK) {
            return Err(LaunchError::Interrupted);
        }
        if Instant::now() >= deadline {
            return Err(LaunchError::RemoteHosts {
                missing: format!("{missing:?}"),
                stored,
                endpoint: config.tunnel.listen.clone(),
                seconds: config.tunnel.wait_seconds,
            });
        }
    }
}

/// Whether `host`'s announcement lists at least one actor.
pub(super) fn announces_actors(host: &RemoteHost) -> bool {
    host.processes
        .iter()
        .any(|p| p.name.starts_with(actor::PROCESS_PREFIX))
}
