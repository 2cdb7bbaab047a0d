//! `[tunnel]`: remote actor hosts reaching the run through iceoryx2's tunnel over Zenoh. Read by
//! `uavmeta_tunnel` and by the launcher, which waits for the hosts (`uavmeta_runtime::launch`).

use std::collections::BTreeMap;
use std::path::PathBuf;

use garde::Validate;
use serde::{Deserialize, Serialize};
use smart_default::SmartDefault;

use super::rules::{satisfies, within, Broken};
use super::TaskConfig;

/// Most remote hosts a run lists (`tunnel.max_hosts`).
pub const MAX_HOSTS: usize = 64;

/// The longest `wait_seconds`: a week, far past any launch's wait, and a deadline every clock
/// can add.
pub const MAX_WAIT_SECONDS: f64 = 7.0 * 24.0 * 3600.0;

/// Remote actor hosts reach the run through iceoryx2's tunnel over Zenoh (`uavmeta tunnel`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, SmartDefault, Validate)]
#[serde(deny_unknown_fields, default)]
#[garde(allow_unvalidated)]
pub struct TunnelConfig {
    /// Zenoh endpoint where the launcher's tunnel accepts remote actor hosts, such as
    /// `tcp/0.0.0.0:7447`; empty = no tunnel, local actors only.
    #[garde(custom(satisfies(
        is_endpoint,
        "a Zenoh endpoint PROTOCOL/ADDRESS such as tcp/0.0.0.0:7447, or empty"
    )))]
    pub listen: String,
    /// Remote hosts (`uavmeta tunnel join --host`) whose actors the launcher waits for before it
    /// starts the local ones: until each has joined and the store has stored a transition, so
    /// that a run's data comes from every host it was planned with.
    pub wait_for_hosts: Vec<String>,
    /// Who may serve what: each remote host, by its certificate's name (`uavmeta tunnel certs
    /// --host NAME`, `uavmeta tunnel join --host NAME`), with the tasks its actors may publish
    /// for (`"*"`: every task), such as `{ actors-1 = ["lambda-0", "lambda-100"] }`. A host not
    /// listed publishes nothing; the tunnel's access control enforces it (docs/SECURITY.md).
    pub hosts: BTreeMap<String, Vec<String>>,
    /// The largest fraction of a task's dataset that one remote host's transitions may fill;
    /// beyond it they are dropped as surplus, so that no remote host completes a dataset alone
    /// while the learner host's actors serve the task.
    #[default(0.5)]
    #[garde(custom(satisfies(|s: &f64| *s > 0.0 && *s <= 1.0, "a fraction in (0, 1]")))]
    pub max_host_share: f64,
    /// Remote hosts whose processes the launcher lists (Prometheus targets, log); later ones are
    /// ignored.
    #[default(8)]
    #[garde(custom(within(1..=MAX_HOSTS, format!("between 1 and {MAX_HOSTS} hosts"))))]
    pub max_hosts: usize,
    /// How long the launcher waits for `wait_for_hosts` before it gives up, at most a week.
    #[default(120.0)]
    #[garde(custom(satisfies(
        |s: &f64| *s > 0.0 && *s <= MAX_WAIT_SECONDS,
        "seconds > 0 and at most a week (604800)"
    )))]
    pub wait_seconds: f64,
    /// The run's CA certificate (PEM). With a `tls/` endpoint, which any address beyond loopback
    /// needs, a remote host is admitted only with a certificate this CA signed (mutual TLS).
    /// `uavmeta tunnel certs` makes the CA and every host's certificate.
    pub ca: PathBuf,
    /// This host's certificate (PEM), signed by `ca`, naming the address remote hosts connect to.
    pub certificate: PathBuf,
    /// The private key (PEM) of `certificate`; readable by this user only.
    pub private_key: PathBuf,
    /// A file of `user:password` lines (Zenoh's user-password dictionary): a remote host must also
    /// present one of them (`uavmeta tunnel join --credentials FILE`). Empty: certificates only.
    pub credentials: PathBuf,
}

/// In `tunnel.hosts`, every task.
pub const ALL_TASKS: &str = "*";

/// What [`is_host_name`] accepts, for error messages.
pub const HOST_NAME_RULE: &str = "1 to 64 letters, digits, `-`, `_` and `.`, not starting with `.`";

/// A remote host's name as `uavmeta tunnel certs` accepts it, within Zenoh's and iceoryx2's
/// limits: [`HOST_NAME_RULE`].
pub fn is_host_name(name: &str) -> bool {
    (1..=64).contains(&name.len())
        && !name.starts_with('.')
        && (name.chars()).all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'))
}

/// A Zenoh endpoint `PROTOCOL/ADDRESS`, or empty (no tunnel).
fn is_endpoint(listen: &str) -> bool {
    listen.is_empty()
        || listen
            .split_once('/')
            .is_some_and(|(p, a)| !p.is_empty() && !a.is_empty())
}

