//! A figure drawn with `plotters` into SVG text: a grid of panels, each a chart (linear or logarithmic
//! axes) with its legend beside or below it. Curves are clipped to the data area here, in axis
//! coordinates (log10 of the value on a logarithmic axis), because `plotters` draws a point outside
//! the ranges outside the axes.

use super::style::{self, Role};
use super::{IntervalKind, Legend, Panel, PanelOptions, Series, SeriesStyle};
use plotters::coord::ranged1d::{Ranged, ValueFormatter};
use plotters::coord::Shift;
use plotters::element::DashedPathElement;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};
use std::fmt::Display;

type Area<'a> = DrawingArea<SVGBackend<'a>, Shift>;

fn fail(e: impl Display) -> crate::Error {
    crate::Error::Draw(e.to_string())
}

/// Draws `charts` row by row in `columns` columns; returns the SVG text.
pub fn figure(charts: &[(&Panel, &PanelOptions)], columns: usize) -> crate::Result<String> {
    let columns = columns.min(charts.len()).max(1);
    let rows = charts.len().div_ceil(columns).max(1);
    let legend_width = charts
        .iter()
        .filter(|(_, o)| o.legend == Legend::Right)
        .map(|(p, o)| right_legend_width(&entries(p, o)))
        .max()
        .unwrap_or(0);
    let panel_width = style::panel_width(columns);
    let cell_width = panel_width + legend_width;
    let below_height = charts
        .iter()
        .filter(|(_, o)| o.legend == Legend::Below)
        .map(|(p, o)| flow(&entries(p, o), cell_width).1)
        .max()
        .unwrap_or(0);
    let cell_height = style::PANEL_HEIGHT + below_height;
    let size = (cell_width * columns as u32, cell_height * rows as u32);
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, size).into_drawing_area();
        root.fill(&WHITE).map_err(fail)?;
        let cells = root.split_evenly((rows, columns));
        for (cell, (panel, options)) in cells.iter().zip(charts) {
            let legend = entries(panel, options);
            let plot = match options.legend {
                Legend::Right => {
                    let (plot, side) = cell.split_horizontally(panel_width);
                    draw_right_legend(&side, &legend)?;
                    plot
                }
                Legend::Below => {
                    let (plot, below) = cell.split_vertically(style::PANEL_HEIGHT);
                    draw_below_legend(&below, &legend, cell_width)?;
                    // As wide as the panels with a legend on the right, so the x axes line up.
                    plot.split_horizontally(panel_width).0
                }
                Legend::None => cell.clone(),
            };
            chart(&plot, panel, options)?;
        }
        root.present().map_err(fail)?;
    }
    Ok(svg)
}

/// An axis: its range in data units, and whether it is logarithmic.
#[derive(Debug, Clone, Copy)]
struct Axis {
    lo: f64,
    hi: f64,
    log: bool,
}

impl Axis {
    /// The value in axis coordinates (log10 on a logarithmic axis); `None` where it cannot be drawn.
    fn axis_of(self, v: f64) -> Option<f64> {
        match (v.is_finite(), self.log) {
            (false, _) => None,
            (true, false) => Some(v),
            (true, true) => (v > 0.0).then(|| v.log10()),
        }
    }
    fn value_at(self, a: f64) -> f64 {
        if self.log {
            10f64.powf(a)
        } else {
            a
        }
    }
    fn bounds(self) -> (f64, f64) {
        if self.log {
            (self.lo.log10(), self.hi.log10())
        } else {
            (self.lo, self.hi)
        }
    }
    fn contains(self, v: f64) -> bool {
        v >= self.lo && v <= self.hi
    }
}

/// The range of `values` on a linear or logarithmic axis: 5 % padding on a linear one, whole decades on
/// a logarithmic one.
fn fit(values: impl Iterator<Item = f64>, log: bool) -> (f64, f64) {
    let (lo, hi) = values
        .filter(|v| v.is_finite() && (!log || *v > 0.0))
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
            (a.min(v), b.max(v))
        });
    if !lo.is_finite() {
        return if log { (1.0, 10.0) } else { (0.0, 1.0) };
    }
    if log {
        let lo = 10f64.powf(lo.log10().floor());
        let hi = 10f64.powf(hi.log10().ceil()).max(lo * 10.0);
        // A hair beyond the decades, so that rounding in log10 keeps them among the ticks.
        return (lo * (1.0 - 1e-9), hi * (1.0 + 1e-9));
    }
    let pad = ((hi - lo) * 0.05).max(1e-12 * (1.0 + hi.abs()));
    (lo - pad, hi + pad)
}

