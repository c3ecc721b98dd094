//! `host-sim demo`: the whole story on the XY flexure stage of seed 002 carrying creep that no model
//! declares — identify, compensate, find the residual, add the effect, compensate again.
//!
//! 1. **Identification experiment.** Both axes are driven with a raised cosine 0–120 V (1 Hz on x,
//!    0.7 Hz on y) for `identify_s`; the plant (f64 [`crate::plant::XyStage`], with creep and sensor
//!    noise as host-sim effects) is recorded.
//! 2. **close-loop** ([`crate::close_loop`]) fits the symmetric Bouc-Wen model per axis (firmware-
//!    invertible sets only), diagnoses its residual, adds the effects it finds and refits.
//! 3. **Tracking** a triangle per axis, three ways: the best linear feed-forward; piezo-core's
//!    compensator with the identified base model; the same with the effects close-loop added (their
//!    inverse chain, [`piezo_core::effects`], before the compensator). The plant is the truth.
//!
//! **Loop.** At the loop rate f_s (10 kHz) a voltage u\[k\] is computed per axis and held by the DAC
//! (zero-order hold) over \[k/f_s, (k+1)/f_s); the plant is sampled at k/f_s. The identification record
//! pairs u\[k\] with y\[k+1\] (the sample its hold reaches), and every mode commands one sample ahead, u\[k\]
//! for the reference r\[k+1\]; the error is e\[k\] = y\[k\] − r\[k\].
//!
//! **Uncompensated** (best linear feed-forward): u\[k\] = (r\[k+1\] − c)/g with the affine gain (g, c)
//! fitted by least squares to the plant's own response over the same motion (one extra run driven
//! with r/g0, g0 = stroke/120 V); it removes gain and offset error, so what is left is hysteresis
//! and creep.
//!
//! Output window 0–120 V, no slew limit. Metrics skip the first `settle_s`.

#![allow(clippy::needless_range_loop)] // axis indices run over parallel per-axis arrays

use crate::close_loop::full::AxisModel;
use crate::close_loop::{close_loop, CloseLoopSettings, Outcome};
use crate::csv::{write_csv, Table};
use crate::effects::Effects;
use crate::identify::Record;
use crate::plant::XyStage;
use crate::plot::{plot_grid, Chart, Interval, Legend, Panel, Role, Series};
use crate::signal::{Piecewise, Signal};
use crate::sim::{simulate, SimSettings};
use piezo_core::effects::{EffectParams, Effects as CoreEffects};
use piezo_core::inverse_chain::{compensate_pair, FeedforwardAxis};
use piezo_core::{
    BoucWen, BoucWenParams, Compensator, CompensatorSettings, ParamError, StaticMap, StaticModel,
};
use std::path::Path;
use std::time::Instant;

/// Voltage window of the P-887 stacks used by every mode, V.
pub const OUTPUT_MIN_V: f64 = 0.0;
/// Upper end of the window (rated voltage), V.
pub const OUTPUT_MAX_V: f64 = 120.0;

/// The effects the demo's plant carries and no model declares (host-sim effect specs).
pub const DEFAULT_PLANT_EFFECTS: [&str; 2] = [
    "creep:tau=0.1/1,weight=0.02/0.02",
    "noise:rms_m=2e-9,seed=11",
];

/// Demo settings.
#[derive(Debug, Clone, PartialEq)]
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
    /// Length of the identification experiment, s.
    pub identify_s: f64,
    /// Effects of the plant (host-sim specs), undeclared to every model.
    pub plant_effects: Vec<String>,
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
            identify_s: 3.0,
            plant_effects: DEFAULT_PLANT_EFFECTS
                .iter()
                .map(|s| s.to_string())
                .collect(),
        }
    }
}

impl DemoSettings {
    /// Checks ranges; the error names the setting (as its command-line option).
    pub fn validate(&self) -> crate::Result<()> {
        let pos = |name: &str, v: f64| {
            if v > 0.0 && v.is_finite() {
                Ok(())
            } else {
                Err(crate::Error::Usage(format!(
                    "{name}: must be positive and finite, got {v}"
                )))
            }
        };
        pos("--x-freq", self.x_frequency_hz)?;
        pos("--y-freq", self.y_frequency_hz)?;
        pos("--duration", self.duration_s)?;
        pos("--rate", self.loop_rate_hz)?;
        pos("--identify", self.identify_s)?;
        if !(self.settle_s >= 0.0 && self.settle_s < self.duration_s) {
            return Err(crate::Error::Usage(format!(
                "--settle: must be in [0, duration), got {}",
                self.settle_s
            )));
        }
        if !(0.0 <= self.low_fraction
            && self.low_fraction < self.high_fraction
            && self.high_fraction <= 1.0)
        {
            return Err(crate::Error::Usage(format!(
                "--low/--high: need 0 <= low < high <= 1, got {} and {}",
                self.low_fraction, self.high_fraction
            )));
        }
        for (name, seconds) in [
            ("--duration", self.duration_s),
            ("--identify", self.identify_s),
        ] {
            let n = (seconds * self.loop_rate_hz).round();
            if !(10.0..=5e7).contains(&n) {
                return Err(crate::Error::Usage(format!(
                    "{name} × --rate: {n} samples, need 10 .. 5e7"
                )));
            }
        }
        self.effects()?;
        Ok(())
    }

