//! `host-sim demo`: the XY flexure stage of seed 002 tracking a triangle on both axes, with and without the
//! inverse compensator of `piezo-core`.
//!
//! **Loop.** At the loop rate f_s (10 kHz) a voltage u[k] is computed per axis and held by the DAC
//! (zero-order hold) over [k/f_s, (k+1)/f_s); the plant ([`crate::plant::XyStage`], f64 Dormand–Prince,
//! its hysteresis state moved along each DAC step) is sampled at k/f_s. Both modes command one sample
//! ahead, u[k] for the reference r[k+1], since u[k] acts over the period that ends at (k+1)/f_s; the error is
//! e[k] = y[k] − r[k].
//!
//! **Uncompensated** (best linear feed-forward): u[k] = (r[k+1] − c)/g with the affine gain (g, c)
//! fitted by least squares to the plant's own response over the same motion (one extra run driven
//! with r/g0, g0 = stroke/120 V); it removes gain and offset error, so what is left is hysteresis.
//!
//! **Compensated**: per axis a [`piezo_core::Compensator`] on the static n = 1 model of the stack,
//! y = G·d·(u − h), i.e. k1 = G·d, k2 = −G·d, with the plant's own stack gain d, its Bouc-Wen α, β, γ
//! and the static gain G of the flexure (platform displacement per unit of free stack elongation,
//! ≈ 1.68). Output window 0–120 V, no slew limit.
//!
//! The core is given the output window as the model's input range
//! ([`piezo_core::BoucWen::with_input_range`]): over all states of the bounded class the unloading
//! slope at |h| = α/(β + γ) (≈ 20.9 V for x) would exceed 1 and dy/du change sign, but inside 0–120 V
//! |h| stays below the loading reach L(120 V) ≈ 13.7 V, where the map is monotone, so the core accepts
//! the plant's true set.
//!
//! Metrics skip the first `settle_s` (ringing of the first DAC step from rest).

#![allow(clippy::needless_range_loop)] // axis indices run over parallel per-axis arrays

use crate::csv::{write_csv, Table};
use crate::effects::Effects;
use crate::plant::XyStage;
use crate::plot::{plot_panels, Panel, Series};
use crate::signal::{Piecewise, Signal};
use crate::sim::{simulate, SimSettings};
use piezo_core::{
    BoucWen, BoucWenParams, Compensator, CompensatorSettings, CompensatorState, ParamError,
    StaticMap, StaticModel,
};
use std::path::Path;
use std::time::Instant;

/// Voltage window of the P-887 stacks used by both modes, V.
pub const OUTPUT_MIN_V: f64 = 0.0;
/// Upper end of the window (rated voltage), V.
pub const OUTPUT_MAX_V: f64 = 120.0;

/// Demo settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DemoSettings {
    /// Triangle frequency of the x axis, Hz.
    pub x_frequency_hz: f64,
    /// Triangle frequency of the y axis, Hz.
    pub y_frequency_hz: f64,
    /// Record length, s.
    pub duration_s: f64,
    /// Lower end of the reference, fraction of the stroke.
    pub low_fraction: f64,
    /// Upper end of the reference, fraction of the stroke.
    pub high_fraction: f64,
    /// Loop (DAC and sensor) rate, Hz.
    pub loop_rate_hz: f64,
    /// Time skipped at the start of the metrics, s.
    pub settle_s: f64,
}

impl Default for DemoSettings {
    fn default() -> Self {
        Self {
            x_frequency_hz: 2.0,
            y_frequency_hz: 1.0,
            duration_s: 2.0,
            low_fraction: 0.1,
            high_fraction: 0.9,
            loop_rate_hz: 10_000.0,
            settle_s: 0.01,
        }
    }
}

