//! Zenoh sessions and the keys uavmeta declares on them besides the tunnel's own, and who may
//! open one: Zenoh's own mutual TLS (a `tls/` endpoint; each side presents a certificate the
//! run's CA signed) and user-password authentication (a dictionary file on the learner's host, a
//! credentials file on a remote host). Nothing here is uavmeta's own cryptography.

use std::path::{Path, PathBuf};

use zenoh::{Session, Wait};

use crate::TunnelError;

impl TunnelError {
    /// The error of Zenoh at `endpoint`, for `map_err`.
    pub(crate) fn zenoh<E: std::fmt::Display>(endpoint: &str) -> impl Fn(E) -> Self + Copy + '_ {
        move |e| Self::Zenoh {
            endpoint: endpoint.into(),
            message: e.to_string(),
        }
    }
}

/// The key the learner host's tunnel answers the handshake on, and holds its liveliness token on.
pub fn run_key(run_id: &str) -> String {
    format!("uavmeta/runs/{run_id}")
}

/// Where a remote host announces its actors' metrics endpoints.
pub(crate) fn hosts_key(run_id: &str, host: &str) -> String {
    format!("uavmeta/runs/{run_id}/hosts/{host}")
}

/// The files that admit a host to a run's tunnel; every path names a PEM or text file, never a
/// secret itself.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Security {
    /// The run's CA certificate: the other side's certificate must be signed by it.
    pub ca: Option<PathBuf>,
    /// This host's certificate and its private key.
    pub certificate: Option<PathBuf>,
    pub private_key: Option<PathBuf>,
    /// On the learner's host, a file of `user:password` lines; on a remote host, a file with its
    /// own `user:password` line.
    pub credentials: Option<PathBuf>,
}

impl Security {
    /// The learner host's settings from `[tunnel]` (empty paths are unset).
    pub fn of_config(t: &uavmeta_proto::config::TunnelConfig) -> Self {
        let set = |p: &PathBuf| (!p.as_os_str().is_empty()).then(|| p.clone());
        Self {
            ca: set(&t.ca),
            certificate: set(&t.certificate),
            private_key: set(&t.private_key),
            credentials: set(&t.credentials),
        }
    }

    /// Each file set, with the key or flag that names it, must be readable now: Zenoh would only
    /// say that a link failed.
    pub fn check_files(&self, endpoint: &str, names: [&str; 4]) -> Result<(), TunnelError> {
        let error = TunnelError::zenoh(endpoint);
        let files = [
            &self.ca,
            &self.certificate,
            &self.private_key,
            &self.credentials,
        ];
        for (name, file) in names.into_iter().zip(files) {
            if let Some(path) = file {
                std::fs::File::open(path).map_err(|e| {
                    error(format!("{name} = {}: cannot read it: {e}", path.display()))
                })?;
            }
        }
        let tls = endpoint.starts_with("tls/");
        let missing = [&self.ca, &self.certificate, &self.private_key]
            .iter()
            .zip(names)
            .find(|(file, _)| file.is_none())
            .map(|(_, name)| name);
        match (tls, missing) {
            (true, Some(name)) => Err(error(format!(
                "a tls/ endpoint needs {name} (`uavmeta tunnel certs` makes the files)"
            ))),
            _ => Ok(()),
        }
    }
}

/// The learner's host: a peer listening on `endpoint`, under `access` if given.
pub(crate) fn listen(
    endpoint: &str,
    security: &Security,
    access: Option<&Access>,
) -> Result<Session, TunnelError> {
    let access = access.map(|a| ("access_control", a.to_json()));
    open(endpoint, "peer", "listen/endpoints", security, access)
}

/// Who may put what on the learner host's session, enforced by Zenoh's access control: each
/// remote host, known by the name its certificate was made for (the TLS link's authenticated
/// name, not what the host says), may put only on the channels of its own transition services
/// and on its own announcement key; it may subscribe, query and offer within the run's keys;
/// anything else it sends, and everything from a host not listed, is dropped on arrival.
#[derive(Debug, Clone)]
pub(crate) struct Access {
    pub run_id: String,
    /// Per host, the iceoryx2 service hashes of its transition services.
    pub hosts: Vec<(String, Vec<String>)>,
}

impl Access {
    /// Zenoh's `access_control` settings.
    fn to_json(&self) -> String {
        let run = run_key(&self.run_id);
        let everything = [
            "put",
            "delete",
            "declare_subscriber",
            "query",
            "declare_queryable",
            "reply",
            "liveliness_token",
            "declare_liveliness_subscriber",
            "liveliness_query",
        ];
        let mut rules = vec![
            serde_json::json!({"id": "to-hosts", "messages": everything, "flows": ["egress"],
                "permission": "allow", "key_exprs": ["**"]}),
            serde_json::json!({"id": "from-hosts", "messages": &everything[2..],
                "flows": ["ingress"], "permission": "allow",
                "key_exprs": ["iox2/**", run.clone(), format!("{run}/**")]}),
        ];
        let mut subjects = vec![serde_json::json!({"id": "hosts",
            "cert_common_names": self.hosts.iter().map(|(h, _)| h).collect::<Vec<_>>()})];
        let mut policies = vec![serde_json::json!({"rules": ["to-hosts", "from-hosts"],
            "subjects": ["hosts"]})];
        for (i, (host, hashes)) in self.hosts.iter().enumerate() {
            let mut keys: Vec<String> = (hashes.iter())
                .map(|hash| format!("iox2/v1/channel/{hash}/*"))
                .collect();
            keys.push(hosts_key(&self.run_id, host));
            rules.push(
                serde_json::json!({"id": format!("puts-{i}"), "messages": ["put"],
                "flows": ["ingress"], "permission": "allow", "key_exprs": keys}),
            );
            subjects.push(serde_json::json!({"id": format!("host-{i}"),
                "cert_common_names": [host]}));
            policies.push(serde_json::json!({"rules": [format!("puts-{i}")],
                "subjects": [format!("host-{i}")]}));
        }
        serde_json::json!({"enabled": true, "default_permission": "deny", "rules": rules,
            "subjects": subjects, "policies": policies})
        .to_string()
    }
}

