//! Draws a dashboard from a Prometheus server: each time-series panel's targets as range queries
//! over the window, each panel to its own PNG, and an overview PNG with every panel and row
//! heading where Grafana's grid puts them.
//!
//! Variables are put into the PromQL as Grafana does: a `label_values` variable takes the one
//! value Prometheus has for it in the window (given values win, and several values must be
//! chosen from); `$__interval` is the query step and `$__rate_interval` Grafana's
//! `max($__interval + scrape interval, 4 * scrape interval)`. The step is the scrape interval,
//! or longer so that no panel asks for more than [`MAX_POINTS`] points.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use uavmeta_plot::timeseries::{self, Cell, Placed, TimeSeries};

use crate::grafana::{Dashboard, GridPos, LabelValues, Panel, Target};
use crate::prometheus::{Prometheus, PrometheusError, Series, Window};
use crate::RenderError;
use uavmeta_proto::fs::FileError;

/// Pixels of one of the grid's 24 columns (a 1920-pixel dashboard) and of one height unit
/// (Grafana's 30 plus its 8 between panels).
pub const COLUMN: u32 = 80;
pub const ROW: u32 = 38;
/// Pixels between neighbouring panels.
const GAP: u32 = 8;
const COLUMNS: u32 = 24;
/// Points of a series at most, about a panel's width in pixels.
pub const MAX_POINTS: u32 = 600;

pub struct Options {
    /// The window ends here and reaches this far back.
    pub end: SystemTime,
    pub range: Duration,
    /// The scrape interval of the server's targets, for `$__rate_interval` and the step.
    pub scrape_interval: Duration,
    /// Variable values chosen by the caller, by name.
    pub variables: BTreeMap<String, String>,
    /// The directory the PNG files go to; created if missing.
    pub out: PathBuf,
}

/// What became of one panel.
#[derive(Debug, Clone, PartialEq)]
pub enum Outcome {
    Drawn {
        series: usize,
    },
    /// Every query succeeded and none returned a point in the window.
    NoData,
    /// A query failed (invalid PromQL, an unknown variable); the panel is drawn empty.
    Failed(String),
}

#[derive(Debug, Clone)]
pub struct PanelReport {
    pub title: String,
    pub path: PathBuf,
    pub size: (u32, u32),
    pub outcome: Outcome,
}

#[derive(Debug, Clone)]
pub struct Report {
    /// Every variable with the value the queries used.
    pub variables: BTreeMap<String, String>,
    pub window: Window,
    pub panels: Vec<PanelReport>,
    pub overview: PathBuf,
    pub overview_size: (u32, u32),
}

/// A time-series panel's series, or why its queries failed.
type Queried = Result<Vec<TimeSeries>, String>;

/// A panel's size in pixels, from its place on the grid.
pub fn panel_size(grid: GridPos) -> (u32, u32) {
    (grid.w * COLUMN - GAP, grid.h * ROW - GAP)
}

/// Draws every time-series panel of `dashboard` from `prometheus` into `options.out`, one PNG
/// each (`<id>-<title>.png`) and `overview.png`. A panel whose query fails or returns nothing is
/// drawn empty and reported; an unreachable server, an unresolvable variable or an unwritable
/// file stops the rendering.
pub fn render(
    dashboard: &Dashboard,
    prometheus: &Prometheus,
    options: &Options,
) -> Result<Report, RenderError> {
    std::fs::create_dir_all(&options.out)
        .map_err(FileError::at(&options.out, "create the output directory"))?;
    let window = window(options);
    let variables = resolve_variables(dashboard, prometheus, options, &window)?;
    let mut expanded = variables.clone();
    expanded.extend(interval_variables(&window, options.scrape_interval));
    let mut queried = Vec::new();
    for panel in &dashboard.panels {
        let series = match &panel.timeseries {
            Some(config) => Some(panel_series(
                prometheus,
                &config.targets,
                &expanded,
                &window,
            )?),
            None => None,
        };
        queried.push((panel, series));
    }
    let mut panels = Vec::new();
    for (panel, series) in &queried {
        if let Some(series) = series {
            panels.push(write_panel(panel, series, &window, &options.out)?);
        }
    }
    let (overview, overview_size) =
        write_overview(dashboard, &queried, &variables, &window, &options.out)?;
    Ok(Report {
        variables,
        window,
        panels,
        overview,
        overview_size,
    })
}

