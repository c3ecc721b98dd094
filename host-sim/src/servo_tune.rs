//! `host-sim servo-tune`: the feedback servo of each axis (`[x.servo]`, `[y.servo]`) from the
//! stage file's own model and the stage's first mode, by `piezo_core::servo::tune`.
//!
//! Per axis the tuning plant is `P(s) = g·ω_n²/(s² + 2ζω_n s + ω_n²)·e^{−sτ}` with
//! - g: the model's small-signal gain dy/du of largest magnitude (`StaticModel::slope_range`);
//! - f_n = ω_n/2π and ζ: the first mode — given (`--mode-hz`, `--damping`), or the `mode` effect
//!   close-loop found (`[x.effects] mode_frequency_hz`, `mode_damping`);
//! - τ: the loop's latency as a function of its rate, `τ = p·T + τ_c` with T = 1/`loop_rate_hz`:
//!   `--latency-periods` p loop periods (1.5: half a period for the DAC's zero-order hold and one
//!   for the computation, the reading of tick k answered in the DAC write the next update
//!   latches) plus `--converter-latency-s` τ_c, the converters' own delay whatever the rate
//!   (default 5 µs: the ADS8681's conversion, ≤ 1 µs, its 32-bit SPI frame and the DAC8563's
//!   24-bit frame, ≈ 1.5 and 1.1 µs, and the DAC's settling, ≈ 2 µs; from the datasheets, not
//!   measured on a board). A faster loop has less delay, so the same stage gets a higher
//!   crossover at the same phase margin.
//!
//! The rule (core docs, `piezo_core::servo::tune`): a notch near f_n (centre 0.8–1.25·f_n; a
//! plain notch of Q 1, 0.7, 0.5 or 0.35, or with `--mode-by-phase` also a notch with lead, its
//! poles 2, 4 or 8 times its centre with Q 1, 2 or 2.8, which holds the mode by phase when the
//! loop is fast enough and is unstable when the mode is not where `--mode-hz` says) and a
//! Butterworth low-pass from 0.7 to 5 times max(f_n, 1/(4τ)), searched for the highest crossover
//! with pure integral action, the phase margin asked for (phase unwrapped), a closed loop stable
//! by the Nyquist criterion and |1/(1 + L)| ≤ 1.6, also with f_n ± 10 %. The
//! parameters are written into the stage file and validated by the core with the rest of it.

use piezo_core::servo::{tune, StageDynamics, Tuning, TuningGoal};
use piezo_stage::StageFile;
use std::path::PathBuf;

/// Help after `host-sim servo-tune --help`.
pub const HELP: &str = "Tunes [x.servo] and [y.servo] from the stage file's model (its largest dy/du) and the \
stage's first mode: --mode-hz (one value per axis, comma-separated, or one for both) and --damping, or the `mode` \
effect close-loop added to the file. Latency: --latency-periods loop periods of the file's loop rate plus \
--converter-latency-s. Writes --out (the input file with the \
servo tables; comments are not kept) and prints per axis the crossover, phase margin, sensitivity peak and the \
feedback loop's -3 dB bandwidth as JSON.";

/// Arguments of `servo-tune`.
#[derive(Debug, clap::Args)]
#[command(after_help = HELP)]
pub struct ServoTuneArgs {
    /// The stage file (static models; its loop rate and output limits are the servo's).
    #[arg(long)]
    pub stage: PathBuf,
    /// Stage file to write (may be the same file).
    #[arg(long)]
    pub out: PathBuf,
    /// First mode of each axis (Hz): `F` for both or `FX,FY`; default: the file's mode effect.
    #[arg(long, value_delimiter = ',')]
    pub mode_hz: Vec<f32>,
    /// Damping ratio ζ of the mode (with --mode-hz).
    #[arg(long, default_value_t = 0.02)]
    pub damping: f32,
    /// Phase margin at the crossover (°).
    #[arg(long, default_value_t = 60.0)]
    pub phase_margin_deg: f32,
    /// Sensor-to-actuator latency [loop periods].
    #[arg(long, default_value_t = 1.5)]
    pub latency_periods: f32,
    /// The converters' latency, added whatever the loop rate (s).
    #[arg(long, default_value_t = CONVERTER_LATENCY_S)]
    pub converter_latency_s: f32,
    /// Also try notches with lead, which hold the mode by phase: on a fast loop a higher
    /// crossover, but a loop that is unstable when the mode lies well below --mode-hz (a
    /// payload) or is absent (see piezo_core::servo::TuningGoal::mode_by_phase).
    #[arg(long)]
    pub mode_by_phase: bool,
}

