//! Every metric a uavmeta process exports, named and described once, and the /metrics endpoint
//! that serves them, with the client side the launcher, the terminal display and the tests use to
//! read one.
//!
//! The names are part of the contract between processes: the launcher reads the store's, the
//! Grafana dashboard (`docs/grafana/uavmeta.json`) queries them all, and the end-to-end tests
//! assert on them. So each is declared here once, as a [`Metric`] constant in the module of the
//! process kind that exports it ([`actor`], [`evaluator`], [`store`], [`meta_learner`],
//! [`launcher`]); a process builds its registry from these constants in the `metrics` module
//! beside its loop, and a reader passes the same constant to [`sum`], so a renamed metric is a
//! compile error everywhere rather than a series that silently stops.
//!
//! Naming (Prometheus conventions, checked by `promtool check metrics` in the end-to-end tests and
//! by this module's tests): every name starts with `uavmeta_`, then the process kind, then what is
//! measured, in base units (`_seconds`, `_watts`), with `_total` on counters and only on them.
//! The age of information has no SI unit: the world counts it in time steps (slots), so its
//! gauges end in `_steps`. Latencies are histograms; label values come from small fixed sets (task
//! names, method names, process names, reasons).
//!
//! The endpoint binds `run.metrics_host`; port 0 takes an ephemeral port, which is written to
//! [`RunDir::port_file`] (atomically, so a reader never sees half a number). When the server is
//! dropped it writes the final values to [`RunDir::metrics_snapshot`], so a finished run keeps the
//! figures of processes that are gone, and removes its port file.

use std::collections::HashMap;
use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::PathBuf;
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crate::transport::{write_atomic, RunDir, TransportError};
use prometheus::core::Collector;
use prometheus::{
    Counter, Encoder, Gauge, GaugeVec, Histogram, HistogramOpts, IntCounter, IntCounterVec,
    IntGauge, IntGaugeVec, Opts, Registry, TextEncoder,
};

/// Everything serving or reading metrics can fail on.
#[derive(Debug, thiserror::Error)]
pub enum MetricsError {
    #[error("cannot serve /metrics on {addr}: {message}")]
    Bind { addr: String, message: String },
    #[error(transparent)]
    Run(#[from] TransportError),
    #[error("{}: no metrics port after {waited:?}; is the process running?", path.display())]
    NoPort { path: PathBuf, waited: Duration },
    #[error("{}: expected a port number, found `{text}`", path.display())]
    BadPort { path: PathBuf, text: String },
    #[error("GET http://{addr}/metrics: {message}")]
    Scrape { addr: String, message: String },
    #[error("line {line} of the metrics text: expected `name{{labels}} value`, found `{text}`")]
    Parse { line: usize, text: String },
}

/// What a metric is, which fixes the suffix its name may carry.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    /// Only ever increases; the name ends in `_total`.
    Counter,
    /// Goes up and down; the name does not end in `_total`.
    Gauge,
    /// A latency distribution; the name ends in `_seconds`.
    Histogram,
}

/// One exported metric: its full name (with the `uavmeta_` prefix), its help text and its kind.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Metric {
    pub name: &'static str,
    pub help: &'static str,
    pub kind: Kind,
}

