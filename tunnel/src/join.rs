//! `uavmeta tunnel join`: a remote actor host's end of the tunnel.

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use uavmeta_proto::config::{is_host_name, Config, TunnelConfig, HOST_NAME_RULE};
use uavmeta_proto::payload::SCHEMA_VERSION;
use uavmeta_runtime::run_dir::{write_atomic, RemoteHost, RemoteProcess, RunDir};
use uavmeta_runtime::{domain, liveness, transport};
use zenoh::sample::SampleKind;
use zenoh::{Session, Wait};

use crate::bridge::{Bridge, Forwarders, RunServices, Side};
use crate::handshake::{self, Hello, Outcome, RunInfo};
use crate::session::{self, hosts_key, run_key};
use crate::{TunnelError, POLL, SHUTDOWN_LINGER};

/// The process name on a remote host: node and log.
const PROCESS: &str = "tunnel-join";

/// The first wait before trying an unreachable endpoint again; it doubles up to the maximum.
const FIRST_BACKOFF: Duration = Duration::from_millis(250);
const MAX_BACKOFF: Duration = Duration::from_secs(8);

/// Frames the Zenoh carrier's receiving inbox holds (`iceoryx2-integrations-zenoh-link-carrier`
/// 0.10's `channel::CAPACITY`); it drops beyond.
const CARRIER_INBOX: usize = 64;

/// How often the host tells the learner's host which processes it runs.
const ANNOUNCE_EVERY: Duration = Duration::from_millis(250);

/// The flags of `uavmeta tunnel join`.
#[derive(Debug, Clone)]
pub struct JoinOptions {
    /// The learner host's `tunnel.listen` endpoint, such as `tcp/10.0.0.1:7447`.
    pub endpoint: String,
    pub run_id: String,
    /// This host's directory for the run, where its actors run (`uavmeta actor --run DIR`).
    pub dir: PathBuf,
    /// This host's iceoryx2 domain (`run.domain` of its copy of the config).
    pub domain: String,
    /// This host's name, the `host` label of its processes.
    pub host: String,
    /// Where this host's processes' /metrics listen, reachable from the learner's Prometheus.
    pub metrics_host: String,
    /// Give up reaching the learner's host after this long.
    pub patience: Duration,
    /// The files that admit this host (`--ca`, `--certificate`, `--private-key`,
    /// `--credentials`).
    pub security: session::Security,
}

/// The flags that name [`JoinOptions::security`]'s files, in `Security::check_files`' order.
const SECURITY_FLAGS: [&str; 4] = ["--ca", "--certificate", "--private-key", "--credentials"];

