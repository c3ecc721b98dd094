//! Identified parameter sets, the core model each one builds, and the parameter file.
//!
//! Every model simulated here — while fitting and while predicting — is piezo-core's f32 model
//! (`StaticModel`, `StaticModel::asymmetric`, `DynamicModel`), the one the firmware runs. Each set is
//! validated by the core as the stage file validates it: `BoucWen::with_input_range(params, u_min,
//! u_max, STATE_LIMIT)` over the input range of the record, then the model constructor. A set the
//! core refuses is infeasible.
//!
//! A set becomes one axis of the stage file (`piezo_stage::Axis`, [`to_axis`]): the model's tables,
//! the identified input range as the output window, and the provenance (`[x.identified]`).

use piezo_core::{
    Asymmetry, BoucWen, BoucWenParams, DynamicModel, MassSpringDamperParams, ModelState,
    ParamError, StaticMap, StaticModel,
};
use piezo_stage::{Axis, Limits, Provenance};

/// Largest |h| accepted for a range-limited Bouc-Wen set (β + γ ≤ 0): the stage file's.
pub const STATE_LIMIT: f32 = piezo_stage::STATE_LIMIT;

/// The model families `identify` fits: the stage file's own [`piezo_stage::ModelKind`], with
/// its command-line names (`symmetric`, `asymmetric`, `dynamic`, `oscillator`).
pub use piezo_stage::ModelKind;

/// One identified parameter set, in SI units. Serialised as its parameters, named as in the core's
/// structs: `bouc_wen`, then `static_map` and `asymmetry`, `mass_spring_damper` or `oscillator`,
/// with `sample_period_s` and `input_range_v` (`substeps` for the oscillator).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
#[serde(untagged)]
pub enum Identified {
    /// Static (and asymmetric static) model.
    Static {
        /// Bouc-Wen parameters.
        bouc_wen: BoucWenParams,
        /// y = k1·u + k2·h + y0.
        #[serde(rename = "static_map")]
        map: StaticMap,
        /// δ and φ (zero for the symmetric model).
        asymmetry: Asymmetry,
        /// Sample period the asymmetric terms were identified at \[s\].
        sample_period_s: f32,
        /// Validated input range \[V\].
        input_range_v: (f32, f32),
    },
    /// Mass–spring–damper with Bouc-Wen forcing.
    Dynamic {
        /// Bouc-Wen parameters.
        bouc_wen: BoucWenParams,
        /// Mechanics.
        #[serde(rename = "mass_spring_damper")]
        mechanics: MassSpringDamperParams,
        /// Sample period of the discretisation \[s\].
        sample_period_s: f32,
        /// Validated input range \[V\].
        input_range_v: (f32, f32),
    },
    /// Hysteretic oscillator of the Bouc-Wen benchmark.
    Oscillator {
        /// Parameters.
        #[serde(rename = "oscillator")]
        params: piezo_core::OscillatorParams,
        /// Sample period \[s\].
        sample_period_s: f32,
        /// Input upsampling factor: the core runs at sample_period_s / substeps (one RK4 step each)
        /// on the band-limited interpolated input (see `identify::oscillator`).
        substeps: u32,
    },
}

/// A built core model, ready to simulate.
pub enum CoreModel {
    /// Static or asymmetric.
    Static(StaticModel),
    /// Dynamic.
    Dynamic(DynamicModel),
    /// Oscillator.
    Oscillator(piezo_core::HystereticOscillator),
}

/// Validates a Bouc-Wen set over an input range exactly as the firmware's build does.
pub fn bouc_wen(params: BoucWenParams, range: (f32, f32)) -> Result<BoucWen, ParamError> {
    BoucWen::with_input_range(params, range.0, range.1, STATE_LIMIT)
}

impl Identified {
    /// The model family.
    pub fn kind(&self) -> ModelKind {
        match self {
            Self::Static { asymmetry, .. } => {
                if *asymmetry == Asymmetry::default() {
                    ModelKind::Symmetric
                } else {
                    ModelKind::Asymmetric
                }
            }
            Self::Dynamic { .. } => ModelKind::Dynamic,
            Self::Oscillator { .. } => ModelKind::Oscillator,
        }
    }