/// The x and y axes of a panel.
fn axes(panel: &Panel, options: &PanelOptions) -> (Axis, Axis) {
    let points = || panel.series.iter().flat_map(|s| s.points.iter().copied());
    let (x_lo, x_hi) = options
        .x_range
        .unwrap_or_else(|| fit(points().map(|p| p.0), options.log_x));
    let x = Axis {
        lo: x_lo,
        hi: x_hi,
        log: options.log_x,
    };
    let (y_lo, y_hi) = options.y_range.unwrap_or_else(|| {
        let inside = points().filter(|p| x.contains(p.0)).map(|p| p.1);
        let lines = options.reference_lines.iter().map(|l| l.y);
        fit(inside.chain(lines), options.log_y)
    });
    let y = Axis {
        lo: y_lo,
        hi: y_hi,
        log: options.log_y,
    };
    (x, y)
}

/// How one series is drawn.
#[derive(Debug, Clone, Copy)]
struct Look {
    colour: RGBColor,
    width: u32,
    dashed: bool,
    markers: bool,
}

/// The looks of a panel's series, in order; series without a role take the [`Role::Other`] colours in
/// turn.
fn looks(series: &[Series]) -> Vec<Look> {
    let mut other = 0;
    series
        .iter()
        .map(|s| {
            let role = s.role.unwrap_or_else(|| {
                other += 1;
                Role::Other(other - 1)
            });
            let markers = s.style == SeriesStyle::Markers;
            Look {
                colour: role.colour(),
                width: if markers || role == Role::Reference {
                    style::THIN_WIDTH
                } else if role == Role::Measured {
                    style::MEASURED_WIDTH
                } else {
                    style::LINE_WIDTH
                },
                dashed: role == Role::Reference,
                markers,
            }
        })
        .collect()
}

/// What a legend entry shows beside its name.
#[derive(Debug, Clone, Copy)]
enum Key {
    Series(Look),
    Line,
    Band(IntervalKind),
}

fn entries(panel: &Panel, options: &PanelOptions) -> Vec<(String, Key)> {
    let mut out: Vec<(String, Key)> = panel
        .series
        .iter()
        .zip(looks(&panel.series))
        .map(|(s, l)| (s.name.clone(), Key::Series(l)))
        .collect();
    out.extend(
        options
            .reference_lines
            .iter()
            .map(|l| (l.name.clone(), Key::Line)),
    );
    out.extend(
        options
            .intervals
            .iter()
            .map(|i| (i.name.clone(), Key::Band(i.kind))),
    );
    out.retain(|(name, _)| !name.is_empty());
    out
}

fn band_colour(kind: IntervalKind) -> RGBAColor {
    match kind {
        IntervalKind::Window => style::WINDOW_FILL.mix(0.12),
        IntervalKind::Excluded => style::EXCLUDED_FILL.mix(0.28),
    }
}

fn legend_font() -> TextStyle<'static> {
    ("sans-serif", style::LEGEND_FONT)
        .into_font()
        .color(&style::INK)
        .pos(Pos::new(HPos::Left, VPos::Center))
}

fn text_width(text: &str) -> u32 {
    ("sans-serif", style::LEGEND_FONT)
        .into_font()
        .box_size(text)
        .map_or(text.chars().count() as u32 * style::LEGEND_FONT / 2, |b| {
            b.0
        })
}

const KEY_WIDTH: u32 = style::LEGEND_SAMPLE + 12;
const ROW: u32 = style::LEGEND_FONT * 3 / 2;

fn right_legend_width(entries: &[(String, Key)]) -> u32 {
    if entries.is_empty() {
        return 0;
    }
    let widest = entries.iter().map(|e| text_width(&e.0)).max().unwrap_or(0);
    (widest + KEY_WIDTH + 2 * style::LEGEND_GAP).clamp(style::LEGEND_WIDTH.0, style::LEGEND_WIDTH.1)
}

/// `name` broken at spaces into lines of at most `width` px (a single long word stays whole).
fn wrap(name: &str, width: u32) -> Vec<String> {
    let mut lines: Vec<String> = Vec::new();
    for word in name.split(' ') {
        match lines.last_mut() {
            Some(line) if text_width(&format!("{line} {word}")) <= width => {
                line.push(' ');
                line.push_str(word);
            }
            _ => lines.push(word.to_string()),
        }
    }
    lines
}

