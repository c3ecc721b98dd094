//! # piezo-core
//!
//! The one implementation of the piezo hysteresis model that the firmware, the host simulation and the
//! identification all call: the rate-independent Bouc-Wen operator stepped in input increments
//! ([`bouc_wen`]), its output maps — the static map of seed 001 with its asymmetric variant
//! ([`static_model`]) and the mass–spring–damper of seed 000 ([`dynamic_model`]) — the inverse
//! feedforward compensator ([`compensator`]), the two-axis inverse of the effect chain around it
//! ([`inverse_chain`]), the learning step for repeated trajectories ([`learning`]), the error
//! measures of the seeds ([`metrics`]), and the hysteretic oscillator of the Bouc-Wen benchmark
//! ([`oscillator`]). The types the loop, the stage file and the command link share are defined
//! here once: an axis's output limits ([`limits`]) and the reference generator's programs
//! ([`program`]).
//!
//! `no_std`, no allocation, `unsafe` forbidden, f32 on the per-sample path, SI units (volts, metres,
//! seconds, newtons). Parameters are validated once, when built, into types that cannot hold an invalid
//! set; the per-sample steps then return plain values, never fail and never panic. Settings (the
//! validated parameter types) are kept apart from state (`*State` structs), so a new parameter set can
//! take over between two samples from the same state.
#![no_std]
#![forbid(unsafe_code)]

pub mod axis;
pub mod bouc_wen;
pub mod compensator;
pub mod dynamic_model;
pub mod effects;
pub mod envelope;
pub mod error;
#[cfg(test)]
mod fixtures;
pub mod fnv;
pub mod inverse_chain;
pub mod io_chain;
pub mod learning;
pub mod limits;
pub mod math;
pub mod metrics;
pub mod on_target;
pub mod oscillator;
pub mod program;
pub mod sensitivity;
pub mod servo;
pub mod static_model;

pub use axis::AxisParams;
pub use bouc_wen::{
    max_input_span, BoucWen, BoucWenParams, BoundClass, HysteresisState, STATE_LIMIT,
};
pub use compensator::{
    fastest_invertible_slew_v_per_s, is_invertible_slope_range, Command, CommandStatus,
    Compensator, CompensatorSettings, CompensatorState, ZeroReach, MIN_WINDOW_TICKS,
};
pub use dynamic_model::{DynamicModel, DynamicState, MassSpringDamperParams};
pub use envelope::{Envelope, EnvelopeCounts, EnvelopeMonitor, EnvelopePolicy};
pub use error::{ParamError, MIN_SLOPE_RATIO};
pub use fnv::{fnv1a32, Fnv1a32};
pub use inverse_chain::{
    compensate_pair, compensate_periodic_pair, compensate_periodic_single, compensate_single,
    FeedforwardAxis, FeedforwardCounts, InverseChain, PeriodicSettings, PeriodicSettling,
};
pub use io_chain::IoChain;
pub use learning::{
    pass_noise_rms, Learning, LearningParams, PreviousTrial, StepSummary, Trial, TrialNoise,
    GAIN_FIT_MIN_R2, HARMONIC_MODEL_FACTOR, HARMONIC_MODEL_PHASE_RAD, HARMONIC_SNR,
    HARMONIC_STEP_CAP, MAX_HARMONICS, UNMODELLED_MODE_DAMPING,
};
pub use limits::Limits;
pub use on_target::{OnTarget, OnTargetState};
pub use oscillator::{HystereticOscillator, OscillatorParams, OscillatorState};
pub use program::{Program, Wave};
pub use sensitivity::{static_sensitivities, SENSITIVITY_PARAMETERS};
pub use servo::{Servo, ServoMode, ServoOutput, ServoParams, ServoState, ServoStatus};
pub use static_model::{Asymmetry, ModelState, StaticMap, StaticModel, ASYMMETRIC_STATE_FACTOR};
