//! `uavmeta dashboard render`: the Grafana dashboard's panels as PNG files, drawn from a real
//! Prometheus server's data, for where Grafana is not at hand.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime};

use anyhow::{bail, Result};
use clap::{Args, Subcommand};
use uavmeta_dashboard::grafana::Dashboard;
use uavmeta_dashboard::prometheus::Prometheus;
use uavmeta_dashboard::render::{self, Options, Outcome, Report};
use uavmeta_runtime::launch::SCRAPE_INTERVAL_SECONDS;
use uavmeta_runtime::run_dir::RunDir;

#[derive(Subcommand)]
pub enum DashboardCommand {
    /// Draw each time-series panel of a Grafana dashboard as a PNG, and an overview of all on
    /// Grafana's grid, from a Prometheus server's range queries.
    Render(RenderArgs),
}

#[derive(Args)]
pub struct RenderArgs {
    /// Base URL of the Prometheus server (plain HTTP).
    #[arg(long, default_value = "http://127.0.0.1:9090")]
    prometheus: String,
    /// The dashboard JSON, or a run directory: its grafana-dashboard.json, drawn for that run.
    #[arg(long)]
    dashboard: PathBuf,
    /// Directory for the PNG files: one per panel (ID-TITLE.png) and overview.png.
    #[arg(long)]
    out: PathBuf,
    /// Draw the last N minutes.
    #[arg(long, default_value_t = 30, value_parser = clap::value_parser!(u64).range(1..))]
    minutes: u64,
    /// A dashboard variable's value, as Grafana's drop-down chooses it: `--var run=ID`. A
    /// label_values variable left out takes the one value Prometheus has.
    #[arg(long = "var", value_name = "NAME=VALUE", value_parser = name_value)]
    variables: Vec<(String, String)>,
    /// The scrape interval of the server's targets, for $__rate_interval [default: the one a
    /// run's prometheus.yml sets].
    #[arg(long, value_name = "SECONDS", default_value_t = SCRAPE_INTERVAL_SECONDS)]
    scrape_interval: u64,
}

pub fn run(command: DashboardCommand) -> Result<()> {
    match command {
        DashboardCommand::Render(args) => render(args),
    }
}

fn render(args: RenderArgs) -> Result<()> {
    let (file, run) = dashboard_file(&args.dashboard)?;
    let dashboard = Dashboard::read(&file)?;
    let mut variables: BTreeMap<String, String> =
        run.map(|id| ("run".to_string(), id)).into_iter().collect();
    variables.extend(args.variables);
    let options = Options {
        end: SystemTime::now(),
        range: Duration::from_secs(60 * args.minutes),
        scrape_interval: Duration::from_secs(args.scrape_interval),
        variables,
        out: args.out,
    };
    let prometheus = Prometheus::new(&args.prometheus);
    let report = render::render(&dashboard, &prometheus, &options)?;
    print_report(&report);
    judge(&report, &prometheus, args.minutes)
}

/// A run directory's dashboard and run id, or the dashboard file `path` and no run.
fn dashboard_file(path: &Path) -> Result<(PathBuf, Option<String>)> {
    if !path.is_dir() {
        return Ok((path.to_owned(), None));
    }
    let run = RunDir::open(path)?;
    let file = run.grafana_dashboard();
    if !file.is_file() {
        bail!(
            "{}: a directory without grafana-dashboard.json; pass a run directory (uavmeta launch writes one) or a dashboard JSON file",
            path.display()
        );
    }
    Ok((file, Some(run.id().to_string())))
}

/// Each drawn panel on stdout, each empty or failed one on stderr, then the overview.
fn print_report(report: &Report) {
    for panel in &report.panels {
        let (path, title) = (panel.path.display(), &panel.title);
        match &panel.outcome {
            Outcome::Drawn { series } => println!("{path}: `{title}`, {series} series"),
            Outcome::NoData => {
                eprintln!("uavmeta: panel `{title}`: no data in the window, drawn empty ({path})")
            }
            Outcome::Failed(error) => {
                eprintln!("uavmeta: panel `{title}`: {error}; drawn empty ({path})")
            }
        }
    }
    let chosen: Vec<String> = report
        .variables
        .iter()
        .map(|(k, v)| format!("{k} = {v}"))
        .collect();
    println!(
        "{}: {} panels on the dashboard's grid, {}",
        report.overview.display(),
        report.panels.len(),
        chosen.join(", ")
    );
}

/// An error when a panel's query failed, or when no panel had data.
fn judge(report: &Report, prometheus: &Prometheus, minutes: u64) -> Result<()> {
    let count = |f: fn(&Outcome) -> bool| report.panels.iter().filter(|p| f(&p.outcome)).count();
    let failed = count(|o| matches!(o, Outcome::Failed(_)));
    let empty = count(|o| *o == Outcome::NoData);
    let all = report.panels.len();
    if failed > 0 {
        bail!("{failed} of {all} panels failed (above); the others are drawn");
    }
    if empty == all {
        bail!(
            "none of the {all} panels has data in the last {minutes} minutes: is Prometheus at {} scraping the run (prometheus --config.file RUN/prometheus.yml)?",
            prometheus.url()
        );
    }
    Ok(())
}

/// `NAME=VALUE`.
fn name_value(text: &str) -> Result<(String, String), String> {
    match text.split_once('=') {
        Some((name, value)) if !name.is_empty() => Ok((name.to_string(), value.to_string())),
        _ => Err(format!(
            "`{text}`: expected NAME=VALUE, such as run=default-1a2b3c4d"
        )),
    }
}