fn draw_key(area: &Area, key: Key, x: i32, y: i32) -> crate::Result<()> {
    let len = style::LEGEND_SAMPLE as i32;
    match key {
        Key::Series(look) => {
            let line = vec![(x, y), (x + len, y)];
            let stroke = look.colour.stroke_width(look.width.max(style::LINE_WIDTH));
            if look.dashed {
                let stroke = look.colour.stroke_width(look.width);
                area.draw(&DashedPathElement::new(line, 10, 6, stroke))
                    .map_err(fail)?;
            } else {
                area.draw(&PathElement::new(line, stroke)).map_err(fail)?;
            }
            if look.markers {
                let r = style::MARKER_RADIUS as i32;
                area.draw(&Circle::new((x + len / 2, y), r, look.colour.filled()))
                    .map_err(fail)?;
            }
        }
        Key::Line => {
            let stroke = style::REFERENCE_LINE.stroke_width(style::THIN_WIDTH);
            area.draw(&DashedPathElement::new(
                vec![(x, y), (x + len, y)],
                10,
                6,
                stroke,
            ))
            .map_err(fail)?;
        }
        Key::Band(kind) => {
            let h = style::LEGEND_FONT as i32 / 2;
            area.draw(&Rectangle::new(
                [(x, y - h), (x + len, y + h)],
                band_colour(kind).filled(),
            ))
            .map_err(fail)?;
        }
    }
    Ok(())
}

fn draw_right_legend(area: &Area, entries: &[(String, Key)]) -> crate::Result<()> {
    let width = area.dim_in_pixel().0;
    let text_room = width.saturating_sub(KEY_WIDTH + 2 * style::LEGEND_GAP);
    let x = style::LEGEND_GAP as i32;
    // Level with the top of the data area (below the caption).
    let mut y = (style::TITLE_FONT + 3 * style::LEGEND_GAP) as i32;
    for (name, key) in entries {
        let lines = wrap(name, text_room);
        let first = y + ROW as i32 / 2;
        draw_key(area, *key, x, first)?;
        for (i, line) in lines.iter().enumerate() {
            let pos = (
                x + KEY_WIDTH as i32,
                first + (i as u32 * ROW * 4 / 5) as i32,
            );
            area.draw(&Text::new(line.clone(), pos, legend_font()))
                .map_err(fail)?;
        }
        y += (ROW + (lines.len() as u32 - 1) * ROW * 4 / 5) as i32;
    }
    Ok(())
}

/// The entries laid out in rows across `width`: each entry's (x, row), and the height needed.
fn flow(entries: &[(String, Key)], width: u32) -> (Vec<(u32, u32)>, u32) {
    if entries.is_empty() {
        return (Vec::new(), 0);
    }
    let left = style::LEGEND_GAP * 5;
    let (mut x, mut row) = (left, 0);
    let mut at = Vec::new();
    for (name, _) in entries {
        let w = KEY_WIDTH + text_width(name) + 2 * style::LEGEND_GAP;
        if x > left && x + w > width {
            x = left;
            row += 1;
        }
        at.push((x, row));
        x += w;
    }
    (at, (row + 1) * ROW + style::LEGEND_GAP)
}

fn draw_below_legend(area: &Area, entries: &[(String, Key)], width: u32) -> crate::Result<()> {
    let (at, _) = flow(entries, width);
    for ((name, key), (x, row)) in entries.iter().zip(at) {
        let y = (row * ROW + ROW / 2) as i32;
        draw_key(area, *key, x as i32, y)?;
        let pos = ((x + KEY_WIDTH) as i32, y);
        area.draw(&Text::new(name.clone(), pos, legend_font()))
            .map_err(fail)?;
    }
    Ok(())
}

/// The chart of one panel in `area`, on linear or logarithmic axes.
fn chart(area: &Area, panel: &Panel, options: &PanelOptions) -> crate::Result<()> {
    let (x, y) = axes(panel, options);
    let mut builder = ChartBuilder::on(area);
    builder
        .caption(
            &panel.title,
            ("sans-serif", style::TITLE_FONT)
                .into_font()
                .color(&style::INK),
        )
        .margin(style::LEGEND_GAP)
        .margin_right(style::LEGEND_GAP * 2)
        .x_label_area_size(style::AXIS_FONT * 3)
        .y_label_area_size(style::AXIS_FONT * 4 + 10);
    let (xr, yr) = (x.lo..x.hi, y.lo..y.hi);
    match (x.log, y.log) {
        (false, false) => {
            let c = builder.build_cartesian_2d(xr, yr).map_err(fail)?;
            contents(c, panel, options, x, y)
        }
        (true, false) => {
            let c = builder
                .build_cartesian_2d(xr.log_scale(), yr)
                .map_err(fail)?;
            contents(c, panel, options, x, y)
        }
        (false, true) => {
            let c = builder
                .build_cartesian_2d(xr, yr.log_scale())
                .map_err(fail)?;
            contents(c, panel, options, x, y)
        }
        (true, true) => {
            let c = builder
                .build_cartesian_2d(xr.log_scale(), yr.log_scale())
                .map_err(fail)?;
            contents(c, panel, options, x, y)
        }
    }
}

