//! The Grafana dashboard (`docs/grafana/uavmeta.json`, copied into every run directory) against
//! a real Prometheus server scraping a live launch through the run's own `prometheus.yml`: every
//! panel's PromQL must be valid and return series.
//!
//! Prometheus is Debian's `prometheus` package (`make test` installs it); under `CI=true` it must
//! be installed, elsewhere the test skips, saying so.

use std::net::TcpListener;
use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use serde_json::Value;

mod support;
use support::{child_pid, launch, missing_tool, run_dir, wait_until, within, Proc, DQN_RUN};

const DASHBOARD: &str = include_str!("../docs/grafana/uavmeta.json");

/// The scrape interval of a run's prometheus.yml.
const SCRAPE: Duration = Duration::from_secs(uavmeta_runtime::launch::SCRAPE_INTERVAL_SECONDS);

/// A Prometheus server on a free port, its data in `dir`, killed when dropped.
struct Prometheus {
    url: String,
    agent: ureq::Agent,
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
        let server = Prometheus {
            url: format!("http://127.0.0.1:{port}"),
            // Prometheus answers a bad query with 400 and a JSON body naming the error.
            agent: ureq::Agent::config_builder()
                .http_status_as_error(false)
                .timeout_global(Some(Duration::from_secs(30)))
                .build()
                .into(),
            _process: Proc::spawn_program("prometheus", "prometheus", &args),
        };
        // Until it is ready it refuses connections, then answers 503.
        wait_until("Prometheus to be ready", within(60), || {
            server
                .api("/api/v1/query", &[("query", "up".into())])
                .is_ok()
        });
        Some(server)
    }

    /// `GET path?params`: the answer's `data`, or Prometheus's error, or why there is no answer.
    fn api(&self, path: &str, params: &[(&str, String)]) -> Result<Value, String> {
        let mut response = self
            .agent
            .get(format!("{}{path}", self.url))
            .query_pairs(params.iter().map(|(k, v)| (*k, v.as_str())))
            .call()
            .map_err(|e| e.to_string())?;
        let answer: Value = response
            .body_mut()
            .read_json()
            .map_err(|e| format!("not the API: {e}"))?;
        match answer["status"].as_str() {
            Some("success") => Ok(answer["data"].clone()),
            _ => Err(format!("{}: {}", answer["errorType"], answer["error"])),
        }
    }

    /// The series `expr` returns from `start` to now, a point per scrape.
    fn query_range(&self, expr: &str, start: f64) -> Result<Vec<Value>, String> {
        let params = [
            ("query", expr.to_string()),
            ("start", start.to_string()),
            ("end", unix_now().max(start + 1.0).to_string()),
            ("step", SCRAPE.as_secs_f64().to_string()),
        ];
        let data = self.api("/api/v1/query_range", &params)?;
        Ok(data["result"].as_array().cloned().unwrap_or_default())
    }
}

fn unix_now() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .expect("after 1970")
        .as_secs_f64()
}

fn dashboard() -> Value {
    serde_json::from_str(DASHBOARD).expect("the dashboard is JSON")
}

