//! The figures of a run: what `compensate --plot`, `link track --plot` and `link excite --plot`
//! draw, in [`crate::plot`]'s house style.
//!
//! Tracking ([`tracking_charts`]), one column per axis:
//! * position: the reference r (dashed, on top) and the position y — the stage file's forward
//!   model of the commanded voltages (`compensate`) or the sensor (`link track`, drawn as the
//!   measured band) — in µm;
//! * the stack voltage u commanded \[V\];
//! * the tracking error e = y − r (positive: the stage is above the reference), in µm, nm or pm
//!   as its size over the scored window needs.
//!
//! Excitation ([`excitation_charts`]), one row per axis: the commanded voltage u and the sensor y
//! against time, and the loop y against u.
//!
//! Every axis range is taken from the scored window (samples from `from` on); a transient before it
//! is shaded grey ("transient (not scored)") and runs off the axis, clipped, where it is larger.

use crate::demo::scored_range;
use crate::plot::{plot_grid, Chart, Format, Interval, Panel, Role, Series};
use std::path::Path;

/// Points kept per curve (peaks survive the thinning).
const MAX_POINTS: usize = 4000;
/// Metres to micrometres.
const UM: f64 = 1e6;

/// Refuses a figure path whose extension is not `.svg` or `.png`, naming the option `option`.
pub fn check_plot_path(option: &str, path: &Path) -> crate::Result<()> {
    Format::of_path(path)
        .map(|_| ())
        .map_err(|e| crate::Error::Usage(format!("{option} {e}")))
}

/// One axis of a tracking run.
#[derive(Debug, Clone, Copy)]
pub struct TrackAxis<'a> {
    /// `x`, `y` (or empty for a one-axis stage).
    pub name: &'a str,
    /// The reference r per sample \[m\].
    pub reference_m: &'a [f64],
    /// The position y per sample \[m\].
    pub position_m: &'a [f64],
    /// What the position is: "predicted" (a model) or "sensor" (measured).
    pub position: &'a str,
    /// The stack voltage commanded per sample \[V\].
    pub voltage_v: &'a [f64],
}

fn axis_title(name: &str) -> String {
    if name.is_empty() {
        "stage".into()
    } else {
        format!("{name} axis")
    }
}

/// The grey band over `t_s[0]..t_s[from]`, when there is one.
fn transient(t_s: &[f64], from: usize) -> Option<Interval> {
    (from > 0 && from < t_s.len())
        .then(|| Interval::excluded("transient (not scored)", t_s[0], t_s[from]))
}

/// `panel` against time over the whole record, its y range that of the traces `scaled` (SI) times
/// `scale` from sample `from` on, with the transient before it marked.
pub fn timed(panel: Panel, t_s: &[f64], from: usize, scaled: &[&[f64]], scale: f64) -> Chart {
    let (t0, t1) = (t_s[0], t_s[t_s.len() - 1]);
    let (lo, hi) = scored_range(scaled.iter().map(|v| &v[from..]), scale);
    let mut chart = Chart::from(panel).y_range(lo, hi);
    if t1 > t0 {
        chart = chart.x_range(t0, t1);
    }
    if let Some(band) = transient(t_s, from) {
        chart = chart.interval(band);
    }
    chart
}

fn in_time(t_s: &[f64], v: &[f64], scale: f64) -> Vec<(f64, f64)> {
    t_s.iter().zip(v).map(|(&t, &y)| (t, y * scale)).collect()
}

