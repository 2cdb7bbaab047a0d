//! `uavmeta tunnel serve`: the learner host's end of the tunnel.

use std::collections::HashMap;
use std::net::IpAddr;
use std::path::Path;
use std::sync::{Arc, Mutex};
use std::time::Instant;

use uavmeta_proto::config::{is_host_name, Config};
use uavmeta_runtime::run_dir::{write_atomic, FileError, RemoteHost, RemoteProcess, RunDir};
use uavmeta_runtime::{domain, liveness, transport};
use zenoh::{Session, Wait};

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
    let shutdown = transport::control_subscriber(services.shutdown())?;
    let forwarders = Forwarders::new(&services, Side::Learner)?;
    let security = session::Security::of_config(&config.tunnel);
    let keys = [
        "tunnel.ca",
        "tunnel.certificate",
        "tunnel.private_key",
        "tunnel.credentials",
    ];
    security.check_files(endpoint, keys)?;
    let tls = endpoint.starts_with("tls/");
    // Only a TLS link names its host (its certificate's name); a loopback endpoint without TLS
    // authenticates no one, so there is no one to bind (docs/SECURITY.md).
    let access = tls.then(|| session::Access {
        run_id: run.id().to_string(),
        hosts: services.transition_hashes(),
    });
    let session = session::listen(endpoint, &security, access.as_ref())?;
    let zenoh_error = TunnelError::zenoh(endpoint);
    let info = RunInfo::new(run, config);
    let served = handshake::served(config);
    let _handshake = session
        .declare_queryable(run_key(run.id()))
        .callback(move |query| handshake::reply(&query, &info, &served))
        .wait()
        .map_err(zenoh_error)?;
    let hosts_dir = run.remote_hosts_dir();
    std::fs::create_dir_all(&hosts_dir).map_err(FileError::at(&hosts_dir, "create"))?;
    let announcements = Arc::new(Mutex::new(Announcements::new(config.tunnel.max_hosts)));
    let heard = announcements.clone();
    let _hosts = session
        .declare_subscriber(hosts_key(run.id(), "*"))
        .callback(move |sample| {
            let key = sample.key_expr().as_str();
            lock(&heard).receive(key, &sample.payload().to_bytes())
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
        lock(&announcements).flush(&hosts_dir, |host| tunnel_address(&session, host, tls));
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

/// Processes one host may announce: as many actors as one host of a run may run
/// (`uavmeta_proto::config::MAX_ACTORS`), and its tunnel.
const MAX_PROCESSES: usize = uavmeta_proto::config::MAX_ACTORS + 1;
/// A host's announcement is recorded at most this often.
const RECORD_EVERY: std::time::Duration = std::time::Duration::from_secs(1);

/// What remote hosts announced lately, kept as received (the Zenoh callback does nothing else)
/// and recorded by [`Announcements::flush`] on the tunnel's loop: each host at most every
/// [`RECORD_EVERY`], at most `tunnel.max_hosts` of them. An announcement that arrives sooner is
/// not dropped but kept as the host's pending one and recorded once its window opens: a host
/// whose actors start, send and exit within a second announces them only inside that second.
struct Announcements {
    max_hosts: usize,
    last: HashMap<String, Instant>,
    pending: HashMap<String, Vec<u8>>,
}

fn lock(announcements: &Mutex<Announcements>) -> std::sync::MutexGuard<'_, Announcements> {
    announcements.lock().unwrap_or_else(|e| e.into_inner())
}

impl Announcements {
    fn new(max_hosts: usize) -> Self {
        Self {
            max_hosts,
            last: HashMap::new(),
            pending: HashMap::new(),
        }
    }

    /// Keeps the newest announcement of the host its key names, if the host is one of the first
    /// `max_hosts` heard.
    fn receive(&mut self, key: &str, payload: &[u8]) {
        let host = key.rsplit('/').next().unwrap_or(key);
        let known = self.last.contains_key(host) || self.pending.contains_key(host);
        if known || self.last.len() + self.pending.len() < self.max_hosts {
            self.pending.insert(host.to_string(), payload.to_vec());
        }
    }

    /// Records each pending announcement whose host was last recorded at least [`RECORD_EVERY`]
    /// ago, if it is well-formed and `address` knows where the host reaches the tunnel from.
    fn flush(&mut self, dir: &Path, address: impl Fn(&str) -> Option<IpAddr>) {
        let due: Vec<String> = (self.pending.keys())
            .filter(|host| (self.last.get(*host)).is_none_or(|at| at.elapsed() >= RECORD_EVERY))
            .cloned()
            .collect();
        for host in due {
            let payload = self.pending.remove(&host).expect("a pending host");
            let first = self.last.insert(host.clone(), Instant::now()).is_none();
            match recorded(&host, &payload, &address) {
                Ok(bytes) => {
                    if let Err(error) = write_atomic(&dir.join(format!("{host}.json")), &bytes) {
                        tracing::warn!(%error, "cannot record a remote host's announcement");
                    }
                }
                // Said once per host: a host that keeps sending it must not flood the log.
                Err(why) if first => {
                    tracing::warn!(host = %host.escape_debug(), "ignored a remote host's announcement: {why}")
                }
                Err(_) => {}
            }
        }
    }
}

/// What a remote host's announcement is recorded as: its processes' ports at the address the
/// host reaches the tunnel from, whatever address it named (a host says which ports its
/// processes answer on, never where anyone's are).
fn recorded(
    host: &str,
    payload: &[u8],
    address: &impl Fn(&str) -> Option<IpAddr>,
) -> Result<Vec<u8>, &'static str> {
    let mut announced: RemoteHost =
        serde_json::from_slice(payload).map_err(|_| "not an announcement")?;
    if !well_formed(host, &announced) {
        return Err("malformed (a name, or more than one address or too many processes)");
    }
    let ip = address(host).ok_or(
        "no link of the tunnel is authenticated as this host (its certificate names another)",
    )?;
    for process in &mut announced.processes {
        let port = process.metrics.rsplit_once(':').map_or("", |(_, p)| p);
        process.metrics = std::net::SocketAddr::new(ip, port.parse().unwrap_or(0)).to_string();
    }
    Ok(serde_json::to_vec(&announced).expect("serialises"))
}