    fn effects(&self) -> crate::Result<Effects> {
        let mut e = Effects::default();
        for spec in &self.plant_effects {
            e.add_spec(spec)
                .map_err(|err| crate::Error::Usage(format!("--plant-effect {spec}: {err}")))?;
        }
        Ok(e)
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

/// Everything the demo measured.
#[derive(Debug, Clone)]
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
    /// Compensated with the identified base model.
    pub base: ModeRun,
    /// Compensated with the base model and the effects close-loop added.
    pub closed: ModeRun,
    /// The close-loop outcome on the identification record.
    pub close_loop: Outcome,
    /// Wall-clock seconds of the whole demo.
    pub seconds: f64,
}

const AXES: [&str; 2] = ["x", "y"];

/// Runs the XY stage under per-axis ZOH voltages with `effects`; returns the sampled platform
/// positions.
pub fn run_xy_stage(
    stage: &XyStage,
    voltages_v: &[Vec<f64>; 2],
    loop_rate_hz: f64,
    effects: &Effects,
) -> crate::Result<[Vec<f64>; 2]> {
    let n = voltages_v[0].len();
    let times: Vec<f64> = (0..n).map(|k| k as f64 / loop_rate_hz).collect();
    let mut signals: Vec<Box<dyn Signal>> = Vec::with_capacity(2);
    for v in voltages_v {
        let zoh = Piecewise::new(times.clone(), v.clone(), true).map_err(crate::Error::from)?;
        signals.push(Box::new(zoh));
    }
    let settings = SimSettings::new(loop_rate_hz, n as f64 / loop_rate_hz);
    let out = simulate(stage, signals, effects, &settings).map_err(crate::Error::from)?;
    let mut it = out.outputs_m.into_iter();
    match (it.next(), it.next()) {
        (Some(x), Some(y)) => Ok([x, y]),
        _ => Err(crate::Error::Usage(
            "xy-stage returned fewer than two outputs".into(),
        )),
    }
}

// The largest |h| the core may assume (never reached by the stack sets: they are bounded).
use piezo_core::STATE_LIMIT;

/// The compensator of one axis from the plant's own stack parameters, valid over 0–120 V (used by the
/// benches: the model-matched case).
pub fn axis_compensator(
    stage: &XyStage,
    axis: usize,
    loop_rate_hz: f64,
) -> crate::Result<(Compensator, BoucWenParams)> {
    let (ax, ay) = stage.axes();
    let a = if axis == 0 { ax } else { ay };
    let k1 = stage.static_gain()[axis] * stage.stack_gain_m_per_v()[axis];
    let bouc_wen = BoucWenParams {
        a: a.hysteresis.a as f32,
        beta: a.hysteresis.beta as f32,
        gamma: a.hysteresis.gamma as f32,
        n: 1.0,
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
        Compensator::new(StaticModel::new(bw, map)?, window(loop_rate_hz))
    };
    let compensator = build().map_err(|e| {
        crate::Error::Refused(format!(
            "piezo-core refused the {} axis set: {e}",
            AXES[axis]
        ))
    })?;
    Ok((compensator, bouc_wen))
}

fn window(loop_rate_hz: f64) -> CompensatorSettings {
    CompensatorSettings {
        limits: piezo_core::Limits::new(OUTPUT_MIN_V as f32, OUTPUT_MAX_V as f32, f32::INFINITY),
        sample_period_s: (1.0 / loop_rate_hz) as f32,
    }
}

/// The compensator of an identified axis model (its hysteresis part) over 0–120 V.
fn model_compensator(m: &AxisModel, loop_rate_hz: f64) -> crate::Result<Compensator> {
    let (model, _) = m.build()?;
    Compensator::new(model, window(loop_rate_hz)).map_err(|e| {
        crate::Error::Refused(format!(
            "piezo-core's compensator refused the identified set: {e}"
        ))
    })
}

/// Feed-forward voltages for the references `r[k+1]` of both axes with the identified models: the
/// firmware's per-tick chain (`piezo_core::inverse_chain::compensate_pair`, from rest at 0 V); with
/// `effects`, the inverse of the effects close-loop added (coupling by the exact 2×2 inverse,
/// then per axis delay, drift, mode, creep and even term) before each compensator.
fn compensate(
    models: [&AxisModel; 2],
    reference_m: &[Vec<f64>; 2],
    loop_rate_hz: f64,
    effects: bool,
) -> crate::Result<[Vec<f64>; 2]> {
    let n = reference_m[0].len();
    // u[k] is for r[k+1]: the reference one sample ahead, its last sample held.
    let ahead: [Vec<f32>; 2] = std::array::from_fn(|a| {
        (0..n)
            .map(|k| reference_m[a][(k + 1).min(n - 1)] as f32)
            .collect()
    });
    let axis = |a: usize| -> crate::Result<FeedforwardAxis> {
        let m = models[a];
        let params = if effects {
            m.effects
        } else {
            EffectParams::default()
        };
        Ok(FeedforwardAxis {
            compensator: model_compensator(m, loop_rate_hz)?,
            effects: CoreEffects::new(
                params,
                m.sample_period_s,
                piezo_core::effects::OperatingRange {
                    input_v: m.input_range_v,
                    output_m: m.w_range_m,
                },
            )
            .map_err(|e| {
                crate::Error::Refused(format!(
                    "piezo-core refused the {} axis effects: {e}",
                    AXES[a]
                ))
            })?,
            rest_v: OUTPUT_MIN_V as f32,
        })
    };
    let (x, y) = (axis(0)?, axis(1)?);
    let mut ux = vec![0.0f32; n];
    let mut uy = vec![0.0f32; n];
    compensate_pair([&x, &y], [&ahead[0], &ahead[1]], [&mut ux, &mut uy]);
    Ok([ux, uy].map(|u| u.into_iter().map(f64::from).collect()))
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
) -> crate::Result<DemoResult> {
    settings.validate()?;
    let plant_effects = settings.effects()?;
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
    let elapsed = |started: &Instant| started.elapsed().as_secs_f64();

    // 1. Identification experiment (and, alongside, the probe of the linear feed-forward).
    let n_id = (settings.identify_s * fs).round() as usize;
    progress(&format!(
        "demo [1/5] identification experiment: raised cosines 0-120 V, {} s at {fs} Hz, plant with {}",
        settings.identify_s,
        settings.plant_effects.join(" and ")
    ));
    let id_u = identification_input(n_id, fs);
    let probe: [Vec<f64>; 2] = std::array::from_fn(|axis| {
        let g0 = stroke_m[axis] / OUTPUT_MAX_V;
        (0..n)
            .map(|k| clamp(reference_at(axis, k + 1) / g0))
            .collect()
    });
    let (id_y, probe_y) = std::thread::scope(|s| {
        let id = s.spawn(|| run_xy_stage(&stage, &id_u, fs, &plant_effects));
        let pr = run_xy_stage(&stage, &probe, fs, &plant_effects);
        (
            id.join()
                .unwrap_or(Err(crate::Error::Panicked("identification run"))),
            pr,
        )
    });
    let (id_y, probe_y) = (id_y?, probe_y?);

    // 2. close-loop on the record: u[k] paired with y[k+1], the sample its hold reaches.
    progress(&format!(
        "demo [2/5] close-loop: identify the base model, diagnose the residual, add effects ({:.1} s so far)",
        elapsed(&started)
    ));
    let outcome = close_loop_on_record(&id_u, &id_y, fs, progress)?;

    // 3. Uncompensated.
    progress(&format!(
        "demo [3/5] uncompensated run ({:.1} s so far)",
        elapsed(&started)
    ));
    let linear_fit: [(f64, f64); 2] =
        std::array::from_fn(|axis| affine_fit(&probe[axis], &probe_y[axis], skip));
    let linear_v: [Vec<f64>; 2] = std::array::from_fn(|axis| {
        let (g, c) = linear_fit[axis];
        (0..n)
            .map(|k| clamp((reference_at(axis, k + 1) - c) / g))
            .collect()
    });
    // 4 and 5. Compensated with the base model, then with the effects added.
    progress(&format!(
        "demo [4/5] compensated runs: identified base model, and base model + effects ({:.1} s so far)",
        elapsed(&started)
    ));
    let bases = [&outcome.axes[0].base, &outcome.axes[1].base];
    let finals = [&outcome.axes[0].model, &outcome.axes[1].model];
    let base_v = compensate(bases, &reference_m, fs, false)?;
    let closed_v = compensate(finals, &reference_m, fs, true)?;
    let [linear_y, base_y, closed_y] =
        run_in_parallel(&stage, [&linear_v, &base_v, &closed_v], fs, &plant_effects)?;
    let seconds = elapsed(&started);
    progress(&format!("demo [5/5] done in {seconds:.1} s"));

    let run = |voltage_v: [Vec<f64>; 2], measured_m: [Vec<f64>; 2]| {
        let errors = std::array::from_fn(|a| error_stats(&reference_m[a], &measured_m[a], skip));
        ModeRun {
            voltage_v,
            measured_m,
            errors,
        }
    };
    Ok(DemoResult {
        settings: settings.clone(),
        t_s,
        reference_m: reference_m.clone(),
        stroke_m,
        linear_fit,
        linear: run(linear_v, linear_y),
        base: run(base_v, base_y),
        closed: run(closed_v, closed_y),
        close_loop: outcome,
        seconds,
    })
}

/// The identification experiment's voltages: raised cosines 0–120 V, x at 1 Hz, y at 0.7 Hz.
fn identification_input(n_id: usize, fs: f64) -> [Vec<f64>; 2] {
    let id_freqs = [1.0, 0.7];
    std::array::from_fn(|a| {
        (0..n_id)
            .map(|k| {
                let t = k as f64 / fs;
                60.0 - 60.0 * (2.0 * std::f64::consts::PI * id_freqs[a] * t).cos()
            })
            .collect()
    })
}

/// The identification records close-loop reads: u\[k\] paired with y\[k+1\], the sample its
/// hold reaches.
fn identification_records(id_u: &[Vec<f64>; 2], id_y: &[Vec<f64>; 2], fs: f64) -> Vec<Record> {
    let n_id = id_u[0].len();
    (0..2)
        .map(|a| {
            Record::from_parts(
                format!("demo identification record, {} axis", AXES[a]).into(),
                (0..n_id - 1).map(|k| k as f64 / fs).collect(),
                id_u[a][..n_id - 1].to_vec(),
                id_y[a][1..].to_vec(),
            )
        })
        .collect()
}

/// close-loop (firmware-invertible base sets) on the identification record; the effects it added
/// to each axis go to `progress`.
fn close_loop_on_record(
    id_u: &[Vec<f64>; 2],
    id_y: &[Vec<f64>; 2],
    fs: f64,
    progress: &mut dyn FnMut(&str),
) -> crate::Result<Outcome> {
    let records = identification_records(id_u, id_y, fs);
    let outcome = close_loop(
        &records,
        &CloseLoopSettings {
            invertible: true,
            ..Default::default()
        },
    )?;
    for a in &outcome.axes {
        progress(&format!(
            "demo       {} axis: effects added [{}]",
            a.name,
            effect_names(&a.model)
        ));
    }
    Ok(outcome)
}

/// The names of the effects close-loop added to an axis, comma-separated.
fn effect_names(model: &AxisModel) -> String {
    model
        .added
        .iter()
        .map(|e| e.name())
        .collect::<Vec<_>>()
        .join(", ")
}

/// Three runs of the plant, in parallel: the measured positions of each.
fn run_in_parallel(
    stage: &XyStage,
    voltages_v: [&[Vec<f64>; 2]; 3],
    fs: f64,
    effects: &Effects,
) -> crate::Result<[[Vec<f64>; 2]; 3]> {
    let [a, b, c] = voltages_v;
    let (ya, yb, yc) = std::thread::scope(|s| {
        let ha = s.spawn(|| run_xy_stage(stage, a, fs, effects));
        let hb = s.spawn(|| run_xy_stage(stage, b, fs, effects));
        let yc = run_xy_stage(stage, c, fs, effects);
        let join = |h: std::thread::ScopedJoinHandle<'_, crate::Result<[Vec<f64>; 2]>>| {
            h.join().unwrap_or(Err(crate::Error::Panicked("plant run")))
        };
        (join(ha), join(hb), yc)
    });
    Ok([ya?, yb?, yc?])
}

