//! Time-series panels as a Grafana dashboard draws them: a title at the top left, series over
//! clock time (UTC) in the [`PALETTE`]'s colours, the y axis in the panel's unit and the legend
//! listed below the plot. [`panel_png`] writes one panel; [`grid_png`] lays panels and section
//! headings out at given pixel positions on one canvas, as a dashboard shows them.
//!
//! A non-finite value is a gap: the line breaks there, as Grafana's does at a null. A panel
//! without a finite value says "No data" in place of curves.

use std::ops::Range;
use std::path::Path;

use chrono::{DateTime, Utc};
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};

use super::{render, span, Area, DrawError, DrawResult, PlotError, FONT, GRID_LINE, PALETTE};

/// One series: its legend label and its (Unix seconds, value) points in time order.
#[derive(Debug, Clone, PartialEq)]
pub struct TimeSeries {
    pub label: String,
    pub points: Vec<(f64, f64)>,
}

/// How a line joins two points (Grafana's `lineInterpolation`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Interpolation {
    Linear,
    /// Each value holds until the next point.
    StepAfter,
    /// Each value holds from the previous point.
    StepBefore,
}

pub struct Panel<'a> {
    pub title: &'a str,
    pub series: &'a [TimeSeries],
    /// The time shown, in Unix seconds.
    pub window: Range<f64>,
    pub interpolation: Interpolation,
    /// In pixels.
    pub line_width: u32,
    /// A y-axis tick label in the panel's unit.
    pub y_tick: Box<dyn Fn(f64) -> String + 'a>,
}

/// What a grid shows in one rectangle.
pub enum Cell<'a> {
    /// A section's name, as a dashboard row.
    Heading(&'a str),
    Panel(Panel<'a>),
}

/// A cell at its top-left corner and size, in pixels of the grid's canvas (whose top
/// [`GRID_TITLE_HEIGHT`] pixels hold its title).
pub struct Placed<'a> {
    pub corner: (u32, u32),
    pub size: (u32, u32),
    pub cell: Cell<'a>,
}

/// Pixels at the top of a grid that hold its title.
pub const GRID_TITLE_HEIGHT: u32 = 40;
/// Pixels at the top of a panel that hold its title.
const TITLE_STRIP: u32 = 26;
const LEGEND_LINE: u32 = 18;
/// Length of a legend entry's line, in pixels.
const LEGEND_SWATCH: u32 = 16;
/// The most of a panel's height the legend may take; what does not fit is counted instead.
const LEGEND_SHARE: f64 = 0.35;
/// Pixels between two time-axis labels, at least.
const TIME_LABEL_SPACING: f64 = 90.0;
const BORDER: RGBColor = RGBColor(210, 210, 210);

/// Writes `panel` to the PNG file `path`, `size` pixels.
pub fn panel_png(path: &Path, size: (u32, u32), panel: &Panel) -> Result<(), PlotError> {
    render(path, size, |root| draw_panel(root, panel))
}

/// Writes a `size`-pixel canvas to the PNG file `path`: `title` across the top, every cell at its
/// place.
pub fn grid_png(
    path: &Path,
    size: (u32, u32),
    title: &str,
    cells: &[Placed],
) -> Result<(), PlotError> {
    render(path, size, |root| {
        root.draw(&Text::new(title, (12, 10), (FONT, 22)))?;
        for placed in cells {
            let (x, y) = (placed.corner.0 as i32, placed.corner.1 as i32);
            let area = root.clone().shrink((x, y), placed.size);
            match &placed.cell {
                Cell::Heading(text) => area.draw(&Text::new(
                    *text,
                    (8, placed.size.1 as i32 / 2),
                    TextStyle::from((FONT, 18)).pos(Pos::new(HPos::Left, VPos::Center)),
                ))?,
                Cell::Panel(panel) => draw_panel(&area, panel)?,
            }
        }
        Ok(())
    })
}

/// The panel's frame, title, plot and legend on `area`.
fn draw_panel(area: &Area, panel: &Panel) -> DrawResult {
    let (width, height) = area.dim_in_pixel();
    area.draw(&Rectangle::new(
        [(0, 0), (width as i32 - 1, height as i32 - 1)],
        BORDER,
    ))?;
    area.draw(&Text::new(panel.title, (8, 6), (FONT, 15)))?;
    let legend = legend_lines(area, panel.series, width, height)?;
    let legend_height = LEGEND_LINE * legend.len() as u32 + 4;
    let plot = area.margin(TITLE_STRIP, legend_height, 2, 8);
    draw_plot(&plot, panel)?;
    let legend_area = area.margin(height - legend_height, 0, 8, 8);
    draw_legend_lines(&legend_area, &legend)
}