/// τ_c: the ADC conversion and both SPI frames plus the DAC's settling \[s\] (module docs).
pub const CONVERTER_LATENCY_S: f32 = 5e-6;

/// The loop's latency τ = p·T + τ_c \[s\] (module docs).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Latency {
    /// p: loop periods (zero-order hold and computation).
    pub periods: f32,
    /// τ_c: the converters' delay \[s\].
    pub converter_s: f32,
}

impl Latency {
    /// 1.5 periods plus [`CONVERTER_LATENCY_S`].
    pub const DEFAULT: Latency = Latency {
        periods: 1.5,
        converter_s: CONVERTER_LATENCY_S,
    };

    /// τ at the loop period `sample_period_s` \[s\].
    pub fn at_period(&self, sample_period_s: f32) -> f32 {
        self.periods * sample_period_s + self.converter_s
    }
}

/// One axis's tuning: the mode it used and the core's result.
#[derive(Debug, Clone, Copy)]
pub struct AxisTuning {
    /// `x` or `y`.
    pub axis: &'static str,
    /// The dynamics the rule was given.
    pub dynamics: StageDynamics,
    /// Parameters and margins.
    pub tuning: Tuning,
}

/// The first mode of axis `index` \[Hz, 1\]: `given` (one value for all axes, or one per axis)
/// with `damping`, else the axis's `mode` effect.
fn first_mode(
    file: &StageFile,
    index: usize,
    given: &[f32],
    damping: f32,
) -> crate::Result<(f32, f32)> {
    match given.len() {
        0 => {}
        1 => return Ok((given[0], damping)),
        n if n == file.axes().len() => return Ok((given[index], damping)),
        n => {
            return Err(crate::Error::Refused(format!(
                "--mode-hz has {n} values for {} axes",
                file.axes().len()
            )))
        }
    }
    let (name, axis) = file.axes()[index];
    let e = axis.effects;
    if e.mode_frequency_hz > 0.0 {
        Ok((e.mode_frequency_hz, e.mode_damping))
    } else {
        Err(crate::Error::Refused(format!(
            "axis {name}: no first mode: give --mode-hz (and --damping), or let close-loop find \
             the `mode` effect"
        )))
    }
}

/// Tunes every axis of `file` and writes the parameters into it (validated by the core).
pub fn tune_file(
    file: &mut StageFile,
    mode_hz: &[f32],
    damping: f32,
    goal: &TuningGoal,
    latency: Latency,
) -> crate::Result<Vec<AxisTuning>> {
    let valid = file.validate().map_err(crate::Error::from)?;
    let mut out = Vec::new();
    for (index, v) in valid.axes.iter().enumerate() {
        let compensator = v.compensator.ok_or_else(|| {
            crate::Error::Refused(format!(
                "axis {}: servo tuning needs a static model (symmetric or asymmetric)",
                v.name
            ))
        })?;
        let (f, zeta) = first_mode(file, index, mode_hz, damping)?;
        let dynamics = StageDynamics::from_compensator(
            &compensator,
            f,
            zeta,
            latency.at_period(valid.sample_period_s),
        );
        let tuning = tune(&dynamics, goal, compensator.settings())
            .map_err(|e| crate::Error::Refused(format!("servo tuning of axis {}: {e}", v.name)))?;
        out.push(AxisTuning {
            axis: v.name,
            dynamics,
            tuning,
        });
    }
    file.x.servo = Some(out[0].tuning.params);
    if let (Some(y), Some(t)) = (file.y.as_mut(), out.get(1)) {
        y.servo = Some(t.tuning.params);
    }
    file.validate().map_err(crate::Error::from)?;
    Ok(out)
}

