//! The named entries of close-loop's parameter vector θ ([`super::full::AxisModel::encode`]):
//! the base model's (β, γ, n, k1, k2, y0), then each added effect's. Each [`Param`] names one
//! field of the core's [`piezo_core::BoucWenParams`], [`piezo_core::StaticMap`] or
//! [`piezo_core::effects::EffectParams`], by the field's name in reports, and writes its value
//! there ([`Param::set`], in the field's SI unit; θ holds the natural logarithm of the
//! time constants, gains and frequencies fitted on a log scale, see [`super::full::ParamSpec`]).

use super::full::AxisModel;

/// One named parameter of θ (serialised as [`Param::name`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize)]
#[serde(into = "&'static str")]
pub enum Param {
    /// Bouc-Wen β.
    Beta,
    /// Bouc-Wen γ.
    Gamma,
    /// Bouc-Wen exponent n.
    Exponent,
    /// Linear gain k1 \[m/V\].
    LinearGain,
    /// Hysteretic gain k2 \[m per unit h\].
    HysteresisGain,
    /// Sensor offset y0 \[m\].
    Offset,
    /// Logarithmic creep per decade g_log \[m/V\].
    LogCreepGain,
    /// First Kelvin–Voigt creep element's gain g₀ \[m/V\].
    CreepGain0,
    /// Second Kelvin–Voigt creep element's gain g₁ \[m/V\].
    CreepGain1,
    /// First Kelvin–Voigt creep element's time constant τ₀ \[s\].
    CreepTimeConstant0,
    /// Second Kelvin–Voigt creep element's time constant τ₁ \[s\].
    CreepTimeConstant1,
    /// Settling drift amplitude A of A·(1 − e^(−t/τ)) \[m\].
    DriftSettling,
    /// Settling drift time constant τ \[s\].
    DriftSettlingTimeConstant,
    /// Linear drift rate r of r·t \[m/s\].
    DriftRate,
    /// Output delay D \[s\].
    Delay,
    /// Even-term coefficient e of e·(u − u_c)² \[m/V²\].
    EvenCoefficient,
    /// Second-order mode frequency f \[Hz\].
    ModeFrequency,
    /// Second-order mode damping ratio ζ.
    ModeDamping,
    /// Cross-axis coupling κ.
    Coupling,
    /// Relaxation gain g of the hysteretic part.
    RelaxationGain,
    /// Relaxation time constant τ_w \[s\].
    RelaxationTimeConstant,
    /// Time constant τ_v of the lag that drives the Bouc-Wen operator \[s\].
    HysteresisLag,
    /// Second relaxation element's gain g₁.
    RelaxationGain1,
    /// Second relaxation element's time constant τ_w₁ \[s\].
    RelaxationTimeConstant1,
    /// Spread W of the relaxation times \[decades\].
    RelaxationSpread,
    /// Rate-dependent gain c of the Bouc-Wen operator, A·(1 + c·|v̇|) \[s/V\].
    HysteresisRateGain,
}

impl From<Param> for &'static str {
    fn from(param: Param) -> Self {
        param.name()
    }
}

impl Param {
    /// Every parameter, in θ's order of effects.
    pub const ALL: [Self; 26] = [
        Self::Beta,
        Self::Gamma,
        Self::Exponent,
        Self::LinearGain,
        Self::HysteresisGain,
        Self::Offset,
        Self::LogCreepGain,
        Self::CreepGain0,
        Self::CreepGain1,
        Self::CreepTimeConstant0,
        Self::CreepTimeConstant1,
        Self::DriftSettling,
        Self::DriftSettlingTimeConstant,
        Self::DriftRate,
        Self::Delay,
        Self::EvenCoefficient,
        Self::ModeFrequency,
        Self::ModeDamping,
        Self::Coupling,
        Self::RelaxationGain,
        Self::RelaxationTimeConstant,
        Self::HysteresisLag,
        Self::RelaxationGain1,
        Self::RelaxationTimeConstant1,
        Self::RelaxationSpread,
        Self::HysteresisRateGain,
    ];

    /// The Kelvin–Voigt elements' gains, element by element.
    pub const CREEP_GAINS: [Self; 2] = [Self::CreepGain0, Self::CreepGain1];

    /// The Kelvin–Voigt elements' time constants, element by element.
    pub const CREEP_TIME_CONSTANTS: [Self; 2] =
        [Self::CreepTimeConstant0, Self::CreepTimeConstant1];