/// Grafana's `$__interval` (the step) and `$__rate_interval`, as the queries use them.
pub fn interval_variables(window: &Window, scrape_interval: Duration) -> [(String, String); 2] {
    let scrape = scrape_interval.as_secs_f64().max(1.0);
    let rate_interval = (window.step + scrape).max(4.0 * scrape);
    [
        ("__interval".into(), format!("{}s", window.step)),
        ("__rate_interval".into(), format!("{rate_interval}s")),
    ]
}

/// The window `options` ask for, its step the scrape interval or more.
fn window(options: &Options) -> Window {
    let end = options
        .end
        .duration_since(UNIX_EPOCH)
        .unwrap_or_default()
        .as_secs_f64()
        .floor();
    let range = options.range.as_secs_f64().max(1.0);
    let scrape = options.scrape_interval.as_secs_f64().max(1.0);
    let step = scrape.max((range / f64::from(MAX_POINTS)).ceil());
    Window {
        start: end - range,
        end,
        step,
    }
}

/// Every variable's value: given, or the single value Prometheus has for a `label_values` one.
fn resolve_variables(
    dashboard: &Dashboard,
    prometheus: &Prometheus,
    options: &Options,
    window: &Window,
) -> Result<BTreeMap<String, String>, RenderError> {
    let known: Vec<&str> = dashboard
        .variables
        .iter()
        .map(|v| v.name.as_str())
        .collect();
    if let Some(name) = options
        .variables
        .keys()
        .find(|n| !known.contains(&n.as_str()))
    {
        return Err(RenderError::UnknownVariable {
            name: name.clone(),
            known: known.join(", "),
        });
    }
    let mut values = BTreeMap::new();
    for variable in &dashboard.variables {
        let name = variable.name.clone();
        let value = match (options.variables.get(&name), &variable.label_values) {
            (Some(given), _) => given.clone(),
            (None, Some(query)) => label_value(prometheus, &name, query, window)?,
            (None, None) => return Err(RenderError::NoQuery { name }),
        };
        values.insert(name, value);
    }
    Ok(values)
}

/// The one value Prometheus has for the variable `name`'s `query` in `window`.
fn label_value(
    prometheus: &Prometheus,
    name: &str,
    query: &LabelValues,
    window: &Window,
) -> Result<String, RenderError> {
    let mut found = prometheus.label_values(query, window)?;
    let (name, url) = (name.to_string(), prometheus.url().to_string());
    match found.len() {
        1 => Ok(found.remove(0)),
        0 => Err(RenderError::NoValue {
            name,
            url,
            query: query.to_string(),
        }),
        _ => Err(RenderError::Choices {
            name,
            url,
            values: found,
        }),
    }
}

/// A panel's series, or why it has none. Only an unreachable server is an error.
fn panel_series(
    prometheus: &Prometheus,
    targets: &[Target],
    variables: &BTreeMap<String, String>,
    window: &Window,
) -> Result<Queried, RenderError> {
    let mut all = Vec::new();
    for target in targets.iter().filter(|t| !t.hide) {
        let expr = match expand(&target.expr, variables) {
            Ok(expr) => expr,
            Err(error) => return Ok(Err(format!("target {}: {error}", target.ref_id))),
        };
        match prometheus.query_range(&expr, window) {
            Ok(series) => all.extend(series.iter().map(|s| time_series(s, target, window))),
            Err(error @ PrometheusError::Unreachable { .. }) => return Err(error.into()),
            Err(error) => return Ok(Err(format!("target {}: {error}", target.ref_id))),
        }
    }
    Ok(Ok(all))
}

/// `expr` with each `$name` and `${name}` replaced by the variable's value.
pub fn expand(expr: &str, variables: &BTreeMap<String, String>) -> Result<String, String> {
    let mut out = String::with_capacity(expr.len());
    let mut rest = expr;
    while let Some(dollar) = rest.find('$') {
        out.push_str(&rest[..dollar]);
        let after = &rest[dollar + 1..];
        let (name, tail) = match after.strip_prefix('{') {
            Some(braced) => braced
                .split_once('}')
                .ok_or_else(|| format!("`{expr}`: an unclosed ${{"))?,
            None => after.split_at(
                after
                    .find(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))
                    .unwrap_or(after.len()),
            ),
        };
        let value = variables
            .get(name)
            .ok_or_else(|| format!("`{expr}`: `${name}` is not a variable of the dashboard"))?;
        out.push_str(value);
        rest = tail;
    }
    out.push_str(rest);
    Ok(out)
}

