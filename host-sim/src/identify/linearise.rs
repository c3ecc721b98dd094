//! The Jacobian of an identified set's output with respect to its parameters as written in the
//! report's `params`, and the residual, over the scored samples: what
//! [`crate::uncertainty::estimate`] turns into standard errors, correlations and a prediction band.
//!
//! The fit itself runs in reduced coordinates (`fit`'s module doc: A = 1, the linear parameters
//! projected out, θ = (log10(H/U), r, n[, d, p])); its covariance is that of the parameters as
//! written because the Jacobian is taken in them directly, which is the delta method applied to
//! the whole map θ, lin → params (at the optimum the projected fit and the full fit have the same
//! covariance).
//!
//! * Static models, y = k1·u + k2·h + y0: ∂y/∂k1 = u, ∂y/∂k2 = h, ∂y/∂y0 = 1 and
//!   ∂y/∂(β, γ, n, δ, φ) = k2·∂h/∂(β, γ, n, δ, φ) from the core's forward sensitivities
//!   ([`piezo_core::static_sensitivities`], exact for the core's discretisation). A is the scale
//!   convention (the Bouc-Wen scale is redundant with k2) and is held.
//! * Dynamic model: central differences of the core's f32 simulation in each of A, β, γ, n,
//!   m0, c0, k0, x0 (the force per volt, ±1, is the convention), steps 10⁻³ of the value.
//!
//! With free offsets over several records each record's offset is a parameter of its own: the
//! first record's is the reported one (the stage file keeps it), the others are nuisance columns.

use super::fit_records;
use super::model::{CoreModel, Identified, ModelKind};
use super::{simulate_records, Record};
use crate::uncertainty::{Linearised, Parameter};
use piezo_core::{static_sensitivities, SENSITIVITY_PARAMETERS};

/// Relative central-difference step of the dynamic model's parameters.
const RELATIVE_STEP: f64 = 1e-3;

/// The Jacobian and residual of `set` fitted to `record` from sample `from` (`model`: the family
/// fitted; `fit_shift`: the asymmetric model's input shift φ was fitted; `free_offset`: each
/// record had its own offset). An error for the oscillator model and for a set the core refuses.
pub fn linearise(
    set: &Identified,
    record: &Record,
    from: usize,
    model: ModelKind,
    fit_shift: bool,
    free_offset: bool,
) -> crate::Result<Linearised> {
    let (predicted, _, _) =
        fit_records(set, record, from, free_offset).map_err(crate::Error::from)?;
    let n = record.u.len();
    let residual: Vec<f64> = (from..n).map(|k| record.y_m[k] - predicted[k]).collect();
    let (parameters, mut columns, offset) = match *set {
        Identified::Static { .. } => static_columns(set, record, from, model, fit_shift)?,
        Identified::Dynamic { .. } => dynamic_columns(set, record, from)?,
        Identified::Oscillator { .. } => {
            return Err(crate::Error::Fit(
                "not computed for the oscillator model".into(),
            ));
        }
    };
    if free_offset && record.segments.len() > 1 {
        // Each record's own offset: an indicator column per record, the first one reported.
        let ranges = record.segment_ranges();
        let indicator = |(a, b): (usize, usize)| -> Vec<f64> {
            (from..n)
                .map(|k| if k >= a && k < b { 1.0 } else { 0.0 })
                .collect()
        };
        columns[offset] = indicator(ranges[0]);
        columns.extend(ranges[1..].iter().map(|&r| indicator(r)));
    }
    Ok(Linearised {
        parameters,
        columns,
        residual,
    })
}

type Columns = (Vec<Parameter>, Vec<Vec<f64>>, usize);

