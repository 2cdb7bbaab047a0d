//! The Grafana dashboard (`docs/grafana/uavmeta.json`, copied into every run directory) against
//! a real Prometheus server scraping a live launch through the run's own `prometheus.yml`: every
//! panel's PromQL must be valid and return series.
//!
//! Prometheus is Debian's `prometheus` package (`make test` installs it); under `CI=true` it must
//! be installed, elsewhere the test skips, saying so.

use std::collections::BTreeMap;
use std::fs::File;
use std::net::TcpListener;
use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use serde_json::Value;
use uavmeta_dashboard::grafana::{Dashboard, Panel};
use uavmeta_dashboard::prometheus::{self, Window};
use uavmeta_dashboard::render::{self, panel_size, COLUMN, ROW};
use uavmeta_plot::timeseries::GRID_TITLE_HEIGHT;
use uavmeta_plot::PALETTE;

mod support;
use support::{child_pid, launch, missing_tool, run_dir, wait_until, within, Proc, DQN_RUN};

const DASHBOARD: &str = include_str!("../docs/grafana/uavmeta.json");

/// The scrape interval of a run's prometheus.yml.
const SCRAPE: Duration = Duration::from_secs(uavmeta_runtime::launch::SCRAPE_INTERVAL_SECONDS);

/// A Prometheus server on a free port, its data in `dir`, killed when dropped.
struct Prometheus {
    api: prometheus::Prometheus,
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
            api: prometheus::Prometheus::new(&format!("http://127.0.0.1:{port}")),
            _process: process,
        };
        // Until it is ready it refuses connections, then answers 503.
        wait_until("Prometheus to be ready", within(60), || {
            server
                .api
                .query_range("up", &window_since(unix_now()))
                .is_ok()
        });
        Some(server)
    }
}

fn unix_now() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .expect("after 1970")
        .as_secs_f64()
}

/// From `start` to now, a point per scrape.
fn window_since(start: f64) -> Window {
    Window {
        start,
        end: unix_now().max(start + 1.0),
        step: SCRAPE.as_secs_f64(),
    }
}