/// A series as drawn: named by the target's legend format, a gap (NaN) wherever a step has no
/// point.
fn time_series(series: &Series, target: &Target, window: &Window) -> TimeSeries {
    let mut points: Vec<(f64, f64)> = Vec::with_capacity(series.points.len());
    for &(t, v) in &series.points {
        if points
            .last()
            .is_some_and(|&(t0, _)| t - t0 > 1.5 * window.step)
        {
            points.push((t, f64::NAN));
        }
        points.push((t, v));
    }
    TimeSeries {
        label: legend(target.legend_format.as_deref(), &series.labels),
        points,
    }
}

/// The series' name: `format` with each `{{label}}` replaced by its value (empty when the series
/// lacks it); without a format, `metric{label="value", ...}` as Grafana names it.
pub fn legend(format: Option<&str>, labels: &BTreeMap<String, String>) -> String {
    match format.filter(|f| !f.is_empty() && *f != "__auto") {
        Some(format) => {
            let mut out = String::new();
            let mut rest = format;
            while let Some((before, after)) = rest.split_once("{{") {
                let Some((name, tail)) = after.split_once("}}") else {
                    break;
                };
                out.push_str(before);
                out.push_str(labels.get(name.trim()).map_or("", String::as_str));
                rest = tail;
            }
            out.push_str(rest);
            out.trim().to_string()
        }
        None => {
            let pairs: Vec<String> = labels
                .iter()
                .filter(|(name, _)| *name != "__name__")
                .map(|(name, value)| format!("{name}=\"{value}\""))
                .collect();
            let metric = labels.get("__name__").map_or("", String::as_str);
            format!("{metric}{{{}}}", pairs.join(", "))
        }
    }
}

/// Writes one panel's PNG.
fn write_panel(
    panel: &Panel,
    series: &Queried,
    window: &Window,
    out: &Path,
) -> Result<PanelReport, RenderError> {
    let path = out.join(file_name(panel));
    let size = panel_size(panel.grid);
    timeseries::panel_png(&path, size, &plot_panel(panel, series, window))?;
    let outcome = match series {
        Err(error) => Outcome::Failed(error.clone()),
        Ok(series)
            if series
                .iter()
                .all(|s| s.points.iter().all(|p| !p.1.is_finite())) =>
        {
            Outcome::NoData
        }
        Ok(series) => Outcome::Drawn {
            series: series.len(),
        },
    };
    Ok(PanelReport {
        title: panel.title.clone(),
        path,
        size,
        outcome,
    })
}

/// The panel as the plot crate draws it; a failed panel has no series.
fn plot_panel<'a>(panel: &'a Panel, series: &'a Queried, window: &Window) -> timeseries::Panel<'a> {
    let config = panel
        .timeseries
        .as_ref()
        .expect("only time-series panels are drawn");
    let unit = config.unit;
    timeseries::Panel {
        title: &panel.title,
        series: series.as_deref().unwrap_or_default(),
        window: window.start..window.end,
        interpolation: config.interpolation,
        line_width: config.line_width,
        y_tick: Box::new(move |y| unit.format(y)),
    }
}

/// `<id>-<title in lower case, words joined by dashes>.png`: `02-transitions-stored-per-task.png`.
fn file_name(panel: &Panel) -> String {
    let lower = panel.title.to_lowercase();
    let words: Vec<&str> = lower
        .split(|c: char| !c.is_alphanumeric())
        .filter(|w| !w.is_empty())
        .collect();
    format!("{:02}-{}.png", panel.id, words.join("-"))
}

