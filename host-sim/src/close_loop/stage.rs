//! The models `close-loop` found as stage-file axes, and their predictions through piezo-stage's
//! chain (`AxisChain::simulate`, `piezo_stage::simulate_pair` for two coupled axes): exactly the
//! code `predict` and the firmware run, from rest at the first input (`ModelState::at_rest(u0)`,
//! `EffectsState::at_rest(u0)`).
//!
//! Scores of a prediction p of a record y over its scored samples: `rms` = √(mean (y − p)²), and
//! `rms_zeroed` = √(mean (y − p − ō)²) with ō = mean(y − p), one constant offset re-estimated on the
//! record (a sensor's zero differs between runs).

use super::full::AxisModel;
use super::Outcome;
use crate::identify::Record;
use crate::stage_file::{stage_and_io, write_stage, WrittenStage};
use piezo_core::Asymmetry;
use piezo_stage::{simulate_pair, Axis, AxisChain, Limits, Provenance, StageFile, AXIS_NAMES};
use std::path::Path;

/// Slew limit written for every axis \[V/s\]: the stage file's default.
pub const SLEW_LIMIT_V_PER_S: f32 = piezo_stage::DEFAULT_SLEW_LIMIT_V_PER_S;

/// The output window for a record's input: its range rounded outwards to a tenth of the power of
/// ten below its span (0–3.6 V stays 0–3.6 V, 0.2–119.7 V gives 0–120 V).
pub fn output_window(u: &[f64]) -> (f32, f32) {
    let (lo, hi) = crate::identify::min_max(u);
    let span = (hi - lo).max(1e-9);
    let step = 10f64.powf(span.log10().floor() - 1.0);
    // A value within 1e-6 of a step is on it (0.0 stays 0, 3.6000001 is 3.6).
    let (a, b) = (
        ((lo / step + 1e-6).floor() * step) as f32,
        ((hi / step - 1e-6).ceil() * step) as f32,
    );
    if b > a {
        (a, b)
    } else {
        (lo as f32, hi as f32)
    }
}

/// The stage-file axis of a model (output window = the model's input range, slew 1e5 V/s).
pub fn stage_axis(m: &AxisModel, identified: Option<Provenance>) -> Axis {
    let mut axis = Axis::static_model(
        m.bouc_wen,
        m.map,
        Asymmetry::default(),
        Limits {
            output_min_v: m.input_range_v.0,
            output_max_v: m.input_range_v.1,
            slew_limit_v_per_s: SLEW_LIMIT_V_PER_S,
            envelope_policy: Default::default(),
        },
    );
    axis.effects = m.effects;
    axis.identified = identified;
    axis
}

/// Predicts the records' outputs \[m\] from their inputs with `models` through piezo-stage's chain
/// at the models' sample period; two axes run coupled (`simulate_pair`).
pub fn predict(models: &[&AxisModel], us: &[Vec<f32>]) -> crate::Result<Vec<Vec<f64>>> {
    let ts = models
        .first()
        .ok_or_else(|| crate::Error::Refused("no axis".into()))?
        .sample_period_s;
    let mut chains = Vec::new();
    for (m, name) in models.iter().zip(AXIS_NAMES) {
        let axis = stage_axis(m, None);
        let valid = axis.build(name, ts, m.input_range_v).map_err(|e| {
            crate::Error::Refused(format!("piezo-stage refused the {name} axis: {e}"))
        })?;
        chains.push(valid.chain);
    }
    let n = us.iter().map(Vec::len).min().unwrap_or(0);
    let mut out: Vec<Vec<f32>> = vec![vec![0.0; n]; chains.len()];
    match chains.as_slice() {
        [chain] => chain.simulate(&us[0][..n], |k, y| out[0][k] = y),
        [AxisChain::Static {
            model: mx,
            effects: ex,
        }, AxisChain::Static {
            model: my,
            effects: ey,
        }] => {
            let (ox, oy) = out.split_at_mut(1);
            simulate_pair(
                (mx, ex),
                (my, ey),
                [&us[0][..n], &us[1][..n]],
                [&mut ox[0], &mut oy[0]],
            );
        }
        _ => {
            return Err(crate::Error::Refused(
                "close-loop predicts one or two static axes".into(),
            ))
        }
    }
    Ok(out
        .into_iter()
        .map(|v| v.into_iter().map(f64::from).collect())
        .collect())
}

/// The scores of a prediction (module doc).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Fit {
    /// RMS \[m\].
    pub rms: f64,
    /// RMS with one constant offset re-estimated \[m\].
    pub rms_zeroed: f64,
    /// The offset ō = mean(y − p) \[m\].
    pub offset: f64,
    /// Largest |y − p| \[m\].
    pub max_abs: f64,
    /// Coefficient of determination.
    pub r2: f64,
}

