//! Figures in one house style, written as SVG or PNG (chosen by the file extension).
//!
//! Every figure is drawn once, with `plotters`, as SVG text; a `.png` is that SVG rasterised by
//! `resvg` (usvg + tiny-skia, anti-aliased, pure Rust), so the two formats show the same figure. Text is
//! DejaVu Sans, embedded by the `dejavu` crate: `plotters` measures it with `ab_glyph`, `usvg` renders
//! it from the same bytes, so no system font library is needed (no fontconfig, no freetype).
//!
//! A figure is a grid of [`Panel`]s ([`plot_panels`]: one column; [`plot_grid`]: several). A panel is a
//! title, axis labels with units and [`Series`]; a series has a [`Role`] that fixes its colour in every
//! figure (measured, model, reference, residual, and one per controller mode: open-loop,
//! feed-forward, feedback, feed-forward + feedback); the reference is drawn dashed and on top of the
//! other curves, and a measured series as a broad light band under them, so that a model lying on
//! the measurement shows inside it instead of hiding it. Curves are clipped to the data area; legends sit outside it; "um" in an axis label is
//! written µm; tick labels carry the decimals their step needs and never read "−0.0".
//!
//! Panel options ([`PanelOptions`]; a [`Panel`] with options is a [`Chart`], built with the same
//! methods on either):
//! * `log_log()` / `log_x()` / `log_y()` — logarithmic axes (e.g. an amplitude spectrum), labelled in
//!   decades; non-positive values are left out.
//! * `y_range(lo, hi)` / `x_range(lo, hi)` — explicit axis ranges, e.g. to scale an error on the
//!   scored window while a transient outside it runs off the axis (clipped). Otherwise the y range
//!   covers the points inside the x range and the reference lines.
//! * `reference_line(ReferenceLine::new("noise floor", y))` — a dashed horizontal line with a legend
//!   entry.
//! * `interval(Interval::window("validation", x0, x1))` — a marked x-interval, shaded blue;
//!   `Interval::excluded("transient (not scored)", x0, x1)` shades it grey.
//! * `legend(Legend::Right | Legend::Below | Legend::None)` — where the legend goes (right by default).
//!
//! [`plot_svg`] and [`plot_simulation`] draw a simulation (outputs against time and the hysteresis
//! loop).

mod draw;
mod raster;
pub mod style;

pub use style::Role;

use crate::sim::SimOutput;
use plotters::style::FontStyle;
use std::fmt;
use std::path::Path;
use std::sync::Once;

static FONTS: Once = Once::new();

/// Registers the embedded DejaVu Sans as the `sans-serif` family for text measurement (once per
/// process).
pub fn ensure_fonts() {
    FONTS.call_once(|| {
        // The embedded TTF is valid; a failure would only leave text out of the plots.
        let _ = plotters::style::register_font(
            "sans-serif",
            FontStyle::Normal,
            dejavu::sans::regular(),
        );
        let _ = plotters::style::register_font("sans-serif", FontStyle::Bold, dejavu::sans::bold());
    });
}

/// How a series is drawn.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SeriesStyle {
    /// Connected line.
    Line,
    /// Dots with connecting line (few points, e.g. a staircase loop).
    Markers,
}

/// One named curve of a panel.
#[derive(Debug, Clone, PartialEq)]
pub struct Series {
    /// Legend entry.
    pub name: String,
    /// (x, y) points in plot units; non-finite points break the line.
    pub points: Vec<(f64, f64)>,
    /// Line or markers.
    pub style: SeriesStyle,
    /// What the curve shows (its colour); `None`: the next colour of [`Role::Other`].
    pub role: Option<Role>,
}

impl Series {
    /// A line of at most about `max_points` points: longer traces keep the smallest and the largest
    /// y of each run of consecutive points, so peaks and the noise band survive the thinning.
    pub fn line(name: impl Into<String>, points: Vec<(f64, f64)>, max_points: usize) -> Self {
        Self {
            name: name.into(),
            points: decimate(points, max_points),
            style: SeriesStyle::Line,
            role: None,
        }
    }
    /// Markers joined by a thin line.
    pub fn markers(name: impl Into<String>, points: Vec<(f64, f64)>) -> Self {
        Self {
            name: name.into(),
            points,
            style: SeriesStyle::Markers,
            role: None,
        }
    }
    /// The same series drawn in the colour (and, for [`Role::Reference`], the dashes) of `role`.
    pub fn role(mut self, role: Role) -> Self {
        self.role = Some(role);
        self
    }
}