/// A remote host: a client of the learner host's peer at `endpoint`. A client's session fails to
/// open while it cannot connect (or is refused), so that is an error to report, not a wait.
pub fn connect(endpoint: &str, security: &Security) -> Result<Session, TunnelError> {
    open(endpoint, "client", "connect/endpoints", security, None)
}

/// Zenoh's settings for `security`, as (key, JSON value) pairs; `listening` picks the TLS keys of
/// a listener or of a connecting client.
fn security_settings(
    security: &Security,
    listening: bool,
) -> Result<Vec<(&'static str, String)>, String> {
    let json = |value: &str| serde_json::to_string(value).expect("strings serialise");
    let path = |p: &Path| json(&p.display().to_string());
    let mut settings = Vec::new();
    let (certificate, key) = match listening {
        true => (
            "transport/link/tls/listen_certificate",
            "transport/link/tls/listen_private_key",
        ),
        false => (
            "transport/link/tls/connect_certificate",
            "transport/link/tls/connect_private_key",
        ),
    };
    if let Some(ca) = &security.ca {
        settings.push(("transport/link/tls/root_ca_certificate", path(ca)));
        // Mutual TLS: the listener asks every client for a certificate the CA signed.
        settings.push(("transport/link/tls/enable_mtls", "true".into()));
        settings.push(("transport/link/tls/verify_name_on_connect", "true".into()));
    }
    if let Some(file) = &security.certificate {
        settings.push((certificate, path(file)));
    }
    if let Some(file) = &security.private_key {
        settings.push((key, path(file)));
    }
    match (&security.credentials, listening) {
        (Some(file), true) => settings.push(("transport/auth/usrpwd/dictionary_file", path(file))),
        (Some(file), false) => {
            let (user, password) = read_credentials(file)?;
            settings.push(("transport/auth/usrpwd/user", json(&user)));
            settings.push(("transport/auth/usrpwd/password", json(&password)));
        }
        (None, _) => {}
    }
    Ok(settings)
}

/// The first `user:password` line of a remote host's credentials file.
fn read_credentials(file: &Path) -> Result<(String, String), String> {
    let text = std::fs::read_to_string(file)
        .map_err(|e| format!("credentials file {}: cannot read it: {e}", file.display()))?;
    let line = text
        .lines()
        .map(str::trim)
        .find(|l| !l.is_empty() && !l.starts_with('#'));
    match line.and_then(|l| l.split_once(':')) {
        Some((user, password)) if !user.is_empty() && !password.is_empty() => {
            Ok((user.to_string(), password.to_string()))
        }
        _ => Err(format!(
            "credentials file {}: expected a line `user:password`",
            file.display()
        )),
    }
}

fn open(
    endpoint: &str,
    mode: &str,
    endpoints_key: &str,
    security: &Security,
    access: Option<(&str, String)>,
) -> Result<Session, TunnelError> {
    let error = TunnelError::zenoh(endpoint);
    let mut config = zenoh::Config::default();
    let json = |value: &str| serde_json::to_string(value).expect("strings serialise");
    let settings = [
        ("mode", json(mode)),
        (endpoints_key, format!("[{}]", json(endpoint))),
        // Only the named endpoint: multicast scouting would join any uavmeta run on the LAN (and
        // every concurrent test on this machine) into one Zenoh network.
        ("scouting/multicast/enabled", "false".into()),
        // The tunnel's relays publish under `iox2/v1/channel/...`. Zenoh's default for a put is to
        // drop it when the link's queue stays full for a millisecond; block instead, so a slow
        // link slows the actors (backpressure) rather than losing their batches.
        (
            "qos/publication",
            r#"[{"key_exprs": ["iox2/v1/channel/**"], "config": {"congestion_control": "block"}}]"#
                .into(),
        ),
    ];
    for (key, value) in settings.into_iter().chain(access) {
        config
            .insert_json5(key, &value)
            .map_err(|e| error(format!("config {key} = {value}: {e}")))?;
    }
    for (key, value) in security_settings(security, mode == "peer").map_err(error)? {
        // The value is left out of the error: it may be a password.
        config
            .insert_json5(key, &value)
            .map_err(|e| error(format!("config {key}: {e}")))?;
    }
    zenoh::open(config).wait().map_err(|e| error(e.to_string()))
}
