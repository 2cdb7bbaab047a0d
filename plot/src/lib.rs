//! PNG charts in one style: uavmeta reproduce's figures.
//!
//! - [`line_chart`]: curves over epochs with shaded 95% confidence bands and dashed reference
//!   levels; [`bar_chart`]: grouped bars with confidence whiskers; [`trajectory_chart`]: UAV paths
//!   on the grid with the rain zone. They take summary statistics from `uavmeta_proto::stats` and
//!   the rain zone from `uavmeta_proto::config`.
//!
//! Every chart is written to a PNG file on a white canvas in the [`PALETTE`]'s colours. Text is
//! set in DejaVu Sans compiled into the binary (`plot/assets/`, licence beside it), so a figure
//! renders the same on every machine and needs no system fonts.
//!
//! Non-finite values (the NaN of a run that diverged, the mean of an epoch no run reached) are
//! left out: a curve breaks around them and a bar is not drawn. A chart with no finite value at
//! all is still written, with axes over [0, 1] and its legend, so the figure of a failed
//! experiment exists and shows that it is empty instead of stopping the other figures.
//!
//! ```
//! use uavmeta_plot::{line_chart, Band, LineChart, Series};
//!
//! let dir = tempfile::tempdir().unwrap();
//! let x = vec![1.0, 2.0, 3.0];
//! let runs = [vec![-300.0, -250.0, -220.0], vec![-320.0, -260.0, -210.0]];
//! let series = [Series { label: "CQL-MAML".into(), band: Band::from_runs(x, &runs) }];
//! let chart = LineChart {
//!     title: "Meta-test reward",
//!     x_label: "epoch",
//!     y_label: "reward",
//!     series: &series,
//!     references: &[],
//!     floor: None,
//! };
//! line_chart(&dir.path().join("reward.png"), &chart).unwrap();
//! ```

use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::Once;

use plotters::coord::types::RangedCoordf64;
use plotters::coord::Shift;
use plotters::element::DashedPathElement;
use plotters::prelude::*;
use plotters::style::register_font;
use plotters::style::text_anchor::{HPos, Pos, VPos};
use uavmeta_proto::config::RainZone;
use uavmeta_proto::stats::Estimate;

/// The family name the embedded font is registered under.
const FONT: &str = "sans-serif";
static DEJAVU_SANS: &[u8] = include_bytes!("../assets/DejaVuSans.ttf");

/// Tableau's ten colours, then ten of Kelly's colours of maximum contrast that differ from them:
/// told apart in print and by most colour-blind readers. The n-th series of a chart is drawn in
/// the n-th colour (cycling); a figure's methods and references together (up to 18 in figure 5)
/// each get their own.
pub const PALETTE: [RGBColor; 20] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(127, 127, 127),
    RGBColor(188, 189, 34),
    RGBColor(23, 190, 207),
    RGBColor(0, 0, 0),
    RGBColor(0, 0, 128),
    RGBColor(128, 128, 0),
    RGBColor(0, 128, 128),
    RGBColor(128, 0, 0),
    RGBColor(244, 200, 0),
    RGBColor(147, 170, 0),
    RGBColor(89, 51, 21),
    RGBColor(83, 55, 122),
    RGBColor(166, 189, 215),
];
const BAND_ALPHA: f64 = 0.2;
const RAIN: RGBColor = RGBColor(120, 170, 220);
const GRID_LINE: RGBColor = RGBColor(200, 200, 200);

/// Line and bar charts, in pixels.
const CHART_SIZE: (u32, u32) = (1000, 650);
/// Width of one trajectory panel, in pixels.
const PANEL_WIDTH: u32 = 560;
/// Share of a trajectory panel's height above the grid, kept free for the legend.
const LEGEND_STRIP: f64 = 0.3;
/// Pixels of a trajectory panel outside its plotting area: across (margins and y labels) and
/// down (the titles, margins and x labels).
const PANEL_FRAME: (u32, u32) = (60, 125);
/// Share of a group's slot on the x axis that its bars fill.
const BAR_SPAN: f64 = 0.8;

type Area<'a> = DrawingArea<BitMapBackend<'a>, Shift>;
type DrawError = DrawingAreaErrorKind<<BitMapBackend<'static> as DrawingBackend>::ErrorType>;
type DrawResult = Result<(), DrawError>;

#[derive(Debug, thiserror::Error)]
pub enum PlotError {
    #[error("{}: cannot draw the chart: {cause}", path.display())]
    Draw { path: PathBuf, cause: String },
}

/// A curve over seeds: per x, the mean and the half-width of its 95% confidence interval.
#[derive(Debug, Clone, PartialEq)]
pub struct Band {
    pub x: Vec<f64>,
    pub mean: Vec<f64>,
    pub ci95: Vec<f64>,
}