impl Fit {
    /// The scores of `p` against `y`.
    pub fn of(y: &[f64], p: &[f64]) -> Self {
        let n = y.len().max(1) as f64;
        let r: Vec<f64> = y.iter().zip(p).map(|(a, b)| a - b).collect();
        let offset = r.iter().sum::<f64>() / n;
        let sse: f64 = r.iter().map(|v| v * v).sum();
        let mean_y = y.iter().sum::<f64>() / n;
        let sst: f64 = y.iter().map(|v| (v - mean_y).powi(2)).sum();
        Self {
            rms: (sse / n).sqrt(),
            rms_zeroed: (r.iter().map(|v| (v - offset).powi(2)).sum::<f64>() / n).sqrt(),
            offset,
            max_abs: r.iter().fold(0.0, |m, v| m.max(v.abs())),
            r2: if sst > 0.0 { 1.0 - sse / sst } else { f64::NAN },
        }
    }
}

/// One axis of a validation record with both predictions.
#[derive(Debug, Clone)]
pub struct ValidationAxis {
    /// Times of the scored samples \[s\].
    pub t_s: Vec<f64>,
    /// Input \[V\].
    pub u: Vec<f64>,
    /// Measured \[m\].
    pub y: Vec<f64>,
    /// Base model's prediction \[m\].
    pub before: Vec<f64>,
    /// Final model's prediction \[m\].
    pub after: Vec<f64>,
}

/// The prediction of another record by the base and the final model.
#[derive(Debug, Clone)]
pub struct Validation {
    /// The record.
    pub data: String,
    /// First scored time \[s\].
    pub start_s: f64,
    /// Scored samples per axis.
    pub samples: usize,
    /// Base model, all axes together.
    pub before: Fit,
    /// Final model, all axes together.
    pub after: Fit,
    /// Per axis.
    pub axes: Vec<ValidationAxis>,
}

impl Validation {
    /// For the report: the record, both models' scores and their ratios (not the series).
    pub fn report(&self) -> ValidationReport<'_> {
        ValidationReport {
            data: &self.data,
            start_s: self.start_s,
            samples: self.samples,
            before: self.before,
            after: self.after,
            ratio_rms: self.after.rms / self.before.rms,
            ratio_rms_zeroed: self.after.rms_zeroed / self.before.rms_zeroed,
        }
    }
}

/// The prediction of another record in a report ([`Validation::report`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ValidationReport<'a> {
    /// The record.
    pub data: &'a str,
    /// First scored time \[s\].
    pub start_s: f64,
    /// Scored samples per axis.
    pub samples: usize,
    /// Base model, all axes together.
    pub before: Fit,
    /// Final model, all axes together.
    pub after: Fit,
    /// RMS of the final model over that of the base.
    pub ratio_rms: f64,
    /// The same with one offset re-estimated.
    pub ratio_rms_zeroed: f64,
}

/// Both models predict `records` from their first sample (seeing only u), scored from `start_s`.
pub fn validate(outcome: &Outcome, records: &[Record], start_s: f64) -> crate::Result<Validation> {
    if records.len() != outcome.axes.len() {
        return Err(crate::Error::Refused(format!(
            "--validate: {} axes, the fit has {}",
            records.len(),
            outcome.axes.len()
        )));
    }
    let from = records[0].index_at(start_s);
    let us: Vec<Vec<f32>> = records
        .iter()
        .map(|r| r.u.iter().map(|&v| v as f32).collect())
        .collect();
    let base: Vec<&AxisModel> = outcome.axes.iter().map(|a| &a.base).collect();
    let last: Vec<&AxisModel> = outcome.axes.iter().map(|a| &a.model).collect();
    let before = predict(&base, &us)?;
    let after = predict(&last, &us)?;
    let mut axes = Vec::new();
    let (mut y, mut b, mut a) = (Vec::new(), Vec::new(), Vec::new());
    for (i, r) in records.iter().enumerate() {
        let n = before[i].len().min(r.y_m.len());
        let from = from.min(n);
        y.extend_from_slice(&r.y_m[from..n]);
        b.extend_from_slice(&before[i][from..n]);
        a.extend_from_slice(&after[i][from..n]);
        axes.push(ValidationAxis {
            t_s: r.t_s[from..n].to_vec(),
            u: r.u[from..n].to_vec(),
            y: r.y_m[from..n].to_vec(),
            before: before[i][from..n].to_vec(),
            after: after[i][from..n].to_vec(),
        });
    }
    Ok(Validation {
        data: records[0].path.display().to_string(),
        start_s,
        samples: records[0].u.len().saturating_sub(from),
        before: Fit::of(&y, &b),
        after: Fit::of(&y, &a),
        axes,
    })
}

