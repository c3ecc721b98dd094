//! # piezo-stage: the stage file
//!
//! One TOML file says everything about a stage that the tools and the firmware need: its name and
//! loop rate, the converter and amplifier chain, and per axis the model, the effects around it, the
//! output limits and where the set came from. It is defined once here (serde derive), read and
//! written by this crate only, and validated with piezo-core's own constructors, called the same
//! way by every consumer: `host-sim identify|close-loop` write it, `host-sim predict|compensate`
//! and the firmware's build read it.
//!
//! ```toml
//! [stage]
//! name = "xy-stage"                  # with `version`: the version string the firmware logs
//! version = "1"
//! loop_rate_hz = 10000.0             # the firmware's control rate; effects are discretised at it
//!
//! [io]                               # the chain DAC → amplifier → stack, sensor → ADC
//! placeholder = false                # true: not measured, written by a tool without a stage file
//! dac_part = "DAC8563"
//! dac_range_v = [0.0, 5.0]           # DAC output span [V]
//! amplifier_gain_v_per_v = 24.0      # stack volts per DAC volt
//! adc_part = "ADS8681"
//! adc_range_v = [-10.24, 10.24]      # ADC input span [V]
//! sensor_range_v = [0.0, 10.0]       # sensor output span [V], within the ADC's
//! sensor_m_per_v = 1.0e-5            # displacement per sensor volt [m/V]
//!
//! [x]
//! model = "symmetric"                # symmetric | asymmetric | dynamic | oscillator
//! [x.bouc_wen]                       # a, beta, gamma, n
//! [x.static_map]                     # k1_m_per_v, k2_m_per_h, offset_m (symmetric, asymmetric)
//! [x.asymmetry]                      # delta_per_v_s, input_shift_s (asymmetric)
//! [x.mass_spring_damper]             # mass_kg, damping_n_s_per_m, ... (dynamic)
//! [x.oscillator]                     # the benchmark oscillator (oscillator; substeps below)
//! [x.effects]                        # optional: creep, even term, mode (mode_frequency_hz,
//!                                    # mode_damping, mode_relative_damping), delay, drift, coupling,
//!                                    # rate-dependent hysteresis (hysteresis_lag_s,
//!                                    # hysteresis_rate_gain_s_per_v, relaxation_*)
//! [x.limits]                         # output_min_v, output_max_v, slew_limit_v_per_s,
//!                                    # envelope_policy = "warn" | "feedback-only" (default
//!                                    # warn: what the firmware does while a command leaves
//!                                    # the identified envelope, see below)
//! [x.servo]                          # optional: kp_v_per_m, ki_v_per_m_s, lowpass_*, notch_*,
//!                                    # transfer_time_constant_s (piezo_core::servo::tune)
//! [x.on_target]                     # optional: tolerance_m, ticks (when the firmware says the axis
//!                                    # is on target; defaults: 8 ADC steps in metres, 1 ms of ticks)
//! [x.identified]                     # optional: data, window_s, method, fit_rms_m,
//!                                    # input_range_v, sample_period_s, and (optional, for
//!                                    # files written before them) input_rate_max_v_per_s,
//!                                    # band_hz = [lo, hi]
//! [y]                                # optional second axis, same tables
//! ```
//!
//! Units are SI throughout (V, m, s, Hz). The parameter tables are piezo-core's own structs
//! (`BoucWenParams`, `StaticMap`, `Asymmetry`, `MassSpringDamperParams`, `OscillatorParams`,
//! `effects::EffectParams`), so their keys are the core's field names and a new core field is a
//! new key. Unknown keys are refused with the list of valid ones; every error names the file, the
//! line and column, and the key path (`x.bouc_wen.gamma`): [`StageError`].
//!
//! # Validation ([`StageFile::validate`], [`Check`])
//! Per axis, in this order: `BoucWen::with_input_range(bouc_wen, output_min_v, output_max_v,
//! STATE_LIMIT)` (the output window is the only input the stage will see), the model constructor
//! of its family, `Compensator::new` with the limits and `sample_period_s = 1 / loop_rate_hz`
//! (static models), then `effects::Effects::new(effects, 1 / loop_rate_hz, range)` with
//! `range = OperatingRange::first_loading(..)` (the window and the first loading's output over
//! it: the effects' plausibility bounds are relative to them), `Servo::new(servo, limits,
//! linear gain)` (its loop gains). The io chain: `IoChain::check_limits` (the output window within
//! `dac_range_v × amplifier_gain_v_per_v`, a finite slew limit that leaves a full-window move
//! `MIN_WINDOW_TICKS` ticks), `IoChain::check` (the sensor span within the ADC's).
//! [`Check::Models`] is the same without the compensator and the drive-span check: what a forward
//! simulation of the file needs (`host-sim predict` runs sets that are not invertible).
//!
//! # Identified envelope ([`Axis::envelope`], `piezo_core::envelope`)
//! `[x.identified]` says what the record the set was fitted to covered: its input range
//! `input_range_v` (smallest and largest input), its largest rate `input_rate_max_v_per_s` =
//! max |u\[k\] − u\[k−1\]| / T_record, and its band `band_hz` (informational: the narrowest band
//! of the input's periodogram above DC that holds 99 % of its variance, 0.5 % left out on each
//! side, [`input_band_hz`]). The firmware counts the ticks whose commanded voltage or rate leaves
//! the range or the rate and applies `[x.limits] envelope_policy`: `warn` (the default) counts
//! and flags only; `feedback-only` hands the axis to its servo alone while outside (refused
//! without `[x.servo]` or without `[x.identified]`). A file without `input_rate_max_v_per_s`
//! checks the range only.
//!
//! # Initial state
//! Every consumer starts a record or a run that begins at u0 at rest there:
//! `ModelState::at_rest(u0)` and `effects::EffectsState::at_rest(u0)` ([`AxisChain::simulate`]).

