//! `predict`: runs a stage file's model on a record, exactly as the firmware runs it, and scores it.
//!
//! Per axis the chain is piezo-stage's (`AxisChain`: piezo-core's `StaticModel` then
//! `effects::Effects`, or the dynamic model), built at the record's sample period, from rest at the
//! record's first input (`ModelState::at_rest(u0)`, `EffectsState::at_rest(u0)`); two static axes
//! run together with their coupling (`piezo_stage::simulate_pair`). The model sees only u.
//!
//! Input range: the Bouc-Wen state is validated over the hull of the output window, the
//! identified input range and the record's input range, so a bounded set (β + γ > 0) is never
//! clamped to the range it was identified on. A set that is only bounded over a finite range
//! (β + γ ≤ 0) and cannot be extended to the record's range is built over its own range and the
//! input is clamped there; either way the report says how many samples leave the identified range
//! and how far (`outside_identified_range`).
//!
//! Each axis's report names the effects its chain ran (`effects_ran`, [`effects_ran`]): every
//! effect of the stage file's `[x.effects]` with a non-zero part, named and in the form
//! `close-loop` reports (creep "Kelvin-Voigt, 2 elements" or "logarithmic", drift "linear" or
//! "exponential settling", dynamics "stack-driven", rate-dependent hysteresis "input lag",
//! "relaxation" or "spread relaxation"); none for the dynamic and oscillator models, which run without effects.

use super::model::from_axis;
use super::{check_finite, fit_block, min_max, oscillator, FitBlock, Record};
use crate::csv::{write_csv, Table};
use crate::plot::{plot_grid, Chart, Panel, Role, Series};
use crate::track_plot::timed;
use piezo_stage::{simulate_pair, Axis, AxisChain, Check, ModelKind, StageFile};
use serde_json::{json, Value};
use std::path::Path;

/// Where an axis's input left the identified range.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RangeExcursion {
    /// The identified input range \[V\].
    pub identified_v: (f64, f64),
    /// Samples outside it.
    pub samples: usize,
    /// Share of the samples outside it.
    pub fraction: f64,
    /// Largest distance outside it \[V\].
    pub max_v: f64,
    /// Whether the model had to clamp the input (a set bounded only over its range).
    pub clamped: bool,
}

