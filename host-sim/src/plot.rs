//! Plots with `plotters`, as SVG or PNG (chosen by the file extension).
//!
//! Text is laid out and rasterised with `ab_glyph` from the DejaVu Sans font that the `dejavu` crate
//! embeds in the binary, so neither backend needs a system font library (no fontconfig, no freetype):
//! the plots build and render on a bare CI machine. [`plot_svg`] draws a simulation (outputs against
//! time and the hysteresis loop); [`plot_panels`] draws any stack of [`Panel`]s.

use crate::sim::SimOutput;
use plotters::coord::Shift;
use plotters::prelude::*;
use std::fmt;
use std::path::Path;
use std::sync::Once;

static FONTS: Once = Once::new();

/// Registers the embedded DejaVu Sans as the `sans-serif` family (once per process).
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
    /// (x, y) points in plot units.
    pub points: Vec<(f64, f64)>,
    /// Line or markers.
    pub style: SeriesStyle,
}

impl Series {
    /// A line, decimated to at most `max_points` points by taking every k-th point.
    pub fn line(name: impl Into<String>, points: Vec<(f64, f64)>, max_points: usize) -> Self {
        let stride = points.len().div_ceil(max_points.max(2)).max(1);
        let points = if stride > 1 {
            points.into_iter().step_by(stride).collect()
        } else {
            points
        };
        Self {
            name: name.into(),
            points,
            style: SeriesStyle::Line,
        }
    }
    /// Markers joined by a thin line.
    pub fn markers(name: impl Into<String>, points: Vec<(f64, f64)>) -> Self {
        Self {
            name: name.into(),
            points,
            style: SeriesStyle::Markers,
        }
    }
}

/// One chart: title, axis labels (with units) and curves.
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

const PALETTE: [RGBColor; 6] = [
    RGBColor(31, 119, 180),
    RGBColor(214, 39, 40),
    RGBColor(44, 160, 44),
    RGBColor(255, 127, 14),
    RGBColor(148, 103, 189),
    RGBColor(0, 0, 0),
];

/// Draws `panels` stacked vertically into `path` (`.png` → bitmap, anything else → SVG).
pub fn plot_panels(path: &Path, panels: &[Panel]) -> Result<(), PlotError> {
    ensure_fonts();
    let err = |e: &dyn fmt::Display| PlotError {
        path: path.display().to_string(),
        message: e.to_string(),
    };
    create_parent(path).map_err(|e| err(&e))?;
    let size = (1000, 380 * panels.len().max(1) as u32);
    let is_png = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("png"));
    if is_png {
        let root = BitMapBackend::new(path, size).into_drawing_area();
        draw_panels(&root, panels).map_err(|e| err(&e))?;
        root.present().map_err(|e| err(&e))
    } else {
        let root = SVGBackend::new(path, size).into_drawing_area();
        draw_panels(&root, panels).map_err(|e| err(&e))?;
        root.present().map_err(|e| err(&e))
    }
}

fn draw_panels<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    panels: &[Panel],
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    root.fill(&WHITE)?;
    let areas = root.split_evenly((panels.len().max(1), 1));
    for (area, panel) in areas.iter().zip(panels) {
        let xr = range(
            panel
                .series
                .iter()
                .flat_map(|s| s.points.iter().map(|p| p.0)),
        );
        let yr = range(
            panel
                .series
                .iter()
                .flat_map(|s| s.points.iter().map(|p| p.1)),
        );
        let mut chart = ChartBuilder::on(area)
            .caption(&panel.title, ("sans-serif", 18))
            .margin(10)
            .x_label_area_size(40)
            .y_label_area_size(70)
            .build_cartesian_2d(xr.0..xr.1, yr.0..yr.1)?;
        chart
            .configure_mesh()
            .x_desc(panel.x_label.as_str())
            .y_desc(panel.y_label.as_str())
            .label_style(("sans-serif", 13))
            .draw()?;
        for (i, s) in panel.series.iter().enumerate() {
            let c = PALETTE[i % PALETTE.len()];
            let width = if s.style == SeriesStyle::Markers {
                1
            } else {
                2
            };
            chart
                .draw_series(LineSeries::new(
                    s.points.iter().copied(),
                    c.stroke_width(width),
                ))?
                .label(s.name.clone())
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], c.stroke_width(2))
                });
            if s.style == SeriesStyle::Markers {
                chart.draw_series(s.points.iter().map(|&p| Circle::new(p, 3, c.filled())))?;
            }
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .label_font(("sans-serif", 13))
            .draw()?;
    }
    Ok(())
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
        write!(f, "{}: plotting failed: {}", self.path, self.message)
    }
}