impl Band {
    /// The band of `runs` (one curve per seed) over `x`. A run shorter than `x` counts only where
    /// it has values; where no run has one, the mean is NaN and the curve breaks.
    pub fn from_runs(x: Vec<f64>, runs: &[Vec<f64>]) -> Band {
        let estimates: Vec<Estimate> = (0..x.len())
            .map(|i| Estimate::from_samples(runs.iter().filter_map(|run| run.get(i).copied())))
            .collect();
        Band {
            x,
            mean: estimates.iter().map(|e| e.mean).collect(),
            ci95: estimates.iter().map(|e| e.ci95).collect(),
        }
    }

    /// The runs of consecutive points with a finite x and mean, as (x, mean, ci95); a non-finite
    /// half-width draws as none.
    fn segments(&self) -> Vec<Vec<(f64, f64, f64)>> {
        let mut segments = vec![];
        let mut current = vec![];
        for ((&x, &mean), &ci) in self.x.iter().zip(&self.mean).zip(&self.ci95) {
            if x.is_finite() && mean.is_finite() {
                current.push((x, mean, if ci.is_finite() { ci } else { 0.0 }));
            } else if !current.is_empty() {
                segments.push(std::mem::take(&mut current));
            }
        }
        if !current.is_empty() {
            segments.push(current);
        }
        segments
    }
}

/// One curve of a line chart.
#[derive(Debug, Clone, PartialEq)]
pub struct Series {
    pub label: String,
    pub band: Band,
}

/// A level drawn as a dashed horizontal line with a legend entry: a heuristic's or online DQN's
/// figure beside the learning curves.
#[derive(Debug, Clone, PartialEq)]
pub struct Reference {
    pub label: String,
    pub value: f64,
}

pub struct LineChart<'a> {
    pub title: &'a str,
    pub x_label: &'a str,
    pub y_label: &'a str,
    pub series: &'a [Series],
    pub references: &'a [Reference],
    /// The least value the plotted quantity can take (0 for counts and losses): a band is cut
    /// there rather than reaching into values that cannot occur.
    pub floor: Option<f64>,
}

/// Writes `chart` to the PNG file `path`: each series its mean line over a shaded band of the same
/// colour, each reference a dashed line, the y range covering every band and reference.
pub fn line_chart(path: &Path, chart: &LineChart) -> Result<(), PlotError> {
    let segments: Vec<_> = chart.series.iter().map(|s| s.band.segments()).collect();
    let points = || segments.iter().flatten().flatten();
    let lower = |mean: f64, ci: f64| {
        chart
            .floor
            .map_or(mean - ci, |floor| (mean - ci).max(floor))
    };
    let x_range = span(points().map(|&(x, _, _)| x), 0.0);
    let y_range = span(
        points()
            .flat_map(|&(_, mean, ci)| [lower(mean, ci), mean + ci])
            .chain(chart.references.iter().map(|r| r.value)),
        0.05,
    );
    let corner = legend_corner(points().map(|&(x, mean, _)| (x, mean)), &x_range, &y_range);

    render(path, CHART_SIZE, |root| {
        let mut ctx = ChartBuilder::on(root)
            .caption(chart.title, (FONT, 24))
            .margin(15)
            .x_label_area_size(50)
            .y_label_area_size(80)
            .build_cartesian_2d(x_range.clone(), y_range.clone())?;
        ctx.configure_mesh()
            .x_desc(chart.x_label)
            .y_desc(chart.y_label)
            .x_label_formatter(&|&x| axis_tick(x))
            .y_label_formatter(&|&y| axis_tick(y))
            .label_style((FONT, 14))
            .axis_desc_style((FONT, 16))
            .light_line_style(WHITE.mix(0.0))
            .draw()?;

        for (i, (series, segments)) in chart.series.iter().zip(&segments).enumerate() {
            let colour = PALETTE[i % PALETTE.len()];
            for segment in segments {
                draw_segment(&mut ctx, segment, colour, lower)?;
            }
            // Drawn empty so that the legend lists every series, even one with no finite point.
            ctx.draw_series(LineSeries::new(
                std::iter::empty::<(f64, f64)>(),
                colour.stroke_width(2),
            ))?
            .label(series.label.as_str())
            .legend(move |(x, y)| PathElement::new([(x, y), (x + 24, y)], colour.stroke_width(2)));
        }

        for (j, reference) in chart.references.iter().enumerate() {
            let style = PALETTE[(chart.series.len() + j) % PALETTE.len()].stroke_width(2);
            let level: Vec<(f64, f64)> = [x_range.start, x_range.end]
                .into_iter()
                .filter(|_| reference.value.is_finite())
                .map(|x| (x, reference.value))
                .collect();
            ctx.draw_series(DashedLineSeries::new(level, 10, 6, style))?
                .label(reference.label.as_str())
                .legend(move |(x, y)| DashedPathElement::new([(x, y), (x + 24, y)], 6, 3, style));
        }

        draw_legend(&mut ctx, corner)
    })
}

