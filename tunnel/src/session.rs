//! Zenoh sessions and the keys uavmeta declares on them besides the tunnel's own.

use zenoh::{Session, Wait};

use crate::TunnelError;

/// The key the learner host's tunnel answers the handshake on, and holds its liveliness token on.
pub(crate) fn run_key(run_id: &str) -> String {
    format!("uavmeta/runs/{run_id}")
}

/// Every run a host serves, for the error naming them when a requested one is not among them.
pub(crate) const ALL_RUNS: &str = "uavmeta/runs/*";

/// Where a remote host announces its actors' metrics endpoints.
pub(crate) fn hosts_key(run_id: &str, host: &str) -> String {
    format!("uavmeta/runs/{run_id}/hosts/{host}")
}

/// The learner's host: a peer listening on `endpoint`.
pub(crate) fn listen(endpoint: &str) -> Result<Session, TunnelError> {
    open(endpoint, "peer", "listen/endpoints")
}

/// A remote host: a client of the learner host's peer at `endpoint`. A client's session fails to
/// open while it cannot connect, so an unreachable endpoint is an error to report, not a wait.
pub(crate) fn connect(endpoint: &str) -> Result<Session, TunnelError> {
    open(endpoint, "client", "connect/endpoints")
}

fn open(endpoint: &str, mode: &str, endpoints_key: &str) -> Result<Session, TunnelError> {
    let error = |message: String| TunnelError::Zenoh {
        endpoint: endpoint.into(),
        message,
    };
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
    for (key, value) in settings {
        config
            .insert_json5(key, &value)
            .map_err(|e| error(format!("config {key} = {value}: {e}")))?;
    }
    zenoh::open(config).wait().map_err(|e| error(e.to_string()))
}
