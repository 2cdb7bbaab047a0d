//! The Grafana dashboard (`docs/grafana/uavmeta.json`, copied into every run directory) against
//! a real Prometheus server scraping a live launch through the run's own `prometheus.yml`: every
//! panel's PromQL must be valid and return series.
//!
//! Prometheus is Debian's `prometheus` package (`make test` installs it); under `CI=true` it must
//! be installed, elsewhere the test skips, saying so.

use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

use serde_json::Value;

mod support;
use support::{child_pid, launch, missing_tool, run_dir, wait_until, within, Proc, DQN_RUN};

const DASHBOARD: &str = include_str!("../docs/grafana/uavmeta.json");

/// What Grafana puts in place of `$__rate_interval`: four scrape intervals or more.
const RATE_INTERVAL: &str = "1m";

/// A Prometheus server on a free port, its data in `dir`, killed when dropped.
struct Prometheus {
    port: u16,
    _process: Proc,
}

impl Prometheus {
    /// Starts Prometheus on `config`; `None` (after saying why) when it is not installed.
    fn start(config: &Path, dir: &Path) -> Option<Prometheus> {
        if let Err(error) = Command::new("prometheus").arg("--version").output() {
            missing_tool("prometheus", &error);
            return None;
        }
        let port = TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .expect("a free port")
            .port();
        let args = [
            format!("--config.file={}", config.display()),
            format!("--web.listen-address=127.0.0.1:{port}"),
            format!("--storage.tsdb.path={}", dir.join("tsdb").display()),
        ];
        let process = Proc::spawn_program("prometheus", "prometheus", &args);
        let server = Prometheus {
            port,
            _process: process,
        };
        wait_until("Prometheus to be ready", within(60), || {
            server
                .get("/-/ready")
                .is_some_and(|(status, _)| status == 200)
        });
        Some(server)
    }

    /// `GET path` over HTTP/1.0: the status and body, `None` if the server does not answer.
    fn get(&self, path: &str) -> Option<(u16, String)> {
        let mut stream = TcpStream::connect(("127.0.0.1", self.port)).ok()?;
        stream
            .set_read_timeout(Some(Duration::from_secs(30)))
            .ok()?;
        write!(stream, "GET {path} HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n").ok()?;
        let mut response = String::new();
        stream.read_to_string(&mut response).ok()?;
        let (head, body) = response.split_once("\r\n\r\n")?;
        let status = head.split_whitespace().nth(1)?.parse().ok()?;
        Some((status, body.to_string()))
    }

    /// The series `expr` returns now, or Prometheus's error when it is not valid PromQL.
    fn query(&self, expr: &str) -> Result<Vec<Value>, String> {
        let path = format!("/api/v1/query?query={}", percent_encode(expr));
        let (status, body) = self.get(&path).ok_or("Prometheus did not answer")?;
        let answer: Value = serde_json::from_str(&body)
            .map_err(|e| format!("HTTP {status}, not JSON ({e}): {body}"))?;
        match answer["status"].as_str() {
            Some("success") => Ok(answer["data"]["result"]
                .as_array()
                .cloned()
                .unwrap_or_default()),
            _ => Err(format!("HTTP {status}: {}", answer["error"])),
        }
    }
}

/// A query string's value: every byte but the unreserved ones as `%XX`.
fn percent_encode(text: &str) -> String {
    text.bytes()
        .map(|b| match b {
            b'A'..=b'Z' | b'a'..=b'z' | b'0'..=b'9' | b'-' | b'_' | b'.' | b'~' => {
                (b as char).to_string()
            }
            _ => format!("%{b:02X}"),
        })
        .collect()
}

/// Every panel's queries (rows' nested panels included), as (panel title, PromQL).
fn panel_queries(dashboard: &Value) -> Vec<(String, String)> {
    let mut found = Vec::new();
    let mut panels: Vec<&Value> = dashboard["panels"]
        .as_array()
        .expect("panels")
        .iter()
        .collect();
    while let Some(panel) = panels.pop() {
        panels.extend(panel["panels"].as_array().into_iter().flatten());
        for target in panel["targets"].as_array().into_iter().flatten() {
            let title = panel["title"].as_str().expect("a titled panel");
            let expr = target["expr"].as_str().expect("a PromQL target");
            found.push((title.to_string(), expr.to_string()));
        }
    }
    found
}

/// The `run` variable's query, `label_values(<metric>, run)`: its metric.
fn run_variable_metric(dashboard: &Value) -> String {
    let variables = dashboard["templating"]["list"]
        .as_array()
        .expect("variables");
    let run = variables
        .iter()
        .find(|v| v["name"] == "run")
        .expect("a `run` variable");
    let query = run["query"].as_str().expect("a label_values query");
    let metric = query
        .strip_prefix("label_values(")
        .and_then(|q| q.strip_suffix(", run)"))
        .unwrap_or_else(|| panic!("`{query}`: expected label_values(<metric>, run)"));
    metric.to_string()
}