    /// Builds (and so validates) the core model.
    pub fn build(&self) -> Result<CoreModel, ParamError> {
        match *self {
            Self::Static {
                bouc_wen: bw,
                map,
                asymmetry,
                sample_period_s,
                input_range_v,
            } => {
                let h = bouc_wen(bw, input_range_v)?;
                Ok(CoreModel::Static(StaticModel::with_asymmetry(
                    h,
                    map,
                    asymmetry,
                    sample_period_s,
                )?))
            }
            Self::Dynamic {
                bouc_wen: bw,
                mechanics,
                sample_period_s,
                input_range_v,
            } => Ok(CoreModel::Dynamic(DynamicModel::new(
                bouc_wen(bw, input_range_v)?,
                mechanics,
                sample_period_s,
            )?)),
            Self::Oscillator {
                params,
                sample_period_s,
                substeps,
            } => Ok(CoreModel::Oscillator(
                piezo_core::HystereticOscillator::new(params, sample_period_s, substeps)?,
            )),
        }
    }
}

impl CoreModel {
    /// Simulates from rest at `u[0]` and calls `visit(k, y_k)` for every sample. No allocation.
    pub fn simulate(&self, u: &[f32], mut visit: impl FnMut(usize, f32)) {
        let Some(&u0) = u.first() else { return };
        match self {
            Self::Static(m) => {
                let mut s = ModelState::at_rest(u0);
                for (k, &v) in u.iter().enumerate() {
                    visit(k, m.step(&mut s, v));
                }
            }
            Self::Dynamic(m) => {
                let mut s = m.at_rest(u0);
                for (k, &v) in u.iter().enumerate() {
                    visit(k, m.step(&mut s, v));
                }
            }
            Self::Oscillator(m) => {
                let mut s = piezo_core::OscillatorState::default();
                for (k, &v) in u.iter().enumerate() {
                    visit(k, m.step(&mut s, v));
                }
            }
        }
    }
}

/// The stage-file axis of a set: its model tables, limits = the validated input range (the
/// window the firmware may drive; the oscillator: the force range), the stage file's default slew
/// ([`piezo_stage::DEFAULT_SLEW_LIMIT_V_PER_S`]), and where it came from.
pub fn to_axis(set: &Identified, provenance: Provenance) -> Axis {
    let limits = |range: (f32, f32)| Limits {
        output_min_v: range.0,
        output_max_v: range.1,
        slew_limit_v_per_s: piezo_stage::DEFAULT_SLEW_LIMIT_V_PER_S,
        envelope_policy: Default::default(),
    };
    let mut axis = match *set {
        Identified::Static {
            bouc_wen,
            map,
            asymmetry,
            input_range_v,
            ..
        } => Axis::static_model(bouc_wen, map, asymmetry, limits(input_range_v)),
        Identified::Dynamic {
            bouc_wen,
            mechanics,
            input_range_v,
            ..
        } => {
            let mut axis = Axis::static_model(
                bouc_wen,
                StaticMap {
                    k1_m_per_v: 1.0,
                    k2_m_per_h: 0.0,
                    offset_m: 0.0,
                },
                Asymmetry::default(),
                limits(input_range_v),
            );
            axis.model = ModelKind::Dynamic;
            axis.static_map = None;
            axis.mass_spring_damper = Some(mechanics);
            axis
        }
        Identified::Oscillator {
            params, substeps, ..
        } => {
            let range = (provenance.input_range_v[0], provenance.input_range_v[1]);
            let mut axis = Axis::static_model(
                BoucWenParams {
                    a: 1.0,
                    beta: 0.0,
                    gamma: 0.0,
                    n: 1.0,
                },
                StaticMap {
                    k1_m_per_v: 1.0,
                    k2_m_per_h: 0.0,
                    offset_m: 0.0,
                },
                Asymmetry::default(),
                limits(range),
            );
            axis.model = ModelKind::Oscillator;
            axis.bouc_wen = None;
            axis.static_map = None;
            axis.oscillator = Some(params);
            axis.substeps = Some(substeps);
            axis
        }
    };
    axis.identified = Some(provenance);
    axis
}

