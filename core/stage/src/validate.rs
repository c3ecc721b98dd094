//! Validation: the core's constructors, called the same way for every consumer, and the chain
//! they build.
//!
//! Forward chain of a static axis (piezo-core `StaticModel` then `effects::Effects`), per sample k
//! at the sample period T it was built for:
//! `w[k] = k1·u[k] + k2·h[k] + y0`, `z[k] = M(w + e·(u[k−1] − u_c)² + creep)[k]`,
//! `y[k] = z(k − D) + drift(t_k) + κ·z_other(k − D)`; see `piezo_core::effects` for each term.

use crate::error::{StageError, StageErrorKind};
use crate::{Axis, Io, ModelKind, StageFile, STATE_LIMIT};
use piezo_core::effects::{couple, Effects, EffectsState, OperatingRange};
use piezo_core::{
    Asymmetry, BoucWen, Compensator, CompensatorSettings, DynamicModel, EnvelopeMonitor,
    EnvelopePolicy, HystereticOscillator, IoChain, ModelState, OnTarget, OscillatorState,
    ParamError, Servo, StaticModel,
};

/// Strokes a piezo stage plausibly has over its output window \[m\]: 10 nm to 10 mm. A stage
/// file whose model gives a stroke outside is refused (a record read in the wrong unit).
pub const PLAUSIBLE_STROKE_M: (f64, f64) = (1e-8, 1e-2);

/// The built model of one axis at one sample period.
// Built once per validation and copied by value like the core's models: boxing the static chain
// would cost an allocation for nothing.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Clone, Copy)]
pub enum AxisChain {
    /// A static (symmetric or asymmetric) model followed by the effect chain: what the firmware runs.
    Static {
        /// The hysteresis model.
        model: StaticModel,
        /// The effects around it.
        effects: Effects,
    },
    /// The mass–spring–damper model (no effects).
    Dynamic(DynamicModel),
    /// The benchmark oscillator (no effects).
    Oscillator(HystereticOscillator),
}

/// One validated axis.
#[derive(Debug, Clone, Copy)]
pub struct ValidAxis {
    /// `x` or `y`.
    pub name: &'static str,
    /// The model family.
    pub kind: ModelKind,
    /// The chain at the sample period it was built for.
    pub chain: AxisChain,
    /// The inverse compensator (static models whose map is invertible, built by
    /// [`StageFile::validate`]).
    pub compensator: Option<Compensator>,
    /// Secant gain of the first loading over the output window \[m/V\] (static models; the
    /// uncompensated baseline).
    pub linear_gain_m_per_v: f32,
    /// Output at `output_min_v` at rest \[m\].
    pub rest_output_m: f32,
    /// The Bouc-Wen input range the model was built over \[V\].
    pub input_range_v: (f32, f32),
    /// The feedback servo (`[x.servo]`, built by [`StageFile::validate`] with the output limits
    /// and the loop period).
    pub servo: Option<Servo>,
    /// The identified envelope's per-tick check at the loop period (`[x.identified]` with
    /// `[x.limits] envelope_policy`, [`Axis::envelope`]; built by [`StageFile::validate`]).
    pub envelope: Option<EnvelopeMonitor>,
    /// The on-target band (`[x.on_target]`, its defaults from `[io]` and the loop rate,
    /// [`Axis::on_target_band`]; set by [`StageFile::validate`]).
    pub on_target: OnTarget,
}

/// A validated stage file at its loop rate: what the firmware runs.
#[derive(Debug, Clone)]
pub struct ValidStage {
    /// Loop period \[s\].
    pub sample_period_s: f32,
    /// The axes, x first.
    pub axes: Vec<ValidAxis>,
}

fn located(key: String, e: ParamError) -> StageError {
    StageError::core(&key, e)
}