/// The address from which `host` reaches the tunnel: the remote end of a link whose TLS
/// certificate names `host`; on a plain (loopback) endpoint, which authenticates no one, the
/// remote end of any link.
fn tunnel_address(session: &Session, host: &str, tls: bool) -> Option<IpAddr> {
    let links = session.info().links().wait();
    links
        .into_iter()
        .filter(|link| !tls || link.auth_identifier() == Some(host))
        .find_map(|link| {
            let address = link.dst().address();
            let (ip, _port) = address.as_str().rsplit_once(':')?;
            ip.trim_start_matches('[')
                .trim_end_matches(']')
                .parse()
                .ok()
        })
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
    is_host_name(host)
        && announced.host == host
        && announced.processes.len() <= MAX_PROCESSES
        && names.len() == announced.processes.len()
        && names.iter().all(|n| is_host_name(n))
        && addresses.len() <= 1
        && !addresses.contains(&None)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn announcement(host: &str, address: &str, port: u16) -> Vec<u8> {
        let host = RemoteHost {
            host: host.into(),
            processes: vec![RemoteProcess {
                name: "actor-lambda-0".into(),
                metrics: format!("{address}:{port}"),
            }],
        };
        serde_json::to_vec(&host).expect("serialises")
    }

    /// Where every host reaches the tunnel from, in these tests.
    fn from_b(host: &str) -> Option<IpAddr> {
        (host == "b").then(|| "10.0.0.2".parse().expect("an address"))
    }

    #[test]
    fn an_announcement_inside_the_rate_limit_is_recorded_when_the_window_opens_not_dropped() {
        let dir = tempfile::tempdir().expect("temp dir");
        let file = dir.path().join("b.json");
        let mut seen = Announcements::new(8);
        seen.receive("run/hosts/b", &announcement("b", "10.0.0.2", 9001));
        seen.flush(dir.path(), from_b);
        let first = std::fs::read(&file).expect("first recorded");
        assert_eq!(first, announcement("b", "10.0.0.2", 9001));
        seen.receive("run/hosts/b", &announcement("b", "10.0.0.2", 9002));
        // Wait on the condition: flushing until the newer announcement is written.
        let deadline = Instant::now() + std::time::Duration::from_secs(60);
        while std::fs::read(&file).expect("recorded") != announcement("b", "10.0.0.2", 9002) {
            assert!(
                Instant::now() < deadline,
                "the pending announcement was never recorded"
            );
            std::thread::sleep(std::time::Duration::from_millis(50));
            seen.flush(dir.path(), from_b);
        }
    }

    #[test]
    fn a_malformed_announcement_two_addresses_or_another_hosts_name_is_not_recorded() {
        let dir = tempfile::tempdir().expect("temp dir");
        let mut seen = Announcements::new(8);
        seen.receive("run/hosts/b", b"{not json");
        seen.flush(dir.path(), from_b);
        let two_addresses = br#"{"host":"b","processes":[{"name":"a","metrics":"10.0.0.2:1"},{"name":"c","metrics":"10.0.0.9:2"}]}"#;
        std::thread::sleep(RECORD_EVERY);
        seen.receive("run/hosts/b", two_addresses);
        seen.receive("run/hosts/c", &announcement("b", "10.0.0.2", 9001));
        seen.flush(dir.path(), from_b);
        let written: Vec<_> = std::fs::read_dir(dir.path()).expect("dir").collect();
        assert!(written.is_empty(), "recorded: {written:?}");
    }

    #[test]
    fn targets_are_recorded_at_the_hosts_tunnel_address_for_at_most_max_hosts_hosts() {
        let dir = tempfile::tempdir().expect("temp dir");
        let mut seen = Announcements::new(1);
        seen.receive("run/hosts/b", &announcement("b", "127.0.0.1", 22));
        seen.receive("run/hosts/d", &announcement("d", "10.0.0.4", 1));
        seen.flush(dir.path(), |_| "10.0.0.2".parse().ok());
        let recorded: RemoteHost =
            serde_json::from_slice(&std::fs::read(dir.path().join("b.json")).expect("b"))
                .expect("an announcement");
        assert_eq!(recorded.processes[0].metrics, "10.0.0.2:22");
        assert!(
            !dir.path().join("d.json").exists(),
            "a host beyond max_hosts"
        );
    }

    #[test]
    fn a_host_announcing_more_processes_than_one_host_may_run_is_not_recorded() {
        let dir = tempfile::tempdir().expect("temp dir");
        let mut seen = Announcements::new(8);
        let processes = |n: usize| RemoteHost {
            host: "b".into(),
            processes: (0..n)
                .map(|i| RemoteProcess {
                    name: format!("actor-{i}"),
                    metrics: format!("10.0.0.2:{}", 1000 + i),
                })
                .collect(),
        };
        let too_many = serde_json::to_vec(&processes(MAX_PROCESSES + 1)).expect("serialises");
        seen.receive("run/hosts/b", &too_many);
        seen.flush(dir.path(), from_b);
        assert!(
            !dir.path().join("b.json").exists(),
            "{MAX_PROCESSES} + 1 recorded"
        );
        std::thread::sleep(RECORD_EVERY);
        let most = serde_json::to_vec(&processes(MAX_PROCESSES)).expect("serialises");
        seen.receive("run/hosts/b", &most);
        seen.flush(dir.path(), from_b);
        assert!(
            dir.path().join("b.json").exists(),
            "{MAX_PROCESSES} not recorded"
        );
    }
}