/// The dashboard as `uavmeta dashboard render` reads it.
fn dashboard() -> Dashboard {
    Dashboard::parse(DASHBOARD, Path::new("docs/grafana/uavmeta.json")).expect("the dashboard")
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
fn resolve_run(prometheus: &Prometheus, dashboard: &Dashboard, run: &Path, start: f64) -> String {
    let variable = dashboard
        .variables
        .iter()
        .find(|v| v.name == "run")
        .expect("a `run` variable");
    let query = variable
        .label_values
        .as_ref()
        .expect("a label_values query");
    let mut runs = Vec::new();
    wait_until("the run variable's values", within(60), || {
        runs = prometheus
            .api
            .label_values(query, &window_since(start))
            .unwrap_or_else(|e| panic!("{e}"));
        !runs.is_empty()
    });
    assert_eq!(runs, [run_id(run)], "{query:?}'s runs");
    runs.remove(0)
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
        pending.retain(|(title, expr)| {
            match prometheus.api.query_range(expr, &window_since(start)) {
                Ok(series) => series.is_empty(),
                Err(error) => panic!("panel `{title}`: `{expr}` is not valid: {error}"),
            }
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

/// Every panel's queries, as (title, PromQL), with the variables put in as
/// `uavmeta dashboard render` puts them for a window since `start`.
fn queries(dashboard: &Dashboard, run_label: &str, start: f64) -> Vec<(String, String)> {
    let mut variables = BTreeMap::from([("run".to_string(), run_label.to_string())]);
    variables.extend(render::interval_variables(&window_since(start), SCRAPE));
    let mut found = Vec::new();
    for panel in &dashboard.panels {
        for target in panel.timeseries.iter().flat_map(|t| &t.targets) {
            let expr = render::expand(&target.expr, &variables)
                .unwrap_or_else(|e| panic!("panel `{}`: {e}", panel.title));
            found.push((panel.title.clone(), expr));
        }
    }
    found
}

/// Actors live for seconds, shorter than Prometheus may take to scrape them twice (a rate needs
/// two samples): the store is held stopped until the actors' panels have series, so that the
/// actors, their dataset incomplete, stay. Then the run goes on, the meta-learner meta-training
/// until stopped, and every other panel must fill; then `uavmeta dashboard render` draws them.
#[test]
fn every_panel_returns_series_from_a_real_prometheus_scraping_a_launch_and_is_drawn() {
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
    let mut pending = queries(&dashboard, &run_label, start);
    assert!(pending.len() >= 16, "{} queries", pending.len());
    wait_for_series(&prometheus, start, &mut pending, |expr| {
        expr.contains("uavmeta_actor_")
    });
    drop(store);
    wait_for_series(&prometheus, start, &mut pending, |_| true);

    check_rendering(
        &prometheus,
        &dashboard,
        &run,
        &dir.path().join("panels"),
        start,
    );
    check_empty_and_broken_panels(&prometheus, &run_label, dir.path(), start);

    launcher.signal(libc::SIGTERM);
    let out = launcher.wait(within(60));
    assert!(
        out.stderr.contains("stopped by a termination request"),
        "{}",
        out.stderr
    );
}

/// `uavmeta dashboard render` on the run directory: every time-series panel reported drawn,
/// its PNG the panel's size on the grid with curves in series colours, and the overview the
/// grid's size with curves.
fn check_rendering(
    prometheus: &Prometheus,
    dashboard: &Dashboard,
    run: &Path,
    out: &Path,
    start: f64,
) {
    let done = render_cli(prometheus.api.url(), run, out, start, &[]);
    assert!(done.status.success(), "{}", done.stderr);
    let drawn = drawn_panels(&done.stdout);
    let panels: Vec<&Panel> = dashboard
        .panels
        .iter()
        .filter(|p| p.timeseries.is_some())
        .collect();
    assert_eq!(drawn.len(), panels.len(), "{}{}", done.stdout, done.stderr);
    for panel in &panels {
        let path = drawn
            .get(&panel.title)
            .unwrap_or_else(|| panic!("`{}` is not drawn: {}", panel.title, done.stdout));
        let image = Image::read(&out.join(path));
        assert_eq!(image.size, panel_size(panel.grid), "{path}");
        let curves = image.curve_pixels();
        assert!(curves >= 10, "{path}: {curves} pixels of curves");
    }
    let overview = Image::read(&out.join("overview.png"));
    let bottom = dashboard
        .panels
        .iter()
        .map(|p| p.grid.y + p.grid.h)
        .max()
        .unwrap_or(0);
    assert_eq!(
        overview.size,
        (24 * COLUMN, GRID_TITLE_HEIGHT + bottom * ROW)
    );
    assert!(overview.curve_pixels() >= 10 * panels.len());
}

/// A panel without data is drawn empty and named, and the command succeeds; one whose query is
/// not PromQL is named with Prometheus's error, the others are still drawn, and it fails.
fn check_empty_and_broken_panels(prometheus: &Prometheus, run_label: &str, dir: &Path, start: f64) {
    let panel = |id: u32, title: &str, expr: &str| {
        serde_json::json!({"type": "timeseries", "id": id, "title": title,
            "gridPos": {"x": 0, "y": 61, "w": 8, "h": 8},
            "targets": [{"refId": "A", "expr": expr}]})
    };
    let file = dir.join("dashboard.json");
    let write = |extra: Vec<Value>| {
        let mut json: Value = serde_json::from_str(DASHBOARD).expect("the dashboard");
        json["panels"].as_array_mut().expect("panels").extend(extra);
        std::fs::write(&file, json.to_string()).expect("write the dashboard");
    };
    let run = format!("run={run_label}");
    let url = prometheus.api.url();

    write(vec![panel(
        90,
        "Nothing scraped",
        "uavmeta_no_such_metric{run=\"$run\"}",
    )]);
    let done = render_cli(url, &file, &dir.join("empty"), start, &["--var", &run]);
    assert!(done.status.success(), "{}", done.stderr);
    assert!(
        done.stderr
            .contains("panel `Nothing scraped`: no data in the window"),
        "{}",
        done.stderr
    );
    let empty = Image::read(&dir.join("empty/90-nothing-scraped.png"));
    assert_eq!(empty.curve_pixels(), 0);

    write(vec![panel(91, "Broken", "rate(up{run=\"$run\"}[1m]")]);
    let done = render_cli(url, &file, &dir.join("broken"), start, &["--var", &run]);
    assert!(!done.status.success());
    let rejected = format!("panel `Broken`: target A: Prometheus at {url} rejected `rate(up{{run=\"{run_label}\"}}[1m]`");
    assert!(done.stderr.contains(&rejected), "{}", done.stderr);
    assert!(done.stderr.contains("uavmeta: 1 of "), "{}", done.stderr);
    assert!(drawn_panels(&done.stdout).len() >= 16, "{}", done.stdout);
}

/// `uavmeta dashboard render` of `dashboard` (a file or a run directory) into `out`, over the
/// minutes since `start`, with `extra` arguments.
fn render_cli(
    url: &str,
    dashboard: &Path,
    out: &Path,
    start: f64,
    extra: &[&str],
) -> support::Finished {
    let minutes = ((unix_now() - start) / 60.0).ceil() as u64 + 1;
    let mut args: Vec<String> = ["dashboard", "render", "--prometheus", url]
        .into_iter()
        .map(String::from)
        .collect();
    args.extend(["--dashboard".into(), dashboard.display().to_string()]);
    args.extend(["--out".into(), out.display().to_string()]);
    args.extend(["--minutes".into(), minutes.to_string()]);
    args.extend(extra.iter().map(|a| a.to_string()));
    Proc::spawn("uavmeta dashboard render", &args).wait(within(60))
}

/// The panels the command reports drawn, by title: their file names.
fn drawn_panels(stdout: &str) -> BTreeMap<String, String> {
    stdout
        .lines()
        .filter_map(|line| {
            let (path, rest) = line.split_once(": `")?;
            let (title, series) = rest.split_once("`, ")?;
            series.ends_with(" series").then_some(())?;
            let name = Path::new(path).file_name()?.to_string_lossy().into_owned();
            Some((title.to_string(), name))
        })
        .collect()
}

/// A decoded PNG: its size and RGB pixels.
struct Image {
    size: (u32, u32),
    rgb: Vec<[u8; 3]>,
}

impl Image {
    fn read(path: &Path) -> Image {
        let file = File::open(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let mut reader = png::Decoder::new(file)
            .read_info()
            .unwrap_or_else(|e| panic!("{}: not a PNG: {e}", path.display()));
        let mut buf = vec![0; reader.output_buffer_size()];
        let info = reader.next_frame(&mut buf).expect("a frame");
        assert_eq!(info.color_type, png::ColorType::Rgb, "{}", path.display());
        Image {
            size: (info.width, info.height),
            rgb: buf[..info.buffer_size()]
                .chunks_exact(3)
                .map(|p| [p[0], p[1], p[2]])
                .collect(),
        }
    }

    /// Pixels of a series colour in the image's top 60%, which the legend (at most 35% of the
    /// panel, at the bottom) never reaches: curves.
    fn curve_pixels(&self) -> usize {
        let colours: Vec<[u8; 3]> = PALETTE.iter().map(|c| [c.0, c.1, c.2]).collect();
        let rows = (self.size.1 * 3 / 5) as usize;
        let top = &self.rgb[..rows * self.size.0 as usize];
        top.iter().filter(|p| colours.contains(p)).count()
    }
}

/// Without a server, with a variable or a dashboard it cannot use, the command says which and
/// fails.
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
    let selectors = dashboard
        .variables
        .iter()
        .filter_map(|v| v.label_values.as_ref()?.selector.clone());
    let exprs = dashboard
        .panels
        .iter()
        .filter_map(|p| p.timeseries.as_ref())
        .flat_map(|s| s.targets.iter().map(|t| t.expr.clone()));
    let mut queried = 0;
    for expr in selectors.chain(exprs) {
        for name in metric_names(&expr) {
            assert!(declared.contains(&name.as_str()), "{name} in `{expr}`");
            queried += 1;
        }
    }
    assert!(queried >= 16, "{queried} metric names in the dashboard");
}

#[test]
fn render_names_an_unreachable_prometheus_and_a_bad_panel() {
    let dir = run_dir("dashboard-errors-");
    // A port just freed: nothing listens on it.
    let port = TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("a free port")
        .port();
    let url = format!("http://127.0.0.1:{port}");
    let repository = Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/grafana/uavmeta.json");
    let done = render_cli(&url, &repository, dir.path(), unix_now(), &[]);
    assert!(!done.status.success());
    assert!(
        done.stderr
            .starts_with(&format!("uavmeta: cannot reach Prometheus at {url}: ")),
        "{}",
        done.stderr
    );

    let done = render_cli(
        &url,
        &repository,
        dir.path(),
        unix_now(),
        &["--var", "rn=x"],
    );
    assert!(
        done.stderr
            .starts_with("uavmeta: --var rn: the dashboard has no variable `rn` (it has: run)"),
        "{}",
        done.stderr
    );
    let done = render_cli(&url, dir.path(), dir.path(), unix_now(), &[]);
    let not_a_run = format!(
        "uavmeta: {}: a directory without grafana-dashboard.json",
        dir.path().display()
    );
    assert!(done.stderr.starts_with(&not_a_run), "{}", done.stderr);

    let mut json: Value = serde_json::from_str(DASHBOARD).expect("the dashboard");
    json["panels"][1]["fieldConfig"]["defaults"]["unit"] = "furlongs".into();
    let file = dir.path().join("dashboard.json");
    std::fs::write(&file, json.to_string()).expect("write the dashboard");
    let done = render_cli(&url, &file, dir.path(), unix_now(), &[]);
    assert!(!done.status.success());
    let named = format!(
        "uavmeta: {}: panels[1] `{}`: unknown variant `furlongs`",
        file.display(),
        json["panels"][1]["title"].as_str().unwrap()
    );
    assert!(done.stderr.starts_with(&named), "{}", done.stderr);
}