impl DemoSettings {
    /// Checks ranges; the error names the setting (as its command-line option).
    pub fn validate(&self) -> Result<(), String> {
        let pos = |name: &str, v: f64| {
            if v > 0.0 && v.is_finite() {
                Ok(())
            } else {
                Err(format!("{name}: must be positive and finite, got {v}"))
            }
        };
        pos("--x-freq", self.x_frequency_hz)?;
        pos("--y-freq", self.y_frequency_hz)?;
        pos("--duration", self.duration_s)?;
        pos("--rate", self.loop_rate_hz)?;
        if !(self.settle_s >= 0.0 && self.settle_s < self.duration_s) {
            return Err(format!(
                "--settle: must be in [0, duration), got {}",
                self.settle_s
            ));
        }
        if !(0.0 <= self.low_fraction
            && self.low_fraction < self.high_fraction
            && self.high_fraction <= 1.0)
        {
            return Err(format!(
                "--low/--high: need 0 <= low < high <= 1, got {} and {}",
                self.low_fraction, self.high_fraction
            ));
        }
        let n = (self.duration_s * self.loop_rate_hz).round();
        if !(10.0..=5e7).contains(&n) {
            return Err(format!("--duration × --rate: {n} samples, need 10 .. 5e7"));
        }
        Ok(())
    }

    fn samples(&self) -> usize {
        (self.duration_s * self.loop_rate_hz).round() as usize
    }

    fn settle_samples(&self) -> usize {
        (self.settle_s * self.loop_rate_hz).ceil() as usize
    }
}

/// Triangle between `low` and `high`, starting at `low` and rising first.
pub fn triangle(low: f64, high: f64, frequency_hz: f64, t_s: f64) -> f64 {
    let p = (t_s * frequency_hz).rem_euclid(1.0);
    let tri = if p < 0.5 { 2.0 * p } else { 2.0 - 2.0 * p };
    low + (high - low) * tri
}

/// Tracking error of one axis in one mode.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ErrorStats {
    /// RMS error, m.
    pub rms_m: f64,
    /// Largest |error|, m.
    pub max_abs_m: f64,
}

/// One mode's run.
#[derive(Debug, Clone, PartialEq)]
pub struct ModeRun {
    /// Commanded voltages per axis, V.
    pub voltage_v: [Vec<f64>; 2],
    /// Measured platform positions per axis, m.
    pub measured_m: [Vec<f64>; 2],
    /// Error statistics per axis.
    pub errors: [ErrorStats; 2],
}

/// The set the compensator of an axis was built from (the plant's own).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CompensatorSet {
    /// k1 = G·d, m/V.
    pub k1_m_per_v: f64,
    /// The plant's Bouc-Wen set, given to the core.
    pub bouc_wen: BoucWenParams,
}

/// Everything the demo measured.
#[derive(Debug, Clone, PartialEq)]
pub struct DemoResult {
    /// Settings used.
    pub settings: DemoSettings,
    /// Sample times, s.
    pub t_s: Vec<f64>,
    /// Reference per axis, m.
    pub reference_m: [Vec<f64>; 2],
    /// Platform stroke per axis (G·free stroke), m.
    pub stroke_m: [f64; 2],
    /// Fitted linear feed-forward per axis: (gain m/V, offset m).
    pub linear_fit: [(f64, f64); 2],
    /// Uncompensated run.
    pub linear: ModeRun,
    /// Compensated run.
    pub compensated: ModeRun,
    /// Compensator parameter sets per axis.
    pub compensator_sets: [CompensatorSet; 2],
    /// Wall-clock seconds of the three plant runs.
    pub plant_seconds: f64,
}

const AXES: [&str; 2] = ["x", "y"];

/// Runs the XY stage under per-axis ZOH voltages; returns the sampled platform positions.
pub fn run_xy_stage(
    stage: &XyStage,
    voltages_v: &[Vec<f64>; 2],
    loop_rate_hz: f64,
) -> Result<[Vec<f64>; 2], String> {
    let n = voltages_v[0].len();
    let times: Vec<f64> = (0..n).map(|k| k as f64 / loop_rate_hz).collect();
    let mut signals: Vec<Box<dyn Signal>> = Vec::with_capacity(2);
    for v in voltages_v {
        let zoh = Piecewise::new(times.clone(), v.clone(), true).map_err(|e| e.to_string())?;
        signals.push(Box::new(zoh));
    }
    let settings = SimSettings::new(loop_rate_hz, n as f64 / loop_rate_hz);
    let out =
        simulate(stage, signals, &Effects::default(), &settings).map_err(|e| e.to_string())?;
    let mut it = out.outputs_m.into_iter();
    match (it.next(), it.next()) {
        (Some(x), Some(y)) => Ok([x, y]),
        _ => Err("xy-stage returned fewer than two outputs".into()),
    }
}