/// The key path a core error names, for an axis `name`.
fn core_key(name: &str, e: &ParamError, section: &str) -> String {
    match e {
        ParamError::NonFinite { field }
        | ParamError::OutOfRange { field, .. }
        | ParamError::Implausible { field, .. } => {
            let section = match *field {
                "output_min_v" | "output_max_v" | "slew_limit_v_per_s" => "limits",
                "input_min_v" | "input_max_v" => "limits",
                "input_range_v" | "input_rate_max_v_per_s" => "identified",
                "k1_m_per_v" | "k2_m_per_h" | "offset_m" => "static_map",
                "delta_per_v_s" | "input_shift_s" => "asymmetry",
                "hysteresis_lag_s" | "hysteresis_rate_gain_s_per_v" => "effects",
                "sample_period_s" => return "stage.loop_rate_hz".into(),
                _ => section,
            };
            format!("{name}.{section}.{field}")
        }
        ParamError::UnboundableClass { .. } => format!("{name}.bouc_wen.beta"),
        ParamError::UnboundedWithoutRange { .. } | ParamError::StateLimitExceeded { .. } => {
            format!("{name}.bouc_wen")
        }
        ParamError::NotInvertible { .. } => format!("{name}.static_map"),
        ParamError::WindowOutsideDrive { .. } => format!("{name}.limits.output_max_v"),
        ParamError::SensorOutsideAdc { .. } => "io.sensor_range_v".into(),
        ParamError::NeedsServo { field } => format!("{name}.limits.{field}"),
        ParamError::Discretisation { .. } => format!("{name}.{section}"),
    }
}

fn missing(name: &str, table: &str, kind: ModelKind) -> StageError {
    StageError::new(
        "",
        StageErrorKind::Invalid,
        &format!("{name}.{table}"),
        format!("missing table: model \"{}\" needs it", kind.name()),
    )
}

impl Axis {
    /// Builds this axis's chain (axis `name`) for the sample period `sample_period_s` \[s\] with
    /// the Bouc-Wen state validated over the input range `input_range_v` \[V\]. No compensator.
    pub fn build(
        &self,
        name: &'static str,
        sample_period_s: f32,
        input_range_v: (f32, f32),
    ) -> Result<ValidAxis, StageError> {
        let bouc_wen = || -> Result<BoucWen, StageError> {
            let params = self
                .bouc_wen
                .ok_or_else(|| missing(name, "bouc_wen", self.model))?;
            BoucWen::with_input_range(params, input_range_v.0, input_range_v.1, STATE_LIMIT)
                .map_err(|e| located(core_key(name, &e, "bouc_wen"), e))
        };
        let (mut linear_gain_m_per_v, mut rest_output_m) = (0.0, 0.0);
        let chain = match self.model {
            ModelKind::Symmetric | ModelKind::Asymmetric => {
                let hysteresis = bouc_wen()?;
                let map = self
                    .static_map
                    .ok_or_else(|| missing(name, "static_map", self.model))?;
                let model = if self.model == ModelKind::Asymmetric {
                    let asymmetry = self
                        .asymmetry
                        .ok_or_else(|| missing(name, "asymmetry", self.model))?;
                    StaticModel::asymmetric(hysteresis, map, asymmetry, sample_period_s)
                } else {
                    if self.asymmetry.is_some_and(|a| a != Asymmetry::default()) {
                        return Err(StageError::new(
                            "",
                            StageErrorKind::Invalid,
                            &format!("{name}.asymmetry"),
                            "given for model \"symmetric\": set model = \"asymmetric\" or remove it"
                                .into(),
                        ));
                    }
                    StaticModel::new(hysteresis, map)
                }
                .map_err(|e| located(core_key(name, &e, "static_map"), e))?;
                let (u0, u1) = (self.limits.output_min_v, self.limits.output_max_v);
                let (rest, gain) = model.first_loading(u0, u1);
                if !(gain.is_finite() && gain != 0.0) {
                    return Err(StageError::new(
                        "",
                        StageErrorKind::Invalid,
                        &format!("{name}.limits"),
                        format!("the model gives no stroke over the output window (first-loading gain {gain} m/V)"),
                    ));
                }
                let stroke_m = f64::from(gain).abs() * (f64::from(u1) - f64::from(u0));
                let (lo, hi) = PLAUSIBLE_STROKE_M;
                if !(lo..=hi).contains(&stroke_m) {
                    return Err(StageError::new(
                        "",
                        StageErrorKind::Invalid,
                        &format!("{name}.static_map.k1_m_per_v"),
                        format!(
                            "the model's stroke over the output window {u0}–{u1} V is {stroke_m:.3e} m \
                             (first-loading gain {gain:.3e} m/V), outside the {lo:.0e}–{hi:.0e} m a piezo \
                             stage has: was the record's output read in the unit its column name says?"
                        ),
                    ));
                }
                let range = OperatingRange::first_loading(rest, gain, (u0, u1));
                let effects = Effects::new(self.effects, sample_period_s, range).map_err(|e| {
                    let key = match e {
                        ParamError::NonFinite { field } | ParamError::OutOfRange { field, .. }
                            if field == "sample_period_s" =>
                        {
                            "stage.loop_rate_hz".to_string()
                        }
                        ParamError::NonFinite { field }
                        | ParamError::OutOfRange { field, .. }
                        | ParamError::Implausible { field, .. } => {
                            format!("{name}.effects.{field}")
                        }
                        _ => format!("{name}.effects.mode_frequency_hz"),
                    };
                    located(key, e)
                })?;
                // The first loading above is the quasi-static one: the lag enters here.
                let model = effects.hysteresis_model(model).map_err(|e| {
                    let field = match &e {
                        ParamError::NonFinite { field } | ParamError::OutOfRange { field, .. } => {
                            field
                        }
                        _ => "hysteresis_lag_s",
                    };
                    located(format!("{name}.effects.{field}"), e)
                })?;
                linear_gain_m_per_v = gain;
                rest_output_m = rest;
                AxisChain::Static { model, effects }
            }
            ModelKind::Dynamic => {
                let mechanics = self
                    .mass_spring_damper
                    .ok_or_else(|| missing(name, "mass_spring_damper", self.model))?;
                let model = DynamicModel::new(bouc_wen()?, mechanics, sample_period_s)
                    .map_err(|e| located(core_key(name, &e, "mass_spring_damper"), e))?;
                AxisChain::Dynamic(model)
            }
            ModelKind::Oscillator => {
                let params = self
                    .oscillator
                    .ok_or_else(|| missing(name, "oscillator", self.model))?;
                let substeps = self.substeps.unwrap_or(1);
                AxisChain::Oscillator(
                    HystereticOscillator::new(params, sample_period_s, substeps)
                        .map_err(|e| located(core_key(name, &e, "oscillator"), e))?,
                )
            }
        };
        if !matches!(chain, AxisChain::Static { .. }) && self.effects != Default::default() {
            return Err(StageError::new(
                "",
                StageErrorKind::Invalid,
                &format!("{name}.effects"),
                "effects run around the static models only (symmetric, asymmetric)".into(),
            ));
        }
        Ok(ValidAxis {
            name,
            kind: self.model,
            chain,
            compensator: None,
            linear_gain_m_per_v,
            rest_output_m,
            input_range_v,
            servo: None,
            envelope: None,
            on_target: OnTarget {
                tolerance_m: f32::MAX,
                ticks: 1,
            },
        })
    }
}

