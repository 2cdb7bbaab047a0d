//! A Grafana dashboard's time-series panels drawn as PNG files from a Prometheus server, for
//! where Grafana is not at hand (it is not packaged for Debian): `uavmeta dashboard render`.
//!
//! - [`grafana`]: the dashboard JSON model read from a file ([`grafana::Dashboard`]): rows,
//!   time-series panels with their PromQL, legend formats and units, and `label_values`
//!   variables; bad JSON is an error naming the file and the panel.
//! - [`prometheus`]: range queries and label values over Prometheus's HTTP API
//!   ([`prometheus::Prometheus`]).
//! - [`render`]: puts the variables into each panel's queries, runs them over a time window and
//!   draws each panel, and an overview of all on Grafana's grid, with `uavmeta_plot::timeseries`.
//!
//! It reads a dashboard file and a Prometheus server and writes PNG files into a directory; the
//! [`render::Report`] says what each panel showed, so that a caller can tell an empty panel
//! from a drawn one.
//!
//! ```no_run
//! use std::time::{Duration, SystemTime};
//! use uavmeta_dashboard::grafana::Dashboard;
//! use uavmeta_dashboard::prometheus::Prometheus;
//! use uavmeta_dashboard::render::{render, Options, Outcome};
//!
//! let dashboard = Dashboard::read("runs/default/grafana-dashboard.json".as_ref()).unwrap();
//! let options = Options {
//!     end: SystemTime::now(),
//!     range: Duration::from_secs(30 * 60),
//!     scrape_interval: Duration::from_secs(5),
//!     variables: Default::default(),
//!     out: "panels".into(),
//! };
//! let report = render(&dashboard, &Prometheus::new("http://127.0.0.1:9090"), &options).unwrap();
//! for panel in &report.panels {
//!     if panel.outcome == Outcome::NoData {
//!         eprintln!("{}: no data", panel.title);
//!     }
//! }
//! println!("{}", report.overview.display());
//! ```

pub mod grafana;
pub mod prometheus;
pub mod render;

use std::path::PathBuf;
use uavmeta_proto::fs::FileError;

pub use prometheus::PrometheusError;

/// A dashboard file that cannot be read or is not one this crate draws.
#[derive(Debug, thiserror::Error)]
pub enum DashboardError {
    #[error("{}: cannot read the dashboard: {source}", path.display())]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{}: not a Grafana dashboard: {source}", path.display())]
    Json {
        path: PathBuf,
        source: serde_json::Error,
    },
    #[error("{}: {place} `{title}`: {cause}", path.display())]
    Panel {
        path: PathBuf,
        /// Where in the file: `panels[3]`, `panels[1].panels[0]`.
        place: String,
        title: String,
        cause: String,
    },
    #[error("{}: variable `{name}`: {cause}", path.display())]
    Variable {
        path: PathBuf,
        name: String,
        cause: String,
    },
}

/// What stops a rendering: every panel's own failures are in its report instead.
#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    #[error(transparent)]
    Prometheus(#[from] PrometheusError),
    #[error("--var {name}: the dashboard has no variable `{name}` (it has: {known})")]
    UnknownVariable { name: String, known: String },
    #[error("variable `{name}` has no label_values query to resolve it by: give its value (--var {name}=VALUE)")]
    NoQuery { name: String },
    #[error("variable `{name}`: Prometheus at {url} has no value of `{query}` in the window: is it scraping the run, and since when?")]
    NoValue {
        name: String,
        url: String,
        query: String,
    },
    #[error("variable `{name}`: Prometheus at {url} has {} values of it in the window ({}); choose one with --var {name}=VALUE", values.len(), values.join(", "))]
    Choices {
        name: String,
        url: String,
        values: Vec<String>,
    },
    #[error(transparent)]
    File(#[from] FileError),
    #[error(transparent)]
    Plot(#[from] uavmeta_plot::PlotError),
}