impl DemoResult {
    fn modes(&self) -> [(&'static str, &ModeRun); 3] {
        [
            ("uncompensated (linear)", &self.linear),
            ("compensated, base model", &self.base),
            ("compensated, + effects", &self.closed),
        ]
    }

    fn effects_of(&self, axis: usize) -> String {
        let names: Vec<&str> = self.close_loop.axes[axis]
            .model
            .added
            .iter()
            .map(|e| e.name())
            .collect();
        if names.is_empty() {
            "none".into()
        } else {
            names.join(", ")
        }
    }

    /// The table printed by `host-sim demo`.
    pub fn table(&self) -> String {
        let mut s = String::new();
        s.push_str(&format!(
            "XY stage with undeclared {}\n\
             close-loop on the identification record: model RMS {:.4} -> {:.4} µm; effects added: x [{}], y [{}]\n",
            self.settings.plant_effects.join(" and "),
            self.close_loop.before.rms * 1e6,
            self.close_loop.after.rms * 1e6,
            self.effects_of(0),
            self.effects_of(1),
        ));
        s.push_str(&format!(
            "tracking: triangle {:.0}–{:.0} % of stroke, x {} Hz, y {} Hz, {} s at {} Hz (metrics after {} s)\n",
            100.0 * self.settings.low_fraction,
            100.0 * self.settings.high_fraction,
            self.settings.x_frequency_hz,
            self.settings.y_frequency_hz,
            self.settings.duration_s,
            self.settings.loop_rate_hz,
            self.settings.settle_s
        ));
        s.push_str("axis  mode                       RMS [µm]  RMS [%]  max [µm]  max [%]\n");
        for axis in 0..2 {
            for (name, run) in self.modes() {
                let e = run.errors[axis];
                let pct = 100.0 / self.stroke_m[axis];
                s.push_str(&format!(
                    "{:<5} {:<25} {:>9.4}  {:>7.3}  {:>8.3}  {:>7.3}\n",
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

    /// `summary.json`: the settings, the error per axis in each mode, the close-loop report.
    pub fn summary(&self) -> Summary<'_> {
        let axis = |a: usize| {
            let st = |r: &ModeRun| {
                let e = r.errors[a];
                ModeError {
                    rms_um: e.rms_m * 1e6,
                    max_um: e.max_abs_m * 1e6,
                    rms_percent_of_stroke: 100.0 * e.rms_m / self.stroke_m[a],
                    max_percent_of_stroke: 100.0 * e.max_abs_m / self.stroke_m[a],
                }
            };
            AxisSummary {
                stroke_um: self.stroke_m[a] * 1e6,
                uncompensated: st(&self.linear),
                compensated_base_model: st(&self.base),
                compensated_with_effects: st(&self.closed),
                rms_ratio_with_effects_over_base: self.closed.errors[a].rms_m
                    / self.base.errors[a].rms_m,
                rms_ratio_base_over_uncompensated: self.base.errors[a].rms_m
                    / self.linear.errors[a].rms_m,
                linear_feedforward: LinearFeedforward {
                    gain_um_per_v: self.linear_fit[a].0 * 1e6,
                    offset_um: self.linear_fit[a].1 * 1e6,
                },
                effects_added: self.close_loop.axes[a]
                    .model
                    .added
                    .iter()
                    .map(|e| e.name())
                    .collect(),
            }
        };
        let settings = &self.settings;
        Summary {
            plant: "xy-stage",
            plant_effects: &settings.plant_effects,
            settings: SettingsSummary {
                x_frequency_hz: settings.x_frequency_hz,
                y_frequency_hz: settings.y_frequency_hz,
                duration_s: settings.duration_s,
                low_fraction_of_stroke: settings.low_fraction,
                high_fraction_of_stroke: settings.high_fraction,
                loop_rate_hz: settings.loop_rate_hz,
                settle_s: settings.settle_s,
                identify_s: settings.identify_s,
                output_window_v: [OUTPUT_MIN_V, OUTPUT_MAX_V],
            },
            x: axis(0),
            y: axis(1),
            close_loop: self.close_loop.report(),
            seconds: self.seconds,
        }
    }

    /// Writes `summary.json`, `demo.csv`, `demo-params.toml` (the final model in the firmware's
    /// format) and the plots (`tracking`, `error`, `loops`, in each of `formats`, e.g.
    /// `["svg", "png"]`) into `dir`. Returns the files written.
    pub fn write(&self, dir: &Path, formats: &[&str]) -> crate::Result<Vec<String>> {
        std::fs::create_dir_all(dir).map_err(crate::Error::write("--out", dir))?;
        let mut written = Vec::new();
        let json_path = dir.join("summary.json");
        let text = serde_json::to_string_pretty(&self.summary()).map_err(crate::Error::from)?;
        std::fs::write(&json_path, text + "\n")
            .map_err(crate::Error::write("--out", &json_path))?;
        written.push(json_path.display().to_string());
        let params_path = dir.join("demo-params.toml");
        // The XY stage's own board: DAC8563 0–5 V, 24 V/V amplifier, ADS8681 ±10.24 V, 0–10 V
        // sensor at 10 µm/V; the demo's loop rate.
        let stage = piezo_stage::Stage {
            name: "demo".into(),
            version: "1".into(),
            loop_rate_hz: crate::stage_file::rate_of(self.settings.loop_rate_hz),
        };
        let io = piezo_stage::Io {
            placeholder: false,
            ..piezo_stage::Io::placeholder()
        };
        let params = crate::close_loop::parameter_file(
            &self.close_loop,
            "demo identification record",
            stage,
            io,
        );
        std::fs::write(&params_path, params).map_err(crate::Error::write("--out", &params_path))?;
        written.push(params_path.display().to_string());

        let mut names = vec!["t_s".to_string()];
        let mut columns = vec![self.t_s.clone()];
        for a in 0..2 {
            let ax = AXES[a];
            names.push(format!("r{ax}_m"));
            columns.push(self.reference_m[a].clone());
            for (mode, run) in [
                ("linear", &self.linear),
                ("base", &self.base),
                ("effects", &self.closed),
            ] {
                names.push(format!("u{ax}_{mode}_V"));
                columns.push(run.voltage_v[a].clone());
                names.push(format!("{ax}_{mode}_m"));
                columns.push(run.measured_m[a].clone());
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
        .map_err(|e| crate::Error::Usage(format!("--out: {e}")))?;
        written.push(csv_path.display().to_string());

        let figures = self.figures();
        for format in formats {
            for (name, charts, columns) in &figures {
                let path = dir.join(format!("{name}.{format}"));
                plot_grid(&path, charts, *columns).map_err(crate::Error::from)?;
                written.push(path.display().to_string());
            }
        }
        Ok(written)
    }

    /// The figures: `tracking` (reference and positions against time), `error` (tracking error against
    /// time, scaled to the scored window, the unscored transient shaded) and `loops` (per axis: the
    /// full-stroke loop, the compensated error against the reference, the drive voltage against the
    /// reference, all over the scored window). Each with its number of columns.
    fn figures(&self) -> [(&'static str, Vec<Chart>, usize); 3] {
        let skip = self
            .settings
            .settle_samples()
            .min(self.t_s.len().saturating_sub(1));
        let mut tracking: Vec<Chart> = Vec::new();
        let mut error = Vec::new();
        let mut loops = Vec::new();
        for a in 0..2 {
            let axis = AxisPlots {
                result: self,
                a,
                skip,
            };
            tracking.push(axis.tracking());
            error.extend(axis.errors());
            loops.extend(axis.loops());
        }
        [
            ("tracking", tracking, 1),
            ("error", error, 1),
            ("loops", loops, 3),
        ]
    }
}

/// Micrometres per metre.
const UM: f64 = 1e6;

/// One axis's panels of [`DemoResult`]'s figures.
struct AxisPlots<'a> {
    /// The demo's result.
    result: &'a DemoResult,
    /// The axis (0: x, 1: y).
    a: usize,
    /// First scored sample.
    skip: usize,
}

impl<'a> AxisPlots<'a> {
    /// The three modes with their names and curve roles.
    fn modes(&self) -> [(&'static str, &'a ModeRun, Role); 3] {
        let r = self.result;
        [
            ("uncompensated", &r.linear, Role::OpenLoop),
            ("base model", &r.base, Role::Other(5)),
            ("base model + effects", &r.closed, Role::Feedforward),
        ]
    }

    /// The axis's reference \[m\].
    fn reference(&self) -> &'a [f64] {
        &self.result.reference_m[self.a]
    }

    /// `v` \[m\] in µm against time.
    fn in_time(&self, name: &str, v: &[f64], role: Role) -> Series {
        let t = &self.result.t_s;
        let points = t.iter().zip(v).map(|(&t, &y)| (t, y * UM)).collect();
        Series::line(name, points, 4000).role(role)
    }

    /// Over the scored window: `ys` times `sy` against the reference in µm, each sample from `skip`
    /// on.
    fn scored(&self, name: &str, ys: &[f64], sy: f64, role: Role) -> Series {
        let (xs, skip) = (self.reference(), self.skip);
        let points = xs[skip..]
            .iter()
            .zip(&ys[skip..])
            .map(|(&x, &y)| (x * UM, y * sy))
            .collect();
        Series::line(name, points, 6000).role(role)
    }

    /// A mode's tracking error \[m\].
    fn err(&self, run: &ModeRun) -> Vec<f64> {
        run.measured_m[self.a]
            .iter()
            .zip(self.reference())
            .map(|(y, r)| y - r)
            .collect()
    }

    /// Reference and measured positions against time.
    fn tracking(&self) -> Chart {
        let ax = AXES[self.a];
        let mut series: Vec<Series> = self
            .modes()
            .iter()
            .map(|(name, run, role)| self.in_time(name, &run.measured_m[self.a], *role))
            .collect();
        series.push(self.in_time("reference", self.reference(), Role::Reference));
        Panel::new(
            format!("{ax} axis: reference and measured platform position"),
            "t [s]",
            format!("{ax} [µm]"),
            series,
        )
        .into()
    }

    /// The tracking error against time. The uncompensated error is a hundred times the compensated
    /// one: a panel each, both scaled to the scored window.
    fn errors(&self) -> [Chart; 2] {
        let (ax, skip, t) = (AXES[self.a], self.skip, &self.result.t_s);
        let transient = || {
            Interval::excluded(
                "transient (not scored)",
                t.first().copied().unwrap_or(0.0),
                t.get(skip).copied().unwrap_or(0.0),
            )
        };
        let error_panel = |title: String, runs: &[(&str, &ModeRun, Role)]| {
            let errors: Vec<Vec<f64>> = runs.iter().map(|(_, run, _)| self.err(run)).collect();
            let (lo, hi) = scored_range(errors.iter().map(|e| &e[skip..]), UM);
            let series = runs
                .iter()
                .zip(&errors)
                .map(|((name, _, role), e)| self.in_time(name, e, *role))
                .collect();
            Panel::new(title, "t [s]", "error [µm]", series)
                .y_range(lo, hi)
                .interval(transient())
        };
        let modes = self.modes();
        [
            error_panel(
                format!("{ax} axis: tracking error, uncompensated"),
                &modes[..1],
            ),
            error_panel(
                format!(
                    "{ax} axis: tracking error, compensated (effects added: {})",
                    self.result.effects_of(self.a)
                ),
                &modes[1..],
            ),
        ]
    }

    /// Over the scored window, against the reference: the measured position (the full-stroke loop),
    /// the compensated error and the drive voltage.
    fn loops(&self) -> [Chart; 3] {
        let (ax, a, modes) = (AXES[self.a], self.a, self.modes());
        let reference = self.reference();
        let mut full_stroke: Vec<Series> = modes
            .iter()
            .map(|(name, run, role)| self.scored(name, &run.measured_m[a], UM, *role))
            .collect();
        full_stroke.push(self.scored("reference", reference, UM, Role::Reference));
        let compensated_error = modes[1..]
            .iter()
            .map(|(name, run, role)| self.scored(name, &self.err(run), UM, *role))
            .collect();
        let voltage = modes
            .iter()
            .map(|(name, run, role)| self.scored(name, &run.voltage_v[a], 1.0, *role))
            .collect();
        let panel = |what: &str, y_label: &str, series: Vec<Series>| {
            Panel::new(
                format!("{ax} axis: {what} against reference"),
                "reference [µm]",
                y_label,
                series,
            )
            .legend(Legend::Below)
        };
        [
            panel("measured", "measured [µm]", full_stroke),
            panel("compensated error", "error [µm]", compensated_error),
            panel("drive voltage", "voltage [V]", voltage),
        ]
    }
}

/// The range of the values of `traces` times `scale`, with 8 % padding.
pub fn scored_range<'a>(traces: impl Iterator<Item = &'a [f64]>, scale: f64) -> (f64, f64) {
    let (lo, hi) = traces
        .flatten()
        .map(|v| v * scale)
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
            (a.min(v), b.max(v))
        });
    if !(lo <= hi) {
        return (-1.0, 1.0);
    }
    let pad = ((hi - lo) * 0.08).max(1e-9);
    (lo - pad, hi + pad)
}

/// Arguments of `demo`.
#[derive(Debug, clap::Args)]
pub struct DemoArgs {
    /// Output directory (created if missing).
    #[arg(long, default_value = "out/demo")]
    pub out: std::path::PathBuf,
    /// Triangle frequency of the x axis (Hz).
    #[arg(long = "x-freq", default_value_t = 2.0)]
    pub x_freq: f64,
    /// Triangle frequency of the y axis (Hz).
    #[arg(long = "y-freq", default_value_t = 1.0)]
    pub y_freq: f64,
    /// Record length (s).
    #[arg(long, default_value_t = 2.0)]
    pub duration: f64,
    /// Lower end of the reference [fraction of the stroke].
    #[arg(long, default_value_t = 0.1)]
    pub low: f64,
    /// Upper end of the reference [fraction of the stroke].
    #[arg(long, default_value_t = 0.9)]
    pub high: f64,
    /// Loop rate in Hz (DAC updates and sensor samples).
    #[arg(long, default_value_t = 10_000.0)]
    pub rate: f64,
    /// Time skipped at the start of the error metrics (s).
    #[arg(long, default_value_t = 0.01)]
    pub settle: f64,
    /// Length of the identification experiment (s).
    #[arg(long, default_value_t = 3.0)]
    pub identify: f64,
    /// Effect the plant carries and no model declares (host-sim effect spec, repeatable; default:
    /// creep:tau=0.1/1,weight=0.02/0.02 and noise:rms_m=2e-9,seed=11; `none` for a clean plant).
    #[arg(long = "plant-effect")]
    pub plant_effects: Vec<String>,
    /// Plot format.
    #[arg(long, value_enum, default_value_t = crate::plot::PlotFormat::Both)]
    pub format: crate::plot::PlotFormat,
}

/// `host-sim demo`: runs the story with the arguments and writes its files.
pub fn demo_cmd(a: &DemoArgs) -> crate::Result<String> {
    let defaults = DemoSettings::default();
    let plant_effects = if a.plant_effects.is_empty() {
        defaults.plant_effects
    } else {
        a.plant_effects
            .iter()
            .filter(|e| e.as_str() != "none")
            .cloned()
            .collect()
    };
    let settings = DemoSettings {
        x_frequency_hz: a.x_freq,
        y_frequency_hz: a.y_freq,
        duration_s: a.duration,
        low_fraction: a.low,
        high_fraction: a.high,
        loop_rate_hz: a.rate,
        settle_s: a.settle,
        identify_s: a.identify,
        plant_effects,
    };
    let result = run_demo(&settings, &mut crate::progress)?;
    let files = result.write(&a.out, a.format.extensions())?;
    Ok(format!("{}written: {}", result.table(), files.join(", ")))
}

/// `summary.json` ([`DemoResult::summary`]).
#[derive(Debug, Clone, serde::Serialize)]
pub struct Summary<'a> {
    /// The plant's name.
    pub plant: &'static str,
    /// The effects the plant was given.
    pub plant_effects: &'a [String],
    /// The run's settings.
    pub settings: SettingsSummary,
    /// Axis x.
    pub x: AxisSummary,
    /// Axis y.
    pub y: AxisSummary,
    /// The close-loop run's report.
    pub close_loop: crate::close_loop::OutcomeReport<'a>,
    /// Wall time of the run \[s\].
    pub seconds: f64,
}

/// The settings of [`Summary`].
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub struct SettingsSummary {
    /// The raster's frequencies \[Hz\].
    pub x_frequency_hz: f64,
    /// The raster's y frequency \[Hz\].
    pub y_frequency_hz: f64,
    /// Each mode's run \[s\].
    pub duration_s: f64,
    /// The lower end of the trajectory, share of the stroke.
    pub low_fraction_of_stroke: f64,
    /// The upper end, share of the stroke.
    pub high_fraction_of_stroke: f64,
    /// The loop rate \[Hz\].
    pub loop_rate_hz: f64,
    /// Settling before the scored part \[s\].
    pub settle_s: f64,
    /// The identification record \[s\].
    pub identify_s: f64,
    /// The output window \[V\].
    pub output_window_v: [f64; 2],
}

/// One axis of [`Summary`] (µm and % of the axis's stroke).
#[derive(Debug, Clone, serde::Serialize)]
pub struct AxisSummary {
    /// The axis's stroke \[µm\].
    pub stroke_um: f64,
    /// With the linear feedforward.
    pub uncompensated: ModeError,
    /// With the base model's compensator.
    pub compensated_base_model: ModeError,
    /// With the compensator of the model close-loop chose.
    pub compensated_with_effects: ModeError,
    /// RMS with effects / RMS with the base model.
    pub rms_ratio_with_effects_over_base: f64,
    /// RMS with the base model / RMS uncompensated.
    pub rms_ratio_base_over_uncompensated: f64,
    /// The straight line the uncompensated run follows.
    pub linear_feedforward: LinearFeedforward,
    /// The effects close-loop added.
    pub effects_added: Vec<&'static str>,
}

/// The tracking error of one mode on one axis.
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub struct ModeError {
    /// RMS \[µm\].
    pub rms_um: f64,
    /// Largest \[µm\].
    pub max_um: f64,
    /// RMS, % of the stroke.
    pub rms_percent_of_stroke: f64,
    /// Largest, % of the stroke.
    pub max_percent_of_stroke: f64,
}

/// y = gain·u + offset.
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub struct LinearFeedforward {
    /// \[µm/V\].
    pub gain_um_per_v: f64,
    /// \[µm\].
    pub offset_um: f64,
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
        assert!(s
            .validate()
            .unwrap_err()
            .to_string()
            .starts_with("--x-freq"));
        let s = DemoSettings {
            low_fraction: 0.9,
            high_fraction: 0.1,
            ..Default::default()
        };
        assert!(s.validate().unwrap_err().to_string().starts_with("--low"));
    }
}