/// The tracking figure's panels: row 1 positions, row 2 voltages, row 3 errors (y − r), one column
/// per axis; `t_s` the sample times \[s\], scored from sample `from`.
pub fn tracking_charts(
    t_s: &[f64],
    axes: &[TrackAxis<'_>],
    from: usize,
) -> crate::Result<Vec<Chart>> {
    check_lengths(
        t_s,
        from,
        axes.iter()
            .flat_map(|a| [a.reference_m, a.position_m, a.voltage_v]),
    )?;
    let mut rows: [Vec<Chart>; 3] = Default::default();
    for a in axes {
        let title = axis_title(a.name);
        let unit = if a.name.is_empty() { "y" } else { a.name };
        let position_role = if a.position == "sensor" {
            Role::Measured
        } else {
            Role::Model
        };
        let position = Panel::new(
            format!("{title}: reference and {} position", a.position),
            "t [s]",
            format!("{unit} [µm]"),
            vec![
                Series::line(a.position, in_time(t_s, a.position_m, UM), MAX_POINTS)
                    .role(position_role),
                Series::line("reference", in_time(t_s, a.reference_m, UM), MAX_POINTS)
                    .role(Role::Reference),
            ],
        );
        rows[0].push(timed(
            position,
            t_s,
            from,
            &[a.position_m, a.reference_m],
            UM,
        ));
        let voltage = Panel::new(
            format!("{title}: stack voltage commanded"),
            "t [s]",
            format!("u{} [V]", a.name),
            vec![
                Series::line("stack voltage", in_time(t_s, a.voltage_v, 1.0), MAX_POINTS)
                    .role(Role::Feedforward),
            ],
        );
        rows[1].push(timed(voltage, t_s, from, &[a.voltage_v], 1.0));
        let error: Vec<f64> = a
            .position_m
            .iter()
            .zip(a.reference_m)
            .map(|(y, r)| y - r)
            .collect();
        let (scale, label) = error_unit(&error[from..]);
        let panel = Panel::new(
            format!("{title}: tracking error ({} − reference)", a.position),
            "t [s]",
            format!("{unit} error [{label}]"),
            vec![
                Series::line("tracking error", in_time(t_s, &error, scale), MAX_POINTS)
                    .role(Role::Residual),
            ],
        );
        rows[2].push(timed(panel, t_s, from, &[&error], scale));
    }
    Ok(rows.into_iter().flatten().collect())
}

/// The unit an error `e` \[m\] is drawn in: µm from 1 µm of largest magnitude on, nm from 1 nm,
/// pm below (so that its tick labels stay short); (metres to the unit, its name).
fn error_unit(e: &[f64]) -> (f64, &'static str) {
    let largest = e
        .iter()
        .filter(|v| v.is_finite())
        .fold(0.0f64, |m, v| m.max(v.abs()));
    if largest >= 1e-6 {
        (UM, "µm")
    } else if largest >= 1e-9 {
        (1e9, "nm")
    } else {
        (1e12, "pm")
    }
}

/// One axis of an excitation run.
#[derive(Debug, Clone, Copy)]
pub struct ExciteAxis<'a> {
    /// `x` or `y`.
    pub name: &'a str,
    /// The stack voltage commanded per sample \[V\].
    pub voltage_v: &'a [f64],
    /// The sensor's reading per sample \[m\].
    pub sensor_m: &'a [f64],
}

/// The excitation figure's panels: per axis (a row each) the commanded voltage, the sensor and
/// the loop sensor against voltage.
pub fn excitation_charts(t_s: &[f64], axes: &[ExciteAxis<'_>]) -> crate::Result<Vec<Chart>> {
    check_lengths(t_s, 0, axes.iter().flat_map(|a| [a.voltage_v, a.sensor_m]))?;
    let mut charts = Vec::new();
    for a in axes {
        let title = axis_title(a.name);
        let voltage = Panel::new(
            format!("{title}: stack voltage commanded"),
            "t [s]",
            format!("u{} [V]", a.name),
            vec![
                Series::line("commanded", in_time(t_s, a.voltage_v, 1.0), MAX_POINTS)
                    .role(Role::Reference),
            ],
        );
        charts.push(timed(voltage, t_s, 0, &[a.voltage_v], 1.0));
        let sensor = Panel::new(
            format!("{title}: sensor"),
            "t [s]",
            format!("{} [µm]", a.name),
            vec![
                Series::line("sensor", in_time(t_s, a.sensor_m, UM), MAX_POINTS)
                    .role(Role::Measured),
            ],
        );
        charts.push(timed(sensor, t_s, 0, &[a.sensor_m], UM));
        let loop_points = a
            .voltage_v
            .iter()
            .zip(a.sensor_m)
            .map(|(&u, &y)| (u, y * UM))
            .collect();
        charts.push(
            Panel::new(
                format!("{title}: loop (sensor against commanded voltage)"),
                format!("u{} [V]", a.name),
                format!("{} [µm]", a.name),
                vec![Series::line("sensor", loop_points, MAX_POINTS).role(Role::Measured)],
            )
            .into(),
        );
    }
    Ok(charts)
}

/// Every trace as long as `t_s`, at least two samples, and `from` before the last.
fn check_lengths<'a>(
    t_s: &[f64],
    from: usize,
    traces: impl Iterator<Item = &'a [f64]>,
) -> crate::Result<()> {
    if t_s.len() < 2 || from + 1 >= t_s.len() {
        return Err(crate::Error::Usage(format!(
            "{} samples scored from sample {from}: nothing to draw",
            t_s.len()
        )));
    }
    for v in traces {
        if v.len() != t_s.len() {
            return Err(crate::Error::Usage(format!(
                "a trace of {} samples against {} times",
                v.len(),
                t_s.len()
            )));
        }
    }
    Ok(())
}

/// Writes `charts` to `path` (SVG or PNG by its extension) in `columns` columns; errors name
/// `option`.
pub fn write_figure(
    option: &str,
    path: &Path,
    charts: &[Chart],
    columns: usize,
) -> crate::Result<()> {
    plot_grid(path, charts, columns).map_err(|e| crate::Error::Usage(format!("{option} {e}")))
}
