//! The one error type of the core: every way a parameter set can be refused when a model or a
//! compensator is built. The per-sample paths never return errors.
//!
//! Each variant names the offending field (as spelled in the parameter structs and in the parameter
//! file) and carries the numbers that made the check fail, so that a caller can print a message that
//! says what to change.

use core::fmt;

/// Why a parameter set was refused. Built once, when a model or compensator is constructed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ParamError {
    /// A field is NaN or ±∞.
    NonFinite {
        /// Field name, e.g. `"beta"`.
        field: &'static str,
    },
    /// A field is outside the interval in which the model is defined or physical.
    OutOfRange {
        /// Field name, e.g. `"mass_kg"`.
        field: &'static str,
        /// The value given.
        value: f32,
        /// What the field must satisfy, e.g. `"> 0"`.
        requirement: &'static str,
    },
    /// The Bouc-Wen set is outside the classes whose state can be bounded at all
    /// (β < 0 after normalising A > 0: unloading pumps |h| up, inner loops ratchet without bound).
    UnboundableClass {
        /// β as given.
        beta: f32,
        /// γ after normalising to A > 0 (γ·sgn A).
        gamma_normalised: f32,
    },
    /// β + γ ≤ 0 (after normalising A > 0): the state grows without bound on loading, and no
    /// finite input range was given to restrict it to.
    UnboundedWithoutRange {
        /// β + γ·sgn A.
        beta_plus_gamma: f32,
    },
    /// β + γ ≤ 0 and the declared input span drives |h| above the declared state limit.
    /// `max_span_v` is the largest input span for which |h| stays within `state_limit`.
    StateLimitExceeded {
        /// Declared input span u_max − u_min \[V\].
        span_v: f32,
        /// Declared limit on |h|.
        state_limit: f32,
        /// Largest admissible span for that limit \[V\] (0 if none).
        max_span_v: f32,
    },
    /// The forward map y(u) is not strictly monotone over the reachable states, so the one-step
    /// inverse does not exist everywhere. `min_slope` and `max_slope` are the extreme values of
    /// dy/du over the reachable set (in output units per volt).
    NotInvertible {
        /// Smallest dy/du over reachable states and both directions.
        min_slope: f32,
        /// Largest dy/du over reachable states and both directions.
        max_slope: f32,
    },
    /// A field is finite and inside the model's domain but physically implausible: a
    /// dimensionless measure of it (`measure`, e.g. the creep's settled gain over the model's
    /// linear gain) exceeds the bound `limit` the core documents for it.
    Implausible {
        /// Field name, e.g. `"creep_gain_m_per_v[0]"`.
        field: &'static str,
        /// The value given.
        value: f32,
        /// What was measured, in words with its formula.
        measure: &'static str,
        /// The measure's value.
        ratio: f32,
        /// Its largest accepted value.
        limit: f32,
    },
    /// The output window ([`crate::Limits`]) reaches outside the stack voltages the DAC and the
    /// amplifier can produce, `dac_range_v × amplifier_gain_v_per_v`.
    WindowOutsideDrive {
        /// The window, lowest and highest voltage \[V\].
        window_v: [f32; 2],
        /// The lowest and highest stack voltage the chain drives \[V\].
        drive_v: [f32; 2],
    },
    /// The sensor's output span reaches outside the ADC's input span.
    SensorOutsideAdc {
        /// The sensor's span \[V\].
        sensor_range_v: [f32; 2],
        /// The ADC's input span \[V\].
        adc_range_v: [f32; 2],
    },
    /// A setting hands the axis to its feedback servo (`envelope_policy = "feedback-only"`), and
    /// the axis has none.
    NeedsServo {
        /// Field name, e.g. `"envelope_policy"`.
        field: &'static str,
    },
    /// The discretised mass–spring–damper could not be built (its matrix exponential did not
    /// converge or produced non-finite coefficients) for this sample period.
    Discretisation {
        /// Sample period \[s\] that was asked for.
        sample_period_s: f32,
    },
}