/// Keeps the minimum and the maximum y of each run of consecutive points (in their order).
fn decimate(points: Vec<(f64, f64)>, max_points: usize) -> Vec<(f64, f64)> {
    let max_points = max_points.max(4);
    if points.len() <= max_points {
        return points;
    }
    let run = points.len().div_ceil(max_points / 2);
    let mut out = Vec::with_capacity(max_points + 2);
    for chunk in points.chunks(run) {
        let by_y = |a: &&(f64, f64), b: &&(f64, f64)| a.1.total_cmp(&b.1);
        let lo = chunk.iter().enumerate().min_by(|a, b| by_y(&a.1, &b.1));
        let hi = chunk.iter().enumerate().max_by(|a, b| by_y(&a.1, &b.1));
        if let (Some((i, &p)), Some((j, &q))) = (lo, hi) {
            match i.cmp(&j) {
                std::cmp::Ordering::Less => out.extend([p, q]),
                std::cmp::Ordering::Greater => out.extend([q, p]),
                std::cmp::Ordering::Equal => out.push(p),
            }
        }
    }
    out
}

/// One chart: title, axis labels (with units) and curves. [`Panel::log_log`], [`Panel::y_range`] and
/// the other option methods turn it into a [`Chart`].
#[derive(Debug, Clone, PartialEq)]
pub struct Panel {
    /// Caption.
    pub title: String,
    /// x-axis label.
    pub x_label: String,
    /// y-axis label.
    pub y_label: String,
    /// Curves.
    pub series: Vec<Series>,
}

/// Where a panel's legend goes; never over the data.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Legend {
    /// In a column to the right of the data area.
    #[default]
    Right,
    /// In rows below the data area.
    Below,
    /// No legend.
    None,
}

/// A dashed horizontal line across the panel, e.g. a noise floor.
#[derive(Debug, Clone, PartialEq)]
pub struct ReferenceLine {
    /// Legend entry.
    pub name: String,
    /// Height in plot units.
    pub y: f64,
}

impl ReferenceLine {
    /// A line at `y` named `name`.
    pub fn new(name: impl Into<String>, y: f64) -> Self {
        Self {
            name: name.into(),
            y,
        }
    }
}

/// How an [`Interval`] is marked.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum IntervalKind {
    /// A window that matters (validation window, scored window): shaded blue.
    Window,
    /// A stretch left out (a transient outside the scored window): shaded grey.
    Excluded,
}

/// A marked x-interval, shaded over the panel's full height.
#[derive(Debug, Clone, PartialEq)]
pub struct Interval {
    /// Legend entry.
    pub name: String,
    /// Start, in x plot units.
    pub start: f64,
    /// End, in x plot units.
    pub end: f64,
    /// Window or excluded stretch.
    pub kind: IntervalKind,
}

impl Interval {
    /// A window that matters, [start, end].
    pub fn window(name: impl Into<String>, start: f64, end: f64) -> Self {
        Self {
            name: name.into(),
            start,
            end,
            kind: IntervalKind::Window,
        }
    }
    /// A stretch left out, [start, end].
    pub fn excluded(name: impl Into<String>, start: f64, end: f64) -> Self {
        Self {
            name: name.into(),
            start,
            end,
            kind: IntervalKind::Excluded,
        }
    }
}

/// The options of a panel; the defaults give linear axes fitted to the data and a legend on the right.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct PanelOptions {
    /// Logarithmic x axis.
    pub log_x: bool,
    /// Logarithmic y axis.
    pub log_y: bool,
    /// Explicit x range; `None`: the data's.
    pub x_range: Option<(f64, f64)>,
    /// Explicit y range; `None`: the data's inside the x range, and the reference lines.
    pub y_range: Option<(f64, f64)>,
    /// Dashed horizontal lines.
    pub reference_lines: Vec<ReferenceLine>,
    /// Shaded x-intervals.
    pub intervals: Vec<Interval>,
    /// Legend position.
    pub legend: Legend,
}

/// A [`Panel`] with its [`PanelOptions`].
#[derive(Debug, Clone, PartialEq)]
pub struct Chart {
    /// Title, labels and curves.
    pub panel: Panel,
    /// Axes, marks and legend.
    pub options: PanelOptions,
}

impl From<Panel> for Chart {
    fn from(panel: Panel) -> Self {
        Self {
            panel,
            options: PanelOptions::default(),
        }
    }
}

