//! Simulated plants: f64 state-space systems driven by input voltages, integrated by [`crate::sim`].
//!
//! Each plant documents its equation, parameters and source. States are SI (m, m/s, rad, N or V for the
//! hysteresis state as the source defines it). None of them calls `piezo-core`.

use std::fmt;

mod bipolar_stack;
mod nac2024;
mod relaxing_stack;
mod stage;
mod xy_stage;

pub use bipolar_stack::BipolarStack;
pub use nac2024::{Nac2024, SecondMode};
pub use relaxing_stack::RelaxingStack;
pub use stage::{AsymmetricStage, StageCase};
pub use xy_stage::{XyAxis, XyStage};

/// The linear form of a plant while every input is held (zero-order hold, u̇ = 0), for the exact
/// propagation over holds of [`crate::sim`] (see [`crate::hold`]).
///
/// With the inputs held, the plant's right-hand side must be f(x) = A·x + g with g constant over the
/// hold (g may depend on the held inputs and on the states the hold freezes), and its free
/// displacement ([`Plant::free_displacement`]) F·x + const. The states a hold freezes (the
/// hysteresis states: ḣ = 0 when u̇ = 0) have zero rows in A; their columns may be anything,
/// zero included, since their contribution to f is constant over the hold. A and F must not depend on
/// the held input values.
#[derive(Debug, Clone, PartialEq)]
pub struct HeldLinear {
    /// A, state_dim × state_dim, row-major.
    pub a: Vec<f64>,
    /// F, outputs × state_dim, row-major: ∂(free displacement)/∂x during a hold.
    pub free_displacement: Vec<f64>,
}

/// Input values seen by a plant at any time (needed by plants with an input time shift).
pub trait InputAt {
    /// (u in V, u̇ in V/s) of input `channel` at `t_s`.
    fn input(&self, channel: usize, t_s: f64) -> (f64, f64);
}

/// Plant errors.
#[derive(Debug, Clone, PartialEq)]
pub enum PlantError {
    /// Unknown plant name.
    UnknownPlant {
        /// Given.
        given: String,
    },
    /// The input would leave the range over which the parameter set is valid.
    InputOutOfRange {
        /// Plant.
        plant: &'static str,
        /// Input span asked for, V.
        span_v: f64,
        /// Largest valid span, V.
        max_span_v: f64,
        /// Why.
        reason: &'static str,
    },
    /// The hysteresis state left its valid range during simulation.
    HysteresisOutOfRange {
        /// Plant.
        plant: &'static str,
        /// |h| reached.
        value: f64,
        /// Limit.
        limit: f64,
    },
    /// An effect or option that this plant does not have.
    Unsupported {
        /// Plant.
        plant: &'static str,
        /// What was asked.
        what: String,
    },
    /// A parameter that is out of range.
    BadParameter {
        /// Name.
        name: &'static str,
        /// Value.
        value: f64,
    },
}

impl fmt::Display for PlantError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::UnknownPlant { given } => {
                write!(f, "unknown plant `{given}`; valid plants: {PLANT_NAMES}")
            }
            Self::InputOutOfRange {
                plant,
                span_v,
                max_span_v,
                reason,
            } => write!(
                f,
                "{plant}: input span {span_v:.3} V exceeds the valid {max_span_v} V ({reason})"
            ),
            Self::HysteresisOutOfRange {
                plant,
                value,
                limit,
            } => {
                write!(
                    f,
                    "{plant}: |h| reached {value:.3e}, above the validity limit {limit}"
                )
            }
            Self::Unsupported { plant, what } => write!(f, "{plant} does not support {what}"),
            Self::BadParameter { name, value } => {
                write!(f, "parameter {name} = {value} is out of range")
            }
        }
    }
}

impl std::error::Error for PlantError {}

/// Plant names accepted by [`PlantKind::from_name`].
pub const PLANT_NAMES: &str =
    "nac2024, stage, xy-stage, bipolar-stack, relaxing-stack, relaxing-stack-shaped, relaxing-stack-stiff";