/// Largest |h| the core may assume for the stack sets (never reached: they are bounded).
const STATE_LIMIT: f32 = 1e3;

/// The compensator of one axis from the plant's parameters, valid over the 0–120 V window.
pub fn axis_compensator(
    stage: &XyStage,
    axis: usize,
    loop_rate_hz: f64,
) -> Result<(Compensator, CompensatorSet), String> {
    let (ax, ay) = stage.axes();
    let a = if axis == 0 { ax } else { ay };
    let k1 = stage.static_gain()[axis] * stage.stack_gain_m_per_v()[axis];
    let bouc_wen = BoucWenParams {
        a: a.hysteresis.a as f32,
        beta: a.hysteresis.beta as f32,
        gamma: a.hysteresis.gamma as f32,
        n: 1.0,
    };
    let settings = CompensatorSettings {
        output_min_v: OUTPUT_MIN_V as f32,
        output_max_v: OUTPUT_MAX_V as f32,
        slew_limit_v_per_s: f32::INFINITY,
        sample_period_s: (1.0 / loop_rate_hz) as f32,
    };
    let build = || -> Result<Compensator, ParamError> {
        let bw = BoucWen::with_input_range(
            bouc_wen,
            OUTPUT_MIN_V as f32,
            OUTPUT_MAX_V as f32,
            STATE_LIMIT,
        )?;
        let map = StaticMap {
            k1_m_per_v: k1 as f32,
            k2_m_per_h: -k1 as f32,
            offset_m: 0.0,
        };
        Compensator::new(StaticModel::new(bw, map)?, settings)
    };
    let compensator =
        build().map_err(|e| format!("piezo-core refused the {} axis set: {e}", AXES[axis]))?;
    Ok((
        compensator,
        CompensatorSet {
            k1_m_per_v: k1,
            bouc_wen,
        },
    ))
}

fn error_stats(reference: &[f64], measured: &[f64], skip: usize) -> ErrorStats {
    let e: Vec<f64> = measured[skip..]
        .iter()
        .zip(&reference[skip..])
        .map(|(y, r)| y - r)
        .collect();
    let rms = (e.iter().map(|v| v * v).sum::<f64>() / e.len().max(1) as f64).sqrt();
    let max = e.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    ErrorStats {
        rms_m: rms,
        max_abs_m: max,
    }
}

/// Least-squares y[k+1] ≈ g·u[k] + c over k + 1 ≥ `skip`.
fn affine_fit(u: &[f64], y: &[f64], skip: usize) -> (f64, f64) {
    let pairs: Vec<(f64, f64)> = (skip.max(1)..y.len()).map(|k| (u[k - 1], y[k])).collect();
    let n = pairs.len() as f64;
    let (mu, my) = pairs
        .iter()
        .fold((0.0, 0.0), |(a, b), &(u, y)| (a + u / n, b + y / n));
    let (mut suu, mut suy) = (0.0, 0.0);
    for &(u, y) in &pairs {
        suu += (u - mu) * (u - mu);
        suy += (u - mu) * (y - my);
    }
    let g = suy / suu;
    (g, my - g * mu)
}