/// One unbroken run of a series' points (x, mean, ci95): its band, with the lower edge at
/// `lower(mean, ci95)`, and its mean line.
fn draw_segment<DB: DrawingBackend>(
    ctx: &mut ChartContext<'_, DB, Cartesian2d<RangedCoordf64, RangedCoordf64>>,
    segment: &[(f64, f64, f64)],
    colour: RGBColor,
    lower: impl Fn(f64, f64) -> f64,
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    // The band's outline: the upper edge left to right, then the lower edge back.
    let outline: Vec<(f64, f64)> = segment
        .iter()
        .map(|&(x, mean, ci)| (x, mean + ci))
        .chain(
            segment
                .iter()
                .rev()
                .map(|&(x, mean, ci)| (x, lower(mean, ci))),
        )
        .collect();
    ctx.draw_series([Polygon::new(outline, colour.mix(BAND_ALPHA).filled())])?;
    ctx.draw_series(LineSeries::new(
        segment.iter().map(|&(x, mean, _)| (x, mean)),
        colour.stroke_width(2),
    ))?;
    // A point between two gaps has no line to show it.
    if let [(x, mean, _)] = segment[..] {
        ctx.draw_series([Circle::new((x, mean), 3, colour.filled())])?;
    }
    Ok(())
}

/// One bar: the value of `label` (a metric, a method) within `group` on the x axis.
#[derive(Debug, Clone, PartialEq)]
pub struct Bar {
    pub group: String,
    pub label: String,
    pub value: Estimate,
}

/// Writes grouped bars to the PNG file `path`: groups along the x axis in order of first
/// appearance, within each group one bar per label (a colour per label, in the legend), each
/// with its 95% confidence whisker and its mean written beside it. Bars start at zero.
pub fn bar_chart(path: &Path, title: &str, y_label: &str, bars: &[Bar]) -> Result<(), PlotError> {
    let groups = first_appearance(bars.iter().map(|b| b.group.as_str()));
    let labels = first_appearance(bars.iter().map(|b| b.label.as_str()));
    let width = BAR_SPAN / labels.len().max(1) as f64;
    // The left edge of a bar: its group's slot is centred on the group's index.
    let left = |bar: &Bar| {
        let g = groups.iter().position(|&g| g == bar.group).unwrap_or(0);
        let l = labels.iter().position(|&l| l == bar.label).unwrap_or(0);
        g as f64 - BAR_SPAN / 2.0 + l as f64 * width
    };
    let drawn: Vec<&Bar> = bars.iter().filter(|b| b.value.mean.is_finite()).collect();
    let (y_range, corner) = bar_y_range(&drawn);
    let x_range = -0.5..groups.len().max(1) as f64 - 0.5;

    render(path, CHART_SIZE, |root| {
        let mut ctx = ChartBuilder::on(root)
            .caption(title, (FONT, 24))
            .margin(15)
            .x_label_area_size(50)
            .y_label_area_size(80)
            .build_cartesian_2d(x_range, y_range)?;
        ctx.configure_mesh()
            .disable_x_mesh()
            // Asking for as many labels as groups puts them at the integers: the group centres.
            .x_labels(groups.len())
            .x_label_formatter(&|&x| tick_name(x, &groups))
            .y_label_formatter(&|&y| axis_tick(y))
            .y_desc(y_label)
            .label_style((FONT, 14))
            .axis_desc_style((FONT, 16))
            .light_line_style(WHITE.mix(0.0))
            .draw()?;
        ctx.draw_series([PathElement::new(
            [(-0.5, 0.0), (groups.len().max(1) as f64 - 0.5, 0.0)],
            BLACK.stroke_width(1),
        )])?;

        for (l, &label) in labels.iter().enumerate() {
            let colour = PALETTE[l % PALETTE.len()];
            let mine = || drawn.iter().filter(move |b| b.label == label);
            ctx.draw_series(mine().map(|b| {
                let x0 = left(b);
                Rectangle::new([(x0, 0.0), (x0 + width, b.value.mean)], colour.filled())
            }))?
            .label(label)
            .legend(move |(x, y)| Rectangle::new([(x, y - 6), (x + 14, y + 6)], colour.filled()));
            // The whisker: mean +- ci95, with caps a third of the bar wide.
            ctx.draw_series(mine().filter(|b| whisker(b.value) > 0.0).flat_map(|b| {
                let (centre, v) = (left(b) + width / 2.0, b.value);
                let (lo, hi, cap) = (v.mean - v.ci95, v.mean + v.ci95, width / 6.0);
                [
                    [(centre, lo), (centre, hi)],
                    [(centre - cap, lo), (centre + cap, lo)],
                    [(centre - cap, hi), (centre + cap, hi)],
                ]
                .map(|line| PathElement::new(line, BLACK.stroke_width(2)))
            }))?;
            ctx.draw_series(mine().map(|b| {
                let (centre, v) = (left(b) + width / 2.0, b.value);
                let (y, anchor, offset) = value_place(v);
                let style = TextStyle::from((FONT, 13).into_font());
                EmptyElement::at((centre, y))
                    + Text::new(
                        significant(v.mean),
                        (0, offset),
                        style.pos(Pos::new(HPos::Center, anchor)),
                    )
            }))?;
        }

        draw_legend(&mut ctx, corner)
    })
}