/// The set of a stage-file axis, with the sample period `sample_period_s` \[s\] of the record it
/// will simulate and its Bouc-Wen input range `input_range_v` \[V\].
pub fn from_axis(
    axis: &Axis,
    sample_period_s: f32,
    input_range_v: (f32, f32),
) -> crate::Result<Identified> {
    let need = |what: &str| {
        crate::Error::Usage(format!("model \"{}\" without `{what}`", axis.model.name()))
    };
    Ok(match axis.model {
        ModelKind::Symmetric | ModelKind::Asymmetric => Identified::Static {
            bouc_wen: axis.bouc_wen.ok_or_else(|| need("bouc_wen"))?,
            map: axis.static_map.ok_or_else(|| need("static_map"))?,
            asymmetry: axis.asymmetry.unwrap_or_default(),
            sample_period_s,
            input_range_v,
        },
        ModelKind::Dynamic => Identified::Dynamic {
            bouc_wen: axis.bouc_wen.ok_or_else(|| need("bouc_wen"))?,
            mechanics: axis
                .mass_spring_damper
                .ok_or_else(|| need("mass_spring_damper"))?,
            sample_period_s,
            input_range_v,
        },
        ModelKind::Oscillator => Identified::Oscillator {
            params: axis.oscillator.ok_or_else(|| need("oscillator"))?,
            sample_period_s,
            substeps: axis.substeps.unwrap_or(1),
        },
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::json_keys as keys;
    use std::collections::BTreeSet;

    const BOUC_WEN: BoucWenParams = BoucWenParams {
        a: 1.0,
        beta: 0.02,
        gamma: 0.015,
        n: 1.5,
    };

    /// Each family serialises as its parameters, named as in the core's structs, with no tag.
    #[test]
    fn each_family_serialises_as_its_parameters() {
        let bouc_wen = BTreeSet::from(["a", "beta", "gamma", "n"]);
        let static_set = Identified::Static {
            bouc_wen: BOUC_WEN,
            map: StaticMap {
                k1_m_per_v: 1e-6,
                k2_m_per_h: -5e-7,
                offset_m: 1e-7,
            },
            asymmetry: Asymmetry {
                delta_per_v_s: 1e-4,
                input_shift_s: 0.0,
            },
            sample_period_s: 1e-4,
            input_range_v: (0.0, 120.0),
        };
        let json = crate::to_json(&static_set).unwrap();
        assert_eq!(
            keys(&json),
            BTreeSet::from([
                "bouc_wen",
                "static_map",
                "asymmetry",
                "sample_period_s",
                "input_range_v",
            ])
        );
        assert_eq!(keys(&json["bouc_wen"]), bouc_wen);
        assert_eq!(
            keys(&json["static_map"]),
            BTreeSet::from(["k1_m_per_v", "k2_m_per_h", "offset_m"])
        );
        assert_eq!(
            keys(&json["asymmetry"]),
            BTreeSet::from(["delta_per_v_s", "input_shift_s"])
        );
        // f32 figures widened to f64, as every report writes them.
        assert_eq!(json["static_map"]["k1_m_per_v"], f64::from(1e-6f32));
        assert_eq!(json["input_range_v"], serde_json::json!([0.0, 120.0]));

        let dynamic = Identified::Dynamic {
            bouc_wen: BOUC_WEN,
            mechanics: MassSpringDamperParams {
                mass_kg: 0.01,
                damping_n_s_per_m: 5.0,
                stiffness_n_per_m: 1e5,
                rest_position_m: 0.0,
                force_per_volt_n_per_v: 0.1,
            },
            sample_period_s: 1e-4,
            input_range_v: (0.0, 120.0),
        };
        let json = crate::to_json(&dynamic).unwrap();
        assert_eq!(
            keys(&json),
            BTreeSet::from([
                "bouc_wen",
                "mass_spring_damper",
                "sample_period_s",
                "input_range_v",
            ])
        );
        assert_eq!(
            keys(&json["mass_spring_damper"]),
            BTreeSet::from([
                "mass_kg",
                "damping_n_s_per_m",
                "stiffness_n_per_m",
                "rest_position_m",
                "force_per_volt_n_per_v",
            ])
        );

        let oscillator = Identified::Oscillator {
            params: piezo_core::OscillatorParams::BENCHMARK,
            sample_period_s: 1.0 / 750.0,
            substeps: 4,
        };
        let json = crate::to_json(&oscillator).unwrap();
        assert_eq!(
            keys(&json),
            BTreeSet::from(["oscillator", "sample_period_s", "substeps"])
        );
        assert_eq!(
            keys(&json["oscillator"]),
            BTreeSet::from([
                "mass_kg",
                "damping_n_s_per_m",
                "stiffness_n_per_m",
                "alpha_n_per_m",
                "beta_per_m",
                "gamma",
                "delta",
                "nu",
            ])
        );
        assert_eq!(json["substeps"], 4);
    }
}