    /// Name in reports: the core's field (with its element index for arrays).
    pub fn name(self) -> &'static str {
        match self {
            Self::Beta => "beta",
            Self::Gamma => "gamma",
            Self::Exponent => "n",
            Self::LinearGain => "k1_m_per_v",
            Self::HysteresisGain => "k2_m_per_h",
            Self::Offset => "offset_m",
            Self::LogCreepGain => "log_creep_gain_m_per_v",
            Self::CreepGain0 => "creep_gain_m_per_v[0]",
            Self::CreepGain1 => "creep_gain_m_per_v[1]",
            Self::CreepTimeConstant0 => "creep_time_constant_s[0]",
            Self::CreepTimeConstant1 => "creep_time_constant_s[1]",
            Self::DriftSettling => "drift_settling_m",
            Self::DriftSettlingTimeConstant => "drift_settling_time_constant_s",
            Self::DriftRate => "drift_rate_m_per_s",
            Self::Delay => "delay_s",
            Self::EvenCoefficient => "even_coefficient_m_per_v2",
            Self::ModeFrequency => "mode_frequency_hz",
            Self::ModeDamping => "mode_damping",
            Self::Coupling => "coupling",
            Self::RelaxationGain => "relaxation_gain[0]",
            Self::RelaxationTimeConstant => "relaxation_time_constant_s[0]",
            Self::HysteresisLag => "hysteresis_lag_s",
            Self::RelaxationGain1 => "relaxation_gain[1]",
            Self::RelaxationTimeConstant1 => "relaxation_time_constant_s[1]",
            Self::RelaxationSpread => "relaxation_spread_decades",
            Self::HysteresisRateGain => "hysteresis_rate_gain_s_per_v",
        }
    }

    /// Whether it is a creep gain (Kelvin–Voigt or logarithmic): a plausible one has the sign of
    /// the stage's static gain dy/du.
    pub fn is_creep_gain(self) -> bool {
        matches!(
            self,
            Self::LogCreepGain | Self::CreepGain0 | Self::CreepGain1
        )
    }

    /// Writes `value` (the parameter's own value in SI, not θ's coordinate) into its field of
    /// `model`, as the core's f32.
    pub fn set(self, model: &mut AxisModel, value: f64) {
        let v = value as f32;
        let e = &mut model.effects;
        match self {
            Self::Beta => model.bouc_wen.beta = v,
            Self::Gamma => model.bouc_wen.gamma = v,
            Self::Exponent => model.bouc_wen.n = v,
            Self::LinearGain => model.map.k1_m_per_v = v,
            Self::HysteresisGain => model.map.k2_m_per_h = v,
            Self::Offset => model.map.offset_m = v,
            Self::LogCreepGain => e.log_creep_gain_m_per_v = v,
            Self::CreepGain0 => e.creep_gain_m_per_v[0] = v,
            Self::CreepGain1 => e.creep_gain_m_per_v[1] = v,
            Self::CreepTimeConstant0 => e.creep_time_constant_s[0] = v,
            Self::CreepTimeConstant1 => e.creep_time_constant_s[1] = v,
            Self::DriftSettling => e.drift_settling_m = v,
            Self::DriftSettlingTimeConstant => e.drift_settling_time_constant_s = v,
            Self::DriftRate => e.drift_rate_m_per_s = v,
            Self::Delay => e.delay_s = v,
            Self::EvenCoefficient => e.even_coefficient_m_per_v2 = v,
            Self::ModeFrequency => e.mode_frequency_hz = v,
            Self::ModeDamping => e.mode_damping = v,
            Self::Coupling => e.coupling = v,
            Self::RelaxationGain => e.relaxation_gain[0] = v,
            Self::RelaxationTimeConstant => e.relaxation_time_constant_s[0] = v,
            Self::HysteresisLag => e.hysteresis_lag_s = v,
            Self::RelaxationGain1 => e.relaxation_gain[1] = v,
            Self::RelaxationTimeConstant1 => e.relaxation_time_constant_s[1] = v,
            Self::RelaxationSpread => e.relaxation_spread_decades = v,
            Self::HysteresisRateGain => e.hysteresis_rate_gain_s_per_v = v,
        }
    }
}

impl std::fmt::Display for Param {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashSet;

    #[test]
    fn every_parameter_has_its_own_name() {
        let names: HashSet<&str> = Param::ALL.iter().map(|p| p.name()).collect();
        assert_eq!(names.len(), Param::ALL.len());
    }
}