#![forbid(unsafe_code)]
// A stage file is read once, at start-up or build time: an error that carries its file, location,
// key and message by value is simpler than a boxed one, and its size costs nothing there.
#![allow(clippy::result_large_err)]

mod error;
mod firmware;
mod validate;

pub use error::{StageError, StageErrorKind};
pub use firmware::FirmwareSet;
pub use piezo_core::AxisParams;
pub use validate::{simulate_pair, AxisChain, Check, ValidAxis, ValidStage, PLAUSIBLE_STROKE_M};

use piezo_core::effects::EffectParams;
use piezo_core::{
    Asymmetry, BoucWenParams, IoChain, MassSpringDamperParams, OscillatorParams, ParamError,
    ServoParams, StaticMap,
};
pub use piezo_core::{Envelope, EnvelopePolicy, OnTarget};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// FNV-1a, 32 bit (offset basis 0x811c9dc5, prime 0x01000193; piezo-core's), of a stage file's
/// bytes: the hash the firmware's build prints at boot and reports in its status, and the one an
/// upload of the same file carries (`host-sim link upload`).
///
/// `h₀ = 0x811c9dc5`, `h_{i+1} = (h_i ⊕ b_i) · 0x01000193 mod 2³²`.
pub use piezo_core::fnv1a32;

/// Largest |h| accepted for a range-limited Bouc-Wen set (β + γ ≤ 0) over the output window
/// (piezo-core's own).
pub use piezo_core::STATE_LIMIT;

/// A whole stage file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StageFile {
    /// Name, version and loop rate.
    pub stage: Stage,
    /// The converter and amplifier chain.
    pub io: Io,
    /// The first axis.
    pub x: Axis,
    /// The second axis of a two-axis stage.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub y: Option<Axis>,
}

/// `[stage]`: what the stage is called and how fast its loop runs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Stage {
    /// Name (with `version`: the version string the firmware logs at boot).
    pub name: String,
    /// Version of this set.
    #[serde(default = "default_version")]
    pub version: String,
    /// Control loop rate \[Hz\]; effects are discretised at 1 / this.
    pub loop_rate_hz: f32,
}

fn default_version() -> String {
    "1".to_string()
}