/// Writes `overview.png`: the title, the variables and the window across the top, then every
/// row heading and panel at its place on the grid. Returns its path and size.
fn write_overview(
    dashboard: &Dashboard,
    panels: &[(&Panel, Option<Queried>)],
    variables: &BTreeMap<String, String>,
    window: &Window,
    out: &Path,
) -> Result<(PathBuf, (u32, u32)), RenderError> {
    let top = timeseries::GRID_TITLE_HEIGHT;
    let bottom = dashboard
        .panels
        .iter()
        .map(|p| p.grid.y + p.grid.h)
        .max()
        .unwrap_or(0);
    let size = (COLUMNS * COLUMN, top + bottom * ROW);
    let cells: Vec<Placed> = panels
        .iter()
        .map(|(panel, series)| Placed {
            corner: (
                panel.grid.x * COLUMN + GAP / 2,
                top + panel.grid.y * ROW + GAP / 2,
            ),
            size: panel_size(panel.grid),
            cell: match series {
                Some(series) => Cell::Panel(plot_panel(panel, series, window)),
                None => Cell::Heading(&panel.title),
            },
        })
        .collect();
    let chosen: Vec<String> = variables
        .iter()
        .map(|(name, value)| format!("{name} = {value}"))
        .collect();
    let title = format!(
        "{}   {}   {} to {} UTC",
        dashboard.title,
        chosen.join(", "),
        utc(window.start, "%Y-%m-%d %H:%M:%S"),
        utc(window.end, "%H:%M:%S"),
    );
    let path = out.join("overview.png");
    timeseries::grid_png(&path, size, &title, &cells)?;
    Ok((path, size))
}

/// Unix seconds `t` as UTC in chrono's `format`.
fn utc(t: f64, format: &str) -> String {
    chrono::DateTime::from_timestamp(t as i64, 0)
        .map_or_else(|| format!("{t} s"), |time| time.format(format).to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn labels(pairs: &[(&str, &str)]) -> BTreeMap<String, String> {
        pairs
            .iter()
            .map(|(k, v)| (k.to_string(), v.to_string()))
            .collect()
    }

    #[test]
    fn variables_are_expanded_in_both_spellings_and_unknown_ones_named() {
        let variables = labels(&[("run", "default-1a2b"), ("__rate_interval", "20s")]);
        assert_eq!(
            expand("rate(x{run=\"$run\"}[${__rate_interval}])", &variables).unwrap(),
            "rate(x{run=\"default-1a2b\"}[20s])"
        );
        let error = expand("x{task=\"$task\"}", &variables).unwrap_err();
        assert!(error.contains("`$task` is not a variable"), "{error}");
        assert!(expand("x[${run", &variables)
            .unwrap_err()
            .contains("unclosed"));
    }

    #[test]
    fn legends_follow_the_format_or_name_the_series() {
        let series = labels(&[("__name__", "up"), ("process", "store"), ("run", "r")]);
        assert_eq!(
            legend(Some("restarts {{process}}"), &series),
            "restarts store"
        );
        assert_eq!(legend(Some("{{ task }} {{process}}"), &series), "store");
        assert_eq!(legend(None, &series), "up{process=\"store\", run=\"r\"}");
        assert_eq!(
            legend(Some("__auto"), &labels(&[("task", "a")])),
            "{task=\"a\"}"
        );
    }

    #[test]
    fn a_step_without_a_point_is_a_gap() {
        let target = Target {
            ref_id: "A".into(),
            expr: "x".into(),
            legend_format: Some("{{task}}".into()),
            hide: false,
        };
        let series = Series {
            labels: labels(&[("task", "lambda-0")]),
            points: vec![(0.0, 1.0), (5.0, 2.0), (20.0, 3.0)],
        };
        let window = Window {
            start: 0.0,
            end: 20.0,
            step: 5.0,
        };
        let drawn = time_series(&series, &target, &window);
        assert_eq!(drawn.label, "lambda-0");
        assert_eq!(drawn.points.len(), 4);
        assert!(drawn.points[2].1.is_nan());
    }

    #[test]
    fn the_step_is_the_scrape_interval_until_a_panel_would_pass_max_points() {
        let options = |minutes: u64| Options {
            end: UNIX_EPOCH + Duration::from_secs(1_000_000),
            range: Duration::from_secs(60 * minutes),
            scrape_interval: Duration::from_secs(5),
            variables: BTreeMap::new(),
            out: PathBuf::new(),
        };
        assert_eq!(window(&options(30)).step, 5.0);
        assert_eq!(window(&options(30)).start, 1_000_000.0 - 1800.0);
        assert_eq!(window(&options(24 * 60)).step, 144.0);
    }

    #[test]
    fn file_names_carry_the_id_and_the_title_words() {
        let panel = Panel {
            id: 6,
            title: "Online DQN return (last 20 episodes)".into(),
            grid: GridPos {
                x: 0,
                y: 0,
                w: 8,
                h: 8,
            },
            timeseries: None,
        };
        assert_eq!(
            file_name(&panel),
            "06-online-dqn-return-last-20-episodes.png"
        );
        assert_eq!(panel_size(panel.grid), (632, 296));
    }
}