/// Runs the demo; `progress` receives one line per phase.
pub fn run_demo(
    settings: &DemoSettings,
    progress: &mut dyn FnMut(&str),
) -> Result<DemoResult, String> {
    settings.validate()?;
    let stage = XyStage::default();
    let fs = settings.loop_rate_hz;
    let n = settings.samples();
    let skip = settings.settle_samples();
    let (ax, ay) = stage.axes();
    let gains = stage.static_gain();
    let stroke_m = [gains[0] * ax.free_stroke_m, gains[1] * ay.free_stroke_m];
    let freqs = [settings.x_frequency_hz, settings.y_frequency_hz];
    let reference_at = |axis: usize, k: usize| {
        triangle(
            settings.low_fraction * stroke_m[axis],
            settings.high_fraction * stroke_m[axis],
            freqs[axis],
            k as f64 / fs,
        )
    };
    let t_s: Vec<f64> = (0..n).map(|k| k as f64 / fs).collect();
    let reference_m: [Vec<f64>; 2] =
        std::array::from_fn(|axis| (0..n).map(|k| reference_at(axis, k)).collect());
    let clamp = |u: f64| u.clamp(OUTPUT_MIN_V, OUTPUT_MAX_V);
    let started = Instant::now();

    // 1. Linear gain fit.
    progress(&format!(
        "demo [1/3] fitting the linear feed-forward ({n} samples at {fs} Hz)"
    ));
    let probe: [Vec<f64>; 2] = std::array::from_fn(|axis| {
        let g0 = stroke_m[axis] / OUTPUT_MAX_V;
        (0..n)
            .map(|k| clamp(reference_at(axis, k + 1) / g0))
            .collect()
    });
    let probe_y = run_xy_stage(&stage, &probe, fs)?;
    let linear_fit: [(f64, f64); 2] =
        std::array::from_fn(|axis| affine_fit(&probe[axis], &probe_y[axis], skip));

    // 2. Uncompensated.
    progress(&format!(
        "demo [2/3] uncompensated run ({:.1} s so far)",
        started.elapsed().as_secs_f64()
    ));
    let linear_v: [Vec<f64>; 2] = std::array::from_fn(|axis| {
        let (g, c) = linear_fit[axis];
        (0..n)
            .map(|k| clamp((reference_at(axis, k + 1) - c) / g))
            .collect()
    });
    let linear_y = run_xy_stage(&stage, &linear_v, fs)?;

    // 3. Compensated: the core computes the voltages; the plant is the truth.
    progress(&format!(
        "demo [3/3] compensated run ({:.1} s so far)",
        started.elapsed().as_secs_f64()
    ));
    let mut compensator_sets = Vec::with_capacity(2);
    let mut comp_v: [Vec<f64>; 2] = [Vec::with_capacity(n), Vec::with_capacity(n)];
    for (axis, volts) in comp_v.iter_mut().enumerate() {
        let (comp, set) = axis_compensator(&stage, axis, fs)?;
        compensator_sets.push(set);
        let mut state = CompensatorState::at_rest(0.0);
        for k in 0..n {
            let cmd = comp.compensate(&mut state, reference_at(axis, k + 1) as f32);
            volts.push(f64::from(cmd.voltage_v));
        }
    }
    let comp_y = run_xy_stage(&stage, &comp_v, fs)?;
    let plant_seconds = started.elapsed().as_secs_f64();
    progress(&format!("demo: plant runs done in {plant_seconds:.1} s"));

    let run = |voltage_v: [Vec<f64>; 2], measured_m: [Vec<f64>; 2]| {
        let errors = std::array::from_fn(|a| error_stats(&reference_m[a], &measured_m[a], skip));
        ModeRun {
            voltage_v,
            measured_m,
            errors,
        }
    };
    let linear = run(linear_v, linear_y);
    let compensated = run(comp_v, comp_y);
    Ok(DemoResult {
        settings: *settings,
        t_s,
        reference_m: reference_m.clone(),
        stroke_m,
        linear_fit,
        linear,
        compensated,
        compensator_sets: [compensator_sets[0], compensator_sets[1]],
        plant_seconds,
    })
}

impl DemoResult {
    /// The table printed by `host-sim demo`.
    pub fn table(&self) -> String {
        let mut s = String::new();
        s.push_str(&format!(
            "XY stage, triangle {:.0}–{:.0} % of stroke, x {} Hz, y {} Hz, {} s at {} Hz (metrics after {} s)\n",
            100.0 * self.settings.low_fraction,
            100.0 * self.settings.high_fraction,
            self.settings.x_frequency_hz,
            self.settings.y_frequency_hz,
            self.settings.duration_s,
            self.settings.loop_rate_hz,
            self.settings.settle_s
        ));
        s.push_str("axis  mode                      RMS [µm]  RMS [%]  max [µm]  max [%]\n");
        for axis in 0..2 {
            for (name, run) in [
                ("uncompensated (linear)", &self.linear),
                ("compensated (piezo-core)", &self.compensated),
            ] {
                let e = run.errors[axis];
                let pct = 100.0 / self.stroke_m[axis];
                s.push_str(&format!(
                    "{:<5} {:<25} {:>8.3}  {:>7.3}  {:>8.3}  {:>7.3}\n",
                    AXES[axis],
                    name,
                    e.rms_m * 1e6,
                    e.rms_m * pct,
                    e.max_abs_m * 1e6,
                    e.max_abs_m * pct
                ));
            }
        }
        s
    }

