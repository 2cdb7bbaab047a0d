//! The part of a Grafana dashboard's JSON model that [`crate::render`] draws: its title, its
//! `label_values` query variables, and its rows and time-series panels with their grid
//! positions, PromQL targets, legend formats, units and line styles.
//!
//! Anything else a panel may hold (tooltips, thresholds, overrides) is not read. A panel of
//! another type than `row` or `timeseries`, a unit or line interpolation not listed here, or a
//! missing field is an error naming the file and the panel.

use std::path::{Path, PathBuf};

use serde::Deserialize;
use serde_json::Value;
use uavmeta_plot::axis_tick;
use uavmeta_plot::timeseries::Interpolation;

use crate::DashboardError;

#[derive(Debug, Clone)]
pub struct Dashboard {
    /// The file it was read from, for messages.
    pub path: PathBuf,
    pub title: String,
    pub variables: Vec<Variable>,
    /// In the file's order, a row's nested panels after it.
    pub panels: Vec<Panel>,
}

/// A template variable other than a data source, used in PromQL as `$name` or `${name}`.
#[derive(Debug, Clone, PartialEq)]
pub struct Variable {
    pub name: String,
    /// Its query, when it is `label_values([selector,] label)`: Grafana offers the label's
    /// values (on the selector's series) to choose from. Without it, a value must be given.
    pub label_values: Option<LabelValues>,
}

#[derive(Debug, Clone, PartialEq)]
pub struct LabelValues {
    pub selector: Option<String>,
    pub label: String,
}

impl std::fmt::Display for LabelValues {
    /// As the dashboard writes it: `label_values(selector, label)`.
    fn fmt(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        match &self.selector {
            Some(selector) => write!(f, "label_values({selector}, {})", self.label),
            None => write!(f, "label_values({})", self.label),
        }
    }
}

/// A panel's place on Grafana's grid: 24 columns, rows of one height unit.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
pub struct GridPos {
    pub x: u32,
    pub y: u32,
    pub w: u32,
    pub h: u32,
}

#[derive(Debug, Clone)]
pub struct Panel {
    pub id: u64,
    pub title: String,
    pub grid: GridPos,
    /// `None` for a row: a heading over the panels below it.
    pub timeseries: Option<TimeSeries>,
}

#[derive(Debug, Clone)]
pub struct TimeSeries {
    pub unit: Unit,
    pub interpolation: Interpolation,
    /// In pixels.
    pub line_width: u32,
    pub targets: Vec<Target>,
}

/// One PromQL query of a panel.
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
pub struct Target {
    #[serde(rename = "refId", default)]
    pub ref_id: String,
    pub expr: String,
    /// `{{label}}` stands for the series' value of `label`; empty or `__auto`, the series is
    /// named by its metric and labels.
    #[serde(rename = "legendFormat", default)]
    pub legend_format: Option<String>,
    /// A hidden target is not queried.
    #[serde(default)]
    pub hide: bool,
}

/// How a panel prints values (Grafana's `fieldConfig.defaults.unit`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Unit {
    /// Grafana's default: the number as it is.
    #[default]
    None,
    /// Thousands as K, millions as Mil, billions as Bil.
    Short,
    /// 0-100 printed with a percent sign.
    Percent,
    /// 0-1 printed as 0-100%.
    PercentUnit,
    /// Watts with an SI prefix (mW, µW).
    Watt,
}

impl Unit {
    /// `value` as an axis label in this unit.
    pub fn format(self, value: f64) -> String {
        match self {
            Unit::None => axis_tick(value),
            Unit::Short => scaled(
                value,
                &[(1e12, " Tri"), (1e9, " Bil"), (1e6, " Mil"), (1e3, " K")],
                "",
            ),
            Unit::Percent => format!("{}%", axis_tick(value)),
            Unit::PercentUnit => format!("{}%", axis_tick(100.0 * value)),
            Unit::Watt => scaled(
                value,
                &[
                    (1e3, " kW"),
                    (1.0, " W"),
                    (1e-3, " mW"),
                    (1e-6, " µW"),
                    (1e-9, " nW"),
                ],
                " W",
            ),
        }
    }
}