/// The final models as stage-file axes with their provenance (x, and y for two-axis records).
pub fn final_axes(outcome: &Outcome, data: &str) -> Vec<Axis> {
    outcome
        .axes
        .iter()
        .map(|a| {
            let (lo, hi) = a.input_range_v;
            stage_axis(
                &a.model,
                Some(Provenance {
                    data: data.to_string(),
                    window_s: [outcome.window_s.0, outcome.window_s.1],
                    method: "close-loop".into(),
                    fit_rms_m: a.fit_after.rms,
                    input_range_v: [lo as f32, hi as f32],
                    sample_period_s: a.model.sample_period_s,
                    input_rate_max_v_per_s: a.envelope.0,
                    band_hz: a.envelope.1,
                }),
            )
        })
        .collect()
}

/// The comment header of the stage file of `outcome` fitted on `data`.
pub fn header(outcome: &Outcome, data: &str) -> String {
    let effects: Vec<String> = outcome
        .axes
        .iter()
        .map(|a| {
            format!(
                "{}: [{}]",
                a.name,
                a.model
                    .added
                    .iter()
                    .map(|e| e.name())
                    .collect::<Vec<_>>()
                    .join(", ")
            )
        })
        .collect();
    format!(
        "host-sim close-loop on {data} ({:.3}-{:.3} s): effects {}",
        outcome.window_s.0,
        outcome.window_s.1,
        effects.join(", ")
    )
}

/// The stage file of the final models: `[stage]` and `[io]` as given, an axis per record axis
/// (with a servo tuned on a `mode` effect, `with_servo`).
pub fn stage_file(
    outcome: &Outcome,
    data: &str,
    stage: piezo_stage::Stage,
    io: piezo_stage::Io,
) -> crate::Result<StageFile> {
    let mut axes = with_servo(&stage, &io, final_axes(outcome, data)).into_iter();
    Ok(StageFile {
        stage,
        io,
        x: axes
            .next()
            .ok_or_else(|| crate::Error::Refused("no axis to write".into()))?,
        y: axes.next(),
    })
}

/// The `[stage]` and `[io]` of the stage file for `records` (the fitted record `data`): from
/// `given` (`--stage`), or named after the record at its rate with a placeholder io chain whose
/// drive range covers the records' output windows ([`output_window`]).
pub fn stage_and_io_for(
    records: &[Record],
    data: &Path,
    given: Option<&Path>,
) -> crate::Result<(piezo_stage::Stage, piezo_stage::Io)> {
    let name = data
        .file_stem()
        .map_or("stage".into(), |s| s.to_string_lossy().to_string());
    let windows: Vec<(f32, f32)> = records.iter().map(|r| output_window(&r.u)).collect();
    let rate = 1.0
        / records
            .first()
            .ok_or_else(|| crate::Error::Refused("no record".into()))?
            .sample_period_s();
    stage_and_io(given, &name, rate, drive_range(&windows))
}

/// Writes the stage file of the final models to `path` with `[stage]` and `[io]` (from
/// [`stage_and_io_for`]) and checks it as `compensate` reads it: what was written and the
/// firmware's verdict. `Err` only for an outcome without axes.
pub fn write_stage_file(
    outcome: &Outcome,
    path: &Path,
    data: &str,
    stage: piezo_stage::Stage,
    io: piezo_stage::Io,
) -> crate::Result<WrittenStage> {
    let file = stage_file(outcome, data, stage, io)?;
    Ok(write_stage(path, &header(outcome, data), &file))
}

/// The smallest range that holds every window \[V\].
pub fn drive_range(windows: &[(f32, f32)]) -> (f32, f32) {
    windows
        .iter()
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), w| {
            (lo.min(w.0), hi.max(w.1))
        })
}

/// Whether `host-sim compensate` (and the firmware) would run `m` as an axis of a stage file at
/// `loop_rate_hz`: the axis as written ([`stage_axis`]: output window = the model's input range)
/// in a one-axis file whose io chain drives that window, checked by `StageFile::validate` (the
/// Bouc-Wen set over the window, the static map, `Compensator::new` (strictly monotone map),
/// `Effects::new` at the loop period) and `compensate`'s feed-forward axes. The io chain of the
/// file finally written is checked with it ([`crate::stage_file::Verdict`]). `Err`: the refusal.
pub fn compensator_check(m: &AxisModel, loop_rate_hz: f32) -> crate::Result<()> {
    let file = StageFile {
        stage: piezo_stage::Stage {
            name: "check".into(),
            version: "1".into(),
            loop_rate_hz,
        },
        io: piezo_stage::Io::placeholder_covering(m.input_range_v),
        x: stage_axis(m, None),
        y: None,
    };
    // As it will be written: the slew limit lowered to what the chain accepts at this rate.
    let file = crate::stage_file::with_feasible_slew(&file);
    let valid = file
        .validate()
        .map_err(|e| crate::Error::Refused(format!("`{}`: {}", e.key, e.message)))?;
    crate::compensate::feedforward_axes(&file, &valid, Path::new("the axis"))?;
    Ok(())
}