/// Whether a Zenoh endpoint (`PROTOCOL/ADDRESS:PORT`) names a loopback address, which only this
/// host's own processes can reach.
pub fn is_loopback_endpoint(endpoint: &str) -> bool {
    let address = endpoint.split_once('/').map_or(endpoint, |(_, a)| a);
    let host = match address.rsplit_once(':') {
        Some((host, _port)) => host,
        None => address,
    };
    let host = host.trim_start_matches('[').trim_end_matches(']');
    host == "localhost"
        || host
            .parse::<std::net::IpAddr>()
            .is_ok_and(|ip| ip.is_loopback())
}

// The tunnel's security (issue #31): secure by default.
impl TunnelConfig {
    /// Hosts to wait for need a tunnel to come through and must be allowed to serve; a tunnel
    /// needs a host that may serve; every host is a certificate name allowed tasks of `tasks`.
    pub(super) fn check_hosts(&self, tasks: &[TaskConfig]) -> Result<(), Broken> {
        if !self.wait_for_hosts.is_empty() && self.listen.is_empty() {
            return Err(Broken::new(
                "tunnel.wait_for_hosts",
                &self.wait_for_hosts,
                "no hosts while tunnel.listen is empty (no tunnel to wait through)",
            ));
        }
        if let Some(host) = (self.wait_for_hosts.iter()).find(|h| !self.hosts.contains_key(*h)) {
            return Err(Broken::new(
                "tunnel.wait_for_hosts",
                host,
                "a host of tunnel.hosts (the hosts allowed to serve tasks)",
            ));
        }
        if !self.listen.is_empty() && self.hosts.is_empty() {
            return Err(Broken::new(
                "tunnel.hosts",
                &self.hosts,
                "at least one remote host with the tasks it may serve while tunnel.listen is set, \
                 such as { actors-1 = [\"*\"] } (the name its certificate was made for)",
            ));
        }
        if self.hosts.len() > self.max_hosts {
            return Err(Broken::new(
                "tunnel.hosts",
                &self.hosts.len(),
                format!("at most tunnel.max_hosts = {} hosts", self.max_hosts),
            ));
        }
        for (host, served) in &self.hosts {
            let key = format!("tunnel.hosts.{host}");
            if !is_host_name(host) {
                return Err(Broken::new(
                    key,
                    host,
                    format!("a certificate's host name: {HOST_NAME_RULE}"),
                ));
            }
            let known = |t: &String| t == ALL_TASKS || tasks.iter().any(|c| &c.name == t);
            if let Some(task) = served.iter().find(|t| !known(t)) {
                return Err(Broken::new(
                    key,
                    task,
                    "a task of [[tasks]], or \"*\" for all",
                ));
            }
        }
        Ok(())
    }

    /// The tasks of `tasks` that remote host `host` may serve (none if it is not listed).
    pub fn tasks_of<'t>(&self, host: &str, tasks: &'t [TaskConfig]) -> Vec<&'t TaskConfig> {
        let served = self.hosts.get(host).map_or(&[][..], Vec::as_slice);
        let all = served.iter().any(|t| t == ALL_TASKS);
        (tasks.iter())
            .filter(|t| all || served.contains(&t.name))
            .collect()
    }

    /// A `tls/` endpoint needs the CA, certificate and key; any other beyond loopback is refused,
    /// since it would let whoever reaches it join the run, unauthenticated and in clear.
    pub(super) fn check_security(&self) -> Result<(), Broken> {
        if self.listen.is_empty() {
            return Ok(());
        }
        if self.listen.starts_with("tls/") {
            return self.check_tls_files();
        }
        match is_loopback_endpoint(&self.listen) {
            true => Ok(()),
            false => Err(Broken::new(
                "tunnel.listen",
                &self.listen,
                "a loopback address, or a tls/ endpoint such as tls/0.0.0.0:7447 with tunnel.ca, \
                 tunnel.certificate and tunnel.private_key set: any other would let every host \
                 that reaches it join the run, unauthenticated and unencrypted. Make the files \
                 with `uavmeta tunnel certs --dir DIR --host NAME --address ADDRESS` \
                 (docs/REMOTE.md)",
            )),
        }
    }

    /// A `tls/` endpoint's CA, certificate and key are all named.
    fn check_tls_files(&self) -> Result<(), Broken> {
        let files = [
            ("tunnel.ca", &self.ca),
            ("tunnel.certificate", &self.certificate),
            ("tunnel.private_key", &self.private_key),
        ];
        match files
            .into_iter()
            .find(|(_, path)| path.as_os_str().is_empty())
        {
            None => Ok(()),
            Some((key, path)) => Err(Broken::new(
                key,
                path,
                "a PEM file for the tls/ endpoint of tunnel.listen (`uavmeta tunnel certs` makes \
                 the run's CA and host certificates)",
            )),
        }
    }
}