impl std::error::Error for PlotError {}

fn range(v: impl Iterator<Item = f64>) -> (f64, f64) {
    let (lo, hi) = v.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), x| {
        (a.min(x), b.max(x))
    });
    if !lo.is_finite() || !hi.is_finite() {
        return (0.0, 1.0);
    }
    let pad = ((hi - lo) * 0.05).max(1e-12 * (1.0 + hi.abs()));
    (lo - pad, hi + pad)
}

const COLOURS: [RGBColor; 2] = [RGBColor(31, 119, 180), RGBColor(214, 39, 40)];

/// Writes an SVG with the time series (top) and the y-vs-u loops (bottom). Outputs are drawn in µm.
pub fn plot_svg(path: &Path, out: &SimOutput, title: &str) -> Result<(), PlotError> {
    let err = |e: &dyn fmt::Display| PlotError {
        path: path.display().to_string(),
        message: e.to_string(),
    };
    ensure_fonts();
    create_parent(path).map_err(|e| err(&e))?;
    let root = SVGBackend::new(path, (900, 900)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(&e))?;
    let (top, bottom) = root.split_vertically(450);
    let micro = |v: &f64| v * 1e6;
    let t_range = range(out.t_s.iter().copied());
    let y_range = range(out.outputs_m.iter().flatten().map(micro));
    let mut chart = ChartBuilder::on(&top)
        .caption(format!("{title}: output vs time"), ("sans-serif", 18))
        .margin(10)
        .x_label_area_size(35)
        .y_label_area_size(60)
        .build_cartesian_2d(t_range.0..t_range.1, y_range.0..y_range.1)
        .map_err(|e| err(&e))?;
    chart
        .configure_mesh()
        .x_desc("t [s]")
        .y_desc("output [µm]")
        .draw()
        .map_err(|e| err(&e))?;
    for (i, (name, ys)) in out.output_names.iter().zip(&out.outputs_m).enumerate() {
        let c = COLOURS[i % 2];
        chart
            .draw_series(LineSeries::new(
                out.t_s.iter().zip(ys).map(|(&t, y)| (t, micro(y))),
                c,
            ))
            .map_err(|e| err(&e))?
            .label(name.clone())
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], c));
    }
    chart
        .configure_series_labels()
        .border_style(BLACK)
        .draw()
        .map_err(|e| err(&e))?;
    let u_range = range(out.inputs_v.iter().flatten().copied());
    let mut chart = ChartBuilder::on(&bottom)
        .caption(format!("{title}: hysteresis loop"), ("sans-serif", 18))
        .margin(10)
        .x_label_area_size(35)
        .y_label_area_size(60)
        .build_cartesian_2d(u_range.0..u_range.1, y_range.0..y_range.1)
        .map_err(|e| err(&e))?;
    chart
        .configure_mesh()
        .x_desc("input [V]")
        .y_desc("output [µm]")
        .draw()
        .map_err(|e| err(&e))?;
    for (i, ys) in out.outputs_m.iter().enumerate() {
        let us = &out.inputs_v[i.min(out.inputs_v.len() - 1)];
        let c = COLOURS[i % 2];
        chart
            .draw_series(LineSeries::new(
                us.iter().zip(ys).map(|(&u, y)| (u, micro(y))),
                c,
            ))
            .map_err(|e| err(&e))?;
    }
    root.present().map_err(|e| err(&e))?;
    Ok(())
}

/// Creates the directory a plot goes into, if it has one and it is missing.
fn create_parent(path: &Path) -> std::io::Result<()> {
    match path.parent().filter(|d| !d.as_os_str().is_empty()) {
        Some(dir) => std::fs::create_dir_all(dir),
        None => Ok(()),
    }
}