/// `[io]`: the drive and sensing chain, from DAC volts to stack volts and from metres to ADC volts.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Io {
    /// True when the section was not measured (written by a tool that had no stage file to carry
    /// it from): a reminder to set it to the real amplifier and sensor.
    #[serde(default, skip_serializing_if = "is_false")]
    pub placeholder: bool,
    /// DAC part name (the firmware drives `DAC8563`).
    pub dac_part: String,
    /// DAC output span \[V\].
    pub dac_range_v: [f32; 2],
    /// Piezo amplifier gain: stack volts per DAC volt \[V/V\].
    pub amplifier_gain_v_per_v: f32,
    /// ADC part name (the firmware drives `ADS8681`).
    pub adc_part: String,
    /// ADC input span \[V\].
    pub adc_range_v: [f32; 2],
    /// Displacement sensor output span \[V\]; within `adc_range_v`.
    pub sensor_range_v: [f32; 2],
    /// Displacement sensor gain \[m/V\].
    pub sensor_m_per_v: f32,
}

fn is_false(b: &bool) -> bool {
    !*b
}

impl Io {
    /// The firmware board's chain (DAC8563 0–5 V, 24 V/V amplifier, ADS8681 ±10.24 V, a 0–10 V
    /// sensor of 10 µm/V), marked as a placeholder: what a tool writes when it has no stage file
    /// to carry the section from.
    pub fn placeholder() -> Self {
        Self {
            placeholder: true,
            dac_part: "DAC8563".into(),
            dac_range_v: [0.0, 5.0],
            amplifier_gain_v_per_v: 24.0,
            adc_part: "ADS8681".into(),
            adc_range_v: [-10.24, 10.24],
            sensor_range_v: [0.0, 10.0],
            sensor_m_per_v: 1.0e-5,
        }
    }

    /// [`Io::placeholder`] widened so that its drive range `dac_range_v × amplifier_gain_v_per_v`
    /// covers `drive_range_v` = (u_min, u_max) \[V\] (the output windows a tool is about to
    /// write), still marked as a placeholder. With u_max ≤ 120 V and u_min ≥ 0 it is the board's
    /// chain unchanged; above, the gain is raised to g = ⌈u_max / 5 V⌉ V/V; with u_min < 0 the
    /// DAC span becomes bipolar, [−5, 5] V, and g = max(24, ⌈max(|u_min|, |u_max|) / 5 V⌉). A
    /// bipolar span is not what the firmware's DAC8563 drives: such a file needs the real `[io]`
    /// before it builds into an image. A non-finite range gives [`Io::placeholder`].
    pub fn placeholder_covering(drive_range_v: (f32, f32)) -> Self {
        let mut io = Self::placeholder();
        let (lo, hi) = drive_range_v;
        if !(lo.is_finite() && hi.is_finite()) {
            return io;
        }
        let dac_max = io.dac_range_v[1];
        let reach = if lo < 0.0 {
            io.dac_range_v = [-dac_max, dac_max];
            hi.max(-lo)
        } else {
            hi
        };
        io.amplifier_gain_v_per_v = io.amplifier_gain_v_per_v.max((reach / dac_max).ceil());
        io
    }
}

/// The model family of an axis, as named in stage files and on the command line.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum ModelKind {
    /// y = k1·u + k2·h + y0 (seed 001 eq. 1): `[x.static_map]`.
    Symmetric,
    /// Seed 001's asymmetric reading (δ-term and input shift φ): `[x.static_map]`, `[x.asymmetry]`.
    Asymmetric,
    /// Seed 000: m0·ẍ + c0·ẋ + k0·(x − x0) = k1·u + h: `[x.mass_spring_damper]`.
    Dynamic,
    /// The Bouc-Wen benchmark's hysteretic oscillator (force input): `[x.oscillator]`.
    Oscillator,
}

