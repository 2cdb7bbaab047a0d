//! Remote actors: a run's services carried between hosts by iceoryx2's own tunnel over Zenoh.
//!
//! Each host runs its processes in its own iceoryx2 domain (`run.domain`); nothing but a tunnel
//! connects two domains. On the learner's host, [`serve`] (`uavmeta tunnel serve`, started by
//! the launcher when `tunnel.listen` is set) opens a Zenoh session listening on that endpoint; on
//! each actor host, [`join`] (`uavmeta tunnel join`) connects to it, makes a local directory for
//! the run, and plain `uavmeta actor --run DIR` processes publish into it as on the learner's host.
//!
//! Both sides run an [`iceoryx2_link::Link`] over the [`iceoryx2_link_tunnel::Tunnel`] with the
//! Zenoh carrier, restricted to the services a remote actor uses, each only its way
//! (`ServiceNames::tunnel_routes`, declared once in `uavmeta_proto::payload`): a remote host's
//! transitions cross under their own name; acknowledgements, dataset announcements and the shutdown cross only as
//! `to-remote/` copies that the learner host's tunnel fills and a remote host's tunnel empties
//! into its own services, so nothing a remote host publishes reaches a learner-host process but
//! its transitions, which the store validates. The same payload types and service names from
//! `uavmeta_proto`, relayed byte for byte. The crates are used as a library rather than by
//! running their CLI (`iox2-link-tunnel-zenoh`) as a child because the tunnel must (1) create
//! the run's services with uavmeta's settings before it mirrors them (a mirror gets iceoryx2's
//! defaults: safe overflow on, no schema attribute, which uavmeta's openers refuse), (2) check
//! the schema version and the run id before bridging anything, with an error naming both sides,
//! and (3) tell the learner's host which remote actors it carries. The CLI can do none of these,
//! and the library costs the same Zenoh build.
//!
//! **Who may join** ([`session::Security`]): Zenoh's mutual TLS against the run's CA, and its
//! user-password authentication on top; every refusal is the one [`TunnelError::NotAdmitted`]
//! (docs/SECURITY.md, "Threat model"; the set-up: docs/REMOTE.md).
//!
//! **Handshake** ([`handshake`]): before bridging, `join` asks the learner's host, by Zenoh query
//! on `uavmeta/runs/<run id>`, for the run; the answer carries the run's hash, config (without
//! its `[tunnel]` section: paths of the learner host's keys are none of a remote host's business)
//! and schema version. Each side refuses the other's mismatching schema version with an error
//! naming both.
//!
//! **Losing the other side**: `join` drops its link when the learner tunnel's Zenoh liveliness
//! token goes, and shakes hands again and builds a new one when it is back (then: docs/REMOTE.md).
//!
//! **Who may publish what**: a remote host's actors publish on services of their own
//! (`ServiceNames::for_host`), for the tasks `tunnel.hosts` lets it serve, and the learner host's
//! session runs Zenoh's access control ([`session::Access`]), by the name on each link's
//! certificate: a host puts only on its own services' channels and its own announcement key. The
//! learner host's own actors' services do not cross at all.
//!
//! **Known costs**: the Zenoh carrier's receiving inbox holds 64 frames and drops beyond, and the
//! link's publishers skip a full subscriber (waiting on its own full one would deadlock it), so a
//! frame dropped there or skipped by a store that fell behind is a gap the store counts as
//! missing: every published transition is stored or counted, but not every one is stored. `join`
//! narrows a remote actor's window of unacknowledged batches to fit the inbox, which makes such
//! drops rare.

use std::time::Duration;

use uavmeta_proto::config::ConfigError;
use uavmeta_runtime::run_dir::FileError;
use uavmeta_runtime::transport::TransportError;

mod bridge;
pub mod certs;
pub mod handshake;
mod join;
mod serve;
pub mod session;

pub use join::{join, JoinOptions};
pub use serve::serve;
pub use session::Security;

/// How often a tunnel looks for new local or remote services; relaying runs in between.
const DISCOVER_EVERY: Duration = Duration::from_millis(100);

/// How long a tunnel sleeps between relaying rounds: local publications do not wake it.
const POLL: Duration = Duration::from_micros(500);

/// After the run's shutdown, how long a tunnel keeps relaying so the other side hears it too.
const SHUTDOWN_LINGER: Duration = Duration::from_secs(3);

#[derive(Debug, thiserror::Error)]
pub enum TunnelError {
    #[error(transparent)]
    Transport(#[from] TransportError),
    #[error(transparent)]
    File(#[from] FileError),
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error("zenoh endpoint `{endpoint}`: {message}")]
    Zenoh { endpoint: String, message: String },
    /// One error for an endpoint that cannot be reached, a run id it does not serve and a
    /// certificate or credentials it refuses, so that a stranger learns nothing of the runs there.
    #[error(
        "cannot join run `{run}` at `{endpoint}` within {waited:?}: nothing there admitted this \
         host to that run. An unreachable endpoint, a run id it does not serve, and a certificate \
         or credentials it refuses look the same from here; check the run id the learner host's \
         `uavmeta launch` logs, this host's --ca, --certificate, --private-key and --credentials, \
         and the learner host's tunnel log"
    )]
    NotAdmitted {
        endpoint: String,
        run: String,
        waited: Duration,
    },
    #[error(
        "--run-id `{run_id}`: expected the run id the learner host's `uavmeta launch` logs, 1 to \
         73 letters, digits, `-` and `_` (no Zenoh wildcards such as `*`)"
    )]
    BadRunId { run_id: String },
    #[error("the run's host at `{endpoint}` refused this host: {message}")]
    Refused { endpoint: String, message: String },
    #[error(
        "the run's host at `{endpoint}` speaks schema version {theirs}, but this uavmeta build \
         speaks version {ours}; run the same uavmeta build on every host"
    )]
    SchemaMismatch {
        endpoint: String,
        theirs: u32,
        ours: u32,
    },
    #[error("iceoryx2 tunnel: cannot {action}: {message}")]
    Link {
        action: &'static str,
        message: String,
    },
}