impl fmt::Display for ParamError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            ParamError::NonFinite { field } => write!(f, "field `{field}` is not a finite number"),
            ParamError::OutOfRange {
                field,
                value,
                requirement,
            } => write!(f, "field `{field}` = {value} is out of range: must be {requirement}"),
            ParamError::UnboundableClass {
                beta,
                gamma_normalised,
            } => write!(
                f,
                "Bouc-Wen fields `beta` = {beta}, `gamma` (normalised to A > 0) = {gamma_normalised}: \
                 beta < 0 lets unloading increase |h| (inner loops ratchet), so the state has no bound \
                 on any input range; beta must be >= 0"
            ),
            ParamError::UnboundedWithoutRange { beta_plus_gamma } => write!(
                f,
                "Bouc-Wen fields `beta` + `gamma` (normalised to A > 0) = {beta_plus_gamma} <= 0: the \
                 state grows without bound on loading; build the model with a finite input range and \
                 a state limit (BoucWen::with_input_range) to use this set over that range only"
            ),
            ParamError::StateLimitExceeded {
                span_v,
                state_limit,
                max_span_v,
            } => write!(
                f,
                "Bouc-Wen set with beta + gamma <= 0: over an input span of {span_v:.1} V the state \
                 reaches |h| > {state_limit}; it stays within |h| <= {state_limit} only for input \
                 spans up to {max_span_v:.1} V (narrow the input range or raise the state limit)"
            ),
            ParamError::NotInvertible {
                min_slope,
                max_slope,
            } => write!(
                f,
                "the forward map is not strictly monotone in u over the reachable hysteresis states \
                 (dy/du ranges over [{min_slope}, {max_slope}]; it must keep one sign and \
                 min/max |dy/du| >= {MIN_SLOPE_RATIO}); the inverse compensator would not be unique"
            ),
            ParamError::Implausible {
                field,
                value,
                measure,
                ratio,
                limit,
            } => write!(
                f,
                "field `{field}` = {value} is implausible: {measure} is {ratio:e}, at most {limit} \
                 is accepted"
            ),
            ParamError::WindowOutsideDrive {
                window_v: [u0, u1],
                drive_v: [d0, d1],
            } => write!(
                f,
                "the output window [{u0}, {u1}] V exceeds what the DAC and amplifier drive: \
                 io.dac_range_v × io.amplifier_gain_v_per_v = [{d0}, {d1}] V"
            ),
            ParamError::SensorOutsideAdc {
                sensor_range_v: [s0, s1],
                adc_range_v: [a0, a1],
            } => write!(
                f,
                "the sensor span [{s0}, {s1}] V exceeds the ADC's input span [{a0}, {a1}] V"
            ),
            ParamError::NeedsServo { field } => write!(
                f,
                "field `{field}` hands the axis to its feedback servo, and the axis has none \
                 (add a servo, or use \"warn\")"
            ),
            ParamError::Discretisation { sample_period_s } => write!(
                f,
                "could not discretise the mass-spring-damper at `sample_period_s` = {sample_period_s} s"
            ),
        }
    }
}

/// So that a caller's error can name the core's refusal as its `source()`.
impl core::error::Error for ParamError {}

/// Smallest accepted ratio min|dy/du| / max|dy/du| for an invertible map: the inverse amplifies an
/// error in the reference by at most the inverse of this ratio relative to its best direction.
pub const MIN_SLOPE_RATIO: f32 = 0.01;

/// Checks that `value` is finite.
pub(crate) fn finite(field: &'static str, value: f32) -> Result<f32, ParamError> {
    if value.is_finite() {
        Ok(value)
    } else {
        Err(ParamError::NonFinite { field })
    }
}

/// Checks that `value` is finite and strictly positive.
pub(crate) fn positive(field: &'static str, value: f32) -> Result<f32, ParamError> {
    finite(field, value)?;
    if value > 0.0 {
        Ok(value)
    } else {
        Err(ParamError::OutOfRange {
            field,
            value,
            requirement: "> 0",
        })
    }
}