impl Axis {
    /// The axis's envelope check at the loop period `sample_period_s` \[s\]
    /// ([`Axis::envelope`], [`piezo_core::AxisParams::envelope_monitor`]): refused when the
    /// policy is `feedback-only` and the axis has no `[x.identified]` envelope or no servo.
    fn envelope_monitor(
        &self,
        name: &str,
        sample_period_s: f32,
    ) -> Result<Option<EnvelopeMonitor>, StageError> {
        let Some(envelope) = self.envelope() else {
            if self.limits.envelope_policy == EnvelopePolicy::FeedbackOnly {
                return Err(invalid(
                    &format!("{name}.limits.envelope_policy"),
                    format!(
                        "\"feedback-only\" acts outside the identified envelope, and the axis has \
                         none: add [{name}.identified] (identify or close-loop write it) or use \"warn\""
                    ),
                ));
            }
            return Ok(None);
        };
        let policy = self.limits.envelope_policy;
        if policy == EnvelopePolicy::FeedbackOnly && self.servo.is_none() {
            let e = ParamError::NeedsServo {
                field: "envelope_policy",
            };
            return Err(located(core_key(name, &e, "limits"), e));
        }
        envelope
            .monitor(policy, sample_period_s)
            .map(Some)
            .map_err(|e| located(core_key(name, &e, "identified"), e))
    }
}

/// The `[x.on_target]` key a core refusal of the band names.
fn on_target_field(e: &ParamError) -> &'static str {
    match e {
        ParamError::NonFinite { field } | ParamError::OutOfRange { field, .. } => field,
        _ => "tolerance_m",
    }
}

fn invalid(key: &str, message: String) -> StageError {
    StageError::new("", StageErrorKind::Invalid, key, message)
}

