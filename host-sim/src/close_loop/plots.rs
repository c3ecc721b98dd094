//! Plots of a `close-loop` run, per axis: the residual of the base and the final model over the fit
//! window (in time, against u, its amplitude spectrum) and the loops; with `--validate`, the same
//! models' prediction of the validation window (measured and predicted in time, and the residuals).

use super::stage::ValidationAxis;
use super::{diagnose, AxisOutcome, Outcome, Validation};
use crate::identify::Record;
use crate::plot::{plot_panels, AsChart, Chart, Panel, ReferenceLine, Series};
use std::path::Path;

fn pts(x: &[f64], y: &[f64]) -> Vec<(f64, f64)> {
    x.iter().copied().zip(y.iter().copied()).collect()
}

fn um(v: &[f64]) -> Vec<f64> {
    v.iter().map(|x| x * 1e6).collect()
}

/// Writes the plots into `dir` in each of `formats` (e.g. `["svg", "png"]`); returns the files.
pub fn write_plots(
    outcome: &Outcome,
    records: &[Record],
    dir: &Path,
    formats: &[&str],
) -> crate::Result<Vec<String>> {
    std::fs::create_dir_all(dir).map_err(crate::Error::write("--plots", dir))?;
    let mut written = Vec::new();
    for (i, a) in outcome.axes.iter().enumerate() {
        let after_name = after_name(a);
        let panels = fit_panels(a, &records[i], outcome.from, &after_name);
        let stem = format!("close-loop-{}", a.name);
        write_files(dir, &stem, formats, &panels, &mut written)?;
        let Some(v) = outcome
            .validation
            .as_ref()
            .and_then(|v| v.axes.get(i).map(|x| (v, x)))
        else {
            continue;
        };
        let (validation, va) = v;
        let panels = validation_panels(a, validation, va, &after_name);
        let stem = format!("close-loop-{}-validation", a.name);
        write_files(dir, &stem, formats, &panels, &mut written)?;
    }
    Ok(written)
}

/// `panels` into `dir`/`stem`.`ext` for each of `formats`; the files are appended to `written`.
fn write_files<P: AsChart>(
    dir: &Path,
    stem: &str,
    formats: &[&str],
    panels: &[P],
    written: &mut Vec<String>,
) -> crate::Result<()> {
    for ext in formats {
        let path = dir.join(format!("{stem}.{ext}"));
        plot_panels(&path, panels).map_err(crate::Error::from)?;
        written.push(path.display().to_string());
    }
    Ok(())
}

/// The final model's name in the legends: "after (+ creep (Kelvin-Voigt, 1 element) + …)".
fn after_name(a: &AxisOutcome) -> String {
    let effects: Vec<String> = a
        .model
        .added
        .iter()
        .map(|e| {
            let form = a.model.form(*e);
            if form.is_empty() {
                e.name().to_string()
            } else {
                format!("{} ({form})", e.name())
            }
        })
        .collect();
    format!(
        "after (+ {})",
        if effects.is_empty() {
            "nothing".to_string()
        } else {
            effects.join(" + ")
        }
    )
}