/// A bar's whisker: its 95% half-width, none when that is not finite.
fn whisker(v: Estimate) -> f64 {
    if v.ci95.is_finite() {
        v.ci95
    } else {
        0.0
    }
}

/// The y range of a bar chart, from zero over every bar and whisker, with room for the legend on
/// the side the bars grow towards, and the legend's corner there.
fn bar_y_range(drawn: &[&Bar]) -> (Range<f64>, SeriesLabelPosition) {
    let y_range = span(
        drawn
            .iter()
            .flat_map(|b| {
                [
                    b.value.mean - whisker(b.value),
                    b.value.mean + whisker(b.value),
                ]
            })
            .chain([0.0]),
        0.05,
    );
    let room = 0.25 * (y_range.end - y_range.start);
    if y_range.end.abs() >= y_range.start.abs() {
        (
            y_range.start..y_range.end + room,
            SeriesLabelPosition::UpperRight,
        )
    } else {
        (
            y_range.start - room..y_range.end,
            SeriesLabelPosition::LowerRight,
        )
    }
}

/// Where a bar's mean is written: just beyond its whisker's end, on the side the bar grows to
/// (y, the text's vertical anchor, its offset in pixels).
fn value_place(v: Estimate) -> (f64, VPos, i32) {
    if v.mean >= 0.0 {
        (v.mean + whisker(v), VPos::Bottom, -4)
    } else {
        (v.mean - whisker(v), VPos::Top, 4)
    }
}

pub struct TrajectoryChart<'a> {
    pub title: &'a str,
    pub grid_cells: u32,
    pub device_cells: &'a [(u32, u32)],
    pub rain: Option<RainZone>,
    /// A label (the method) and the UAV's cells in time order.
    pub paths: &'a [(String, Vec<(u32, u32)>)],
}

/// Writes the PNG file `path`: one panel per path, side by side, each the grid with its cell
/// lines, the rain zone shaded, the devices as triangles and the path through the cell centres
/// from a start marker to an end marker.
pub fn trajectory_chart(path: &Path, chart: &TrajectoryChart) -> Result<(), PlotError> {
    let panels = chart.paths.len().max(1);
    // Square cells: the plotting area is as much taller than wide as the legend strip adds.
    let grid_px = (PANEL_WIDTH - PANEL_FRAME.0) as f64;
    let height = (grid_px * (1.0 + LEGEND_STRIP)) as u32 + PANEL_FRAME.1;
    render(path, (PANEL_WIDTH * panels as u32, height), |root| {
        let root = root.titled(chart.title, (FONT, 24))?;
        for (i, area) in root.split_evenly((1, panels)).iter().enumerate() {
            let colour = PALETTE[i % PALETTE.len()];
            let (label, cells) = chart
                .paths
                .get(i)
                .map_or(("", &[][..]), |(label, cells)| (label.as_str(), &cells[..]));
            trajectory_panel(area, chart, label, cells, colour)?;
        }
        Ok(())
    })
}

