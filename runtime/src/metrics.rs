//! A process's /metrics endpoint, and the client side the launcher, the terminal display and the
//! tests use to read one. What is served, every metric's name, help text and kind, is declared
//! once in `uavmeta_proto::metrics`; a process builds its registry from those declarations
//! ([`Register`]) in the `metrics` module beside its loop, and a reader passes the same
//! declaration to [`sum`], so a renamed metric is a compile error everywhere rather than a series
//! that silently stops.
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

use prometheus::core::Collector;
use prometheus::{
    Counter, Encoder, Gauge, GaugeVec, Histogram, HistogramOpts, IntCounter, IntCounterVec,
    IntGauge, IntGaugeVec, Opts, Registry, TextEncoder,
};
use uavmeta_proto::metrics::{Kind, Metric};

use crate::run_dir::{write_atomic, FileError, RunDir};
use crate::transport::TransportError;

/// Everything serving or reading metrics can fail on.
#[derive(Debug, thiserror::Error)]
pub enum MetricsError {
    #[error("cannot serve /metrics on {addr}: {message}")]
    Bind { addr: String, message: String },
    #[error(transparent)]
    Run(#[from] TransportError),
    #[error(transparent)]
    File(#[from] FileError),
    #[error("{}: no metrics port after {waited:?}; is the process running?", path.display())]
    NoPort { path: PathBuf, waited: Duration },
    #[error("{}: expected a port number, found `{text}`", path.display())]
    BadPort { path: PathBuf, text: String },
    #[error("GET http://{addr}/metrics: {message}")]
    Scrape { addr: String, message: String },
    #[error("line {line} of the metrics text: expected `name{{labels}} value`, found `{text}`")]
    Parse { line: usize, text: String },
}

/// A registry for one process's metrics, with `labels` on every one of them.
pub fn registry(labels: &[(&str, &str)]) -> Registry {
    let labels: HashMap<String, String> = labels
        .iter()
        .map(|(k, v)| (k.to_string(), v.to_string()))
        .collect();
    Registry::new_custom(None, Some(labels)).expect("fixed, valid label names")
}

/// Registers `metric` in `registry` and returns it. Names are `uavmeta_proto::metrics`'s
/// constants, so a duplicate or invalid name is a programming error.
fn register<M: Collector + Clone + 'static>(registry: &Registry, metric: M) -> M {
    registry
        .register(Box::new(metric.clone()))
        .expect("metric names of a process are distinct and valid");
    metric
}

/// A declared [`Metric`] as a Prometheus collector registered in a process's registry:
/// `STEPS.counter(&registry)`. Each method checks (in debug builds) that the metric was declared
/// of that kind.
pub trait Register {
    /// An integer counter in `registry`.
    fn counter(self, registry: &Registry) -> IntCounter;
    /// A counter of seconds (a float) in `registry`.
    fn seconds_counter(self, registry: &Registry) -> Counter;
    /// An integer counter per value of `labels` in `registry`.
    fn counter_vec(self, registry: &Registry, labels: &[&str]) -> IntCounterVec;
    /// A gauge in `registry`.
    fn gauge(self, registry: &Registry) -> Gauge;
    /// An integer gauge in `registry`.
    fn int_gauge(self, registry: &Registry) -> IntGauge;
    /// A gauge per value of `labels` in `registry`.
    fn gauge_vec(self, registry: &Registry, labels: &[&str]) -> GaugeVec;
    /// An integer gauge per value of `labels` in `registry`.
    fn int_gauge_vec(self, registry: &Registry, labels: &[&str]) -> IntGaugeVec;
    /// A latency histogram in seconds in `registry`, buckets from 10 microseconds to about 10
    /// seconds.
    fn latency_histogram(self, registry: &Registry) -> Histogram;
}

/// The name and help of `metric`, declared as a `kind`.
fn opts(metric: Metric, kind: Kind) -> Opts {
    debug_assert_eq!(metric.kind, kind, "{} is a {:?}", metric.name, metric.kind);
    Opts::new(metric.name, metric.help)
}

impl Register for Metric {
    fn counter(self, registry: &Registry) -> IntCounter {
        let counter = IntCounter::with_opts(opts(self, Kind::Counter)).expect("valid counter");
        register(registry, counter)
    }

    fn seconds_counter(self, registry: &Registry) -> Counter {
        let counter = Counter::with_opts(opts(self, Kind::Counter)).expect("valid counter");
        register(registry, counter)
    }

    fn counter_vec(self, registry: &Registry, labels: &[&str]) -> IntCounterVec {
        let counter = IntCounterVec::new(opts(self, Kind::Counter), labels).expect("valid counter");
        register(registry, counter)
    }

    fn gauge(self, registry: &Registry) -> Gauge {
        register(
            registry,
            Gauge::with_opts(opts(self, Kind::Gauge)).expect("valid gauge"),
        )
    }

    fn int_gauge(self, registry: &Registry) -> IntGauge {
        let gauge = IntGauge::with_opts(opts(self, Kind::Gauge)).expect("valid gauge");
        register(registry, gauge)
    }

    fn gauge_vec(self, registry: &Registry, labels: &[&str]) -> GaugeVec {
        let gauge = GaugeVec::new(opts(self, Kind::Gauge), labels).expect("valid gauge");
        register(registry, gauge)
    }

    fn int_gauge_vec(self, registry: &Registry, labels: &[&str]) -> IntGaugeVec {
        let gauge = IntGaugeVec::new(opts(self, Kind::Gauge), labels).expect("valid gauge");
        register(registry, gauge)
    }

    fn latency_histogram(self, registry: &Registry) -> Histogram {
        let buckets = prometheus::exponential_buckets(1e-5, 4.0, 11).expect("valid buckets");
        let histogram = HistogramOpts::from(opts(self, Kind::Histogram)).buckets(buckets);
        register(
            registry,
            Histogram::with_opts(histogram).expect("valid histogram"),
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

/// A live process of `run`: its samples, through the port file it wrote; `None` while it has
/// none (not started, restarting, or not answering).
pub fn scrape_process(run: &RunDir, host: &str, process: &str) -> Option<Vec<Sample>> {
    let port = std::fs::read_to_string(run.port_file(process)).ok()?;
    let text = scrape(host, port.trim().parse().ok()?).ok()?;
    parse(&text).ok()
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