    /// The JSON summary.
    pub fn summary_json(&self) -> serde_json::Value {
        use serde_json::json;
        let axis = |a: usize| {
            let st = |r: &ModeRun| {
                let e = r.errors[a];
                json!({
                    "rms_um": e.rms_m * 1e6,
                    "max_um": e.max_abs_m * 1e6,
                    "rms_percent_of_stroke": 100.0 * e.rms_m / self.stroke_m[a],
                    "max_percent_of_stroke": 100.0 * e.max_abs_m / self.stroke_m[a],
                })
            };
            let set = &self.compensator_sets[a];
            let p = |b: &BoucWenParams| json!({"alpha": b.a, "beta": b.beta, "gamma": b.gamma, "n": b.n});
            json!({
                "stroke_um": self.stroke_m[a] * 1e6,
                "uncompensated": st(&self.linear),
                "compensated": st(&self.compensated),
                "rms_ratio_compensated_over_uncompensated":
                    self.compensated.errors[a].rms_m / self.linear.errors[a].rms_m,
                "linear_feedforward": {"gain_um_per_v": self.linear_fit[a].0 * 1e6, "offset_um": self.linear_fit[a].1 * 1e6},
                "compensator": {
                    "k1_m_per_v": set.k1_m_per_v,
                    "k2_m_per_h": -set.k1_m_per_v,
                    "bouc_wen": p(&set.bouc_wen),
                },
            })
        };
        json!({
            "plant": "xy-stage",
            "settings": {
                "x_frequency_hz": self.settings.x_frequency_hz,
                "y_frequency_hz": self.settings.y_frequency_hz,
                "duration_s": self.settings.duration_s,
                "low_fraction_of_stroke": self.settings.low_fraction,
                "high_fraction_of_stroke": self.settings.high_fraction,
                "loop_rate_hz": self.settings.loop_rate_hz,
                "settle_s": self.settings.settle_s,
                "output_window_v": [OUTPUT_MIN_V, OUTPUT_MAX_V],
            },
            "x": axis(0),
            "y": axis(1),
            "plant_seconds": self.plant_seconds,
        })
    }