/// The series' curves against clock time, or "No data".
fn draw_plot(area: &Area, panel: &Panel) -> DrawResult {
    let (width, _) = area.dim_in_pixel();
    let values = panel
        .series
        .iter()
        .flat_map(|s| s.points.iter().map(|p| p.1));
    let y_range = span(values, 0.05);
    let height = y_range.end - y_range.start;
    let x_labels = (f64::from(width) / TIME_LABEL_SPACING).max(2.0);
    // Ticks are whole minutes once they are a minute apart or more.
    let clock = if (panel.window.end - panel.window.start) / x_labels < 60.0 {
        "%H:%M:%S"
    } else {
        "%H:%M"
    };
    let mut ctx = ChartBuilder::on(area)
        .x_label_area_size(20)
        .y_label_area_size(60)
        .build_cartesian_2d(
            utc(panel.window.start)..utc(panel.window.end),
            y_range.clone(),
        )?;
    ctx.configure_mesh()
        .x_labels(x_labels as usize)
        .x_label_formatter(&|t| t.format(clock).to_string())
        .y_labels(5)
        // A tick at zero computed as 5.6e-16 prints as zero.
        .y_label_formatter(&|&y| (panel.y_tick)(if y.abs() < 1e-9 * height { 0.0 } else { y }))
        .label_style((FONT, 11))
        .bold_line_style(GRID_LINE.mix(0.5))
        .light_line_style(TRANSPARENT)
        .axis_style(BORDER)
        .draw()?;

    let mut drawn = false;
    for (i, series) in panel.series.iter().enumerate() {
        let style = PALETTE[i % PALETTE.len()].stroke_width(panel.line_width.max(1));
        for segment in segments(&series.points) {
            drawn = true;
            let line = interpolate(&segment, panel.interpolation);
            let line: Vec<_> = line.into_iter().map(|(t, v)| (utc(t), v)).collect();
            if let [point] = line[..] {
                // A point between two gaps has no line to show it.
                ctx.draw_series([Circle::new(point, 2, style.filled())])?;
            } else {
                ctx.draw_series(LineSeries::new(line, style))?;
            }
        }
    }
    if !drawn {
        let centre = (
            utc((panel.window.start + panel.window.end) / 2.0),
            (y_range.start + y_range.end) / 2.0,
        );
        let style = TextStyle::from((FONT, 16)).pos(Pos::new(HPos::Center, VPos::Center));
        ctx.draw_series([Text::new("No data", centre, style)])?;
    }
    Ok(())
}

/// Unix seconds `t` as a UTC time, to the millisecond.
fn utc(t: f64) -> DateTime<Utc> {
    DateTime::from_timestamp_millis((1000.0 * t) as i64).unwrap_or_default()
}

/// The runs of consecutive finite points.
fn segments(points: &[(f64, f64)]) -> Vec<Vec<(f64, f64)>> {
    points
        .split(|(t, v)| !(t.is_finite() && v.is_finite()))
        .filter(|run| !run.is_empty())
        .map(<[_]>::to_vec)
        .collect()
}

/// The vertices of the line through `points`: the points, with a corner before each step.
fn interpolate(points: &[(f64, f64)], interpolation: Interpolation) -> Vec<(f64, f64)> {
    let mut line = Vec::with_capacity(2 * points.len());
    for (i, &(t, v)) in points.iter().enumerate() {
        if let Some(&(t0, v0)) = i.checked_sub(1).map(|j| &points[j]) {
            match interpolation {
                Interpolation::Linear => {}
                Interpolation::StepAfter => line.push((t, v0)),
                Interpolation::StepBefore => line.push((t0, v)),
            }
        }
        line.push((t, v));
    }
    line
}

/// A legend entry: its series' colour and label, or no colour for the count of series left out.
type Entry = (Option<RGBColor>, String);

/// The legend's entries flowed into lines of a panel `width` pixels wide; lines past the legend's
/// share of the `height` are left out, and a last line counts the series they held.
fn legend_lines(
    area: &Area,
    series: &[TimeSeries],
    width: u32,
    height: u32,
) -> Result<Vec<Vec<Entry>>, DrawError> {
    let room = width.saturating_sub(16);
    let mut lines: Vec<Vec<Entry>> = vec![];
    let mut used = room;
    for (i, s) in series.iter().enumerate() {
        let (text_width, _) = area.estimate_text_size(&s.label, &legend_style())?;
        let entry_width = LEGEND_SWATCH + 6 + text_width + 16;
        if used + entry_width > room {
            lines.push(vec![]);
            used = 0;
        }
        used += entry_width;
        let colour = PALETTE[i % PALETTE.len()];
        if let Some(line) = lines.last_mut() {
            line.push((Some(colour), s.label.clone()));
        }
    }
    let most = ((LEGEND_SHARE * f64::from(height)) as u32 / LEGEND_LINE).max(1) as usize;
    if lines.len() > most {
        lines.truncate(most - 1);
        let shown: usize = lines.iter().map(Vec::len).sum();
        lines.push(vec![(None, format!("+{} more", series.len() - shown))]);
    }
    Ok(lines)
}

/// Each line's entries left to right: a short line in the series' colour, then its label.
fn draw_legend_lines(area: &Area, lines: &[Vec<Entry>]) -> DrawResult {
    let style = legend_style().pos(Pos::new(HPos::Left, VPos::Center));
    for (row, line) in lines.iter().enumerate() {
        let y = (LEGEND_LINE * row as u32 + LEGEND_LINE / 2) as i32;
        let mut x = 0;
        for (colour, label) in line {
            if let Some(colour) = colour {
                let swatch = [(x, y), (x + LEGEND_SWATCH as i32, y)];
                area.draw(&PathElement::new(swatch, colour.stroke_width(3)))?;
                x += LEGEND_SWATCH as i32 + 6;
            }
            area.draw(&Text::new(label.as_str(), (x, y), style.clone()))?;
            let (text_width, _) = area.estimate_text_size(label, &style)?;
            x += text_width as i32 + 16;
        }
    }
    Ok(())
}

fn legend_style() -> TextStyle<'static> {
    TextStyle::from((FONT, 12))
}