/// An f32 as the f64 with the same shortest decimal form (3221.0, not 3220.999…).
fn tidy(x: f32) -> f64 {
    x.to_string().parse().unwrap_or(f64::NAN)
}

/// The JSON report of a tuning.
pub fn report(tunings: &[AxisTuning]) -> Vec<TuningReport> {
    tunings
        .iter()
        .map(|t| {
            let p = t.tuning.params;
            TuningReport {
                axis: t.axis,
                gain_m_per_v: tidy(t.dynamics.gain_m_per_v),
                mode_frequency_hz: tidy(t.dynamics.mode_frequency_hz),
                mode_damping: tidy(t.dynamics.mode_damping),
                latency_s: tidy(t.dynamics.latency_s),
                crossover_hz: tidy(t.tuning.crossover_hz),
                phase_margin_deg: tidy(t.tuning.phase_margin_deg),
                sensitivity_peak: tidy(t.tuning.sensitivity_peak),
                closed_loop_bandwidth_hz: tidy(t.tuning.closed_loop_bandwidth_hz),
                servo: ServoReport {
                    kp_v_per_m: tidy(p.kp_v_per_m),
                    ki_v_per_m_s: tidy(p.ki_v_per_m_s),
                    lowpass_frequency_hz: tidy(p.lowpass_frequency_hz),
                    lowpass_q: tidy(p.lowpass_q),
                    notch_frequency_hz: tidy(p.notch_frequency_hz),
                    notch_q: tidy(p.notch_q),
                    notch_pole_frequency_hz: tidy(p.notch_pole_frequency_hz),
                    transfer_time_constant_s: tidy(p.transfer_time_constant_s),
                },
            }
        })
        .collect()
}

/// One axis of the tuning report (SI; each f32 figure as its shortest decimal).
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub struct TuningReport {
    /// `x` or `y`.
    pub axis: &'static str,
    /// The static gain the rule was given \[m/V\].
    pub gain_m_per_v: f64,
    /// First mode \[Hz\].
    pub mode_frequency_hz: f64,
    /// Its damping ratio.
    pub mode_damping: f64,
    /// Latency \[s\].
    pub latency_s: f64,
    /// Crossover \[Hz\].
    pub crossover_hz: f64,
    /// Phase margin \[°\].
    pub phase_margin_deg: f64,
    /// Peak of |S|.
    pub sensitivity_peak: f64,
    /// Closed-loop −3 dB bandwidth \[Hz\].
    pub closed_loop_bandwidth_hz: f64,
    /// The servo's parameters.
    pub servo: ServoReport,
}

/// The servo's parameters in [`TuningReport`] (as the stage file's `servo` table).
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub struct ServoReport {
    /// Proportional gain \[V/m\].
    pub kp_v_per_m: f64,
    /// Integral gain \[V/(m·s)\].
    pub ki_v_per_m_s: f64,
    /// Low-pass corner \[Hz\].
    pub lowpass_frequency_hz: f64,
    /// Low-pass Q.
    pub lowpass_q: f64,
    /// Notch centre \[Hz\].
    pub notch_frequency_hz: f64,
    /// Notch Q.
    pub notch_q: f64,
    /// The notch's poles \[Hz\] (0: at its centre, a plain notch).
    pub notch_pole_frequency_hz: f64,
    /// Bumpless-transfer time constant \[s\].
    pub transfer_time_constant_s: f64,
}

/// `host-sim servo-tune`.
pub fn servo_tune_cmd(a: &ServoTuneArgs) -> crate::Result<String> {
    let (mut file, _) =
        StageFile::load(&a.stage).map_err(|e| crate::Error::Refused(format!("--stage: {e}")))?;
    let goal = TuningGoal {
        phase_margin_deg: a.phase_margin_deg,
        mode_by_phase: a.mode_by_phase,
        ..TuningGoal::default()
    };
    let latency = Latency {
        periods: a.latency_periods,
        converter_s: a.converter_latency_s,
    };
    if !(latency.periods >= 0.0 && latency.converter_s >= 0.0 && latency.converter_s.is_finite()) {
        return Err(crate::Error::Refused(format!(
            "--latency-periods {} / --converter-latency-s {}: each must be finite and >= 0",
            latency.periods, latency.converter_s
        )));
    }
    let tunings = tune_file(&mut file, &a.mode_hz, a.damping, &goal, latency)?;
    let header = format!(
        "Stage file {} with its servo tuned by host-sim servo-tune",
        a.stage.display()
    );
    file.write(&a.out, &header)
        .map_err(|e| crate::Error::Refused(format!("--out: {e}")))?;
    eprintln!("wrote {}", a.out.display());
    serde_json::to_string_pretty(&report(&tunings)).map_err(crate::Error::from)
}