/// The static models' columns (module doc) and the index of the offset's.
fn static_columns(
    set: &Identified,
    record: &Record,
    from: usize,
    model: ModelKind,
    fit_shift: bool,
) -> crate::Result<Columns> {
    let Identified::Static {
        bouc_wen,
        map,
        asymmetry,
        ..
    } = *set
    else {
        return Err(crate::Error::Fit("not a static set".into()));
    };
    let Ok(CoreModel::Static(core)) = set.build() else {
        return Err(crate::Error::Fit("the core refuses the set".into()));
    };
    let u: Vec<f32> = record.u.iter().map(|&v| v as f32).collect();
    let n = u.len();
    let mut h = vec![0.0f64; n];
    let mut sens = vec![[0.0f64; SENSITIVITY_PARAMETERS]; n];
    for (a, b) in record.segment_ranges() {
        static_sensitivities(&core, &u[a..b], &mut h[a..b], &mut sens[a..b]);
    }
    let k2 = f64::from(map.k2_m_per_h);
    let mut parameters = vec![
        Parameter::new("bouc_wen.beta", f64::from(bouc_wen.beta)),
        Parameter::new("bouc_wen.gamma", f64::from(bouc_wen.gamma)),
        Parameter::new("bouc_wen.n", f64::from(bouc_wen.n)),
        Parameter::new("static_map.k1_m_per_v", f64::from(map.k1_m_per_v)),
        Parameter::new("static_map.k2_m_per_h", k2),
        Parameter::new("static_map.offset_m", f64::from(map.offset_m)),
    ];
    let sensitivity = |i: usize| -> Vec<f64> { (from..n).map(|k| k2 * sens[k][i]).collect() };
    let mut columns = vec![
        sensitivity(0),
        sensitivity(1),
        sensitivity(2),
        (from..n).map(|k| f64::from(u[k])).collect(),
        (from..n).map(|k| h[k]).collect(),
        vec![1.0; n - from],
    ];
    if model == ModelKind::Asymmetric {
        parameters.push(Parameter::new(
            "asymmetry.delta_per_v_s",
            f64::from(asymmetry.delta_per_v_s),
        ));
        columns.push(sensitivity(3));
        if fit_shift {
            parameters.push(Parameter::new(
                "asymmetry.input_shift_s",
                f64::from(asymmetry.input_shift_s),
            ));
            columns.push(sensitivity(4));
        }
    }
    Ok((parameters, columns, 5))
}

/// The dynamic model's columns by central differences (module doc) and the index of x0's.
fn dynamic_columns(set: &Identified, record: &Record, from: usize) -> crate::Result<Columns> {
    const NAMES: [&str; 8] = [
        "bouc_wen.a",
        "bouc_wen.beta",
        "bouc_wen.gamma",
        "bouc_wen.n",
        "mass_spring_damper.mass_kg",
        "mass_spring_damper.damping_n_s_per_m",
        "mass_spring_damper.stiffness_n_per_m",
        "mass_spring_damper.rest_position_m",
    ];
    fn field(set: &mut Identified, i: usize) -> Option<&mut f32> {
        let Identified::Dynamic {
            bouc_wen: bw,
            mechanics: m,
            ..
        } = set
        else {
            return None;
        };
        Some(match i {
            0 => &mut bw.a,
            1 => &mut bw.beta,
            2 => &mut bw.gamma,
            3 => &mut bw.n,
            4 => &mut m.mass_kg,
            5 => &mut m.damping_n_s_per_m,
            6 => &mut m.stiffness_n_per_m,
            _ => &mut m.rest_position_m,
        })
    }
    let simulate = |s: &Identified| -> Option<Vec<f64>> {
        let model = s.build().ok()?;
        let y = simulate_records(&model, record);
        y[from..]
            .iter()
            .all(|v| v.is_finite())
            .then(|| y[from..].to_vec())
    };
    let base = simulate(set).ok_or_else(|| crate::Error::Fit("the core refuses the set".into()))?;
    let mut parameters = Vec::new();
    let mut columns = Vec::new();
    for (i, name) in NAMES.iter().enumerate() {
        let mut s = *set;
        let value = f64::from(
            *field(&mut s, i).ok_or_else(|| crate::Error::Fit("not a dynamic set".into()))?,
        );
        parameters.push(Parameter::new(*name, value));
        // x0's step on the scale of the output; the others relative to their value.
        let scale = if i == 7 {
            value
                .abs()
                .max(base.iter().fold(0.0f64, |m, v| m.max(v.abs())))
        } else {
            value.abs()
        };
        let h = RELATIVE_STEP * if scale > 0.0 { scale } else { 1.0 };
        let moved = |delta: f64| -> Option<(f64, Vec<f64>)> {
            let mut t = *set;
            let slot = field(&mut t, i)?;
            *slot = (value + delta) as f32;
            let actual = f64::from(*slot) - value;
            simulate(&t).map(|y| (actual, y))
        };
        let column = match (moved(h), moved(-h)) {
            (Some((a, ya)), Some((b, yb))) => {
                ya.iter().zip(&yb).map(|(p, m)| (p - m) / (a - b)).collect()
            }
            (Some((a, y)), None) | (None, Some((a, y))) => {
                y.iter().zip(&base).map(|(p, q)| (p - q) / a).collect()
            }
            (None, None) => {
                return Err(crate::Error::Fit(format!(
                    "the core refuses the set with {name} moved by ±{:.0e} of its value",
                    RELATIVE_STEP
                )))
            }
        };
        columns.push(column);
    }
    Ok((parameters, columns, 7))
}

