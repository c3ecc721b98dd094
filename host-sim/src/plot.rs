//! SVG plots with `plotters` (SVG backend only: it writes text as SVG `<text>` and needs no system font
//! library, so it builds on a bare CI machine). Two panels: outputs against time, and the hysteresis loop
//! (output against input, per axis).

use crate::sim::SimOutput;
use plotters::prelude::*;
use std::fmt;
use std::path::Path;

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