impl ModelKind {
    /// Name as written in files and reports.
    pub fn name(self) -> &'static str {
        match self {
            Self::Symmetric => "symmetric",
            Self::Asymmetric => "asymmetric",
            Self::Dynamic => "dynamic",
            Self::Oscillator => "oscillator",
        }
    }

    /// Whether the firmware's chain (static model, compensator, effects) can run this family.
    pub fn runs_on_firmware(self) -> bool {
        matches!(self, Self::Symmetric | Self::Asymmetric)
    }
}

/// The slew limit written into the stage files that identify and close-loop make \[V/s\]: 1 V per
/// 10 µs, four times the 24 kV/s of a 100 Hz triangle over 120 V.
pub const DEFAULT_SLEW_LIMIT_V_PER_S: f32 = 1e5;

/// `[x.limits]`: what the stage may be commanded, piezo-core's own type (the one the command
/// link uploads): `output_min_v`, `output_max_v` (the oscillator: the force range \[N\]),
/// `slew_limit_v_per_s`, and `envelope_policy` (`warn` when absent, and then not written).
pub use piezo_core::Limits;

/// `[x.identified]`: where the set came from.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Provenance {
    /// The record the set was fitted to.
    pub data: String,
    /// The scored window of that record \[s\].
    pub window_s: [f64; 2],
    /// The method (`vp-de-lm`, `ga`, `two-step`, `close-loop`).
    pub method: String,
    /// RMS of the fit over the window \[m\].
    pub fit_rms_m: f64,
    /// The input range the record covered \[V\]: the set is known to hold inside it.
    pub input_range_v: [f32; 2],
    /// The record's sample period \[s\] (the rate δ, φ and the dynamics were identified at).
    pub sample_period_s: f32,
    /// The record's largest input rate max |u\[k\] − u\[k−1\]| / T \[V/s\] (absent in files
    /// written before it: no rate check).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub input_rate_max_v_per_s: Option<f32>,
    /// The band of the record's input above DC that holds 99 % of its variance \[Hz\]
    /// ([`input_band_hz`]; informational).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub band_hz: Option<[f32; 2]>,
}

impl Provenance {
    /// The envelope of a record `u` \[V\] sampled every `sample_period_s` \[s\]: its largest
    /// input rate and its band ([`input_rate_max_v_per_s`], [`input_band_hz`]).
    pub fn with_envelope_of(mut self, u: &[f64], sample_period_s: f64) -> Self {
        self.input_rate_max_v_per_s = Some(input_rate_max_v_per_s(u, sample_period_s) as f32);
        self.band_hz = input_band_hz(u, sample_period_s).map(|(lo, hi)| [lo as f32, hi as f32]);
        self
    }
}

/// The largest |u\[k\] − u\[k−1\]| / T of a record \[V/s\] (0 for fewer than two samples).
pub fn input_rate_max_v_per_s(u: &[f64], sample_period_s: f64) -> f64 {
    u.windows(2)
        .map(|w| (w[1] - w[0]).abs())
        .fold(0.0, f64::max)
        / sample_period_s
}

/// The band `[f_lo, f_hi]` \[Hz\] of a record's input above DC that holds 99 % of its variance:
/// the periodogram |U(f_j)|² of the mean-removed input at f_j = j/(N·T), j = 1 … N/2, from the
/// first j whose cumulative share exceeds 0.5 % to the first whose share reaches 99.5 %. The
/// record is first averaged in blocks of ⌈N/4096⌉ samples (a decimation whose own Nyquist
/// frequency bounds the band), so the DFT costs at most 4096 × 2048 terms. `None` for a
/// constant input or fewer than 4 samples.
pub fn input_band_hz(u: &[f64], sample_period_s: f64) -> Option<(f64, f64)> {
    let block = u.len().div_ceil(4096).max(1);
    let x: Vec<f64> = u
        .chunks_exact(block)
        .map(|c| c.iter().sum::<f64>() / block as f64)
        .collect();
    let n = x.len();
    if n < 4 {
        return None;
    }
    let mean = x.iter().sum::<f64>() / n as f64;
    let dt = sample_period_s * block as f64;
    let power: Vec<f64> = (1..=n / 2)
        .map(|j| {
            let w = 2.0 * std::f64::consts::PI * j as f64 / n as f64;
            let (mut re, mut im) = (0.0, 0.0);
            for (k, &v) in x.iter().enumerate() {
                let (s, c) = (w * k as f64).sin_cos();
                re += (v - mean) * c;
                im -= (v - mean) * s;
            }
            re * re + im * im
        })
        .collect();
    let total: f64 = power.iter().sum();
    if !(total.is_finite() && total > 0.0) {
        return None;
    }
    let f = |j: usize| (j + 1) as f64 / (n as f64 * dt);
    let mut cumulative = 0.0;
    let (mut lo, mut hi) = (None, None);
    for (j, p) in power.iter().enumerate() {
        cumulative += p / total;
        if lo.is_none() && cumulative > 0.005 {
            lo = Some(f(j));
        }
        if cumulative >= 0.995 {
            hi = Some(f(j));
            break;
        }
    }
    Some((lo?, hi.unwrap_or(f(power.len() - 1))))
}