impl Chart {
    /// Logarithmic x and y axes.
    pub fn log_log(self) -> Self {
        self.log_x().log_y()
    }
    /// Logarithmic x axis.
    pub fn log_x(mut self) -> Self {
        self.options.log_x = true;
        self
    }
    /// Logarithmic y axis.
    pub fn log_y(mut self) -> Self {
        self.options.log_y = true;
        self
    }
    /// Explicit x range.
    pub fn x_range(mut self, lo: f64, hi: f64) -> Self {
        self.options.x_range = Some((lo, hi));
        self
    }
    /// Explicit y range.
    pub fn y_range(mut self, lo: f64, hi: f64) -> Self {
        self.options.y_range = Some((lo, hi));
        self
    }
    /// Adds a dashed horizontal line.
    pub fn reference_line(mut self, line: ReferenceLine) -> Self {
        self.options.reference_lines.push(line);
        self
    }
    /// Adds a shaded x-interval.
    pub fn interval(mut self, interval: Interval) -> Self {
        self.options.intervals.push(interval);
        self
    }
    /// Sets the legend position.
    pub fn legend(mut self, legend: Legend) -> Self {
        self.options.legend = legend;
        self
    }
}

impl Panel {
    /// A panel; `series` in drawing order (a [`Role::Reference`] series is drawn last).
    pub fn new(
        title: impl Into<String>,
        x_label: impl Into<String>,
        y_label: impl Into<String>,
        series: Vec<Series>,
    ) -> Self {
        Self {
            title: title.into(),
            x_label: x_label.into(),
            y_label: y_label.into(),
            series,
        }
    }
    /// This panel with `options`.
    pub fn with_options(self, options: PanelOptions) -> Chart {
        Chart {
            panel: self,
            options,
        }
    }
    /// [`Chart::log_log`].
    pub fn log_log(self) -> Chart {
        Chart::from(self).log_log()
    }
    /// [`Chart::log_x`].
    pub fn log_x(self) -> Chart {
        Chart::from(self).log_x()
    }
    /// [`Chart::log_y`].
    pub fn log_y(self) -> Chart {
        Chart::from(self).log_y()
    }
    /// [`Chart::x_range`].
    pub fn x_range(self, lo: f64, hi: f64) -> Chart {
        Chart::from(self).x_range(lo, hi)
    }
    /// [`Chart::y_range`].
    pub fn y_range(self, lo: f64, hi: f64) -> Chart {
        Chart::from(self).y_range(lo, hi)
    }
    /// [`Chart::reference_line`].
    pub fn reference_line(self, line: ReferenceLine) -> Chart {
        Chart::from(self).reference_line(line)
    }
    /// [`Chart::interval`].
    pub fn interval(self, interval: Interval) -> Chart {
        Chart::from(self).interval(interval)
    }
    /// [`Chart::legend`].
    pub fn legend(self, legend: Legend) -> Chart {
        Chart::from(self).legend(legend)
    }
}

/// What [`plot_panels`] draws: a [`Panel`] (default options) or a [`Chart`].
pub trait AsChart {
    /// Title, labels and curves.
    fn panel(&self) -> &Panel;
    /// Axes, marks and legend.
    fn options(&self) -> &PanelOptions;
}

static DEFAULT_OPTIONS: PanelOptions = PanelOptions {
    log_x: false,
    log_y: false,
    x_range: None,
    y_range: None,
    reference_lines: Vec::new(),
    intervals: Vec::new(),
    legend: Legend::Right,
};

impl AsChart for Panel {
    fn panel(&self) -> &Panel {
        self
    }
    fn options(&self) -> &PanelOptions {
        &DEFAULT_OPTIONS
    }
}

impl AsChart for Chart {
    fn panel(&self) -> &Panel {
        &self.panel
    }
    fn options(&self) -> &PanelOptions {
        &self.options
    }
}

/// A figure's file format.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    /// `.svg`: the SVG drawn by `plotters`.
    Svg,
    /// `.png`: that SVG rasterised.
    Png,
}

impl Format {
    /// The format named by the extension of `path` (`.svg` or `.png`, any case).
    pub fn of_path(path: &Path) -> Result<Self, PlotError> {
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase);
        match ext.as_deref() {
            Some("svg") => Ok(Format::Svg),
            Some("png") => Ok(Format::Png),
            other => Err(PlotError {
                path: path.display().to_string(),
                message: format!(
                    "unknown plot format {}: the file name must end in .svg or .png",
                    other.map_or("(no extension)".to_string(), |e| format!(".{e}"))
                ),
            }),
        }
    }
}

/// Draws `panels` stacked vertically into `path` (`.svg` or `.png`).
pub fn plot_panels<P: AsChart>(path: &Path, panels: &[P]) -> Result<(), PlotError> {
    plot_grid(path, panels, 1)
}

/// Draws `panels` row by row in `columns` columns into `path` (`.svg` or `.png`).
pub fn plot_grid<P: AsChart>(path: &Path, panels: &[P], columns: usize) -> Result<(), PlotError> {
    let format = Format::of_path(path)?;
    let svg = render_svg(panels, columns).map_err(|e| failed(path, e))?;
    write(path, format, &svg).map_err(|e| failed(path, e))
}