/// A reference plant.
pub trait Plant: Send + Sync {
    /// Short name.
    fn name(&self) -> &'static str;
    /// CSV names of the inputs (`u_V`, or `ux_V`, `uy_V`).
    fn input_names(&self) -> &'static [&'static str];
    /// CSV names of the outputs (`y_m`, or `x_m`, `y_m`).
    fn output_names(&self) -> &'static [&'static str];
    /// Number of states.
    fn state_dim(&self) -> usize;
    /// Rest state at zero input and zero hysteresis state.
    fn initial_state(&self, x: &mut [f64]);
    /// State derivative.
    fn rhs(&self, t_s: f64, x: &[f64], input: &dyn InputAt, dx: &mut [f64]);
    /// Instantaneous monotone jump of input `channel` from `u_from` to `u_to` (zero-order-hold step): moves the
    /// hysteresis state along its rate-independent path; mechanical states are continuous.
    fn input_jump(&self, x: &mut [f64], channel: usize, u_from: f64, u_to: f64);
    /// Measured outputs (m) from state and present inputs.
    fn output(&self, x: &[f64], u: &[f64], y: &mut [f64]);
    /// Quasi-static actuator displacement per output (m), the drive of the creep effect.
    fn free_displacement(&self, x: &[f64], u: &[f64], out: &mut [f64]);
    /// Sample rate of the sensor of the source paper, Hz.
    fn default_sample_rate_hz(&self) -> f64;
    /// Refuses inputs outside the parameter set's validity.
    fn check_input_span(&self, u_min_v: f64, u_max_v: f64) -> Result<(), PlantError>;
    /// Checks a state during simulation.
    fn check_state(&self, _x: &[f64]) -> Result<(), PlantError> {
        Ok(())
    }
    /// The plant's linear form while every input is held ([`HeldLinear`]), or `None` when the plant is
    /// not linear between input jumps (the default): [`crate::sim::simulate`] then integrates every
    /// segment with the adaptive Dormand–Prince pair.
    fn held_input_linear(&self) -> Option<HeldLinear> {
        None
    }
    /// Adds an electrostrictive quadratic term: the linear drive k·u becomes k·(u + e·u²), `e` in 1/V.
    fn set_electrostriction(&mut self, per_v: f64);
}

/// Electrostrictive drive u + e·u² and its derivative.
pub(crate) fn drive(u: f64, du: f64, e_per_v: f64) -> (f64, f64) {
    (u + e_per_v * u * u, du * (1.0 + 2.0 * e_per_v * u))
}

/// One of the plants, by name.
#[allow(clippy::large_enum_variant)] // a handful of plants per run; boxing buys nothing
#[derive(Debug, Clone, PartialEq)]
pub enum PlantKind {
    /// Seed 000 actuator.
    Nac2024(Nac2024),
    /// Seed 001 stage (Case III by default).
    Stage(AsymmetricStage),
    /// Seed 002 XY stage.
    XyStage(XyStage),
    /// Bipolar stack with a spread of dielectric relaxation times and a 740 Hz mode.
    BipolarStack(BipolarStack),
    /// Bipolar stack whose whole strain relaxes (loops widen with rate), saturating, 740 Hz mode.
    RelaxingStack(RelaxingStack),
}

impl PlantKind {
    /// `nac2024`, `stage` (Case III; `stage-case1`, `stage-case2` also accepted), `xy-stage`,
    /// `bipolar-stack`, `relaxing-stack`, `relaxing-stack-shaped` ([`RelaxingStack::shaped`]),
    /// `relaxing-stack-stiff` ([`RelaxingStack::stiff`]).
    pub fn from_name(name: &str) -> Result<Self, PlantError> {
        Ok(match name {
            "nac2024" => Self::Nac2024(Nac2024::published()),
            "stage" | "stage-case3" => Self::Stage(AsymmetricStage::new(StageCase::III)),
            "stage-case1" => Self::Stage(AsymmetricStage::new(StageCase::I)),
            "stage-case2" => Self::Stage(AsymmetricStage::new(StageCase::II)),
            "xy-stage" => Self::XyStage(XyStage::default()),
            "bipolar-stack" => Self::BipolarStack(BipolarStack::default()),
            "relaxing-stack" => Self::RelaxingStack(RelaxingStack::default()),
            "relaxing-stack-shaped" => Self::RelaxingStack(RelaxingStack::shaped()),
            "relaxing-stack-stiff" => Self::RelaxingStack(RelaxingStack::stiff()),
            other => {
                return Err(PlantError::UnknownPlant {
                    given: other.into(),
                })
            }
        })
    }
    /// The plant as a trait object.
    pub fn as_plant(&self) -> &dyn Plant {
        match self {
            Self::Nac2024(p) => p,
            Self::Stage(p) => p,
            Self::XyStage(p) => p,
            Self::BipolarStack(p) => p,
            Self::RelaxingStack(p) => p,
        }
    }
    /// Mutable trait object.
    pub fn as_plant_mut(&mut self) -> &mut dyn Plant {
        match self {
            Self::Nac2024(p) => p,
            Self::Stage(p) => p,
            Self::XyStage(p) => p,
            Self::BipolarStack(p) => p,
            Self::RelaxingStack(p) => p,
        }
    }
}

/// The ±100 V drive the bipolar stacks accept: refuses an input outside −100 V .. 100 V, naming
/// `plant`.
pub(crate) fn check_bipolar_span(
    plant: &'static str,
    reason: &'static str,
    u_min_v: f64,
    u_max_v: f64,
) -> Result<(), PlantError> {
    if u_min_v < -100.0 || u_max_v > 100.0 {
        return Err(PlantError::InputOutOfRange {
            plant,
            span_v: u_max_v - u_min_v,
            max_span_v: 200.0,
            reason,
        });
    }
    Ok(())
}