fn tick_format(axis: Axis, ticks: usize) -> Box<dyn Fn(&f64) -> String> {
    if axis.log {
        Box::new(style::log_tick_format)
    } else {
        Box::new(style::linear_tick_format((axis.lo, axis.hi), ticks))
    }
}

/// Mesh, shaded intervals, curves (the reference last), reference lines and the frame.
fn contents<X, Y>(
    mut chart: ChartContext<SVGBackend, Cartesian2d<X, Y>>,
    panel: &Panel,
    options: &PanelOptions,
    x: Axis,
    y: Axis,
) -> crate::Result<()>
where
    X: Ranged<ValueType = f64> + ValueFormatter<f64>,
    Y: Ranged<ValueType = f64> + ValueFormatter<f64>,
{
    let x_format = tick_format(x, style::X_TICKS);
    let y_format = tick_format(y, style::Y_TICKS);
    chart
        .configure_mesh()
        .x_desc(style::unit_label(&panel.x_label))
        .y_desc(style::unit_label(&panel.y_label))
        .x_labels(style::X_TICKS)
        .y_labels(style::Y_TICKS)
        .x_label_formatter(&x_format)
        .y_label_formatter(&y_format)
        .label_style(
            ("sans-serif", style::TICK_FONT)
                .into_font()
                .color(&style::INK),
        )
        .axis_desc_style(
            ("sans-serif", style::AXIS_FONT)
                .into_font()
                .color(&style::INK),
        )
        .bold_line_style(style::GRID.stroke_width(1))
        .light_line_style(TRANSPARENT)
        .axis_style(style::INK.stroke_width(2))
        .set_all_tick_mark_size(8)
        .draw()
        .map_err(fail)?;
    for i in &options.intervals {
        let (a, b) = (i.start.max(x.lo), i.end.min(x.hi));
        if a < b {
            chart
                .draw_series(std::iter::once(Rectangle::new(
                    [(a, y.lo), (b, y.hi)],
                    band_colour(i.kind).filled(),
                )))
                .map_err(fail)?;
        }
    }
    let looks = looks(&panel.series);
    let mut order: Vec<usize> = (0..panel.series.len()).collect();
    order.sort_by_key(|&i| panel.series[i].role == Some(Role::Reference));
    for i in order {
        let (s, look) = (&panel.series[i], looks[i]);
        let stroke = look.colour.stroke_width(look.width);
        for run in clip(&s.points, x, y) {
            if look.dashed {
                let (dash, gap) = style::DASH;
                chart
                    .draw_series(DashedLineSeries::new(run, dash, gap, stroke))
                    .map_err(fail)?;
            } else {
                chart
                    .draw_series(std::iter::once(PathElement::new(run, stroke)))
                    .map_err(fail)?;
            }
        }
        if look.markers {
            let inside = s
                .points
                .iter()
                .filter(|p| x.contains(p.0) && y.contains(p.1));
            chart
                .draw_series(
                    inside.map(|&p| Circle::new(p, style::MARKER_RADIUS, look.colour.filled())),
                )
                .map_err(fail)?;
        }
    }
    for line in options.reference_lines.iter().filter(|l| y.contains(l.y)) {
        let (dash, gap) = style::DASH;
        let stroke = style::REFERENCE_LINE.stroke_width(style::THIN_WIDTH);
        chart
            .draw_series(DashedLineSeries::new(
                [(x.lo, line.y), (x.hi, line.y)],
                dash,
                gap,
                stroke,
            ))
            .map_err(fail)?;
    }
    chart
        .draw_series(std::iter::once(Rectangle::new(
            [(x.lo, y.lo), (x.hi, y.hi)],
            style::INK.stroke_width(2),
        )))
        .map_err(fail)?;
    Ok(())
}