fn failed(path: &Path, message: crate::Error) -> PlotError {
    PlotError {
        path: path.display().to_string(),
        message: format!("plotting failed: {message}"),
    }
}

/// The SVG text of `panels` in `columns` columns.
pub fn render_svg<P: AsChart>(panels: &[P], columns: usize) -> crate::Result<String> {
    ensure_fonts();
    let charts: Vec<(&Panel, &PanelOptions)> =
        panels.iter().map(|p| (p.panel(), p.options())).collect();
    draw::figure(&charts, columns.max(1))
}

/// Writes the SVG text `svg` to `path` as `format`.
fn write(path: &Path, format: Format, svg: &str) -> crate::Result<()> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(crate::Error::from)?;
    }
    let bytes = match format {
        Format::Svg => svg.as_bytes().to_vec(),
        Format::Png => raster::png(svg)?,
    };
    std::fs::write(path, bytes).map_err(crate::Error::from)
}

/// Plot errors.
#[derive(Debug, Clone, PartialEq)]
pub struct PlotError {
    /// File.
    pub path: String,
    /// What failed.
    pub message: String,
}

impl fmt::Display for PlotError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}: {}", self.path, self.message)
    }
}

impl std::error::Error for PlotError {}

/// The panels of a simulation: outputs against time (µm) and each output against its input (the
/// hysteresis loop).
pub fn simulation_panels(out: &SimOutput, title: &str) -> Vec<Chart> {
    let axis = |name: &str| name.trim_end_matches("_m").to_string();
    let role = Role::Other;
    let time = out
        .output_names
        .iter()
        .zip(&out.outputs_m)
        .enumerate()
        .map(|(i, (name, ys))| {
            let points = out.t_s.iter().zip(ys).map(|(&t, y)| (t, y * 1e6)).collect();
            Series::line(axis(name), points, 6000).role(role(i))
        })
        .collect();
    let loops = out
        .output_names
        .iter()
        .zip(&out.outputs_m)
        .enumerate()
        .filter(|_| !out.inputs_v.is_empty())
        .map(|(i, (name, ys))| {
            let us = &out.inputs_v[i.min(out.inputs_v.len() - 1)];
            let points = us.iter().zip(ys).map(|(&u, y)| (u, y * 1e6)).collect();
            Series::line(axis(name), points, 6000).role(role(i))
        })
        .collect();
    vec![
        Panel::new(
            format!("{title}: output against time"),
            "t [s]",
            "output [µm]",
            time,
        )
        .into(),
        Panel::new(
            format!("{title}: hysteresis loop"),
            "input [V]",
            "output [µm]",
            loops,
        )
        .into(),
    ]
}

/// Writes a simulation's figure ([`simulation_panels`]) to `path`, as SVG or PNG by its extension.
pub fn plot_simulation(path: &Path, out: &SimOutput, title: &str) -> Result<(), PlotError> {
    plot_panels(path, &simulation_panels(out, title))
}

/// Writes a simulation's figure ([`simulation_panels`]) to `path` as SVG, whatever its extension.
pub fn plot_svg(path: &Path, out: &SimOutput, title: &str) -> Result<(), PlotError> {
    let svg = render_svg(&simulation_panels(out, title), 1).map_err(|e| failed(path, e))?;
    write(path, Format::Svg, &svg).map_err(|e| failed(path, e))
}

/// Plot formats.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum PlotFormat {
    /// SVG only.
    Svg,
    /// PNG only (text from the embedded DejaVu font).
    Png,
    /// Both.
    Both,
}

impl PlotFormat {
    /// File extensions of the format.
    pub fn extensions(self) -> &'static [&'static str] {
        match self {
            Self::Svg => &["svg"],
            Self::Png => &["png"],
            Self::Both => &["svg", "png"],
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn thinning_keeps_the_peaks() {
        let mut pts: Vec<(f64, f64)> = (0..10_000).map(|k| (k as f64, 0.0)).collect();
        pts[5_003].1 = 7.0;
        pts[7_001].1 = -3.0;
        let s = Series::line("s", pts, 1000);
        assert!(s.points.len() <= 1002, "{}", s.points.len());
        assert!(s.points.contains(&(5_003.0, 7.0)));
        assert!(s.points.contains(&(7_001.0, -3.0)));
        assert!(s.points.windows(2).all(|w| w[0].0 < w[1].0));
    }

    #[test]
    fn format_follows_the_extension() {
        assert_eq!(Format::of_path(Path::new("a/b.SVG")), Ok(Format::Svg));
        assert_eq!(Format::of_path(Path::new("b.png")), Ok(Format::Png));
        let e = Format::of_path(Path::new("b.pdf")).unwrap_err();
        assert!(e.to_string().contains(".pdf"), "{e}");
        assert!(Format::of_path(Path::new("b")).is_err());
    }
}