/// Joins the run, then relays its services until SIGINT/SIGTERM or shortly after its shutdown.
pub fn join(options: &JoinOptions) -> Result<(), TunnelError> {
    if !is_host_name(&options.host) {
        return Err(TunnelError::Refused {
            endpoint: options.endpoint.clone(),
            message: format!(
                "host name `{}`: expected {HOST_NAME_RULE}, as `uavmeta tunnel certs --host` \
                 makes them",
                options.host
            ),
        });
    }
    check_run_id(&options.run_id)?;
    check_endpoint(options)?;
    let hello = Hello {
        schema_version: SCHEMA_VERSION,
        host: options.host.clone(),
    };
    let (session, info) = reach(options, &hello)?;
    let (run, config) = make_run_dir(options, &info)?;
    let node = domain::node(&format!("{}-{PROCESS}-services", run.id()), &config.run)?;
    // A killed predecessor's subscribers would block the actors on full buffers.
    domain::cleanup_dead_nodes(&node);
    let services = RunServices::open(&node, &run, &config)?;
    let shutdown = transport::control_subscriber(services.shutdown())?;
    let forwarders = Forwarders::new(&services, Side::Remote)?;
    let present = Arc::new(AtomicBool::new(false));
    let _presence = watch_presence(&session, options, present.clone())?;
    tracing::info!(run = run.id(), dir = %run.root().display(), "joined the run: start actors with `uavmeta actor --run {}`", run.root().display());
    let mut bridge = None;
    let mut last_announce: Option<Instant> = None;
    let mut shutdown_at = None;
    while liveness::keep_running(&node, POLL) {
        bridge = follow(
            bridge, &present, options, &hello, &session, &config, &services,
        )?;
        if let Some(bridge) = &mut bridge {
            bridge.relay();
        }
        forwarders.pump();
        if last_announce.is_none_or(|at| at.elapsed() >= ANNOUNCE_EVERY) {
            last_announce = Some(Instant::now());
            announce(&session, &run, options);
        }
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

/// A run id is what `RunDir` makes: letters, digits, `-` and `_`. Anything else, a Zenoh
/// wildcard above all (`*`, `**`, `$*`), would ask every run the tunnel serves at once.
fn check_run_id(run_id: &str) -> Result<(), TunnelError> {
    let plain = |c: char| c.is_ascii_alphanumeric() || matches!(c, '-' | '_');
    match (1..=MAX_RUN_ID).contains(&run_id.len()) && run_id.chars().all(plain) {
        true => Ok(()),
        false => Err(TunnelError::BadRunId {
            run_id: run_id.escape_debug().to_string(),
        }),
    }
}

/// The longest run id `RunDir` makes: 64 characters of the directory's name, `-` and 8 hex
/// digits.
const MAX_RUN_ID: usize = 73;

/// Refuses to join in clear beyond loopback (the run's data and this host's actors would be open
/// to anyone on the way), and files named by the flags that cannot be read.
fn check_endpoint(options: &JoinOptions) -> Result<(), TunnelError> {
    let endpoint = &options.endpoint;
    if !endpoint.starts_with("tls/") && !uavmeta_proto::config::is_loopback_endpoint(endpoint) {
        return Err(TunnelError::Refused {
            endpoint: endpoint.clone(),
            message: "joining beyond loopback needs a tls/ endpoint, with --ca, --certificate \
                      and --private-key from the run's `uavmeta tunnel certs`"
                .into(),
        });
    }
    options.security.check_files(endpoint, SECURITY_FLAGS)?;
    match &options.security.certificate {
        Some(file) if endpoint.starts_with("tls/") => check_certificate_name(options, file),
        _ => Ok(()),
    }
}

/// The common name of the PEM certificate `pem`, if it has one.
fn common_name(pem: &[u8]) -> Result<Option<String>, String> {
    let (_, pem) = x509_parser::pem::parse_x509_pem(pem).map_err(|e| e.to_string())?;
    let certificate = pem.parse_x509().map_err(|e| e.to_string())?;
    let name = certificate.subject().iter_common_name().next();
    Ok(name.and_then(|n| n.as_str().ok()).map(str::to_string))
}

/// Over TLS the learner's host knows this host by its certificate's name: `--host` must be it,
/// or nothing this host publishes would be let in.
fn check_certificate_name(
    options: &JoinOptions,
    file: &std::path::Path,
) -> Result<(), TunnelError> {
    let refused = |message: String| TunnelError::Refused {
        endpoint: options.endpoint.clone(),
        message,
    };
    let pem = std::fs::read_to_string(file).map_err(|e| {
        refused(format!(
            "--certificate {}: cannot read it: {e}",
            file.display()
        ))
    })?;
    let name = common_name(pem.as_bytes()).map_err(|e| {
        refused(format!(
            "--certificate {}: not a PEM certificate: {e}",
            file.display()
        ))
    })?;
    match name {
        Some(name) if name == options.host => Ok(()),
        name => Err(refused(format!(
            "--host {} but --certificate {} names {}: the learner's host knows this host by \
             its certificate's name; pass --host {0}",
            options.host,
            file.display(),
            name.as_deref().unwrap_or("no common name"),
        ))),
    }
}

/// Connects to the endpoint and shakes hands, retrying with backoff (and saying so) while the
/// endpoint cannot be reached, refuses this host or its tunnel does not answer for the run, for
/// up to `patience`; then one error that does not tell these apart.
fn reach(options: &JoinOptions, hello: &Hello) -> Result<(Session, RunInfo), TunnelError> {
    let start = Instant::now();
    let mut backoff = FIRST_BACKOFF;
    let mut session = None;
    loop {
        let problem = match &session {
            None => match session::connect(&options.endpoint, &options.security) {
                Ok(opened) => {
                    session = Some(opened);
                    continue;
                }
                Err(error) => error.to_string(),
            },
            Some(open) => match handshake::ask(open, &options.endpoint, &options.run_id, hello)? {
                Outcome::Joined(info) => return Ok((session.expect("connected"), info)),
                Outcome::Unanswered => format!("no tunnel answers for run `{}`", options.run_id),
            },
        };
        if start.elapsed() + backoff > options.patience {
            return Err(TunnelError::NotAdmitted {
                endpoint: options.endpoint.clone(),
                run: options.run_id.clone(),
                waited: start.elapsed(),
            });
        }
        tracing::warn!(endpoint = %options.endpoint, "{problem}; trying again in {backoff:?}");
        std::thread::sleep(backoff);
        backoff = (backoff * 2).min(MAX_BACKOFF);
    }
}

/// Writes this host's directory for the run: the learner host's config, with this host's domain
/// and metrics address, and the run's identity.
fn make_run_dir(options: &JoinOptions, info: &RunInfo) -> Result<(RunDir, Config), TunnelError> {
    let origin = format!("run `{}` at {}", info.run_id, options.endpoint);
    let mut config = Config::from_toml_str(&info.config, &origin, &[])?;
    config.run.domain = options.domain.clone();
    config.run.metrics_host = options.metrics_host.clone();
    config.run.dir = options.dir.clone();
    // An actor keeps up to 2 * subscriber_buffer + 2 batches unacknowledged in flight; across the
    // tunnel they queue in the Zenoh carrier's inbox (64 frames, `CARRIER_INBOX`) and the store's
    // buffer, which drop what does not fit: keep the window within them.
    config.run.subscriber_buffer = config.run.subscriber_buffer.min(CARRIER_INBOX / 2 - 1);
    // What this host may serve, which its actors check before they publish.
    config.tunnel = TunnelConfig {
        hosts: [(options.host.clone(), info.tasks.clone())].into(),
        ..TunnelConfig::default()
    };
    config.validate()?;
    let run = RunDir::create_remote(&options.dir, &info.run_id, info.run_hash, &options.host)?;
    write_atomic(&run.config_file(), config.to_toml_string().as_bytes())?;
    Ok((run, config))
}

/// Keeps `present` telling whether the learner host's tunnel is up, from its liveliness token.
fn watch_presence(
    session: &Session,
    options: &JoinOptions,
    present: Arc<AtomicBool>,
) -> Result<zenoh::pubsub::Subscriber<()>, TunnelError> {
    session
        .liveliness()
        .declare_subscriber(run_key(&options.run_id))
        .history(true)
        .callback(move |sample| present.store(sample.kind() == SampleKind::Put, Ordering::SeqCst))
        .wait()
        .map_err(TunnelError::zenoh(&options.endpoint))
}

/// The bridge to keep: none while the learner host's tunnel is away, so that the actors see their
/// store go and hold their batches; a new one, after a new handshake, when it is back, whose new
/// subscriber makes the actors send everything unacknowledged again.
fn follow(
    bridge: Option<Bridge>,
    present: &AtomicBool,
    options: &JoinOptions,
    hello: &Hello,
    session: &Session,
    config: &Config,
    services: &RunServices,
) -> Result<Option<Bridge>, TunnelError> {
    let endpoint = &options.endpoint;
    match (present.load(Ordering::SeqCst), bridge) {
        (false, Some(_)) => {
            tracing::warn!(%endpoint, "lost the run's tunnel; the actors hold their batches until it is back");
            Ok(None)
        }
        (true, None) => match handshake::ask(session, endpoint, &options.run_id, hello)? {
            Outcome::Joined(_) => {
                tracing::info!(%endpoint, "bridging the run's services");
                let process = format!("{}-{PROCESS}", options.run_id);
                Ok(Some(Bridge::new(&process, config, session, services)?))
            }
            Outcome::Unanswered => Ok(None),
        },
        (_, bridge) => Ok(bridge),
    }
}

/// Tells the learner's host which processes run here and where their /metrics answer.
fn announce(session: &Session, run: &RunDir, options: &JoinOptions) {
    let processes = std::fs::read_dir(run.ports_dir())
        .into_iter()
        .flatten()
        .flatten()
        .filter_map(|entry| {
            let name = entry
                .file_name()
                .to_string_lossy()
                .strip_suffix(".port")?
                .to_string();
            let port = std::fs::read_to_string(entry.path()).ok()?;
            Some(RemoteProcess {
                name,
                metrics: format!("{}:{}", options.metrics_host, port.trim()),
            })
        })
        .collect();
    let host = RemoteHost {
        host: options.host.clone(),
        processes,
    };
    let payload = serde_json::to_vec(&host).expect("serialises");
    if let Err(error) = session
        .put(hosts_key(run.id(), &options.host), payload)
        .wait()
    {
        tracing::warn!(%error, "cannot announce this host's processes");
    }
}
