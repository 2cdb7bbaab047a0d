//! `uavmeta tunnel serve`: the learner host's end of the tunnel.

use std::time::Instant;

use uavmeta_proto::config::Config;
use uavmeta_runtime::run_dir::{write_atomic, RemoteHost, RemoteProcess, RunDir};
use uavmeta_runtime::{domain, liveness, transport};
use zenoh::Wait;

use crate::bridge::{Bridge, Forwarders, RunServices, Side};
use crate::handshake::{self, RunInfo};
use crate::session::{self, hosts_key, run_key};
use crate::{TunnelError, POLL, SHUTDOWN_LINGER};

/// The process name: node, port file, log.
pub const PROCESS: &str = "tunnel";

/// Serves `run` to remote actor hosts on `config.tunnel.listen` until SIGINT/SIGTERM, or shortly
/// after the run's shutdown.
pub fn serve(run: &RunDir, config: &Config) -> Result<(), TunnelError> {
    let endpoint = &config.tunnel.listen;
    let node = domain::node(&format!("{}-{PROCESS}-services", run.id()), &config.run)?;
    // A killed predecessor's subscribers would block the actors on full buffers.
    domain::cleanup_dead_nodes(&node);
    let services = RunServices::open(&node, run, config)?;
    let shutdown = transport::control_subscriber(services.shutdown(), config)?;
    let forwarders = Forwarders::new(&services, config, Side::Learner)?;
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
    let announcements = std::sync::Arc::new(std::sync::Mutex::new(Announcements::default()));
    let heard = announcements.clone();
    let record_dir = hosts_dir.clone();
    let _hosts = session
        .declare_subscriber(hosts_key(run.id(), "*"))
        .callback(move |sample| {
            let key = sample.key_expr().as_str();
            lock(&heard).record(&record_dir, key, &sample.payload().to_bytes())
        })
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
    while liveness::keep_running(&node, POLL) {
        forwarders.pump();
        bridge.relay();
        lock(&announcements).flush(&hosts_dir);
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

/// Remote hosts a run records at most; later ones are ignored.
const MAX_HOSTS: usize = 64;
/// Processes one host may announce.
const MAX_PROCESSES: usize = 256;
/// A host's announcement is recorded at most this often.
const RECORD_EVERY: std::time::Duration = std::time::Duration::from_secs(1);

/// What remote hosts announced lately, so that each is recorded at most every [`RECORD_EVERY`]
/// and at most [`MAX_HOSTS`] are. An announcement that arrives sooner is not dropped but kept as
/// the host's pending one and recorded once its window opens ([`Announcements::flush`]): a host
/// whose actors start, send and exit within a second announces them only inside that second.
#[derive(Default)]
struct Announcements {
    last: std::collections::HashMap<String, Instant>,
    pending: std::collections::HashMap<String, Vec<u8>>,
}

fn lock(
    announcements: &std::sync::Mutex<Announcements>,
) -> std::sync::MutexGuard<'_, Announcements> {
    announcements.lock().unwrap_or_else(|e| e.into_inner())
}

impl Announcements {
    /// Writes what a remote host announced where the launcher reads it, if it is well-formed:
    /// a plain host name, processes of plain names, all at one `ADDRESS:PORT` address of the
    /// host's (a remote host names where its own processes answer, never a list of anyone's).
    fn record(&mut self, dir: &std::path::Path, key: &str, payload: &[u8]) {
        let host = key.rsplit('/').next().unwrap_or(key);
        let known = self.last.contains_key(host);
        if !known && self.last.len() >= MAX_HOSTS {
            return;
        }
        let announced: Option<RemoteHost> = serde_json::from_slice(payload).ok();
        match announced.filter(|a| well_formed(host, a)) {
            Some(_) => {
                self.pending.insert(host.to_string(), payload.to_vec());
                self.flush(dir);
            }
            None if !known => {
                tracing::warn!(host = %host.escape_debug(), "ignored a malformed remote host announcement")
            }
            None => {}
        }
    }
}

impl Announcements {
    /// Records each host's pending announcement whose host was last recorded at least
    /// [`RECORD_EVERY`] ago.
    fn flush(&mut self, dir: &std::path::Path) {
        let due: Vec<String> = (self.pending.keys())
            .filter(|host| (self.last.get(*host)).is_none_or(|at| at.elapsed() >= RECORD_EVERY))
            .cloned()
            .collect();
        for host in due {
            let payload = self.pending.remove(&host).expect("a pending host");
            self.last.insert(host.clone(), Instant::now());
            let path = dir.join(format!("{host}.json"));
            if let Err(error) = write_atomic(&path, &payload) {
                tracing::warn!(%error, "cannot record a remote host's announcement");
            }
        }
    }
}

fn plain_name(name: &str) -> bool {
    (1..=64).contains(&name.len())
        && !name.starts_with('.')
        && name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'))
}

fn well_formed(host: &str, announced: &RemoteHost) -> bool {
    let address = |p: &RemoteProcess| {
        let (address, port) = p.metrics.rsplit_once(':')?;
        port.parse::<u16>().ok().map(|_| address.to_string())
    };
    let addresses: std::collections::BTreeSet<Option<String>> =
        announced.processes.iter().map(address).collect();
    let names: std::collections::BTreeSet<&str> = announced
        .processes
        .iter()
        .map(|p| p.name.as_str())
        .collect();
    plain_name(host)
        && announced.host == host
        && announced.processes.len() <= MAX_PROCESSES
        && names.len() == announced.processes.len()
        && names.iter().all(|n| plain_name(n))
        && addresses.len() <= 1
        && !addresses.contains(&None)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn announcement(port: u16) -> Vec<u8> {
        let host = RemoteHost {
            host: "b".into(),
            processes: vec![RemoteProcess {
                name: "actor-lambda-0".into(),
                metrics: format!("10.0.0.2:{port}"),
            }],
        };
        serde_json::to_vec(&host).expect("serialises")
    }

    #[test]
    fn an_announcement_inside_the_rate_limit_is_recorded_when_the_window_opens_not_dropped() {
        let dir = tempfile::tempdir().expect("temp dir");
        let file = dir.path().join("b.json");
        let mut seen = Announcements::default();
        seen.record(dir.path(), "run/hosts/b", &announcement(9001));
        assert_eq!(
            std::fs::read(&file).expect("first recorded"),
            announcement(9001)
        );
        seen.record(dir.path(), "run/hosts/b", &announcement(9002));
        // Wait on the condition: flushing until the newer announcement is written.
        let deadline = Instant::now() + std::time::Duration::from_secs(60);
        while std::fs::read(&file).expect("recorded") != announcement(9002) {
            assert!(
                Instant::now() < deadline,
                "the pending announcement was never recorded"
            );
            std::thread::sleep(std::time::Duration::from_millis(50));
            seen.flush(dir.path());
        }
    }

    #[test]
    fn a_malformed_announcement_two_addresses_or_another_hosts_name_is_not_recorded() {
        let dir = tempfile::tempdir().expect("temp dir");
        let mut seen = Announcements::default();
        seen.record(dir.path(), "run/hosts/b", b"{not json");
        let two_addresses = br#"{"host":"b","processes":[{"name":"a","metrics":"10.0.0.2:1"},{"name":"c","metrics":"10.0.0.9:2"}]}"#;
        seen.record(dir.path(), "run/hosts/b", two_addresses);
        seen.record(dir.path(), "run/hosts/c", &announcement(9001));
        seen.flush(dir.path());
        let written: Vec<_> = std::fs::read_dir(dir.path()).expect("dir").collect();
        assert!(written.is_empty(), "recorded: {written:?}");
    }
}
