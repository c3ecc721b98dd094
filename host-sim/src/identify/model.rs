//! Identified parameter sets, the core model each one builds, and the parameter file.
//!
//! Every model simulated here — while fitting and while predicting — is piezo-core's f32 model
//! (`StaticModel`, `StaticModel::asymmetric`, `DynamicModel`), the one the firmware runs. Each set is
//! validated by the core exactly as the firmware's `build/params.rs` validates it:
//! `BoucWen::with_input_range(params, u_min, u_max, 1e6)` over the input range of the record, then the
//! model constructor. A set the core refuses is infeasible.
//!
//! The parameter file is the firmware's format (`firmware/params/xy-stage.toml`: `[x.bouc_wen]`,
//! `[x.static_map]`, `[x.limits]` and the same for `y`, both axes holding the one identified set) plus
//! tables the firmware ignores: `[identification]` (model, method, record), `[x.asymmetry]` and
//! `[x.mass_spring_damper]`. For the dynamic model, `[x.static_map]` holds its quasi-static map
//! (k1/k0, 1/k0, x0), which is what the firmware's static compensator can use.

use piezo_core::{
    Asymmetry, BoucWen, BoucWenParams, DynamicModel, MassSpringDamperParams, ModelState,
    ParamError, StaticMap, StaticModel,
};

/// Largest |h| accepted for a range-limited Bouc-Wen set (β + γ ≤ 0), as in the firmware's build.
pub const STATE_LIMIT: f32 = 1e6;

/// The model families `identify` fits.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ModelKind {
    /// y = k1·u + k2·h + y0 (seed 001 eq. 1).
    Symmetric,
    /// Seed 001's asymmetric reading: δ-term and input shift φ (core `StaticModel::asymmetric`).
    Asymmetric,
    /// Seed 000: m0·ẍ + c0·ẋ + k0·(x − x0) = k1·u + h (core `DynamicModel`).
    Dynamic,
    /// Benchmark oscillator m·ÿ + c·ẏ + k·y + z = u (core `HystereticOscillator`).
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
}