/// One path on the grid. Cell (i, j) is the unit square centred on (i, j).
fn trajectory_panel(
    area: &Area,
    chart: &TrajectoryChart,
    label: &str,
    cells: &[(u32, u32)],
    colour: RGBColor,
) -> DrawResult {
    let grid = chart.grid_cells.max(1);
    let (lo, hi) = (-0.5, grid as f64 - 0.5);
    let numbers: Vec<String> = (0..grid).map(|c| c.to_string()).collect();
    let numbers: Vec<&str> = numbers.iter().map(String::as_str).collect();
    let mut ctx = ChartBuilder::on(area)
        .caption(label, (FONT, 18))
        .margin(10)
        .x_label_area_size(40)
        .y_label_area_size(40)
        .build_cartesian_2d(lo..hi, lo..hi + LEGEND_STRIP * grid as f64)?;
    ctx.configure_mesh()
        .disable_mesh()
        // Whole steps at most ten labels apart, so labels sit on cell centres.
        .x_labels(10)
        .y_labels((10.0 * (1.0 + LEGEND_STRIP)).ceil() as usize)
        // The cell lines frame the grid; axis lines and ticks would run on into the legend strip.
        .axis_style(TRANSPARENT)
        .set_all_tick_mark_size(0)
        .x_label_formatter(&|&x| tick_name(x, &numbers))
        .y_label_formatter(&|&y| tick_name(y, &numbers))
        .x_desc("x (cell)")
        .y_desc("y (cell)")
        .label_style((FONT, 12))
        .axis_desc_style((FONT, 14))
        .draw()?;

    if let Some(z) = chart.rain {
        let zone = [
            (z.x0 as f64 - 0.5, z.y0 as f64 - 0.5),
            (z.x1 as f64 + 0.5, z.y1 as f64 + 0.5),
        ];
        ctx.draw_series([Rectangle::new(zone, RAIN.mix(0.45).filled())])?
            .label("rain zone")
            .legend(|(x, y)| {
                Rectangle::new([(x, y - 6), (x + 14, y + 6)], RAIN.mix(0.45).filled())
            });
    }
    ctx.draw_series((0..=grid).flat_map(|i| {
        let edge = i as f64 - 0.5;
        [
            PathElement::new([(edge, lo), (edge, hi)], GRID_LINE),
            PathElement::new([(lo, edge), (hi, edge)], GRID_LINE),
        ]
    }))?;

    let centre = |&(x, y): &(u32, u32)| (x as f64, y as f64);
    ctx.draw_series(
        chart
            .device_cells
            .iter()
            .map(|c| TriangleMarker::new(centre(c), 7, BLACK.filled())),
    )?
    .label("IoT device")
    .legend(|(x, y)| TriangleMarker::new((x + 7, y), 6, BLACK.filled()));

    draw_path(&mut ctx, cells, colour)?;

    ctx.configure_series_labels()
        .position(SeriesLabelPosition::UpperLeft)
        .label_font((FONT, 13))
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK.mix(0.4))
        .draw()
}

/// The UAV's path through the cell centres, from a start marker to an end marker.
fn draw_path<DB: DrawingBackend>(
    ctx: &mut ChartContext<'_, DB, Cartesian2d<RangedCoordf64, RangedCoordf64>>,
    cells: &[(u32, u32)],
    colour: RGBColor,
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    let (Some(first), Some(last)) = (cells.first(), cells.last()) else {
        return Ok(());
    };
    let centre = |&(x, y): &(u32, u32)| (x as f64, y as f64);
    ctx.draw_series(LineSeries::new(
        cells.iter().map(centre),
        colour.stroke_width(3),
    ))?
    .label(format!("path ({} moves)", cells.len() - 1))
    .legend(move |(x, y)| PathElement::new([(x, y), (x + 24, y)], colour.stroke_width(3)));
    ctx.draw_series([Circle::new(centre(first), 8, colour.filled())])?
        .label("start")
        .legend(move |(x, y)| Circle::new((x + 7, y), 6, colour.filled()));
    ctx.draw_series([Cross::new(centre(last), 8, BLACK.stroke_width(3))])?
        .label("end")
        .legend(|(x, y)| Cross::new((x + 7, y), 6, BLACK.stroke_width(2)));
    Ok(())
}

/// Draws on a white canvas of `size` pixels and writes it to the PNG file `path`.
fn render(
    path: &Path,
    size: (u32, u32),
    draw: impl FnOnce(&Area) -> DrawResult,
) -> Result<(), PlotError> {
    register_embedded_font();
    let root = BitMapBackend::new(path, size).into_drawing_area();
    root.fill(&WHITE)
        .and_then(|()| draw(&root))
        .and_then(|()| root.present())
        .map_err(|e| PlotError::Draw {
            path: path.to_owned(),
            cause: e.to_string(),
        })
}

fn register_embedded_font() {
    static REGISTER: Once = Once::new();
    REGISTER.call_once(|| {
        // The bytes are a file of this repository, so a failure is a defect of the build, not of
        // any input; every chart test would catch it.
        let registered = register_font(FONT, FontStyle::Normal, DEJAVU_SANS).is_ok();
        assert!(registered, "plot/assets/DejaVuSans.ttf is not a font");
    });
}

/// The range of the finite `values`, widened by `margin` of its width on both sides; one value
/// gets +-0.5 (or 5% of itself if larger), none gives [0, 1].
fn span(values: impl IntoIterator<Item = f64>, margin: f64) -> Range<f64> {
    let (lo, hi) = values
        .into_iter()
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
            (lo.min(v), hi.max(v))
        });
    if lo > hi {
        0.0..1.0
    } else if lo == hi {
        let half = (0.05 * lo.abs()).max(0.5);
        lo - half..hi + half
    } else {
        let pad = margin * (hi - lo);
        lo - pad..hi + pad
    }
}

/// The legend box of every chart, at `corner`.
fn draw_legend<'a, DB: DrawingBackend + 'a, CT: CoordTranslate>(
    ctx: &mut ChartContext<'a, DB, CT>,
    corner: SeriesLabelPosition,
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    ctx.configure_series_labels()
        .position(corner)
        .label_font((FONT, 14))
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK.mix(0.4))
        .draw()
}