/// The run's id, the `run` label the launcher gives every target.
fn run_id(run: &Path) -> String {
    let targets = std::fs::read_to_string(run.join("prometheus-targets.json")).expect("targets");
    let targets: Value = serde_json::from_str(&targets).expect("targets JSON");
    targets[0]["labels"]["run"]
        .as_str()
        .expect("a run label")
        .to_string()
}

/// Resolves the `run` variable as Grafana does, through Prometheus: one run, this one.
fn resolve_run(prometheus: &Prometheus, dashboard: &Value, run: &Path) -> String {
    let metric = run_variable_metric(dashboard);
    let mut runs = Vec::new();
    wait_until("the run variable's series", within(60), || {
        let series = prometheus
            .query(&metric)
            .unwrap_or_else(|e| panic!("{metric}: {e}"));
        runs = series
            .iter()
            .filter_map(|s| s["metric"]["run"].as_str())
            .map(String::from)
            .collect();
        !runs.is_empty()
    });
    assert_eq!(runs, [run_id(run)], "{metric}'s runs");
    runs.remove(0)
}

/// Runs the `pending` queries, dropping each once it returns series, until none of the
/// `wanted` ones is left; fails at once on an invalid query, and on `wanted` ones still empty at
/// the deadline.
fn wait_for_series(
    prometheus: &Prometheus,
    pending: &mut Vec<(String, String)>,
    wanted: impl Fn(&str) -> bool,
) {
    let deadline = within(200);
    let start = Instant::now();
    while pending.iter().any(|(_, expr)| wanted(expr)) {
        pending.retain(|(title, expr)| match prometheus.query(expr) {
            Ok(series) => series.is_empty(),
            Err(error) => panic!("panel `{title}`: `{expr}` is not valid: {error}"),
        });
        let late: Vec<_> = pending.iter().filter(|(_, e)| wanted(e)).collect();
        assert!(
            late.is_empty() || start.elapsed() < deadline,
            "no series after {deadline:?} for these panels: {late:#?}"
        );
        std::thread::sleep(Duration::from_millis(500));
    }
}

/// A process stopped with SIGSTOP, continued when dropped (a stopped process cannot act on the
/// SIGTERM that ends it when its launcher goes).
struct Stopped(i32);

impl Stopped {
    fn new(pid: i32) -> Stopped {
        // SAFETY: a signal to a process this test's launcher started.
        unsafe { libc::kill(pid, libc::SIGSTOP) };
        Stopped(pid)
    }
}

impl Drop for Stopped {
    fn drop(&mut self) {
        // SAFETY: as in `new`.
        unsafe { libc::kill(self.0, libc::SIGCONT) };
    }
}

/// The launch's queries, with the variables put in as Grafana would.
fn queries(dashboard: &Value, run_label: &str) -> Vec<(String, String)> {
    panel_queries(dashboard)
        .into_iter()
        .map(|(title, expr)| {
            let expr = expr
                .replace("$run", run_label)
                .replace("$__rate_interval", RATE_INTERVAL);
            assert!(
                !expr.contains('$'),
                "`{title}`: an unknown variable in `{expr}`"
            );
            (title, expr)
        })
        .collect()
}

/// Actors live for seconds, shorter than Prometheus may take to scrape them twice (a rate needs
/// two samples): the store is held stopped until the actors' panels have series, so that the
/// actors, their dataset incomplete, stay. Then the run goes on, the meta-learner meta-training
/// until stopped, and every other panel must fill.
#[test]
fn every_panel_returns_series_from_a_real_prometheus_scraping_a_launch() {
    let dir = run_dir("e2e-dashboard-");
    let run = dir.path().join("run");
    let run_arg = run.display().to_string();
    let mut overrides = DQN_RUN.to_vec();
    // Never taken for hung while held; w0 announced every two meta-epochs, without end.
    overrides.extend(["run.hang_timeout_seconds=0", "meta.meta_epochs=100000"]);
    let launcher = launch(dir.path(), &run, &overrides);
    wait_until("the store", within(60), || {
        run.join("ports/store.port").exists()
    });
    let store = Stopped::new(child_pid(&[" store ", &run_arg]).expect("the store's pid"));
    let copy = std::fs::read_to_string(run.join("grafana-dashboard.json")).expect("the run's copy");
    assert_eq!(
        copy, DASHBOARD,
        "the run directory holds the repository's dashboard"
    );
    let Some(prometheus) = Prometheus::start(&run.join("prometheus.yml"), dir.path()) else {
        return;
    };
    let dashboard: Value = serde_json::from_str(DASHBOARD).expect("the dashboard is JSON");
    let mut pending = queries(&dashboard, &resolve_run(&prometheus, &dashboard, &run));
    assert!(pending.len() >= 16, "{} queries", pending.len());
    wait_for_series(&prometheus, &mut pending, |expr| {
        expr.contains("uavmeta_actor_")
    });
    drop(store);
    wait_for_series(&prometheus, &mut pending, |_| true);

    launcher.signal(libc::SIGTERM);
    let out = launcher.wait(within(60));
    assert!(
        out.stderr.contains("stopped by a termination request"),
        "{}",
        out.stderr
    );
}