#[cfg(test)]
mod tests {
    use super::*;
    use piezo_core::{Asymmetry, BoucWenParams, StaticMap};

    /// The sensitivity columns agree with central differences of the core's own simulation.
    #[test]
    fn static_columns_match_differences_of_the_simulation() {
        let n = 1500;
        let t_s: Vec<f64> = (0..n).map(|k| k as f64 * 1e-3).collect();
        let u: Vec<f64> = t_s
            .iter()
            .map(|t| 50.0 - 50.0 * (2.0 * std::f64::consts::PI * t).cos())
            .collect();
        let set = Identified::Static {
            bouc_wen: BoucWenParams {
                a: 1.0,
                beta: 0.02,
                gamma: 0.01,
                n: 1.3,
            },
            map: StaticMap {
                k1_m_per_v: 3e-7,
                k2_m_per_h: -2e-7,
                offset_m: 1e-6,
            },
            asymmetry: Asymmetry {
                delta_per_v_s: 0.05,
                input_shift_s: 2e-4,
            },
            sample_period_s: 1e-3,
            input_range_v: (0.0, 100.0),
        };
        let model = set.build().unwrap();
        let y = simulate_records(
            &model,
            &Record::from_parts("r".into(), t_s.clone(), u.clone(), vec![0.0; n]),
        );
        let record = Record::from_parts("r".into(), t_s, u, y);
        let (params, cols, _) =
            static_columns(&set, &record, 0, ModelKind::Asymmetric, true).unwrap();
        assert_eq!(params.len(), 8);
        let with = |i: usize, v: f32| -> Vec<f64> {
            let mut s = set;
            if let Identified::Static {
                bouc_wen,
                map,
                asymmetry,
                ..
            } = &mut s
            {
                *[
                    &mut bouc_wen.beta,
                    &mut bouc_wen.gamma,
                    &mut bouc_wen.n,
                    &mut map.k1_m_per_v,
                    &mut map.k2_m_per_h,
                    &mut map.offset_m,
                    &mut asymmetry.delta_per_v_s,
                    &mut asymmetry.input_shift_s,
                ][i] = v;
            }
            simulate_records(&s.build().unwrap(), &record)
        };
        for (i, col) in cols.iter().enumerate() {
            let v = params[i].value as f32;
            let h = 1e-2 * v.abs();
            let (p, m) = (with(i, v + h), with(i, v - h));
            let step = f64::from(v + h) - f64::from(v - h);
            let diff: Vec<f64> = p.iter().zip(&m).map(|(a, b)| (a - b) / step).collect();
            let norm = diff.iter().map(|d| d * d).sum::<f64>().sqrt();
            let err = diff
                .iter()
                .zip(col)
                .map(|(d, c)| (d - c).powi(2))
                .sum::<f64>()
                .sqrt();
            assert!(err < 0.02 * norm, "{}: {err:e} of {norm:e}", params[i].name);
        }
    }
}