/// Upper or lower right, whichever the curves' right halves leave emptier.
fn legend_corner(
    points: impl Iterator<Item = (f64, f64)>,
    x: &Range<f64>,
    y: &Range<f64>,
) -> SeriesLabelPosition {
    let x_mid = (x.start + x.end) / 2.0;
    let (low, high) = (
        y.start + (y.end - y.start) / 3.0,
        y.end - (y.end - y.start) / 3.0,
    );
    let (below, above) = points
        .filter(|&(px, _)| px >= x_mid)
        .fold((0, 0), |(below, above), (_, py)| {
            (below + (py < low) as usize, above + (py > high) as usize)
        });
    if above <= below {
        SeriesLabelPosition::UpperRight
    } else {
        SeriesLabelPosition::LowerRight
    }
}

/// The name of the group or cell at `x` if `x` is its index, else nothing: tick labels of an
/// axis whose items sit at the integers.
fn tick_name(x: f64, names: &[&str]) -> String {
    let index = x.round();
    if (x - index).abs() > 1e-6 || index < 0.0 {
        return String::new();
    }
    names
        .get(index as usize)
        .map_or_else(String::new, |name| name.to_string())
}

/// The distinct `items` in the order they first appear.
fn first_appearance<'a>(items: impl Iterator<Item = &'a str>) -> Vec<&'a str> {
    let mut seen: Vec<&str> = vec![];
    for item in items {
        if !seen.contains(&item) {
            seen.push(item);
        }
    }
    seen
}

/// An axis tick: whole numbers without decimals (epoch 10, not 10.0), others as [`significant`].
pub fn axis_tick(value: f64) -> String {
    if value == value.round() {
        format!("{value:.0}")
    } else {
        significant(value)
    }
}

/// `value` to three significant digits, without exponent: 0.634, 5.41, -452.
fn significant(value: f64) -> String {
    let magnitude = if value == 0.0 {
        0
    } else {
        value.abs().log10().floor() as i32
    };
    format!("{value:.0$}", (2 - magnitude).max(0) as usize)
}

#[cfg(test)]
mod tests {
    use std::fs::File;

    use super::*;

    /// A decoded PNG: width, height and RGB pixels.
    struct Image {
        width: u32,
        height: u32,
        rgb: Vec<[u8; 3]>,
    }

    impl Image {
        fn read(path: &Path) -> Image {
            let mut reader = png::Decoder::new(File::open(path).unwrap())
                .read_info()
                .unwrap();
            let mut buf = vec![0; reader.output_buffer_size()];
            let info = reader.next_frame(&mut buf).unwrap();
            assert_eq!(info.color_type, png::ColorType::Rgb);
            let rgb = buf[..info.buffer_size()]
                .chunks_exact(3)
                .map(|p| [p[0], p[1], p[2]])
                .collect();
            Image {
                width: info.width,
                height: info.height,
                rgb,
            }
        }

        fn count(&self, colour: RGBColor) -> usize {
            let want = [colour.0, colour.1, colour.2];
            self.rgb.iter().filter(|&&p| p == want).count()
        }

        /// Pixels neither white nor grey in the left half, away from the legend: the data drawn.
        fn coloured_left_half(&self) -> usize {
            self.rgb
                .chunks_exact(self.width as usize)
                .flat_map(|row| &row[..row.len() / 2])
                .filter(|p| p.iter().max().unwrap() - p.iter().min().unwrap() > 30)
                .count()
        }
    }

    fn series(label: &str, x: &[f64], runs: &[Vec<f64>]) -> Series {
        Series {
            label: label.into(),
            band: Band::from_runs(x.to_vec(), runs),
        }
    }

    #[test]
    fn band_is_the_mean_and_95_percent_interval_over_the_runs_present() {
        let runs = [vec![1.0, 2.0, 3.0], vec![3.0, 4.0], vec![5.0]];
        let band = Band::from_runs(vec![10.0, 20.0, 30.0, 40.0], &runs);
        assert_eq!(band.x, [10.0, 20.0, 30.0, 40.0]);
        // x = 10: samples 1, 3, 5: mean 3, sample variance 4, t(2) = 4.303.
        // x = 20: samples 2, 4: mean 3, sample variance 2, t(1) = 12.706.
        // x = 30: the one sample 3, no interval; x = 40: no run reaches it.
        let want_ci = [4.303 * (4.0f64 / 3.0).sqrt(), 12.706, 0.0];
        for (i, want) in want_ci.into_iter().enumerate() {
            assert!((band.mean[i] - 3.0).abs() < 1e-12, "mean at {i}");
            assert!((band.ci95[i] - want).abs() < 1e-9, "ci at {i}");
        }
        assert!(band.mean[3].is_nan() && band.ci95[3].is_nan());
    }