/// The polyline `points` cut to the x and y ranges: the runs that lie inside, each a polyline in data
/// units. A point that cannot be drawn (not finite, or ≤ 0 on a logarithmic axis) ends a run.
fn clip(points: &[(f64, f64)], x: Axis, y: Axis) -> Vec<Vec<(f64, f64)>> {
    let (bx, by) = (x.bounds(), y.bounds());
    let to_axis = |p: (f64, f64)| Some((x.axis_of(p.0)?, y.axis_of(p.1)?));
    let to_data = |p: (f64, f64)| (x.value_at(p.0), y.value_at(p.1));
    let mut runs = Vec::new();
    let mut run: Vec<(f64, f64)> = Vec::new();
    let mut last: Option<(f64, f64)> = None;
    let flush = |run: &mut Vec<(f64, f64)>, runs: &mut Vec<Vec<(f64, f64)>>| {
        if run.len() > 1 {
            runs.push(std::mem::take(run));
        } else {
            run.clear();
        }
    };
    for &p in points {
        let here = to_axis(p);
        match (last, here) {
            (Some(a), Some(b)) => match clip_segment(a, b, bx, by) {
                Some((c, d)) => {
                    if run.is_empty() || c != a {
                        flush(&mut run, &mut runs);
                        run.push(to_data(c));
                    }
                    run.push(to_data(d));
                    if d != b {
                        flush(&mut run, &mut runs);
                    }
                }
                None => flush(&mut run, &mut runs),
            },
            _ => flush(&mut run, &mut runs),
        }
        last = here;
    }
    flush(&mut run, &mut runs);
    runs
}

/// Liang–Barsky: the part of the segment a → b inside [x0, x1] × [y0, y1], if any.
#[allow(clippy::type_complexity)]
fn clip_segment(
    a: (f64, f64),
    b: (f64, f64),
    (x0, x1): (f64, f64),
    (y0, y1): (f64, f64),
) -> Option<((f64, f64), (f64, f64))> {
    let (dx, dy) = (b.0 - a.0, b.1 - a.1);
    let (mut t0, mut t1) = (0.0f64, 1.0f64);
    for (p, q) in [
        (-dx, a.0 - x0),
        (dx, x1 - a.0),
        (-dy, a.1 - y0),
        (dy, y1 - a.1),
    ] {
        if p == 0.0 {
            if q < 0.0 {
                return None;
            }
        } else {
            let r = q / p;
            if p < 0.0 {
                t0 = t0.max(r);
            } else {
                t1 = t1.min(r);
            }
            if t0 > t1 {
                return None;
            }
        }
    }
    let at = |t: f64| {
        if t == 0.0 {
            a
        } else if t == 1.0 {
            b
        } else {
            (a.0 + t * dx, a.1 + t * dy)
        }
    };
    Some((at(t0), at(t1)))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn axis(lo: f64, hi: f64, log: bool) -> Axis {
        Axis { lo, hi, log }
    }

    #[test]
    fn a_spike_is_cut_at_the_frame() {
        let pts = [(0.0, 0.0), (1.0, 10.0), (2.0, 0.0), (3.0, 0.5)];
        let runs = clip(&pts, axis(0.0, 3.0, false), axis(-1.0, 1.0, false));
        assert_eq!(runs.len(), 2);
        assert_eq!(runs[0], vec![(0.0, 0.0), (0.1, 1.0)]);
        assert_eq!(runs[1][0], (1.9, 1.0));
        assert_eq!(*runs[1].last().unwrap(), (3.0, 0.5));
    }

    #[test]
    fn log_axes_leave_out_non_positive_values() {
        let pts = [(1.0, 1.0), (10.0, 0.0), (100.0, 1.0), (1000.0, 10.0)];
        let runs = clip(&pts, axis(1.0, 1000.0, true), axis(0.1, 100.0, true));
        assert_eq!(runs.len(), 1);
        assert_eq!(runs[0].len(), 2);
        assert!((runs[0][1].0 - 1000.0).abs() < 1e-9);
    }

    #[test]
    fn log_ranges_are_whole_decades() {
        let near = |a: (f64, f64), b: (f64, f64)| {
            ((a.0 - b.0) / b.0).abs() < 1e-6 && ((a.1 - b.1) / b.1).abs() < 1e-6
        };
        assert!(near(fit([0.03, 7.0].into_iter(), true), (0.01, 10.0)));
        assert!(near(fit([-1.0, 0.0].into_iter(), true), (1.0, 10.0)));
    }
}