#[cfg(test)]
mod tests {
    use super::*;

    const XY: &str = include_str!("../../firmware/params/xy-stage.toml");

    #[test]
    fn tunes_both_axes_of_the_xy_stage_and_the_core_accepts_them() {
        let mut file = StageFile::parse("xy-stage.toml", XY).unwrap();
        let goal = TuningGoal::default();
        let t = tune_file(&mut file, &[3221.0, 2197.0], 0.02, &goal, Latency::DEFAULT).unwrap();
        assert_eq!(t.len(), 2);
        for a in &t {
            assert!(a.tuning.phase_margin_deg >= 60.0 - 1e-3, "{a:?}");
            assert!(a.tuning.crossover_hz > 50.0 && a.tuning.crossover_hz < 1000.0);
            assert!(a.tuning.params.ki_v_per_m_s > 0.0, "stage gain is positive");
        }
        // A lower mode lowers the crossover.
        assert!(t[1].tuning.crossover_hz < t[0].tuning.crossover_hz);
        let valid = file.validate().unwrap();
        assert!(valid.axes.iter().all(|a| a.servo.is_some()));
    }

    #[test]
    fn without_a_mode_it_says_where_to_get_one() {
        let mut file = StageFile::parse("xy-stage.toml", XY).unwrap();
        let e = tune_file(
            &mut file,
            &[],
            0.02,
            &TuningGoal::default(),
            Latency::DEFAULT,
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("axis x") && e.contains("--mode-hz"), "{e}");
        let e = tune_file(
            &mut file,
            &[1.0, 2.0, 3.0],
            0.02,
            &TuningGoal::default(),
            Latency::DEFAULT,
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("3 values"), "{e}");
    }

    /// The same stage at 10, 20 and 50 kHz: the latency shrinks with the period, so the filters
    /// move up and the crossover rises at the same phase margin: x 419 → 542 → 701 Hz, y 335 →
    /// 425 → 478 Hz (the mode, its ±10 % and the sensitivity peak below it, not the latency,
    /// hold it there).
    #[test]
    fn a_faster_loop_gets_a_higher_crossover() {
        let mut crossover = Vec::new();
        for rate in ["10000.0", "20000.0", "50000.0"] {
            // The file's own rate line (20 kHz in the default file).
            let line = XY
                .lines()
                .find(|l| l.starts_with("loop_rate_hz = "))
                .unwrap();
            let text = XY.replacen(line, &format!("loop_rate_hz = {rate}"), 1);
            let mut file = StageFile::parse("xy-stage.toml", &text).unwrap();
            let goal = TuningGoal::default();
            let t = tune_file(&mut file, &[3221.0, 2197.0], 0.03, &goal, Latency::DEFAULT).unwrap();
            for a in &t {
                assert!(a.tuning.phase_margin_deg >= 60.0 - 1e-3, "{rate}: {a:?}");
            }
            println!(
                "{rate} Hz: latency {:.1} µs, crossover x {:.0} Hz, y {:.0} Hz",
                t[0].dynamics.latency_s * 1e6,
                t[0].tuning.crossover_hz,
                t[1].tuning.crossover_hz
            );
            crossover.push([t[0].tuning.crossover_hz, t[1].tuning.crossover_hz]);
        }
        for i in 0..2 {
            assert!(crossover[1][i] > 1.05 * crossover[0][i], "{crossover:?}");
            assert!(crossover[2][i] > 1.1 * crossover[1][i], "{crossover:?}");
            assert!(crossover[2][i] > 1.4 * crossover[0][i], "{crossover:?}");
        }
    }
}