/// `value` divided by the first of `scales` (largest first) it reaches, with that scale's
/// suffix; zero, and a value below every scale, with `plain`.
fn scaled(value: f64, scales: &[(f64, &str)], plain: &str) -> String {
    let found = scales.iter().find(|(scale, _)| value.abs() >= *scale);
    match found {
        Some(&(scale, suffix)) if value != 0.0 => format!("{}{suffix}", axis_tick(value / scale)),
        _ => format!("{}{plain}", axis_tick(value)),
    }
}

#[derive(Deserialize)]
struct RawDashboard {
    title: String,
    #[serde(default)]
    templating: RawTemplating,
    panels: Vec<Value>,
}

#[derive(Deserialize, Default)]
struct RawTemplating {
    #[serde(default)]
    list: Vec<RawVariable>,
}

#[derive(Deserialize)]
struct RawVariable {
    name: String,
    #[serde(rename = "type")]
    kind: String,
    #[serde(default)]
    query: Value,
}

#[derive(Deserialize)]
#[serde(tag = "type", rename_all = "lowercase")]
enum RawPanel {
    Row {
        #[serde(default)]
        id: u64,
        title: String,
        #[serde(rename = "gridPos")]
        grid: GridPos,
        /// A collapsed row's panels.
        #[serde(default)]
        panels: Vec<Value>,
    },
    Timeseries {
        #[serde(default)]
        id: u64,
        title: String,
        #[serde(rename = "gridPos")]
        grid: GridPos,
        #[serde(rename = "fieldConfig", default)]
        field_config: RawFieldConfig,
        targets: Vec<Target>,
    },
}

#[derive(Deserialize, Default)]
struct RawFieldConfig {
    #[serde(default)]
    defaults: RawDefaults,
}

#[derive(Deserialize, Default)]
struct RawDefaults {
    #[serde(default)]
    unit: Unit,
    #[serde(default)]
    custom: RawCustom,
}

#[derive(Deserialize)]
struct RawCustom {
    #[serde(rename = "lineInterpolation", default)]
    line_interpolation: LineInterpolation,
    #[serde(rename = "lineWidth", default = "one")]
    line_width: u32,
}

impl Default for RawCustom {
    fn default() -> Self {
        RawCustom {
            line_interpolation: LineInterpolation::default(),
            line_width: one(),
        }
    }
}

fn one() -> u32 {
    1
}

/// Grafana's line interpolations; a smooth line is drawn straight.
#[derive(Deserialize, Default, Clone, Copy)]
#[serde(rename_all = "camelCase")]
enum LineInterpolation {
    #[default]
    Linear,
    Smooth,
    StepAfter,
    StepBefore,
}

impl From<LineInterpolation> for Interpolation {
    fn from(line: LineInterpolation) -> Self {
        match line {
            LineInterpolation::Linear | LineInterpolation::Smooth => Interpolation::Linear,
            LineInterpolation::StepAfter => Interpolation::StepAfter,
            LineInterpolation::StepBefore => Interpolation::StepBefore,
        }
    }
}

impl Dashboard {
    /// Reads and checks the dashboard JSON file `path`.
    pub fn read(path: &Path) -> Result<Dashboard, DashboardError> {
        let text = std::fs::read_to_string(path).map_err(|source| DashboardError::Read {
            path: path.to_owned(),
            source,
        })?;
        Dashboard::parse(&text, path)
    }