impl Io {
    /// The chain as the core checks it (part names aside).
    pub fn chain(&self) -> IoChain {
        IoChain {
            dac_range_v: self.dac_range_v,
            amplifier_gain_v_per_v: self.amplifier_gain_v_per_v,
            adc_range_v: self.adc_range_v,
            sensor_range_v: self.sensor_range_v,
            sensor_m_per_v: self.sensor_m_per_v,
        }
    }

    /// The chain's own consistency ([`IoChain::check`]): finite positive gains, ordered spans,
    /// the sensor span inside the ADC's.
    pub fn check(&self) -> Result<(), StageError> {
        self.chain().check().map_err(|e| {
            let key = match e {
                ParamError::NonFinite { field }
                | ParamError::OutOfRange { field, .. }
                | ParamError::Implausible { field, .. } => format!("io.{field}"),
                _ => "io.sensor_range_v".into(),
            };
            located(key, e)
        })
    }
}

/// How much of the firmware's check a reader of the stage file needs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Check {
    /// What a forward simulation of the file needs (`host-sim predict`): the loop rate, the io
    /// chain's own consistency ([`Io::check`]), and per axis the output window, the model of its
    /// family with its effects at the loop period over that window, the compensator's settings
    /// and the servo. Every value the firmware's check reads is checked, but a set need not be
    /// invertible, nor its window inside the drive span, to be simulated: a static set the
    /// compensator refuses as `NotInvertible` is accepted without one, and the window is not
    /// held against `io.dac_range_v × io.amplifier_gain_v_per_v`.
    Models,
    /// Everything the firmware's build checks with piezo-stage: [`Check::Models`], then per static
    /// axis its compensator and its output window inside what the DAC and amplifier drive.
    Firmware,
}

impl StageFile {
    /// Validates the whole file at its loop rate, as the firmware runs it: every axis built over its
    /// output window with its compensator, the io chain checked and the output windows inside
    /// what the DAC and amplifier can drive ([`Check::Firmware`]). Errors carry the key path;
    /// [`StageFile::load`] adds the file, line and column.
    pub fn validate(&self) -> Result<ValidStage, StageError> {
        self.validate_with(Check::Firmware)
    }

    /// Validates the file as `check` says; [`StageFile::validate`] is `Check::Firmware`.
    pub fn validate_with(&self, check: Check) -> Result<ValidStage, StageError> {
        let rate = self.stage.loop_rate_hz;
        if !(rate.is_finite() && rate > 0.0) {
            return Err(invalid(
                "stage.loop_rate_hz",
                format!("{rate} must be finite and > 0"),
            ));
        }
        let sample_period_s = 1.0 / rate;
        self.io.check()?;
        let chain = self.io.chain();
        let mut axes = Vec::new();
        for (name, axis) in self.axes() {
            let l = axis.limits;
            if !(l.output_min_v.is_finite()
                && l.output_max_v.is_finite()
                && l.output_min_v < l.output_max_v)
            {
                return Err(invalid(
                    &format!("{name}.limits"),
                    format!(
                        "output window [{}, {}] V must be finite with min < max",
                        l.output_min_v, l.output_max_v
                    ),
                ));
            }
            let mut valid = axis.build(name, sample_period_s, (l.output_min_v, l.output_max_v))?;
            let settings = CompensatorSettings {
                limits: l,
                sample_period_s,
            };
            if let AxisChain::Static { model, .. } = valid.chain {
                // The compensator runs a hair inside the slew limit, as the firmware's loop runs
                // it in front of its exact output guard (`CompensatorSettings::inside_guard`).
                match (Compensator::new(model, settings.inside_guard()), check) {
                    (Ok(compensator), _) => valid.compensator = Some(compensator),
                    // A forward simulation needs no inverse; every other refusal (the window,
                    // the slew limit) is a value the file must not hold.
                    (Err(ParamError::NotInvertible { .. }), Check::Models) => {}
                    (
                        Err(ParamError::OutOfRange {
                            field: "hysteresis_rate_gain_s_per_v",
                            ..
                        }),
                        Check::Models,
                    ) => {}
                    (
                        Err(
                            e @ ParamError::OutOfRange {
                                field: "hysteresis_rate_gain_s_per_v",
                                ..
                            },
                        ),
                        Check::Firmware,
                    ) => {
                        // Say how fast the model can be inverted: the slew limit that would do.
                        let inside = settings.inside_guard();
                        let fastest = piezo_core::fastest_invertible_slew_v_per_s(
                            &model,
                            l.output_max_v - l.output_min_v,
                            sample_period_s,
                        );
                        return Err(invalid(
                            &format!("{name}.effects.hysteresis_rate_gain_s_per_v"),
                            format!(
                                "{e}; at the slew limit {} V/s the map is not monotone over the \
                                 states and gains it reaches: set {name}.limits.\
                                 slew_limit_v_per_s to at most {fastest:.0} V/s, or lower the gain",
                                inside.limits.slew_limit_v_per_s
                            ),
                        ));
                    }
                    (Err(e), _) => return Err(located(core_key(name, &e, "limits"), e)),
                }
            }
            if let (AxisChain::Static { .. }, Check::Firmware) = (valid.chain, check) {
                chain
                    .check_limits(&settings)
                    .map_err(|e| located(core_key(name, &e, "limits"), e))?;
            }
            if let Some(params) = axis.servo {
                if !matches!(valid.chain, AxisChain::Static { .. }) {
                    return Err(invalid(
                        &format!("{name}.servo"),
                        "the servo runs around the static models only (symmetric, asymmetric)"
                            .into(),
                    ));
                }
                valid.servo = Some(
                    Servo::new(params, settings.inside_guard(), valid.linear_gain_m_per_v)
                        .map_err(|e| located(core_key(name, &e, "servo"), e))?,
                );
            }
            valid.envelope = axis.envelope_monitor(name, sample_period_s)?;
            valid.on_target = axis
                .on_target_band(&chain, sample_period_s)
                .map_err(|e| located(format!("{name}.on_target.{}", on_target_field(&e)), e))?;
            axes.push(valid);
        }
        Ok(ValidStage {
            sample_period_s,
            axes,
        })
    }
}