/// One axis: model, effects, limits and provenance.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Axis {
    /// The model family.
    pub model: ModelKind,
    /// Bouc-Wen parameters (symmetric, asymmetric, dynamic).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub bouc_wen: Option<BoucWenParams>,
    /// y = k1·u + k2·h + y0 (symmetric, asymmetric).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub static_map: Option<StaticMap>,
    /// δ and φ (asymmetric).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub asymmetry: Option<Asymmetry>,
    /// Mechanics (dynamic).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mass_spring_damper: Option<MassSpringDamperParams>,
    /// The benchmark oscillator (oscillator).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub oscillator: Option<OscillatorParams>,
    /// Oscillator: RK4 sub-steps per sample on the interpolated input.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub substeps: Option<u32>,
    /// The effects around the hysteresis model (all zero: none).
    #[serde(default, skip_serializing_if = "is_identity")]
    pub effects: EffectParams,
    /// Output limits.
    pub limits: Limits,
    /// The feedback servo on the sensor (`piezo_core::servo`), on top of the feedforward.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub servo: Option<ServoParams>,
    /// Where the set came from.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub identified: Option<Provenance>,
    /// The on-target band (`[x.on_target]`; absent keys take their defaults,
    /// [`Axis::on_target_band`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub on_target: Option<OnTargetBand>,
}

/// `[x.on_target]`: when the firmware says an axis is on target (`piezo_core::on_target`):
/// |sensor − reference| ≤ `tolerance_m` for `ticks` consecutive ticks.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OnTargetBand {
    /// Largest |sensor − reference| on target \[m\] (default: 8 ADC steps in metres,
    /// `8 · adc_span / 2^16 · sensor_m_per_v`: 25 nm for the default `[io]`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tolerance_m: Option<f32>,
    /// Consecutive ticks inside the band (default: the ticks in 1 ms, ⌈loop_rate_hz / 1000⌉).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ticks: Option<u32>,
}

impl Axis {
    /// The on-target band of this axis for the chain `io` at the loop period `sample_period_s`
    /// \[s\]: `[x.on_target]`'s keys, each absent one from [`OnTarget::default_for`];
    /// validated by [`OnTarget::new`].
    pub fn on_target_band(
        &self,
        io: &IoChain,
        sample_period_s: f32,
    ) -> Result<OnTarget, ParamError> {
        let band = self.on_target.unwrap_or_default();
        let default = OnTarget::default_for(io, sample_period_s);
        let tolerance_m = match band.tolerance_m {
            Some(t) => t,
            None => default?.tolerance_m,
        };
        let ticks = match band.ticks {
            Some(n) => n,
            None => default?.ticks,
        };
        OnTarget::new(tolerance_m, ticks)
    }
}

impl Axis {
    /// The identified envelope of this axis (`[x.identified]`'s input range and largest rate,
    /// `f32::MAX` when the rate is not given; the policy outside it is `[x.limits]
    /// envelope_policy`); `None` without `[x.identified]`.
    pub fn envelope(&self) -> Option<Envelope> {
        self.identified.as_ref().map(|p| Envelope {
            input_range_v: p.input_range_v,
            input_rate_max_v_per_s: p.input_rate_max_v_per_s.unwrap_or(f32::MAX),
        })
    }
}