    /// Checks the dashboard JSON `text`; `path` names it in messages.
    pub fn parse(text: &str, path: &Path) -> Result<Dashboard, DashboardError> {
        let raw: RawDashboard =
            serde_json::from_str(text).map_err(|source| DashboardError::Json {
                path: path.to_owned(),
                source,
            })?;
        let mut panels = Vec::new();
        for (index, value) in raw.panels.into_iter().enumerate() {
            read_panel(path, &format!("panels[{index}]"), value, &mut panels)?;
        }
        let variables = raw
            .templating
            .list
            .into_iter()
            .filter(|v| v.kind != "datasource")
            .map(|v| variable(path, v))
            .collect::<Result<_, _>>()?;
        Ok(Dashboard {
            path: path.to_owned(),
            title: raw.title,
            variables,
            panels,
        })
    }
}

/// Appends the panel `value`, found at `place` (`panels[3]`), and a row's nested panels.
fn read_panel(
    path: &Path,
    place: &str,
    value: Value,
    panels: &mut Vec<Panel>,
) -> Result<(), DashboardError> {
    let title = value["title"].as_str().unwrap_or("untitled").to_string();
    let raw: RawPanel = serde_json::from_value(value).map_err(|e| DashboardError::Panel {
        path: path.to_owned(),
        place: place.to_string(),
        title,
        cause: e.to_string(),
    })?;
    match raw {
        RawPanel::Row {
            id,
            title,
            grid,
            panels: nested,
        } => {
            panels.push(Panel {
                id,
                title,
                grid,
                timeseries: None,
            });
            for (index, value) in nested.into_iter().enumerate() {
                read_panel(path, &format!("{place}.panels[{index}]"), value, panels)?;
            }
        }
        RawPanel::Timeseries {
            id,
            title,
            grid,
            field_config,
            targets,
        } => panels.push(Panel {
            id,
            title,
            grid,
            timeseries: Some(TimeSeries {
                unit: field_config.defaults.unit,
                interpolation: field_config.defaults.custom.line_interpolation.into(),
                line_width: field_config.defaults.custom.line_width,
                targets,
            }),
        }),
    }
    Ok(())
}

/// A variable, its query read when it is `label_values(...)` (as text, or as `{"query": ...}`).
fn variable(path: &Path, raw: RawVariable) -> Result<Variable, DashboardError> {
    let query = raw
        .query
        .as_str()
        .or_else(|| raw.query["query"].as_str())
        .unwrap_or_default();
    let label_values = match query.trim().strip_prefix("label_values(") {
        None => None,
        Some(rest) => Some(
            parse_label_values(rest).ok_or_else(|| DashboardError::Variable {
                path: path.to_owned(),
                name: raw.name.clone(),
                cause: format!("`{query}` is not label_values([selector,] label)"),
            })?,
        ),
    };
    Ok(Variable {
        name: raw.name,
        label_values,
    })
}

