//! `[run]`: where a run writes, its seeds, metrics endpoints and iceoryx2 capacities. Read by
//! `uavmeta_runtime`: its transport, its start-up, the launcher (`uavmeta_runtime::launch`) and
//! every process it starts.

use std::path::PathBuf;

use garde::Validate;
use serde::{Deserialize, Serialize};
use smart_default::SmartDefault;

use super::rules::{at_least, at_most, finite, non_empty, satisfies, toml_seed};

/// Largest `run.transitions_per_message`: an actor's shared memory grows with it x subscriber buffer.
pub const MAX_TRANSITIONS_PER_MESSAGE: usize = 16_384;
/// Largest `run.subscriber_buffer`.
pub const MAX_SUBSCRIBER_BUFFER: usize = 4_096;

/// Longest `run.domain`: the iceoryx2 prefix of every shared-memory name grows with it.
pub const MAX_DOMAIN_LEN: usize = 32;

/// Where a run writes, its seeds, its metrics endpoints and its iceoryx2 capacities.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, SmartDefault, Validate)]
#[serde(deny_unknown_fields, default)]
#[garde(allow_unvalidated)]
pub struct RunConfig {
    /// Run directory: datasets, checkpoints, CSV files, port files.
    #[default("runs/default")]
    pub dir: PathBuf,
    /// Seeds of repeated runs; the first is the seed of a single run.
    #[default(vec![0])]
    #[garde(custom(non_empty("at least one seed")), inner(custom(toml_seed())))]
    pub seeds: Vec<u64>,
    /// Address every /metrics endpoint binds.
    #[default("127.0.0.1")]
    pub metrics_host: String,
    /// Port of the launcher's /metrics; children get 0 (an ephemeral port written to the run dir).
    #[default(0)]
    pub metrics_port: u16,
    /// Transitions per zero-copy message (a batch of the transport).
    #[default(64)]
    #[garde(custom(at_least(1)), custom(at_most(MAX_TRANSITIONS_PER_MESSAGE)))]
    pub transitions_per_message: usize,
    /// Batches a subscriber buffers before publishers wait.
    #[default(64)]
    #[garde(custom(at_least(1)), custom(at_most(MAX_SUBSCRIBER_BUFFER)))]
    pub subscriber_buffer: usize,
    /// Publishers (actors) a transition service admits.
    #[default(64)]
    #[garde(custom(at_least(1)))]
    pub max_publishers: usize,
    /// Restarts of a crashed or hung child before the launcher gives up.
    #[default(5)]
    pub max_restarts: u32,
    /// A launched child whose heartbeat (`uavmeta_runtime::liveness::heartbeat`) has not moved for
    /// this many seconds is taken for hung (stopped, deadlocked, livelocked), killed and restarted
    /// like a crashed one; 0 = never. Every process beats at least every few seconds on this
    /// machine under load, so the default leaves a wide margin.
    #[default(60.0)]
    #[garde(custom(finite(0.0.., "seconds >= 0 (0 = never)")))]
    pub hang_timeout_seconds: f64,
    /// The iceoryx2 domain of this host's processes of the run: their shared memory is named
    /// `iox2_<domain>_...` and iceoryx2's files live in `/tmp/iceoryx2/<domain>/`, so processes of
    /// two domains cannot see each other even on one machine; empty = iceoryx2's default domain.
    /// Only a tunnel (`uavmeta tunnel`) connects domains. A remote host's copy of the config
    /// names its own (`uavmeta tunnel join --domain`).
    #[garde(custom(satisfies(
        is_domain,
        format!("at most {MAX_DOMAIN_LEN} letters, digits, '-' or '_' (empty = default)")
    )))]
    pub domain: String,
}

/// A `run.domain`: at most [`MAX_DOMAIN_LEN`] letters, digits, '-' or '_'.
fn is_domain(domain: &str) -> bool {
    domain.len() <= MAX_DOMAIN_LEN
        && domain
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
}