fn is_identity(e: &EffectParams) -> bool {
    *e == EffectParams::default()
}

impl Axis {
    /// A static axis (symmetric, or asymmetric when `asymmetry` is nonzero).
    pub fn static_model(
        bouc_wen: BoucWenParams,
        static_map: StaticMap,
        asymmetry: Asymmetry,
        limits: Limits,
    ) -> Self {
        let asymmetric = asymmetry != Asymmetry::default();
        Self {
            model: if asymmetric {
                ModelKind::Asymmetric
            } else {
                ModelKind::Symmetric
            },
            bouc_wen: Some(bouc_wen),
            static_map: Some(static_map),
            asymmetry: asymmetric.then_some(asymmetry),
            mass_spring_damper: None,
            oscillator: None,
            substeps: None,
            effects: EffectParams::default(),
            limits,
            servo: None,
            identified: None,
            on_target: None,
        }
    }
}

/// The axis names, in file order.
pub const AXIS_NAMES: [&str; 2] = ["x", "y"];

impl StageFile {
    /// The axes present, with their names.
    pub fn axes(&self) -> Vec<(&'static str, &Axis)> {
        let mut v = vec![(AXIS_NAMES[0], &self.x)];
        if let Some(y) = &self.y {
            v.push((AXIS_NAMES[1], y));
        }
        v
    }

    /// Parses `text` (the contents of `file`, named in errors) without validating it.
    pub fn parse(file: &str, text: &str) -> Result<Self, StageError> {
        let deserializer =
            toml::Deserializer::parse(text).map_err(|e| StageError::toml(file, text, &e, None))?;
        serde_path_to_error::deserialize(deserializer).map_err(|e| {
            let path = e.path().to_string();
            let inner = e.into_inner();
            StageError::toml(file, text, &inner, Some(path))
        })
    }

    /// Reads, parses and validates a stage file as the firmware's build does
    /// ([`StageFile::validate`]); errors name the file, line, column and key.
    pub fn load(path: &Path) -> Result<(Self, ValidStage), StageError> {
        Self::load_with(path, Check::Firmware)
    }

    /// Reads, parses and validates a stage file as `check` says; errors name the file, line,
    /// column and key.
    pub fn load_with(path: &Path, check: Check) -> Result<(Self, ValidStage), StageError> {
        let file = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|e| StageError::io(&file, e))?;
        let stage = Self::parse(&file, &text)?;
        let valid = stage
            .validate_with(check)
            .map_err(|e| e.located(&file, &text))?;
        Ok((stage, valid))
    }

    /// The file's text: a comment header, then the TOML of the tables.
    pub fn to_toml(&self, header: &str) -> String {
        let mut out = String::new();
        for line in header.lines() {
            out.push_str("# ");
            out.push_str(line);
            out.push('\n');
        }
        if self.io.placeholder {
            out.push_str(
                "# [io] is a placeholder (the board's chain): set it to your DAC, amplifier, ADC \
                 and sensor,\n# or pass --stage FILE to carry it from your stage file.\n",
            );
        }
        if !header.is_empty() || self.io.placeholder {
            out.push('\n');
        }
        // Serialising plain data (strings, numbers, arrays, tables) cannot fail.
        out.push_str(&toml::to_string(self).unwrap_or_default());
        out
    }

    /// Writes the file (creating its folder), then reads it back and checks it is the same.
    pub fn write(&self, path: &Path, header: &str) -> Result<(), StageError> {
        let file = path.display().to_string();
        let text = self.to_toml(header);
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).map_err(|e| StageError::io(&file, e))?;
        }
        std::fs::write(path, &text).map_err(|e| StageError::io(&file, e))?;
        let back = Self::parse(&file, &text)?;
        if back != *self {
            return Err(StageError::new(
                &file,
                StageErrorKind::Invalid,
                "",
                "the written file does not read back to the same set (please report)".into(),
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests;