/// `selector, label)` or `label)`, the arguments of `label_values(`.
fn parse_label_values(arguments: &str) -> Option<LabelValues> {
    let inside = arguments.trim_end().strip_suffix(')')?;
    let (selector, label) = match inside.rsplit_once(',') {
        Some((selector, label)) => (Some(selector.trim().to_string()), label.trim()),
        None => (None, inside.trim()),
    };
    let valid = !label.is_empty() && label.chars().all(|c| c.is_ascii_alphanumeric() || c == '_');
    valid.then(|| LabelValues {
        selector,
        label: label.to_string(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use uavmeta_proto::metrics::launcher::CHILDREN_RUNNING;

    const REPOSITORY_DASHBOARD: &str = include_str!("../../docs/grafana/uavmeta.json");

    fn parse(text: &str) -> Result<Dashboard, DashboardError> {
        Dashboard::parse(text, Path::new("dash.json"))
    }

    #[test]
    fn the_repository_dashboard_reads_with_its_rows_panels_and_run_variable() {
        let dashboard = parse(REPOSITORY_DASHBOARD).unwrap();
        let rows: Vec<_> = dashboard
            .panels
            .iter()
            .filter(|p| p.timeseries.is_none())
            .collect();
        let series: Vec<_> = dashboard
            .panels
            .iter()
            .filter_map(|p| p.timeseries.as_ref())
            .collect();
        assert_eq!(rows.len(), 5);
        assert!(series.len() >= 16);
        assert!(series.iter().all(|s| !s.targets.is_empty()));
        assert_eq!(
            dashboard.variables,
            [Variable {
                name: "run".into(),
                label_values: Some(LabelValues {
                    selector: Some(CHILDREN_RUNNING.name.into()),
                    label: "run".into(),
                }),
            }]
        );
        let epsilon = dashboard
            .panels
            .iter()
            .find(|p| p.title == "Online DQN epsilon")
            .unwrap();
        let epsilon = epsilon.timeseries.as_ref().unwrap();
        assert_eq!(epsilon.unit, Unit::PercentUnit);
        assert_eq!(epsilon.interpolation, Interpolation::StepAfter);
    }

    #[test]
    fn a_bad_panel_is_named_by_file_place_and_title() {
        let text = r#"{"title": "t", "panels": [
            {"type": "row", "title": "r", "gridPos": {"x": 0, "y": 0, "w": 24, "h": 1}},
            {"type": "timeseries", "title": "Loss", "gridPos": {"x": 0, "y": 1, "w": 8, "h": 8},
             "fieldConfig": {"defaults": {"unit": "bytes"}}, "targets": []}]}"#;
        let error = parse(text).unwrap_err().to_string();
        assert!(
            error.starts_with("dash.json: panels[1] `Loss`: unknown variant `bytes`"),
            "{error}"
        );

        let text = r#"{"title": "t", "panels": [{"type": "stat", "title": "Up", "gridPos": {"x": 0, "y": 0, "w": 8, "h": 8}}]}"#;
        let error = parse(text).unwrap_err().to_string();
        assert!(
            error.starts_with("dash.json: panels[0] `Up`: unknown variant `stat`"),
            "{error}"
        );

        let text = r#"{"title": "t", "panels": [{"type": "timeseries", "title": "No query", "gridPos": {"x": 0, "y": 0, "w": 8, "h": 8}, "targets": [{"refId": "A"}]}]}"#;
        let error = parse(text).unwrap_err().to_string();
        assert!(
            error.contains("panels[0] `No query`: missing field `expr`"),
            "{error}"
        );
    }

    #[test]
    fn text_that_is_no_dashboard_is_named_with_its_line() {
        let error = parse("{\"title\": \"t\",\n\"panels\": [}")
            .unwrap_err()
            .to_string();
        assert!(
            error.starts_with("dash.json: not a Grafana dashboard"),
            "{error}"
        );
        assert!(error.contains("line 2"), "{error}");
    }

    #[test]
    fn label_values_take_an_optional_selector() {
        assert_eq!(
            parse_label_values("up{job=\"a,b\"}, run)"),
            Some(LabelValues {
                selector: Some("up{job=\"a,b\"}".into()),
                label: "run".into()
            })
        );
        assert_eq!(
            parse_label_values("run )"),
            Some(LabelValues {
                selector: None,
                label: "run".into()
            })
        );
        assert_eq!(parse_label_values("up, run"), None);
        assert_eq!(parse_label_values("up, )"), None);
    }

    #[test]
    fn units_print_as_grafana_does() {
        assert_eq!(Unit::Short.format(1500.0), "1.50 K");
        assert_eq!(Unit::Short.format(12.0), "12");
        assert_eq!(Unit::Short.format(0.0), "0");
        assert_eq!(Unit::PercentUnit.format(0.25), "25%");
        assert_eq!(Unit::Percent.format(25.0), "25%");
        assert_eq!(Unit::Watt.format(0.0005), "500 µW");
        assert_eq!(Unit::Watt.format(0.00125), "1.25 mW");
        assert_eq!(Unit::Watt.format(0.0), "0 W");
        assert_eq!(Unit::None.format(-450.0), "-450");
    }
}