/// The axes with a feedback servo (`[x.servo]`) tuned by `host-sim servo-tune`'s rule when every
/// axis has the `mode` effect (its frequency and damping are the tuning's first mode); as they are
/// otherwise, or when the rule finds no crossover (said on stderr).
fn with_servo(stage: &piezo_stage::Stage, io: &piezo_stage::Io, axes: Vec<Axis>) -> Vec<Axis> {
    if axes.is_empty() || axes.iter().any(|a| a.effects.mode_frequency_hz <= 0.0) {
        return axes;
    }
    // Tuned as it will be written: a rate-dependent gain's slew limit lowered to the speed its
    // compensator inverts (a file at the unlowered limit is refused, and would tune nothing).
    let mut file = crate::stage_file::with_feasible_slew(&piezo_stage::StageFile {
        stage: stage.clone(),
        io: io.clone(),
        x: axes[0].clone(),
        y: axes.get(1).cloned(),
    });
    let goal = piezo_core::servo::TuningGoal::default();
    match crate::servo_tune::tune_file(
        &mut file,
        &[],
        0.0,
        &goal,
        crate::servo_tune::Latency::DEFAULT,
    ) {
        Ok(tunings) => {
            for t in &tunings {
                eprintln!(
                    "close-loop: [{}.servo] tuned on the mode effect ({:.0} Hz): crossover {:.0} Hz, \
                     phase margin {:.0}°",
                    t.axis,
                    t.dynamics.mode_frequency_hz,
                    t.tuning.crossover_hz,
                    t.tuning.phase_margin_deg
                );
            }
            let mut out = vec![file.x];
            out.extend(file.y);
            out
        }
        Err(e) => {
            let e = e.to_string();
            eprintln!(
                "close-loop: no servo written: {}",
                e.trim_start_matches(": ")
            );
            axes
        }
    }
}

/// The stage file's text of the final models with the given `[stage]` (name, version, loop rate)
/// and `[io]` (the board's converter chain).
pub fn parameter_file(
    outcome: &Outcome,
    data: &str,
    stage: piezo_stage::Stage,
    io: piezo_stage::Io,
) -> String {
    let mut axes = final_axes(outcome, data).into_iter();
    let Some(x) = axes.next() else {
        return String::new();
    };
    let file = StageFile {
        stage,
        io,
        x,
        y: axes.next(),
    };
    file.to_toml(&header(outcome, data))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The scores and a validation serialise with the keys of the report (the validation's
    /// series stay out of it).
    #[test]
    fn fits_and_validations_serialise_with_the_keys_of_the_report() {
        use crate::json_keys as keys;
        use std::collections::BTreeSet;
        let before = Fit::of(&[1.0, 2.0, 3.0], &[1.1, 2.0, 2.8]);
        let after = Fit::of(&[1.0, 2.0, 3.0], &[1.0, 2.0, 2.9]);
        let json = crate::to_json(&before).unwrap();
        assert_eq!(
            json,
            serde_json::json!({
                "rms": before.rms,
                "rms_zeroed": before.rms_zeroed,
                "offset": before.offset,
                "max_abs": before.max_abs,
                "r2": before.r2,
            })
        );
        let validation = Validation {
            data: "check.csv".into(),
            start_s: 0.25,
            samples: 3,
            before,
            after,
            axes: vec![ValidationAxis {
                t_s: vec![0.0; 3],
                u: vec![0.0; 3],
                y: vec![0.0; 3],
                before: vec![0.0; 3],
                after: vec![0.0; 3],
            }],
        };
        let json = crate::to_json(&validation.report()).unwrap();
        assert_eq!(
            keys(&json),
            BTreeSet::from([
                "data",
                "start_s",
                "samples",
                "before",
                "after",
                "ratio_rms",
                "ratio_rms_zeroed",
            ])
        );
        assert_eq!(json["ratio_rms"], after.rms / before.rms);
        assert_eq!(
            json["ratio_rms_zeroed"],
            after.rms_zeroed / before.rms_zeroed
        );
        assert_eq!(json["after"], crate::to_json(&after).unwrap());
    }
}