/// One axis's prediction.
#[derive(Debug, Clone)]
pub struct AxisPrediction {
    /// `x` or `y`.
    pub axis: &'static str,
    /// The model family.
    pub model: ModelKind,
    /// Predicted output per sample \[m\].
    pub predicted_m: Vec<f64>,
    /// The fit block over the scored samples.
    pub fit: FitBlock,
    /// Where the input left the identified range.
    pub excursion: RangeExcursion,
    /// The samples whose input left the identified envelope (range or rate), as the firmware
    /// counts them at the record's sample period (`piezo_core::EnvelopeMonitor::count`);
    /// `None` without `[x.identified]`.
    pub envelope: Option<piezo_core::EnvelopeCounts>,
    /// The effects the axis's chain ran: (name, form), as [`effects_ran`] lists them.
    pub effects_ran: Vec<(&'static str, String)>,
}

/// The effects a static axis with the effect parameters `e` runs, in the chain's order, each
/// as (name, form) with the names and forms of `close-loop`'s report (form empty when the effect
/// has one form): creep (Kelvin-Voigt with N elements of gain gᵢ ≠ 0, and/or logarithmic,
/// g_log ≠ 0), drift (linear, rate ≠ 0; exponential settling, A_d ≠ 0), delay (≠ 0), asymmetry
/// (the even term, e ≠ 0), dynamics (f_mode ≠ 0; "stack-driven" when ρ > 0), coupling (κ ≠ 0),
/// rate-dependent hysteresis (input lag τ_v ≠ 0; relaxation, some g_wᵢ ≠ 0, "spread" when W > 0;
/// rate-dependent gain c ≠ 0, alone or "… and rate-dependent gain" beside another form).
pub fn effects_ran(e: &piezo_core::effects::EffectParams) -> Vec<(&'static str, String)> {
    let mut out: Vec<(&'static str, String)> = Vec::new();
    let elements = e.creep_gain_m_per_v.iter().filter(|&&g| g != 0.0).count();
    if elements > 0 {
        let plural = if elements > 1 { "s" } else { "" };
        out.push(("creep", format!("Kelvin-Voigt, {elements} element{plural}")));
    }
    if e.log_creep_gain_m_per_v != 0.0 {
        out.push(("creep", "logarithmic".into()));
    }
    if e.drift_rate_m_per_s != 0.0 {
        out.push(("drift", "linear".into()));
    }
    if e.drift_settling_m != 0.0 {
        out.push(("drift", "exponential settling".into()));
    }
    if e.delay_s != 0.0 {
        out.push(("delay", String::new()));
    }
    if e.even_coefficient_m_per_v2 != 0.0 {
        out.push(("asymmetry", String::new()));
    }
    if e.mode_frequency_hz != 0.0 {
        let form = if e.mode_relative_damping > 0.0 {
            "stack-driven"
        } else {
            ""
        };
        out.push(("dynamics", form.into()));
    }
    if e.coupling != 0.0 {
        out.push(("coupling", String::new()));
    }
    if e.hysteresis_lag_s != 0.0 {
        out.push(("rate-dependent hysteresis", "input lag".into()));
    }

    if e.relaxation_gain.iter().any(|&g| g != 0.0) {
        let form = if e.relaxation_spread_decades > 0.0 {
            "spread relaxation"
        } else {
            "relaxation"
        };
        out.push(("rate-dependent hysteresis", form.into()));
    }
    if e.hysteresis_rate_gain_s_per_v != 0.0 {
        // Beside another form, as close-loop names it ("input lag and rate-dependent gain").
        match out.last_mut() {
            Some((name, form)) if *name == "rate-dependent hysteresis" => {
                form.push_str(" and rate-dependent gain");
            }
            _ => out.push(("rate-dependent hysteresis", "rate-dependent gain".into())),
        }
    }
    out
}

/// `name (form)`, or `name` without a form: as `close-loop` labels an effect.
pub fn effect_label((name, form): &(&'static str, String)) -> String {
    if form.is_empty() {
        (*name).to_string()
    } else {
        format!("{name} ({form})")
    }
}

fn identified_range(axis: &Axis) -> (f64, f64) {
    match &axis.identified {
        Some(p) => (f64::from(p.input_range_v[0]), f64::from(p.input_range_v[1])),
        None => (
            f64::from(axis.limits.output_min_v),
            f64::from(axis.limits.output_max_v),
        ),
    }
}

/// Builds `axis` for `record`: over the hull of window, identified and record ranges when the core
/// accepts it, else over its own ranges (the input is then clamped there).
fn build_for(
    stage: &ReadStage,
    name: &'static str,
    axis: &Axis,
    record: &Record,
) -> crate::Result<(piezo_stage::ValidAxis, bool)> {
    let t = record.sample_period_s() as f32;
    let (ilo, ihi) = identified_range(axis);
    let own = (
        ilo.min(f64::from(axis.limits.output_min_v)) as f32,
        ihi.max(f64::from(axis.limits.output_max_v)) as f32,
    );
    let (rlo, rhi) = min_max(&record.u);
    let hull = (own.0.min(rlo as f32), own.1.max(rhi as f32));
    match axis.build(name, t, hull) {
        Ok(v) => Ok((v, false)),
        Err(_) => axis
            .build(name, t, own)
            .map(|v| (v, hull != own))
            .map_err(|e| {
                crate::Error::Usage(format!(
                    "--params: {} (axis {name} built at the sample period {t} s of {})",
                    e.located(&stage.name, &stage.text),
                    record.path.display()
                ))
            }),
    }
}

/// Predicts every axis of `stage` on `records` (one per axis, same length), scored from `from`;
/// every predicted sample must be finite.
pub fn predict_axes(
    stage: &ReadStage,
    records: &[Record],
    from: usize,
) -> crate::Result<Vec<AxisPrediction>> {
    let axes = stage.file.axes();
    if records.len() != axes.len() {
        return Err(crate::Error::Usage(format!(
            "--params has {} axis(es), the record {}: give one --u/--y column per axis",
            axes.len(),
            records.len()
        )));
    }
    let mut built = Vec::new();
    for ((name, axis), record) in axes.iter().zip(records) {
        let (valid, clamped) = build_for(stage, name, axis, record)?;
        let (ilo, ihi) = identified_range(axis);
        let outside: Vec<f64> = record
            .u
            .iter()
            .map(|&u| (ilo - u).max(u - ihi).max(0.0))
            .filter(|&d| d > 1e-9 * (ihi - ilo).abs().max(1e-12))
            .collect();
        let excursion = RangeExcursion {
            identified_v: (ilo, ihi),
            samples: outside.len(),
            fraction: outside.len() as f64 / record.u.len() as f64,
            max_v: outside.iter().copied().fold(0.0, f64::max),
            clamped,
        };
        built.push((*name, axis, valid, excursion));
    }
    let us: Vec<Vec<f32>> = records
        .iter()
        .map(|r| r.u.iter().map(|&v| v as f32).collect())
        .collect();
    let n = us[0].len();
    let mut predicted: Vec<Vec<f64>> = vec![vec![0.0; n]; us.len()];
    let pair = match (built.first(), built.get(1)) {
        (Some((_, _, a, _)), Some((_, _, b, _))) => match (a.chain, b.chain) {
            (
                AxisChain::Static {
                    model: mx,
                    effects: ex,
                },
                AxisChain::Static {
                    model: my,
                    effects: ey,
                },
            ) => Some(((mx, ex), (my, ey))),
            _ => None,
        },
        _ => None,
    };
    if let Some(((mx, ex), (my, ey))) = pair {
        if us[1].len() != n {
            return Err(crate::Error::Usage(
                "the two axes' records differ in length".into(),
            ));
        }
        let mut ox = vec![0.0f32; n];
        let mut oy = vec![0.0f32; n];
        simulate_pair((&mx, &ex), (&my, &ey), [&us[0], &us[1]], [&mut ox, &mut oy]);
        predicted[0] = ox.iter().map(|&v| f64::from(v)).collect();
        predicted[1] = oy.iter().map(|&v| f64::from(v)).collect();
    } else {
        for (i, (_, axis, valid, _)) in built.iter().enumerate() {
            if axis.model == ModelKind::Oscillator {
                let r = &records[i];
                let set = from_axis(axis, r.sample_period_s() as f32, (0.0, 0.0))?;
                predicted[i] = oscillator::predict(&set, r)?;
            } else {
                let p = &mut predicted[i];
                valid.chain.simulate(&us[i], |k, y| p[k] = f64::from(y));
            }
        }
    }
    built
        .into_iter()
        .zip(predicted)
        .zip(records)
        .map(|(((axis, a, _, excursion), predicted_m), r)| {
            let named = |e: super::NonFinite| {
                crate::Error::Usage(format!(
                    "{axis}: {} on {}: {e}",
                    a.model.name(),
                    r.path.display()
                ))
            };
            check_finite(&r.t_s, &r.y_m, &predicted_m, 0).map_err(named)?;
            let envelope = a
                .envelope()
                .and_then(|e| {
                    e.monitor(a.limits.envelope_policy, r.sample_period_s() as f32)
                        .ok()
                })
                .map(|m| m.count(r.u.iter().map(|&v| v as f32)));
            let effects_ran = match a.model {
                ModelKind::Dynamic | ModelKind::Oscillator => Vec::new(),
                _ => effects_ran(&a.effects),
            };
            Ok(AxisPrediction {
                effects_ran,
                envelope,
                axis,
                model: a.model,
                fit: fit_block(&r.t_s, &r.y_m, &predicted_m, from).map_err(named)?,
                predicted_m,
                excursion,
            })
        })
        .collect()
}

/// JSON of one axis's prediction.
pub fn axis_json(p: &AxisPrediction) -> Value {
    let e = &p.excursion;
    json!({
        "axis": p.axis,
        "model": p.model.name(),
        "fit": p.fit,
        "outside_identified_range": {
            "identified_v": [e.identified_v.0, e.identified_v.1],
            "samples": e.samples,
            "fraction": e.fraction,
            "max_v": e.max_v,
            "clamped": e.clamped,
        },
        "envelope": p.envelope,
        "effects_ran": effects_json(&p.effects_ran),
    })
}

/// `[{"effect": name, "form": form}, …]` of [`effects_ran`].
pub fn effects_json(effects: &[(&'static str, String)]) -> Value {
    json!(effects
        .iter()
        .map(|(name, form)| json!({"effect": name, "form": form}))
        .collect::<Vec<_>>())
}

/// Writes `t_s`, then per axis input, measured, predicted and residual (`u_V,measured_m,…` for one
/// axis; `ux_V,x_measured_m,…,uy_V,y_measured_m,…` for two).
pub fn write_series(path: &Path, records: &[Record], axes: &[AxisPrediction]) -> crate::Result<()> {
    let mut names = vec!["t_s".to_string()];
    let mut columns = vec![records[0].t_s.clone()];
    for (r, p) in records.iter().zip(axes) {
        let (u, prefix) = if axes.len() == 1 {
            ("u_V".to_string(), String::new())
        } else {
            (format!("u{}_V", p.axis), format!("{}_", p.axis))
        };
        names.extend([
            u,
            format!("{prefix}measured_m"),
            format!("{prefix}predicted_m"),
            format!("{prefix}residual_m"),
        ]);
        columns.extend([
            r.u.clone(),
            r.y_m.clone(),
            p.predicted_m.clone(),
            r.y_m
                .iter()
                .zip(&p.predicted_m)
                .map(|(y, q)| y - q)
                .collect(),
        ]);
    }
    let table = Table {
        path: path.into(),
        names,
        columns,
    };
    write_csv(path, &table).map_err(|e| crate::Error::Usage(format!("--out: {e}")))
}

/// The figure of a prediction, three panels per axis in a row: measured and predicted against
/// time (the measurement a light band, the prediction drawn over it), the loops (scored samples,
/// from `from` on) and the residual (measured − predicted) against time. The time panels show the
/// whole record with the samples before `from` shaded grey as the transient (not scored), and
/// take their y range from the scored samples only, so a start-up transient runs off the axis
/// instead of squeezing the scored part.
pub fn prediction_charts(records: &[Record], axes: &[AxisPrediction], from: usize) -> Vec<Chart> {
    let mut charts = Vec::new();
    for (r, p) in records.iter().zip(axes) {
        let um = 1e6;
        let time = |v: &[f64]| -> Vec<(f64, f64)> {
            r.t_s.iter().zip(v).map(|(&t, &y)| (t, y * um)).collect()
        };
        let residual: Vec<f64> = r
            .y_m
            .iter()
            .zip(&p.predicted_m)
            .map(|(y, q)| y - q)
            .collect();
        let label = format!("{} [µm]", p.axis);
        charts.push(timed(
            Panel::new(
                format!("{}: measured and predicted", p.axis),
                "t [s]",
                label.clone(),
                vec![
                    Series::line("measured", time(&r.y_m), 4000).role(Role::Measured),
                    Series::line("predicted", time(&p.predicted_m), 4000).role(Role::Model),
                ],
            ),
            &r.t_s,
            from,
            &[&r.y_m, &p.predicted_m],
            um,
        ));
        let scored = |y: &[f64]| -> Vec<(f64, f64)> {
            r.u[from..]
                .iter()
                .zip(&y[from..])
                .map(|(&u, &y)| (u, y * um))
                .collect()
        };
        charts.push(
            Panel::new(
                format!("{}: loops", p.axis),
                "u [V]",
                label,
                vec![
                    Series::line("measured", scored(&r.y_m), 4000).role(Role::Measured),
                    Series::line("predicted", scored(&p.predicted_m), 4000).role(Role::Model),
                ],
            )
            .into(),
        );
        charts.push(timed(
            Panel::new(
                format!("{}: residual (measured − predicted)", p.axis),
                "t [s]",
                format!("{} residual [µm]", p.axis),
                vec![Series::line("residual", time(&residual), 4000).role(Role::Residual)],
            ),
            &r.t_s,
            from,
            &[&residual],
            um,
        ));
    }
    charts
}

/// Writes [`prediction_charts`] as `dir`/`name`.svg and .png; returns the files.
pub fn write_plots(
    dir: &Path,
    name: &str,
    records: &[Record],
    axes: &[AxisPrediction],
    from: usize,
) -> crate::Result<Vec<String>> {
    std::fs::create_dir_all(dir).map_err(crate::Error::write("--plots", dir))?;
    let charts = prediction_charts(records, axes, from);
    let mut written = Vec::new();
    for ext in ["svg", "png"] {
        let path = dir.join(format!("{name}.{ext}"));
        plot_grid(&path, &charts, 3).map_err(crate::Error::from)?;
        written.push(path.display().to_string());
    }
    Ok(written)
}

/// A stage file as read for prediction: its name and text (for located errors) and its tables.
#[derive(Debug, Clone)]
pub struct ReadStage {
    /// The file, as named in errors.
    pub name: String,
    /// Its text.
    pub text: String,
    /// Its tables, validated with [`Check::Models`].
    pub file: StageFile,
}

/// Reads and validates a stage file for prediction ([`Check::Models`]: every value the
/// firmware's check reads; errors name the file, line, column and key).
pub fn read_stage(path: &Path) -> crate::Result<ReadStage> {
    let name = path.display().to_string();
    let text = std::fs::read_to_string(path).map_err(crate::Error::read("--params", path))?;
    ReadStage::parse(name, text).map_err(|e| crate::Error::Usage(format!("--params: {e}")))
}

impl ReadStage {
    /// Parses and validates the text of a stage file named `name` ([`Check::Models`]); the error
    /// names the file, line, column and key.
    pub fn parse(name: String, text: String) -> crate::Result<Self> {
        let file = StageFile::parse(&name, &text).map_err(crate::Error::from)?;
        file.validate_with(Check::Models)
            .map_err(|e| crate::Error::from(e.located(&name, &text)))?;
        Ok(ReadStage { name, text, file })
    }

    /// Why the firmware's check ([`Check::Firmware`]) would still refuse the file (a static set
    /// that is not invertible, an output window beyond the drive span), located; `None` when it
    /// accepts it.
    pub fn firmware_refusal(&self) -> Option<String> {
        self.file
            .validate()
            .err()
            .map(|e| e.located(&self.name, &self.text).to_string())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::plot::IntervalKind;

    /// The time panels show the whole record with the transient before the scored window shaded
    /// grey, and their y range is the scored samples' (a 1 mm start-up jump runs off the axis).
    #[test]
    fn prediction_plots_scale_on_the_scored_window_and_mark_the_transient() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../firmware/params/xy-stage.toml");
        let stage = read_stage(&path).unwrap();
        let n = 400;
        let t_s: Vec<f64> = (0..n).map(|k| k as f64 / 20_000.0).collect();
        let u: Vec<f64> = t_s
            .iter()
            .map(|t| 60.0 - 60.0 * (2.0 * std::f64::consts::PI * 50.0 * t).cos())
            .collect();
        let from = 100;
        let y_m: Vec<f64> = (0..n)
            .map(|k| if k < from { 1e-3 } else { 20e-6 })
            .collect();
        let records: Vec<Record> = (0..2)
            .map(|_| Record::from_parts("r.csv".into(), t_s.clone(), u.clone(), y_m.clone()))
            .collect();
        let axes = predict_axes(&stage, &records, from).unwrap();
        let charts = prediction_charts(&records, &axes, from);
        assert_eq!(charts.len(), 6);
        for i in [0, 2, 3, 5] {
            let o = &charts[i].options;
            assert_eq!(
                o.x_range,
                Some((t_s[0], t_s[n - 1])),
                "{}",
                charts[i].panel.title
            );
            let band = &o.intervals[0];
            assert_eq!(band.kind, IntervalKind::Excluded);
            assert_eq!((band.start, band.end), (t_s[0], t_s[from]));
            let (lo, hi) = o.y_range.unwrap();
            assert!(
                hi < 500.0 && lo > -500.0,
                "{}: {lo}..{hi} µm",
                charts[i].panel.title
            );
            // The whole record is drawn, the transient too.
            assert_eq!(charts[i].panel.series[0].points.len(), n);
        }
        let measured = &charts[0].panel.series;
        assert_eq!(
            (measured[0].role, measured[1].role),
            (Some(Role::Measured), Some(Role::Model))
        );
        // The loops: scored samples only.
        assert_eq!(charts[1].panel.series[0].points.len(), n - from);
    }
}