/// The fit window of record `r` from sample `from`: the residual of the base and the final model in
/// time, against u and as a spectrum, and the loops.
fn fit_panels(a: &AxisOutcome, r: &Record, from: usize, after_name: &str) -> Vec<Chart> {
    let ts = r.sample_period_s();
    // The residual over the whole record \[m\]; the fit window's, from `from` on, in µm.
    let whole = |p: &[f64]| -> Vec<f64> { (0..p.len()).map(|k| r.y_m[k] - p[k]).collect() };
    let (wb, wa) = (whole(&a.before), whole(&a.after));
    let fit_um =
        |w: &[f64]| -> Vec<f64> { w[from.min(w.len())..].iter().map(|v| v * 1e6).collect() };
    let (rb, ra) = (fit_um(&wb), fit_um(&wa));
    let u: Vec<f64> = r.u[from..].to_vec();
    let spec = |v: &[f64]| -> Vec<(f64, f64)> {
        diagnose::spectrum(v, ts)
            .into_iter()
            .filter(|p| p.0 > 0.0 && p.1 > 0.0)
            .collect()
    };
    // The amplitude a white noise of the estimated σ gives in this spectrum (Hann window over
    // N samples: 2σ·√(Σw²)/Σw = σ·√(6/N)) [µm].
    let noise_floor_um = a.noise_m * 1e6 * (6.0 / rb.len().max(1) as f64).sqrt();
    // In time the whole record, its scale set by the fit window and the transient before it
    // shaded (\[m\] for the scale, drawn in µm).
    let in_um = |v: &[f64]| -> Vec<(f64, f64)> {
        r.t_s.iter().zip(v).map(|(&t, &y)| (t, y * 1e6)).collect()
    };
    vec![
        crate::track_plot::timed(
            Panel {
                title: format!("{}: residual in time (scored from the fit window)", a.name),
                x_label: "t [s]".into(),
                y_label: "residual [um]".into(),
                series: vec![
                    Series::line("before (base model)", in_um(&wb), 4000),
                    Series::line(after_name, in_um(&wa), 4000),
                ],
            },
            &r.t_s,
            from,
            &[&wb, &wa],
            1e6,
        ),
        Panel {
            title: format!("{}: residual against the input", a.name),
            x_label: "u [V]".into(),
            y_label: "residual [um]".into(),
            series: vec![
                Series::line("before", pts(&u, &rb), 4000),
                Series::line(after_name, pts(&u, &ra), 4000),
            ],
        }
        .into(),
        Panel {
            title: format!("{}: residual amplitude spectrum", a.name),
            x_label: "f [Hz]".into(),
            y_label: "amplitude [µm]".into(),
            series: vec![
                Series::line("before", spec(&rb), 1000),
                Series::line(after_name, spec(&ra), 1000),
            ],
        }
        .log_log()
        .reference_line(ReferenceLine::new(
            format!("white noise of σ = {:.3} µm", a.noise_m * 1e6),
            noise_floor_um,
        )),
        Panel {
            title: format!("{}: loops", a.name),
            x_label: "u [V]".into(),
            y_label: format!("{} [µm]", a.name),
            series: vec![
                Series::line("measured", pts(&u, &um(&r.y_m[from..])), 4000),
                Series::line("base model", pts(&u, &um(&a.before[from..])), 4000),
                Series::line(after_name, pts(&u, &um(&a.after[from..])), 4000),
            ],
        }
        .into(),
    ]
}

/// The validation window of `validation`'s axis `va`: measured and predicted in time, and the
/// residuals.
fn validation_panels(
    a: &AxisOutcome,
    validation: &Validation,
    va: &ValidationAxis,
    after_name: &str,
) -> Vec<Panel> {
    let res = |p: &[f64]| -> Vec<f64> { va.y.iter().zip(p).map(|(y, p)| (y - p) * 1e6).collect() };
    vec![
        Panel {
            title: format!(
                "{}: validation window of {} (from {} s): measured and predicted",
                a.name, validation.data, validation.start_s
            ),
            x_label: "t [s]".into(),
            y_label: "y [um]".into(),
            series: vec![
                Series::line("measured", pts(&va.t_s, &um(&va.y)), 4000),
                Series::line("base model", pts(&va.t_s, &um(&va.before)), 4000),
                Series::line(after_name, pts(&va.t_s, &um(&va.after)), 4000),
            ],
        },
        Panel {
            title: format!(
                "{}: validation residual (rms {:.4} -> {:.4} um, zeroed {:.4} -> {:.4} um)",
                a.name,
                validation.before.rms * 1e6,
                validation.after.rms * 1e6,
                validation.before.rms_zeroed * 1e6,
                validation.after.rms_zeroed * 1e6
            ),
            x_label: "t [s]".into(),
            y_label: "residual [um]".into(),
            series: vec![
                Series::line("before (base model)", pts(&va.t_s, &res(&va.before)), 4000),
                Series::line(after_name, pts(&va.t_s, &res(&va.after)), 4000),
            ],
        },
    ]
}