    #[test]
    fn segments_break_at_non_finite_points() {
        let band = Band {
            x: vec![0.0, 1.0, 2.0, 3.0, 4.0],
            mean: vec![1.0, f64::NAN, 2.0, 3.0, f64::INFINITY],
            ci95: vec![0.5, 0.5, f64::NAN, 1.0, 0.0],
        };
        assert_eq!(
            band.segments(),
            [
                vec![(0.0, 1.0, 0.5)],
                vec![(2.0, 2.0, 0.0), (3.0, 3.0, 1.0)]
            ]
        );
    }

    #[test]
    fn line_chart_draws_bands_lines_and_references() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("convergence.png");
        let x: Vec<f64> = (1..=30).map(f64::from).collect();
        let curve = |offset: f64| -> Vec<Vec<f64>> {
            (0..5)
                .map(|seed| {
                    x.iter()
                        .map(|e| -400.0 + offset + 8.0 * e + 20.0 * f64::from(seed))
                        .collect()
                })
                .collect()
        };
        let all = [
            series("CQL-MAML", &x, &curve(40.0)),
            // One seed: a line without a band.
            series("CQL", &x, &curve(0.0)[..1]),
        ];
        let references = [
            Reference {
                label: "online DQN".into(),
                value: -150.0,
            },
            Reference {
                label: "stalest".into(),
                value: -300.0,
            },
        ];
        let chart = LineChart {
            title: "Meta-test reward, lambda = 300",
            x_label: "epoch",
            y_label: "reward",
            series: &all,
            references: &references,
            floor: None,
        };
        line_chart(&path, &chart).unwrap();