    /// Writes `demo.csv`, `summary.json` and the plots (`tracking`, `error`, `loops`, in each of
    /// `formats`, e.g. `["svg", "png"]`) into `dir`. Returns the files written.
    pub fn write(&self, dir: &Path, formats: &[&str]) -> Result<Vec<String>, String> {
        std::fs::create_dir_all(dir).map_err(|e| format!("--out {}: {e}", dir.display()))?;
        let mut written = Vec::new();
        let json_path = dir.join("summary.json");
        let text = serde_json::to_string_pretty(&self.summary_json()).map_err(|e| e.to_string())?;
        std::fs::write(&json_path, text + "\n")
            .map_err(|e| format!("--out {}: {e}", json_path.display()))?;
        written.push(json_path.display().to_string());

        let mut names = vec!["t_s".to_string()];
        let mut columns = vec![self.t_s.clone()];
        for a in 0..2 {
            let ax = AXES[a];
            for (name, col) in [
                (format!("r{ax}_m"), &self.reference_m[a]),
                (format!("u{ax}_linear_V"), &self.linear.voltage_v[a]),
                (format!("{ax}_linear_m"), &self.linear.measured_m[a]),
                (
                    format!("u{ax}_compensated_V"),
                    &self.compensated.voltage_v[a],
                ),
                (
                    format!("{ax}_compensated_m"),
                    &self.compensated.measured_m[a],
                ),
            ] {
                names.push(name);
                columns.push(col.clone());
            }
        }
        let csv_path = dir.join("demo.csv");
        write_csv(
            &csv_path,
            &Table {
                path: csv_path.clone(),
                names,
                columns,
            },
        )
        .map_err(|e| format!("--out: {e}"))?;
        written.push(csv_path.display().to_string());

        let um = 1e6;
        let t = &self.t_s;
        let series_t = |name: &str, v: &[f64], scale: f64| {
            Series::line(
                name,
                t.iter().zip(v).map(|(&t, &y)| (t, y * scale)).collect(),
                4000,
            )
        };
        let mut tracking = Vec::new();
        let mut error = Vec::new();
        let mut loops = Vec::new();
        for a in 0..2 {
            let ax = AXES[a];
            tracking.push(Panel {
                title: format!("{ax} axis: reference and measured platform position"),
                x_label: "t [s]".into(),
                y_label: format!("{ax} [µm]"),
                series: vec![
                    series_t("reference", &self.reference_m[a], um),
                    series_t("uncompensated", &self.linear.measured_m[a], um),
                    series_t("compensated", &self.compensated.measured_m[a], um),
                ],
            });
            let err = |run: &ModeRun| -> Vec<f64> {
                run.measured_m[a]
                    .iter()
                    .zip(&self.reference_m[a])
                    .map(|(y, r)| y - r)
                    .collect()
            };
            error.push(Panel {
                title: format!("{ax} axis: tracking error (measured − reference)"),
                x_label: "t [s]".into(),
                y_label: "error [µm]".into(),
                series: vec![
                    series_t("uncompensated", &err(&self.linear), um),
                    series_t("compensated", &err(&self.compensated), um),
                ],
            });
            let pairs = |xs: &[f64], ys: &[f64], sx: f64, sy: f64| -> Vec<(f64, f64)> {
                xs.iter().zip(ys).map(|(&x, &y)| (x * sx, y * sy)).collect()
            };
            loops.push(Panel {
                title: format!("{ax} axis: measured against reference"),
                x_label: "reference [µm]".into(),
                y_label: "measured [µm]".into(),
                series: vec![
                    Series::line(
                        "uncompensated",
                        pairs(&self.reference_m[a], &self.linear.measured_m[a], um, um),
                        6000,
                    ),
                    Series::line(
                        "compensated",
                        pairs(
                            &self.reference_m[a],
                            &self.compensated.measured_m[a],
                            um,
                            um,
                        ),
                        6000,
                    ),
                ],
            });
            loops.push(Panel {
                title: format!("{ax} axis: drive voltage against reference"),
                x_label: "reference [µm]".into(),
                y_label: "voltage [V]".into(),
                series: vec![
                    Series::line(
                        "uncompensated",
                        pairs(&self.reference_m[a], &self.linear.voltage_v[a], um, 1.0),
                        6000,
                    ),
                    Series::line(
                        "compensated",
                        pairs(
                            &self.reference_m[a],
                            &self.compensated.voltage_v[a],
                            um,
                            1.0,
                        ),
                        6000,
                    ),
                ],
            });
        }
        for format in formats {
            for (name, panels) in [
                ("tracking", &tracking),
                ("error", &error),
                ("loops", &loops),
            ] {
                let path = dir.join(format!("{name}.{format}"));
                plot_panels(&path, panels).map_err(|e| e.to_string())?;
                written.push(path.display().to_string());
            }
        }
        Ok(written)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn triangle_starts_low_and_peaks_at_half_period() {
        assert_eq!(triangle(1.0, 3.0, 2.0, 0.0), 1.0);
        assert!((triangle(1.0, 3.0, 2.0, 0.25) - 3.0).abs() < 1e-12);
        assert!((triangle(1.0, 3.0, 2.0, 0.125) - 2.0).abs() < 1e-12);
    }

    #[test]
    fn affine_fit_recovers_a_line_with_one_sample_lag() {
        let u: Vec<f64> = (0..100).map(|k| k as f64).collect();
        let y: Vec<f64> = (0..100).map(|k| 2.0 * (k as f64 - 1.0) + 0.5).collect();
        let (g, c) = affine_fit(&u, &y, 0);
        assert!((g - 2.0).abs() < 1e-12 && (c - 0.5).abs() < 1e-9, "{g} {c}");
    }

    #[test]
    fn settings_errors_name_the_option() {
        let s = DemoSettings {
            x_frequency_hz: -1.0,
            ..Default::default()
        };
        assert!(s.validate().unwrap_err().starts_with("--x-freq"));
        let s = DemoSettings {
            low_fraction: 0.9,
            high_fraction: 0.1,
            ..Default::default()
        };
        assert!(s.validate().unwrap_err().starts_with("--low"));
    }
}