/// Declares a process kind's metrics as [`Metric`] constants, and `ALL`, the list of them.
macro_rules! declare {
    ($($(#[$doc:meta])* $id:ident: $kind:ident $name:literal, $help:literal;)*) => {
        $($(#[$doc])* pub const $id: Metric = Metric {
            name: concat!("uavmeta_", $name),
            help: $help,
            kind: Kind::$kind,
        };)*
        /// Every metric of this process kind.
        pub const ALL: &[Metric] = &[$($id),*];
    };
}

/// An actor's metrics; its registry labels every one with its `task` and `actor` id.
pub mod actor {
    use super::{Kind, Metric};
    declare! {
        STEPS: Counter "actor_steps_total", "Environment steps taken (for dqn-online, training steps included).";
        TRANSITIONS_PUBLISHED: Counter "actor_transitions_published_total", "Transitions delivered to the store's service, each counted once.";
        BATCHES_RESENT: Counter "actor_batches_resent_total", "Batches sent again because iceoryx2 reported them delivered to no store.";
        STORE_CHANGES: Counter "actor_store_changes_total", "Times a new store replaced the one the actor sent to, so the actor sent again what that store had not acknowledged.";
        TRANSITIONS_RESENT: Counter "actor_transitions_resent_total", "Transitions delivered again to a store that replaced the one they went to (not in transitions_published).";
        TRANSITIONS_UNACKNOWLEDGED: Gauge "actor_transitions_unacknowledged", "Transitions sent but not yet acknowledged as appended by the store, which the actor keeps to send again.";
        TRANSITIONS_LOST: Counter "actor_transitions_lost_total", "Transitions delivered to no store because the store went away during the send and run.keep_until_stored is off; the restarted store counts them as missing.";
        BATCHES_PUBLISHED: Counter "actor_batches_published_total", "Batches sent to the store's service.";
        EPISODES: Counter "actor_episodes_total", "Episodes finished by the behaviour policy.";
        EPISODE_RETURN: Gauge "actor_episode_return", "Return of the last finished episode.";
        EPISODE_AOI: Gauge "actor_episode_aoi_steps", "Mean AoI over steps and devices of the last finished episode, in time steps.";
        EPISODE_POWER: Gauge "actor_episode_power_watts", "Mean transmit power per step of the last finished episode, in watts.";
        EPISODE_OUTAGES: Gauge "actor_episode_outages", "Steps in outage of the last finished episode.";
        BACKPRESSURE_WAIT: Counter "actor_backpressure_wait_seconds_total", "Time blocked because the store's buffer was full or no store was connected.";
        BATCH_DURATION: Histogram "actor_batch_duration_seconds", "Time to roll out and send one batch.";
        /// Labelled by `phase` (`uavmeta_actors::actor::Phase`).
        PHASE: Gauge "actor_phase", "1 for what the actor is doing: training (its online DQN agent), sending (transitions to the store), sent (all of them, waiting for the store).";
        /// Exported by `dqn-online` actors only: another policy has no exploration rate to report,
        /// and a 0 would read as one.
        ONLINE_DQN_EPSILON: Gauge "actor_online_dqn_epsilon", "Exploration rate of the online DQN agent's epsilon-greedy policy.";
        /// The window is `uavmeta_actors::policy::dqn_online::RECENT_EPISODES` (a test there
        /// checks that this text names it).
        ONLINE_DQN_RECENT_RETURN: Gauge "actor_online_dqn_recent_return", "Mean return of the online DQN agent's last 20 finished training episodes.";
    }
}

/// The dataset store's metrics, labelled by `task`.
pub mod store {
    use super::{Kind, Metric};
    declare! {
        BATCHES_RECEIVED: Counter "store_batches_received_total", "Batches received from actors.";
        TRANSITIONS_RECEIVED: Counter "store_transitions_received_total", "Transitions received from actors.";
        TRANSITIONS_STORED: Counter "store_transitions_stored_total", "Transitions appended to the dataset file by this store process.";
        /// Labelled by `reason` too, one of [`DROPPED_REASONS`].
        TRANSITIONS_DROPPED: Counter "store_transitions_dropped_total", "Received transitions not stored: duplicate (sequence number already stored), surplus (the dataset was complete), foreign (another run, world or schema), invalid (the batch failed validation; see store_transitions_rejected_total).";
        /// Labelled by `actor` and `reason` too, one of [`REJECTION_REASONS`]; actors beyond
        /// [`REJECTION_ACTORS`] distinct ids share the actor label [`OTHER_ACTORS`].
        TRANSITIONS_REJECTED: Counter "store_transitions_rejected_total", "Transitions of batches dropped whole because one transition failed validation, by actor and by the check it failed: non_finite, action, position, aoi, step, reward, next_state (the world gives another), sequence_window (numbered far ahead of what the actor has stored).";
        TRANSITIONS_MISSING: Counter "store_transitions_missing_total", "Sequence numbers skipped by an actor's batches: transitions lost in transit, counted from the dataset file on start.";
        DATASET_TRANSITIONS: Gauge "store_dataset_transitions", "Transitions in the task's dataset file.";
        DATASET_READY: Gauge "store_dataset_ready", "1 once the task's dataset holds collect.transitions and is announced.";
        BATCH_LATENCY: Histogram "store_batch_latency_seconds", "Time from an actor's send to the store's receive of a batch.";
        APPEND_DURATION: Histogram "store_append_duration_seconds", "Time to append and flush one batch to its dataset file.";
    }

    /// `reason`: the sequence number is already stored.
    pub const DUPLICATE: &str = "duplicate";
    /// `reason`: the task's dataset was already complete.
    pub const SURPLUS: &str = "surplus";
    /// `reason`: from another run, world or schema.
    pub const FOREIGN: &str = "foreign";
    /// `reason`: the batch failed validation ([`TRANSITIONS_REJECTED`] says which check).
    pub const INVALID: &str = "invalid";
    /// Why a received transition was not stored: the `reason` label's fixed set.
    pub const DROPPED_REASONS: [&str; 4] = [DUPLICATE, SURPLUS, FOREIGN, INVALID];

    /// Rejection `reason`: a reward that is NaN or infinite.
    pub const NON_FINITE: &str = "non_finite";
    /// Rejection `reason`: an action not below 5K.
    pub const ACTION: &str = "action";
    /// Rejection `reason`: a cell off the grid, or not the world's fixed start cell at step 0.
    pub const POSITION: &str = "position";
    /// Rejection `reason`: an AoI outside [1, aoi_max], or above what the step index allows.
    pub const AOI: &str = "aoi";
    /// Rejection `reason`: a step index at or past the horizon, or a truncation flag that
    /// disagrees with it.
    pub const STEP: &str = "step";
    /// Rejection `reason`: the reward is not what the world gives for (s, a).
    pub const REWARD: &str = "reward";
    /// Rejection `reason`: s(t+1) is not what the world gives for (s, a).
    pub const NEXT_STATE: &str = "next_state";
    /// Rejection `reason`: a first sequence number far ahead of what the actor has stored.
    pub const SEQUENCE_WINDOW: &str = "sequence_window";
    /// The rejection `reason` label's fixed set.
    pub const REJECTION_REASONS: [&str; 8] = [
        NON_FINITE,
        ACTION,
        POSITION,
        AOI,
        STEP,
        REWARD,
        NEXT_STATE,
        SEQUENCE_WINDOW,
    ];
    /// Distinct actor ids the rejection counter labels by their own id; the label set stays
    /// small whatever ids a hostile publisher makes up.
    pub const REJECTION_ACTORS: usize = 256;
    /// The `actor` label of rejections from actors beyond [`REJECTION_ACTORS`].
    pub const OTHER_ACTORS: &str = "other";
}

/// The evaluator's metrics; its gauges are labelled by `task` and `method`.
pub mod evaluator {
    use super::{Kind, Metric};
    declare! {
        RETURN: Gauge "evaluator_return", "Mean episode return of the latest evaluated checkpoint.";
        AOI: Gauge "evaluator_aoi_steps", "Mean AoI over steps and devices of the latest evaluated checkpoint, in time steps.";
        POWER: Gauge "evaluator_power_watts", "Mean transmit power per step of the latest evaluated checkpoint, in watts.";
        OUTAGES: Gauge "evaluator_outages", "Mean steps in outage per episode of the latest evaluated checkpoint.";
        EPOCH: Gauge "evaluator_epoch", "Training epochs (meta-epochs for maml-init) behind the latest evaluated checkpoint.";
        CHECKPOINTS_EVALUATED: Counter "evaluator_checkpoints_evaluated_total", "Checkpoints evaluated.";
        EVALUATION_DURATION: Histogram "evaluator_evaluation_duration_seconds", "Time to load and evaluate one checkpoint.";
    }
}

/// The meta-learner's metrics.
pub mod meta_learner {
    use super::{Kind, Metric};
    declare! {
        META_EPOCH: Gauge "meta_learner_meta_epoch", "Meta-epochs behind w0.";
        META_LOSS: Gauge "meta_learner_meta_loss", "Meta-loss (sum of the adapted weights' query losses) of the last meta-epoch.";
        META_EPOCH_DURATION: Histogram "meta_learner_meta_epoch_duration_seconds", "Time of one meta-epoch.";
        CHECKPOINTS_WRITTEN: Counter "meta_learner_checkpoints_written_total", "Checkpoints written and announced.";
        FINE_TUNE_EPOCHS: Counter "meta_learner_fine_tune_epochs_total", "Meta-test fine-tuning epochs run.";
    }
}

/// The launcher's metrics; the per-child counters are labelled by `process`.
pub mod launcher {
    use super::{Kind, Metric};
    declare! {
        CHILD_RESTARTS: Counter "launcher_child_restarts_total", "Restarts of a crashed child process.";
        CHILD_HANGS: Counter "launcher_child_hangs_total", "Children killed because their heartbeat stopped (run.hang_timeout_seconds).";
        CHILDREN_RUNNING: Gauge "launcher_children_running", "Child processes running.";
        DATASETS_READY: Gauge "launcher_datasets_ready", "Tasks whose dataset the store announced complete.";
        CHECKPOINTS_ANNOUNCED: Counter "launcher_checkpoints_announced_total", "Checkpoints the meta-learner announced.";
    }
}

/// Every metric of every process kind.
pub fn all() -> impl Iterator<Item = Metric> {
    [
        actor::ALL,
        store::ALL,
        evaluator::ALL,
        meta_learner::ALL,
        launcher::ALL,
    ]
    .into_iter()
    .flatten()
    .copied()
}

/// A registry for one process's metrics, with `labels` on every one of them.
pub fn registry(labels: &[(&str, &str)]) -> Registry {
    let labels: HashMap<String, String> = labels
        .iter()
        .map(|(k, v)| (k.to_string(), v.to_string()))
        .collect();
    Registry::new_custom(None, Some(labels)).expect("fixed, valid label names")
}

/// Registers `metric` in `registry` and returns it. Names are the constants above, so a duplicate
/// or invalid name is a programming error.
fn register<M: Collector + Clone + 'static>(registry: &Registry, metric: M) -> M {
    registry
        .register(Box::new(metric.clone()))
        .expect("metric names of a process are distinct and valid");
    metric
}

impl Metric {
    fn opts(self, kind: Kind) -> Opts {
        debug_assert_eq!(self.kind, kind, "{} is a {:?}", self.name, self.kind);
        Opts::new(self.name, self.help)
    }

    /// An integer counter in `registry`.
    pub fn counter(self, registry: &Registry) -> IntCounter {
        let counter = IntCounter::with_opts(self.opts(Kind::Counter)).expect("valid counter");
        register(registry, counter)
    }

    /// A counter of seconds (a float) in `registry`.
    pub fn seconds_counter(self, registry: &Registry) -> Counter {
        let counter = Counter::with_opts(self.opts(Kind::Counter)).expect("valid counter");
        register(registry, counter)
    }

    /// An integer counter per value of `labels` in `registry`.
    pub fn counter_vec(self, registry: &Registry, labels: &[&str]) -> IntCounterVec {
        let counter = IntCounterVec::new(self.opts(Kind::Counter), labels).expect("valid counter");
        register(registry, counter)
    }

    /// A gauge in `registry`.
    pub fn gauge(self, registry: &Registry) -> Gauge {
        register(
            registry,
            Gauge::with_opts(self.opts(Kind::Gauge)).expect("valid gauge"),
        )
    }

    /// An integer gauge in `registry`.
    pub fn int_gauge(self, registry: &Registry) -> IntGauge {
        let gauge = IntGauge::with_opts(self.opts(Kind::Gauge)).expect("valid gauge");
        register(registry, gauge)
    }

    /// A gauge per value of `labels` in `registry`.
    pub fn gauge_vec(self, registry: &Registry, labels: &[&str]) -> GaugeVec {
        let gauge = GaugeVec::new(self.opts(Kind::Gauge), labels).expect("valid gauge");
        register(registry, gauge)
    }

    /// An integer gauge per value of `labels` in `registry`.
    pub fn int_gauge_vec(self, registry: &Registry, labels: &[&str]) -> IntGaugeVec {
        let gauge = IntGaugeVec::new(self.opts(Kind::Gauge), labels).expect("valid gauge");
        register(registry, gauge)
    }

    /// A latency histogram in seconds in `registry`, buckets from 10 microseconds to about 10
    /// seconds.
    pub fn latency_histogram(self, registry: &Registry) -> Histogram {
        let buckets = prometheus::exponential_buckets(1e-5, 4.0, 11).expect("valid buckets");
        let opts = HistogramOpts::from(self.opts(Kind::Histogram)).buckets(buckets);
        register(
            registry,
            Histogram::with_opts(opts).expect("valid histogram"),
        )
    }
}

/// A process's /metrics endpoint, served from a background thread until dropped.
pub struct MetricsServer {
    registry: Registry,
    server: Arc<tiny_http::Server>,
    thread: Option<JoinHandle<()>>,
    port: u16,
    port_file: PathBuf,
    snapshot: PathBuf,
}

impl MetricsServer {
    /// Serves `registry` on `host:port` (0: any free port) for process `process` of `run`.
    pub fn start(
        registry: Registry,
        host: &str,
        port: u16,
        run: &RunDir,
        process: &str,
    ) -> Result<Self, MetricsError> {
        let addr = format!("{host}:{port}");
        let server = tiny_http::Server::http(&addr).map_err(|e| MetricsError::Bind {
            addr: addr.clone(),
            message: e.to_string(),
        })?;
        let port = server
            .server_addr()
            .to_ip()
            .map(|a| a.port())
            .ok_or_else(|| MetricsError::Bind {
                addr: addr.clone(),
                message: "not an IP socket".into(),
            })?;
        let server = Arc::new(server);
        let thread = {
            let server = Arc::clone(&server);
            let registry = registry.clone();
            std::thread::Builder::new()
                .name("metrics".into())
                .spawn(move || serve(&server, &registry))
                .map_err(|e| MetricsError::Bind {
                    addr,
                    message: e.to_string(),
                })?
        };
        let port_file = run.port_file(process);
        write_atomic(&port_file, format!("{port}\n").as_bytes())?;
        Ok(Self {
            registry,
            server,
            thread: Some(thread),
            port,
            port_file,
            snapshot: run.metrics_snapshot(process),
        })
    }

    pub fn port(&self) -> u16 {
        self.port
    }

    /// The current metrics in the text exposition format.
    pub fn render(&self) -> String {
        render(&self.registry)
    }
}

impl Drop for MetricsServer {
    fn drop(&mut self) {
        self.server.unblock();
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
        let _ = std::fs::remove_file(&self.port_file);
        if let Err(error) = write_atomic(&self.snapshot, render(&self.registry).as_bytes()) {
            tracing::warn!("cannot keep the final metrics: {error}");
        }
    }
}

fn render(registry: &Registry) -> String {
    let mut buffer = Vec::new();
    TextEncoder::new()
        .encode(&registry.gather(), &mut buffer)
        .expect("text encoding into memory cannot fail");
    String::from_utf8(buffer).expect("the text format is UTF-8")
}

fn serve(server: &tiny_http::Server, registry: &Registry) {
    for request in server.incoming_requests() {
        let response = if request.url() == "/metrics" {
            let header =
                tiny_http::Header::from_bytes("Content-Type", TextEncoder::new().format_type())
                    .expect("a static header is valid");
            tiny_http::Response::from_string(render(registry)).with_header(header)
        } else {
            tiny_http::Response::from_string("uavmeta serves /metrics only\n").with_status_code(404)
        };
        // A client that hung up mid-response is its own problem, not the process's.
        let _ = request.respond(response);
    }
}

/// Waits up to `timeout` for process `process` of `run` to publish its metrics port.
pub fn wait_for_port(run: &RunDir, process: &str, timeout: Duration) -> Result<u16, MetricsError> {
    let path = run.port_file(process);
    let start = Instant::now();
    loop {
        if let Ok(text) = std::fs::read_to_string(&path) {
            return text
                .trim()
                .parse()
                .map_err(|_| MetricsError::BadPort { path, text });
        }
        if start.elapsed() >= timeout {
            return Err(MetricsError::NoPort {
                path,
                waited: timeout,
            });
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// `GET /metrics` from `host:port`: the body, in the text exposition format.
pub fn scrape(host: &str, port: u16) -> Result<String, MetricsError> {
    let addr = format!("{host}:{port}");
    let error = |message: String| MetricsError::Scrape {
        addr: addr.clone(),
        message,
    };
    let mut stream = TcpStream::connect(&addr).map_err(|e| error(e.to_string()))?;
    stream
        .set_read_timeout(Some(Duration::from_secs(5)))
        .map_err(|e| error(e.to_string()))?;
    write!(stream, "GET /metrics HTTP/1.0\r\nHost: {addr}\r\n\r\n")
        .map_err(|e| error(e.to_string()))?;
    let mut response = String::new();
    stream
        .read_to_string(&mut response)
        .map_err(|e| error(e.to_string()))?;
    let (head, body) = response
        .split_once("\r\n\r\n")
        .ok_or_else(|| error("no end of headers".into()))?;
    let ok = head.starts_with("HTTP/1.") && head.split_whitespace().nth(1) == Some("200");
    if !ok {
        return Err(error(format!(
            "unexpected status: {}",
            head.lines().next().unwrap_or("")
        )));
    }
    Ok(body.to_string())
}

/// One sample of the text format: `name{labels} value`.
#[derive(Debug, Clone, PartialEq)]
pub struct Sample {
    pub name: String,
    pub labels: Vec<(String, String)>,
    pub value: f64,
}

impl Sample {
    pub fn label(&self, key: &str) -> Option<&str> {
        self.labels
            .iter()
            .find(|(k, _)| k == key)
            .map(|(_, v)| v.as_str())
    }
}

/// Parses the samples of a text exposition (comments skipped). Label values may not contain
/// `,` or `"` escapes, which uavmeta's fixed label sets never do.
pub fn parse(text: &str) -> Result<Vec<Sample>, MetricsError> {
    let mut samples = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let bad = || MetricsError::Parse {
            line: i + 1,
            text: line.to_string(),
        };
        let (series, value) = line.rsplit_once(' ').ok_or_else(bad)?;
        let value: f64 = match value {
            "+Inf" => f64::INFINITY,
            "-Inf" => f64::NEG_INFINITY,
            v => v.parse().map_err(|_| bad())?,
        };
        let (name, labels) = match series.split_once('{') {
            None => (series, Vec::new()),
            Some((name, rest)) => {
                let inner = rest.strip_suffix('}').ok_or_else(bad)?;
                let labels = inner
                    .split(',')
                    .filter(|pair| !pair.is_empty())
                    .map(|pair| {
                        let (k, v) = pair.split_once('=').ok_or_else(bad)?;
                        let v = v
                            .strip_prefix('"')
                            .and_then(|v| v.strip_suffix('"'))
                            .ok_or_else(bad)?;
                        Ok((k.to_string(), v.to_string()))
                    })
                    .collect::<Result<Vec<_>, MetricsError>>()?;
                (name, labels)
            }
        };
        if name.is_empty()
            || !name
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == ':')
        {
            return Err(bad());
        }
        samples.push(Sample {
            name: name.to_string(),
            labels,
            value,
        });
    }
    Ok(samples)
}

/// The sum of every sample of `metric` whose labels include all of `labels`.
pub fn sum(samples: &[Sample], metric: Metric, labels: &[(&str, &str)]) -> f64 {
    samples
        .iter()
        .filter(|s| s.name == metric.name && labels.iter().all(|(k, v)| s.label(k) == Some(v)))
        .map(|s| s.value)
        .sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    const STEPS: Metric = Metric {
        name: "uavmeta_test_steps_total",
        help: "Steps.",
        kind: Kind::Counter,
    };
    const LATENCY: Metric = Metric {
        name: "uavmeta_test_latency_seconds",
        help: "Latency.",
        kind: Kind::Histogram,
    };

    /// The one sample named `name` (a histogram's `_count` or `_bucket`) with `labels`.
    fn value(samples: &[Sample], name: &str, labels: &[(&str, &str)]) -> f64 {
        samples
            .iter()
            .find(|s| s.name == name && labels.iter().all(|(k, v)| s.label(k) == Some(v)))
            .map_or(f64::NAN, |s| s.value)
    }

    #[test]
    fn names_follow_the_conventions_and_are_distinct() {
        let mut names = std::collections::BTreeSet::new();
        for metric in all() {
            let name = metric.name;
            assert!(names.insert(name), "{name} is declared twice");
            assert!(name.starts_with("uavmeta_"), "{name}");
            assert!(
                name.chars()
                    .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '_'),
                "{name}"
            );
            assert_eq!(
                name.ends_with("_total"),
                metric.kind == Kind::Counter,
                "{name}"
            );
            if metric.kind == Kind::Histogram {
                assert!(name.ends_with("_seconds"), "{name}");
            }
            assert!(metric.help.ends_with('.'), "{name}: {}", metric.help);
        }
    }

    #[test]
    fn serves_scrapes_and_parses_then_keeps_a_snapshot() {
        let dir = tempfile::tempdir().expect("temp dir");
        let run = RunDir::create(dir.path()).expect("run dir");
        let registry = registry(&[]);
        let steps = STEPS.counter(&registry);
        let latency = LATENCY.latency_histogram(&registry);
        steps.inc_by(41);
        latency.observe(0.003);
        let server = MetricsServer::start(registry, "127.0.0.1", 0, &run, "unit").expect("start");
        let port = wait_for_port(&run, "unit", Duration::from_secs(1)).expect("port file");
        assert_eq!(port, server.port());
        steps.inc();
        let samples = parse(&scrape("127.0.0.1", port).expect("scrape")).expect("parse");
        assert_eq!(sum(&samples, STEPS, &[]), 42.0);
        assert_eq!(
            value(&samples, "uavmeta_test_latency_seconds_count", &[]),
            1.0
        );
        assert_eq!(
            value(
                &samples,
                "uavmeta_test_latency_seconds_bucket",
                &[("le", "+Inf")]
            ),
            1.0
        );
        drop(server);
        assert!(!run.port_file("unit").exists());
        let snapshot = std::fs::read_to_string(run.metrics_snapshot("unit")).expect("snapshot");
        assert_eq!(
            sum(&parse(&snapshot).expect("parse snapshot"), STEPS, &[]),
            42.0
        );
    }

    #[test]
    fn parse_rejects_garbage_with_its_line() {
        let err = parse("# HELP x y\nok_total 1\nbroken{a=\"b\" 2\n")
            .unwrap_err()
            .to_string();
        assert!(err.contains("line 3"), "{err}");
    }
}