impl AxisChain {
    /// Simulates one axis (no coupling) from rest at `u_v[0]`: `visit(k, y_k)` per sample.
    pub fn simulate(&self, u_v: &[f32], mut visit: impl FnMut(usize, f32)) {
        let Some(&u0) = u_v.first() else { return };
        match self {
            Self::Static { model, effects } => {
                let mut s = ModelState::at_rest(u0);
                let mut e = EffectsState::at_rest(u0);
                for (k, &u) in u_v.iter().enumerate() {
                    let w = model.step(&mut s, u);
                    effects.forward_z(&mut e, s.input_v, w);
                    visit(k, effects.output_m(&e));
                }
            }
            Self::Dynamic(m) => {
                let mut s = m.at_rest(u0);
                for (k, &u) in u_v.iter().enumerate() {
                    visit(k, m.step(&mut s, u));
                }
            }
            Self::Oscillator(m) => {
                let mut s = OscillatorState::default();
                for (k, &u) in u_v.iter().enumerate() {
                    visit(k, m.step(&mut s, u));
                }
            }
        }
    }
}

/// Simulates two static axes with their coupling, each from rest at its first input:
/// `y_x = z_x(k − D_x) + drift_x + κ_x·z_y(k − D_x)` and the same for y (`piezo_core::effects`).
/// Writes `min` of the lengths samples into `y_out`.
pub fn simulate_pair(
    x: (&StaticModel, &Effects),
    y: (&StaticModel, &Effects),
    u_v: [&[f32]; 2],
    y_out: [&mut [f32]; 2],
) {
    let n = u_v[0]
        .len()
        .min(u_v[1].len())
        .min(y_out[0].len())
        .min(y_out[1].len());
    if n == 0 {
        return;
    }
    let [ox, oy] = y_out;
    let mut sx = ModelState::at_rest(u_v[0][0]);
    let mut sy = ModelState::at_rest(u_v[1][0]);
    let mut ex = EffectsState::at_rest(u_v[0][0]);
    let mut ey = EffectsState::at_rest(u_v[1][0]);
    for k in 0..n {
        let wx = x.0.step(&mut sx, u_v[0][k]);
        let wy = y.0.step(&mut sy, u_v[1][k]);
        x.1.forward_z(&mut ex, sx.input_v, wx);
        y.1.forward_z(&mut ey, sy.input_v, wy);
        let kx = x.1.params().coupling;
        let ky = y.1.params().coupling;
        let (cx, _) = couple(kx, 0.0, x.1.delayed_z(&ex), x.1.delayed_z(&ey));
        let (_, cy) = couple(0.0, ky, y.1.delayed_z(&ex), y.1.delayed_z(&ey));
        ox[k] = cx + x.1.drift_m(&ex);
        oy[k] = cy + y.1.drift_m(&ey);
    }
}