/// The `run` variable's query, `label_values(SELECTOR, run)`: its selector.
fn run_selector(dashboard: &Value) -> String {
    let variables = dashboard["templating"]["list"]
        .as_array()
        .expect("variables");
    let run = variables
        .iter()
        .find(|v| v["name"] == "run")
        .expect("a `run` variable");
    let query = run["query"].as_str().expect("a query");
    let selector = query
        .strip_prefix("label_values(")
        .and_then(|q| q.strip_suffix(", run)"))
        .unwrap_or_else(|| panic!("`{query}` is not label_values(SELECTOR, run)"));
    selector.to_string()
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

/// Resolves the `run` variable as Grafana does, through its label_values query: one run, this
/// one.
fn resolve_run(prometheus: &Prometheus, dashboard: &Value, run: &Path, start: f64) -> String {
    let params = [
        ("match[]", run_selector(dashboard)),
        ("start", start.to_string()),
    ];
    let mut runs = Value::Null;
    wait_until("the run variable's values", within(60), || {
        runs = prometheus
            .api("/api/v1/label/run/values", &params)
            .unwrap_or_else(|e| panic!("{e}"));
        runs.as_array().is_some_and(|r| !r.is_empty())
    });
    let id = run_id(run);
    assert_eq!(runs, serde_json::json!([id]), "the `run` variable's values");
    id
}

/// Every time-series panel's queries, as (title, PromQL).
fn panel_queries(dashboard: &Value) -> Vec<(String, String)> {
    let panels = dashboard["panels"].as_array().expect("panels");
    let series = panels.iter().filter(|p| p["type"] == "timeseries");
    series
        .flat_map(|panel| {
            let title = panel["title"].as_str().expect("a title").to_string();
            let targets = panel["targets"].as_array().expect("targets").clone();
            let exprs = targets
                .into_iter()
                .map(|t| t["expr"].as_str().expect("an expr").to_string());
            exprs.map(move |expr| (title.clone(), expr))
        })
        .collect()
}

/// `expr` with the dashboard's variables put in as Grafana does over a window of scrapes:
/// `$run`, and `$__rate_interval` = max(step + scrape interval, 4 x scrape interval).
fn expand(expr: &str, run_label: &str) -> String {
    let rate_interval = 4 * SCRAPE.as_secs();
    let expr = expr
        .replace("$__rate_interval", &format!("{rate_interval}s"))
        .replace("$run", run_label);
    assert!(
        !expr.contains('$'),
        "`{expr}`: a variable the test does not know"
    );
    expr
}

/// Runs the `pending` queries over the window since `start`, dropping each once it returns
/// series, until none of the `wanted` ones is left; fails at once on an invalid query, and on
/// `wanted` ones still empty at the deadline.
fn wait_for_series(
    prometheus: &Prometheus,
    start: f64,
    pending: &mut Vec<(String, String)>,
    wanted: impl Fn(&str) -> bool,
) {
    let deadline = within(200);
    let begun = Instant::now();
    while pending.iter().any(|(_, expr)| wanted(expr)) {
        pending.retain(|(title, expr)| match prometheus.query_range(expr, start) {
            Ok(series) => series.is_empty(),
            Err(error) => panic!("panel `{title}`: `{expr}` is not valid: {error}"),
        });
        let late: Vec<_> = pending.iter().filter(|(_, e)| wanted(e)).collect();
        assert!(
            late.is_empty() || begun.elapsed() < deadline,
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

/// Actors live for seconds, shorter than Prometheus may take to scrape them twice (a rate needs
/// two samples): the store is held stopped until the actors' panels have series, so that the
/// actors, their dataset incomplete, stay. Then the run goes on, the meta-learner meta-training
/// until stopped, and every other panel must fill.
#[test]
fn every_panel_returns_series_from_a_real_prometheus_scraping_a_launch() {
    let start = unix_now();
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
    let dashboard = dashboard();
    let run_label = resolve_run(&prometheus, &dashboard, &run, start);
    let mut pending: Vec<_> = panel_queries(&dashboard)
        .into_iter()
        .map(|(title, expr)| (title, expand(&expr, &run_label)))
        .collect();
    assert!(pending.len() >= 16, "{} queries", pending.len());
    wait_for_series(&prometheus, start, &mut pending, |expr| {
        expr.contains("uavmeta_actor_")
    });
    drop(store);
    wait_for_series(&prometheus, start, &mut pending, |_| true);

    // A query that is not PromQL is refused by name, so the checks above could fail.
    let broken = format!("rate(up{{run=\"{run_label}\"}}[1m]");
    let error = prometheus.query_range(&broken, start).unwrap_err();
    assert!(error.contains("bad_data"), "{error}");

    launcher.signal(libc::SIGTERM);
    let out = launcher.wait(within(60));
    assert!(
        out.stderr.contains("stopped by a termination request"),
        "{}",
        out.stderr
    );
}

/// Every metric name in a PromQL expression: the words that start with `uavmeta_`, a histogram's
/// `_bucket`, `_count` and `_sum` series read as the histogram.
fn metric_names(expr: &str) -> Vec<String> {
    expr.split(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))
        .filter(|word| word.starts_with("uavmeta_"))
        .map(|word| {
            ["_bucket", "_count", "_sum"]
                .iter()
                .find_map(|suffix| word.strip_suffix(suffix))
                .filter(|base| base.ends_with("_seconds"))
                .unwrap_or(word)
                .to_string()
        })
        .collect()
}

/// Every metric the dashboard queries is one the processes declare (`uavmeta_proto::metrics`), so
/// a renamed metric cannot leave a panel empty; no Prometheus needed.
#[test]
fn the_dashboard_queries_only_declared_metrics() {
    let declared: Vec<&str> = uavmeta_proto::metrics::all().map(|m| m.name).collect();
    let dashboard = dashboard();
    let exprs = panel_queries(&dashboard).into_iter().map(|(_, expr)| expr);
    let mut queried = 0;
    for expr in std::iter::once(run_selector(&dashboard)).chain(exprs) {
        for name in metric_names(&expr) {
            assert!(declared.contains(&name.as_str()), "{name} in `{expr}`");
            queried += 1;
        }
    }
    assert!(queried >= 16, "{queried} metric names in the dashboard");
}