        let image = Image::read(&path);
        assert_eq!((image.width, image.height), CHART_SIZE);
        // Each series' line and each reference's dashes in their own colour.
        for colour in &PALETTE[..4] {
            assert!(image.count(*colour) > 100, "{colour:?}");
        }
        // The first series' band: its blue, pale over white. The second has one run, so no band.
        let pale_blue = |p: &[u8; 3]| p[0] > 180 && p[0] < 250 && p[2] > p[0] + 15;
        assert!(image.rgb.iter().filter(|p| pale_blue(p)).count() > 20_000);
    }

    /// Figure 5 draws 12 methods and 6 references: each in a colour no other entry has.
    #[test]
    fn a_chart_of_eighteen_entries_draws_each_in_its_own_colour() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("many.png");
        let x: Vec<f64> = (1..=20).map(f64::from).collect();
        let all: Vec<Series> = (0..12)
            .map(|i| {
                let run = vec![x.iter().map(|e| 30.0 * f64::from(i) + e).collect()];
                series(&format!("method {i}"), &x, &run)
            })
            .collect();
        let references: Vec<Reference> = (0..6)
            .map(|j| Reference {
                label: format!("reference {j}"),
                value: -50.0 - 40.0 * f64::from(j),
            })
            .collect();
        let chart = LineChart {
            title: "eighteen",
            x_label: "epoch",
            y_label: "return",
            series: &all,
            references: &references,
            floor: None,
        };
        line_chart(&path, &chart).unwrap();
        let image = Image::read(&path);
        let colours = &PALETTE[..all.len() + references.len()];
        for (i, colour) in colours.iter().enumerate() {
            assert!(!colours[..i].contains(colour), "{colour:?} twice");
            assert!(image.count(*colour) > 50, "{colour:?}");
        }
    }

    #[test]
    fn bar_chart_draws_one_bar_per_label_and_group() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("aoi.png");
        let bar = |group: &str, label: &str, mean: f64, ci95: f64| Bar {
            group: group.into(),
            label: label.into(),
            value: Estimate { mean, ci95 },
        };
        let bars = [
            bar("cql-maml", "AoI", 5.4, 0.3),
            bar("cql-maml", "power (mW)", 0.63, 0.05),
            bar("cql", "AoI", 6.1, 0.4),
            bar("cql", "power (mW)", 0.8, 0.1),
            bar("dqn", "AoI", 9.3, 1.2),
        ];
        bar_chart(&path, "AoI and power at lambda = 300", "value", &bars).unwrap();

        let image = Image::read(&path);
        assert_eq!((image.width, image.height), CHART_SIZE);
        let (aoi, power) = (image.count(PALETTE[0]), image.count(PALETTE[1]));
        assert!(aoi > 0 && power > 0);
        // Three AoI bars against two short power bars.
        assert!(aoi > 4 * power, "AoI {aoi} px, power {power} px");
    }

    #[test]
    fn trajectory_chart_has_a_panel_per_path_and_the_rain_zone() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("trajectories.png");
        let paths = [
            (
                "CQL-MAML".to_string(),
                vec![(0, 0), (1, 0), (2, 0), (2, 1), (3, 1), (3, 2)],
            ),
            ("CQL".to_string(), vec![(9, 9), (8, 9), (8, 8), (8, 8)]),
        ];
        let chart = TrajectoryChart {
            title: "Trajectories on the rain task",
            grid_cells: 10,
            device_cells: &[(1, 1), (5, 7), (9, 0)],
            rain: Some(RainZone {
                x0: 3,
                y0: 3,
                x1: 6,
                y1: 5,
            }),
            paths: &paths,
        };
        trajectory_chart(&path, &chart).unwrap();

        let image = Image::read(&path);
        assert_eq!(image.width, 2 * PANEL_WIDTH);
        assert!(image.height > PANEL_WIDTH);
        let (left, right): (Vec<_>, Vec<_>) = image
            .rgb
            .chunks_exact(image.width as usize)
            .map(|row| row.split_at(PANEL_WIDTH as usize))
            .unzip();
        let count = |half: &[&[[u8; 3]]], c: RGBColor| {
            half.iter()
                .flat_map(|row| row.iter())
                .filter(|&&p| p == [c.0, c.1, c.2])
                .count()
        };
        // Each path in its panel only.
        assert!(count(&left, PALETTE[0]) > 100 && count(&left, PALETTE[1]) == 0);
        assert!(count(&right, PALETTE[1]) > 100 && count(&right, PALETTE[0]) == 0);
        // The rain zone's 4 x 3 cells are shaded in both panels.
        let rain = image.rgb.iter().filter(|p| p[2] > p[0] + 40).count();
        assert!(rain > 2 * 12 * 400, "{rain} rain pixels");
    }

    /// Empty and all-NaN data are not an error: the chart is written with its axes and legend
    /// and nothing in it.
    #[test]
    fn charts_without_finite_data_are_written_empty() {
        let dir = tempfile::tempdir().unwrap();
        let nan = Band {
            x: vec![1.0, 2.0],
            mean: vec![f64::NAN; 2],
            ci95: vec![f64::NAN; 2],
        };
        let empty = Band::from_runs(vec![], &[]);
        let all = [
            Series {
                label: "diverged".into(),
                band: nan,
            },
            Series {
                label: "never ran".into(),
                band: empty,
            },
        ];
        let references = [Reference {
            label: "missing".into(),
            value: f64::NAN,
        }];
        let chart = LineChart {
            title: "nothing",
            x_label: "epoch",
            y_label: "reward",
            series: &all,
            references: &references,
            floor: None,
        };
        let line = dir.path().join("line.png");
        line_chart(&line, &chart).unwrap();
        let no_series = dir.path().join("no-series.png");
        line_chart(
            &no_series,
            &LineChart {
                series: &[],
                references: &[],
                ..chart
            },
        )
        .unwrap();
        let constant = dir.path().join("constant.png");
        line_chart(
            &constant,
            &LineChart {
                series: &[series("flat", &[1.0, 2.0, 3.0], &[vec![-7.0; 3]])],
                references: &[],
                ..chart
            },
        )
        .unwrap();

        let bars = dir.path().join("bars.png");
        bar_chart(&bars, "nothing", "value", &[]).unwrap();
        let nan_bar = dir.path().join("nan-bar.png");
        let bar = Bar {
            group: "cql".into(),
            label: "AoI".into(),
            value: Estimate::from_samples([]),
        };
        bar_chart(&nan_bar, "nothing", "value", &[bar]).unwrap();

        let trajectories = dir.path().join("trajectories.png");
        let no_path = TrajectoryChart {
            title: "nothing",
            grid_cells: 4,
            device_cells: &[],
            rain: None,
            paths: &[("idle".into(), vec![])],
        };
        trajectory_chart(&trajectories, &no_path).unwrap();

        for path in [&line, &no_series, &bars, &nan_bar] {
            let image = Image::read(path);
            assert_eq!((image.width, image.height), CHART_SIZE);
            assert_eq!(image.coloured_left_half(), 0, "{}", path.display());
        }
        // The flat series is drawn, centred in a widened range.
        assert!(Image::read(&constant).count(PALETTE[0]) > 100);
        assert_eq!(Image::read(&trajectories).width, PANEL_WIDTH);
    }

    #[test]
    fn an_unwritable_path_is_an_error_naming_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("no-such-dir").join("bars.png");
        let err = bar_chart(&path, "t", "y", &[]).unwrap_err();
        assert!(
            err.to_string().starts_with(&path.display().to_string()),
            "{err}"
        );
    }

    #[test]
    fn axis_ticks_print_whole_numbers_without_decimals() {
        assert_eq!(axis_tick(10.0), "10");
        assert_eq!(axis_tick(-450.0), "-450");
        assert_eq!(axis_tick(0.25), "0.250");
    }

    #[test]
    fn values_are_printed_to_three_significant_digits() {
        let printed: Vec<String> = [0.634_21, 5.4123, -452.37, 0.0, 12_345.6]
            .into_iter()
            .map(significant)
            .collect();
        assert_eq!(printed, ["0.634", "5.41", "-452", "0.00", "12346"]);
    }
}
