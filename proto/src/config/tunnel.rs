//! `[tunnel]`: remote actor hosts reaching the run through iceoryx2's tunnel over Zenoh. Read by
//! `uavmeta_tunnel` and by the launcher, which waits for the hosts (`uavmeta_runtime::launch`).

use std::path::PathBuf;

use garde::Validate;
use serde::{Deserialize, Serialize};
use smart_default::SmartDefault;

use super::rules::{positive, satisfies, within, Broken};

/// Most remote hosts a run lists (`tunnel.max_hosts`).
pub const MAX_HOSTS: usize = 64;

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
    /// Remote hosts whose processes the launcher lists (Prometheus targets, log); later ones are
    /// ignored.
    #[default(8)]
    #[garde(custom(within(1..=MAX_HOSTS, format!("between 1 and {MAX_HOSTS} hosts"))))]
    pub max_hosts: usize,
    /// How long the launcher waits for `wait_for_hosts` before it gives up.
    #[default(120.0)]
    #[garde(custom(positive("seconds > 0")))]
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
    /// Hosts to wait for need a tunnel to come through.
    pub(super) fn check_hosts(&self) -> Result<(), Broken> {
        match self.wait_for_hosts.is_empty() || !self.listen.is_empty() {
            true => Ok(()),
            false => Err(Broken::new(
                "tunnel.wait_for_hosts",
                &self.wait_for_hosts,
                "no hosts while tunnel.listen is empty (no tunnel to wait through)",
            )),
        }
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
