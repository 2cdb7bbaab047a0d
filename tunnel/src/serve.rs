//! `uavmeta tunnel serve`: the learner host's end of the tunnel.

use std::time::Instant;

use uavmeta_proto::config::Config;
use uavmeta_proto::transport::{self, write_atomic, RunDir};
use zenoh::sample::Sample;
use zenoh::Wait;

use crate::bridge::{Bridge, RunServices};
use crate::handshake::{self, RunInfo};
use crate::session::{self, hosts_key, run_key};
use crate::{TunnelError, POLL, SHUTDOWN_LINGER};

/// The process name: node, port file, log.
pub const PROCESS: &str = "tunnel";

/// Serves `run` to remote actor hosts on `config.tunnel.listen` until SIGINT/SIGTERM, or shortly
/// after the run's shutdown.
pub fn serve(run: &RunDir, config: &Config) -> Result<(), TunnelError> {
    let endpoint = &config.tunnel.listen;
    let node = transport::node(&format!("{}-{PROCESS}-services", run.id()), &config.run)?;
    // A killed predecessor's subscribers would block the actors on full buffers.
    transport::cleanup_dead_nodes(&node);
    let services = RunServices::open(&node, run, config)?;
    let shutdown = transport::control_subscriber(&services.shutdown, config)?;
    let security = session::Security::of_config(&config.tunnel);
    let keys = [
        "tunnel.ca",
        "tunnel.certificate",
        "tunnel.private_key",
        "tunnel.credentials",
    ];
    security.check_files(endpoint, keys)?;
    let session = session::listen(endpoint, &security)?;
    let zenoh_error = |e: zenoh::Error| TunnelError::Zenoh {
        endpoint: endpoint.clone(),
        message: e.to_string(),
    };
    let info = RunInfo::new(run, config);
    let _handshake = session
        .declare_queryable(run_key(run.id()))
        .callback(move |query| handshake::reply(&query, &info))
        .wait()
        .map_err(zenoh_error)?;
    let hosts_dir = run.remote_hosts_dir();
    std::fs::create_dir_all(&hosts_dir).map_err(|source| transport::TransportError::Io {
        path: hosts_dir.clone(),
        action: "create",
        source,
    })?;
    let _hosts = session
        .declare_subscriber(hosts_key(run.id(), "*"))
        .callback(move |sample| record_host(&hosts_dir, &sample))
        .wait()
        .map_err(zenoh_error)?;
    let mut bridge = Bridge::new(
        &format!("{}-{PROCESS}", run.id()),
        config,
        &session,
        &services,
    )?;
    // The first discovery opens the relays, whose Zenoh subscribers are declared before the
    // token: a remote host that sees the token finds them, and sends nothing into the void.
    bridge.relay();
    let _token = session
        .liveliness()
        .declare_token(run_key(run.id()))
        .wait()
        .map_err(zenoh_error)?;
    tracing::info!(run = run.id(), %endpoint, "serving the run to remote actor hosts");
    let mut shutdown_at = None;
    while transport::keep_running(&node, POLL) {
        bridge.relay();
        if shutdown_at.is_none() && transport::shutdown_requested(&shutdown)? {
            shutdown_at = Some(Instant::now());
        }
        if shutdown_at.is_some_and(|at| at.elapsed() > SHUTDOWN_LINGER) {
            break;
        }
    }
    tracing::info!("tunnel stopped");
    Ok(())
}

/// Writes what a remote host announced where the launcher reads it.
fn record_host(dir: &std::path::Path, sample: &Sample) {
    let key = sample.key_expr().as_str();
    let host = key.rsplit('/').next().unwrap_or(key);
    let path = dir.join(format!("{host}.json"));
    if let Err(error) = write_atomic(&path, &sample.payload().to_bytes()) {
        tracing::warn!(%error, "cannot record a remote host's announcement");
    }
}