/// One identified parameter set, in SI units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Identified {
    /// Static (and asymmetric static) model.
    Static {
        /// Bouc-Wen parameters.
        bouc_wen: BoucWenParams,
        /// y = k1·u + k2·h + y0.
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
        mechanics: MassSpringDamperParams,
        /// Sample period of the discretisation \[s\].
        sample_period_s: f32,
        /// Validated input range \[V\].
        input_range_v: (f32, f32),
    },
    /// Hysteretic oscillator of the Bouc-Wen benchmark.
    Oscillator {
        /// Parameters.
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
                let m = if asymmetry == Asymmetry::default() {
                    StaticModel::new(h, map)?
                } else {
                    StaticModel::asymmetric(h, map, asymmetry, sample_period_s)?
                };
                Ok(CoreModel::Static(m))
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

    /// JSON of the parameters (SI, names as in the core's structs).
    pub fn to_json(&self) -> serde_json::Value {
        use serde_json::json;
        let bw = |p: &BoucWenParams| json!({"a": p.a, "beta": p.beta, "gamma": p.gamma, "n": p.n});
        match self {
            Self::Static {
                bouc_wen,
                map,
                asymmetry,
                sample_period_s,
                input_range_v,
            } => json!({
                "bouc_wen": bw(bouc_wen),
                "static_map": {"k1_m_per_v": map.k1_m_per_v, "k2_m_per_h": map.k2_m_per_h, "offset_m": map.offset_m},
                "asymmetry": {"delta_per_v_s": asymmetry.delta_per_v_s, "input_shift_s": asymmetry.input_shift_s},
                "sample_period_s": sample_period_s,
                "input_range_v": [input_range_v.0, input_range_v.1],
            }),
            Self::Dynamic {
                bouc_wen,
                mechanics: m,
                sample_period_s,
                input_range_v,
            } => json!({
                "bouc_wen": bw(bouc_wen),
                "mass_spring_damper": {
                    "mass_kg": m.mass_kg, "damping_n_s_per_m": m.damping_n_s_per_m,
                    "stiffness_n_per_m": m.stiffness_n_per_m, "rest_position_m": m.rest_position_m,
                    "force_per_volt_n_per_v": m.force_per_volt_n_per_v},
                "sample_period_s": sample_period_s,
                "input_range_v": [input_range_v.0, input_range_v.1],
            }),
            Self::Oscillator {
                params: p,
                sample_period_s,
                substeps,
            } => json!({
                "oscillator": {
                    "mass_kg": p.mass_kg, "damping_n_s_per_m": p.damping_n_s_per_m,
                    "stiffness_n_per_m": p.stiffness_n_per_m, "alpha_n_per_m": p.alpha_n_per_m,
                    "beta_per_m": p.beta_per_m, "gamma": p.gamma, "delta": p.delta, "nu": p.nu},
                "sample_period_s": sample_period_s,
                "substeps": substeps,
            }),
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

fn num(v: f32) -> String {
    format!("{v:?}")
}

/// The parameter file text (firmware format plus the tables described in the module doc).
pub fn to_toml(set: &Identified, method: &str, data: &str, start_s: f64) -> String {
    let mut out = String::new();
    out.push_str(&format!(
        "# Identified by `host-sim identify` ({} model, method {method}) from {data},\n\
         # fitted from t = {start_s} s. SI units. Both axes hold the one identified set.\n\
         # [io] is not identified: set it to your amplifier and sensor.\n\
         name = \"identified-{}\"\nversion = \"{method}\"\nloop_rate_hz = 10000.0\n\n\
         [io]\namplifier_gain_v_per_v = 1.0\nsensor_m_per_v = 1.0e-5\n\n\
         [identification]\nmodel = \"{}\"\nmethod = \"{method}\"\ndata = {data:?}\nstart_s = {start_s:?}\n",
        set.kind().name(),
        set.kind().name(),
        set.kind().name()
    ));
    match *set {
        Identified::Static {
            sample_period_s, ..
        }
        | Identified::Dynamic {
            sample_period_s, ..
        } => out.push_str(&format!("sample_period_s = {}\n", num(sample_period_s))),
        Identified::Oscillator {
            params: p,
            sample_period_s,
            substeps,
        } => {
            out.push_str(&format!(
                "sample_period_s = {}\nsubsteps = {substeps}\n\n[oscillator]\nmass_kg = {}\n\
                 damping_n_s_per_m = {}\nstiffness_n_per_m = {}\nalpha_n_per_m = {}\nbeta_per_m = {}\n\
                 gamma = {}\ndelta = {}\nnu = {}\n",
                num(sample_period_s),
                num(p.mass_kg),
                num(p.damping_n_s_per_m),
                num(p.stiffness_n_per_m),
                num(p.alpha_n_per_m),
                num(p.beta_per_m),
                num(p.gamma),
                num(p.delta),
                num(p.nu)
            ));
            return out;
        }
    }
    for axis in ["x", "y"] {
        let (bw, map, range) = match *set {
            Identified::Static {
                bouc_wen,
                map,
                input_range_v,
                ..
            } => (bouc_wen, map, input_range_v),
            Identified::Dynamic {
                bouc_wen,
                mechanics: m,
                input_range_v,
                ..
            } => (
                bouc_wen,
                StaticMap {
                    k1_m_per_v: m.force_per_volt_n_per_v / m.stiffness_n_per_m,
                    k2_m_per_h: 1.0 / m.stiffness_n_per_m,
                    offset_m: m.rest_position_m,
                },
                input_range_v,
            ),
            Identified::Oscillator { .. } => unreachable!("returned above"),
        };
        out.push_str(&format!(
            "\n[{axis}.bouc_wen]\na = {}\nbeta = {}\ngamma = {}\nn = {}\n\n[{axis}.static_map]\n\
             k1_m_per_v = {}\nk2_m_per_h = {}\noffset_m = {}\n\n[{axis}.limits]\noutput_min_v = {}\n\
             output_max_v = {}\nslew_limit_v_per_s = 1.0e5\n",
            num(bw.a),
            num(bw.beta),
            num(bw.gamma),
            num(bw.n),
            num(map.k1_m_per_v),
            num(map.k2_m_per_h),
            num(map.offset_m),
            num(range.0),
            num(range.1)
        ));
        match *set {
            Identified::Static { asymmetry, .. } if asymmetry != Asymmetry::default() => out
                .push_str(&format!(
                    "\n[{axis}.asymmetry]\ndelta_per_v_s = {}\ninput_shift_s = {}\n",
                    num(asymmetry.delta_per_v_s),
                    num(asymmetry.input_shift_s)
                )),
            Identified::Dynamic { mechanics: m, .. } => out.push_str(&format!(
                "\n[{axis}.mass_spring_damper]\nmass_kg = {}\ndamping_n_s_per_m = {}\n\
                 stiffness_n_per_m = {}\nrest_position_m = {}\nforce_per_volt_n_per_v = {}\n",
                num(m.mass_kg),
                num(m.damping_n_s_per_m),
                num(m.stiffness_n_per_m),
                num(m.rest_position_m),
                num(m.force_per_volt_n_per_v)
            )),
            _ => {}
        }
    }
    out
}

fn field(file: &str, t: &toml::Table, path: &str, key: &str) -> Result<f32, String> {
    match t.get(key) {
        Some(toml::Value::Float(f)) => Ok(*f as f32),
        Some(toml::Value::Integer(i)) => Ok(*i as f32),
        Some(_) => Err(format!("{file}: `{path}.{key}` must be a number")),
        None => Err(format!("{file}: missing field `{path}.{key}`")),
    }
}

fn sub<'a>(
    file: &str,
    t: &'a toml::Table,
    path: &str,
    key: &str,
) -> Result<&'a toml::Table, String> {
    match t.get(key) {
        Some(toml::Value::Table(s)) => Ok(s),
        _ => Err(format!("{file}: missing table `{path}{key}`")),
    }
}

/// Reads a parameter file written by [`to_toml`] (the x axis for two-axis files) and validates it
/// with the core.
pub fn from_toml(file: &str, text: &str) -> Result<Identified, String> {
    let root: toml::Table = text
        .parse()
        .map_err(|e| format!("{file}: not a valid TOML file: {e}"))?;
    let id = sub(file, &root, "", "identification")?;
    let model = match id.get("model") {
        Some(toml::Value::String(s)) => s.as_str(),
        _ => return Err(format!("{file}: missing `identification.model`")),
    };
    let t = field(file, id, "identification", "sample_period_s")?;
    let set = if model == "oscillator" {
        let o = sub(file, &root, "", "oscillator")?;
        let f = |k| field(file, o, "oscillator", k);
        let substeps = field(file, id, "identification", "substeps")? as u32;
        Identified::Oscillator {
            params: piezo_core::OscillatorParams {
                mass_kg: f("mass_kg")?,
                damping_n_s_per_m: f("damping_n_s_per_m")?,
                stiffness_n_per_m: f("stiffness_n_per_m")?,
                alpha_n_per_m: f("alpha_n_per_m")?,
                beta_per_m: f("beta_per_m")?,
                gamma: f("gamma")?,
                delta: f("delta")?,
                nu: f("nu")?,
            },
            sample_period_s: t,
            substeps,
        }
    } else {
        let x = sub(file, &root, "", "x")?;
        let bw = sub(file, x, "x.", "bouc_wen")?;
        let bouc_wen = BoucWenParams {
            a: field(file, bw, "x.bouc_wen", "a")?,
            beta: field(file, bw, "x.bouc_wen", "beta")?,
            gamma: field(file, bw, "x.bouc_wen", "gamma")?,
            n: field(file, bw, "x.bouc_wen", "n")?,
        };
        let lim = sub(file, x, "x.", "limits")?;
        let range = (
            field(file, lim, "x.limits", "output_min_v")?,
            field(file, lim, "x.limits", "output_max_v")?,
        );
        match model {
            "symmetric" | "asymmetric" => {
                let m = sub(file, x, "x.", "static_map")?;
                let map = StaticMap {
                    k1_m_per_v: field(file, m, "x.static_map", "k1_m_per_v")?,
                    k2_m_per_h: field(file, m, "x.static_map", "k2_m_per_h")?,
                    offset_m: field(file, m, "x.static_map", "offset_m")?,
                };
                let asymmetry = match x.get("asymmetry") {
                    Some(toml::Value::Table(a)) => Asymmetry {
                        delta_per_v_s: field(file, a, "x.asymmetry", "delta_per_v_s")?,
                        input_shift_s: field(file, a, "x.asymmetry", "input_shift_s")?,
                    },
                    _ => Asymmetry::default(),
                };
                Identified::Static {
                    bouc_wen,
                    map,
                    asymmetry,
                    sample_period_s: t,
                    input_range_v: range,
                }
            }
            "dynamic" => {
                let m = sub(file, x, "x.", "mass_spring_damper")?;
                let p = "x.mass_spring_damper";
                Identified::Dynamic {
                    bouc_wen,
                    mechanics: MassSpringDamperParams {
                        mass_kg: field(file, m, p, "mass_kg")?,
                        damping_n_s_per_m: field(file, m, p, "damping_n_s_per_m")?,
                        stiffness_n_per_m: field(file, m, p, "stiffness_n_per_m")?,
                        rest_position_m: field(file, m, p, "rest_position_m")?,
                        force_per_volt_n_per_v: field(file, m, p, "force_per_volt_n_per_v")?,
                    },
                    sample_period_s: t,
                    input_range_v: range,
                }
            }
            other => {
                return Err(format!(
                    "{file}: `identification.model` = {other:?}: expected symmetric, asymmetric, dynamic or oscillator"
                ))
            }
        }
    };
    set.build()
        .map_err(|e| format!("{file}: refused by piezo-core: {e}"))?;
    Ok(set)
}
