//! The parameter file: parse, validate with `piezo-core`'s own constructors, and emit Rust consts.
//!
//! Shared by `build.rs` (which turns `firmware/params/xy-stage.toml`, or the file named by the
//! environment variable `PIEZO_PARAMS`, into `OUT_DIR/params.rs`) and by the host test
//! `firmware/tests/params_file.rs` (which checks the error messages). Every refusal names the file
//! and the field (`x.bouc_wen.gamma`), so a bad file gives a build error that says what to change.
//!
//! File layout (all numbers SI; see `firmware/params/xy-stage.toml`):
//!
//! ```toml
//! name = "xy-stage"            # with `version`: the version string logged at boot
//! version = "1"
//! loop_rate_hz = 10000.0
//! [io]                         # amplifier_gain_v_per_v, sensor_m_per_v
//! [x.bouc_wen]                 # a, beta, gamma, n            (and the same for y)
//! [x.static_map]               # k1_m_per_v, k2_m_per_h, offset_m
//! [x.limits]                   # output_min_v, output_max_v, slew_limit_v_per_s
//! [x.effects]                  # optional (absent: no effect), see below
//! ```
//!
//! Validation per axis, in this order: `BoucWen::with_input_range(bouc_wen, output_min_v,
//! output_max_v, 1e6)` (the window is the only input the model will see), `StaticModel::new`,
//! `Compensator::new` with the limits and `sample_period_s = 1 / loop_rate_hz`, then
//! `piezo_core::effects::Effects::new(effects, 1 / loop_rate_hz, w_range)` with w_range the output
//! range of the first loading over the window, `[y_rest, y_rest + g_lin·(u_max − u_min)]` sorted.
//!
//! # Effects (`[x.effects]`, `[y.effects]`, optional)
//!
//! The effect chain of `piezo_core::effects` around the hysteresis model (written by
//! `host-sim close-loop`); the firmware inverts it each tick (`firmware/src/inverse_chain.rs`):
//!
//! ```toml
//! [x.effects]
//! creep_gain_m_per_v = [g1, g2, g3]     # gᵢ [m/V], up to 3 elements (shorter arrays allowed)
//! creep_time_constant_s = [t1, t2, t3]  # τᵢ [s], > 0 where gᵢ ≠ 0
//! even_coefficient_m_per_v2 = 0.0       # e [m/V²]: e·(u[j−1] − u_c)² on the previous command
//! even_center_v = 0.0                   # u_c [V]
//! mode_frequency_hz = 0.0               # f_mode [Hz]: 0 (none) or in (0, 0.45·loop_rate_hz)
//! mode_damping = 0.0                    # ζ [1], > 0 with a mode
//! delay_s = 0.0                         # D·T [s], 0 ≤ D ≤ 64 samples
//! drift_rate_m_per_s = 0.0              # r_d [m/s]
//! coupling = 0.0                        # κ [1], |κ| < 0.5: part of the other axis's z
//! ```
//!
//! An absent table, or an absent key in it, is zero; all zero is the identity (the loop then runs
//! exactly as without effects). Unknown keys are refused with the list of valid ones; a value the
//! core refuses is reported as `x.effects.<field>` (array elements as `creep_gain_m_per_v[1]`).

use piezo_core::effects::{EffectParams, Effects, MAX_CREEP_ELEMENTS};
use piezo_core::{
    BoucWen, BoucWenParams, Compensator, CompensatorSettings, HysteresisState, ParamError,
    StaticMap, StaticModel,
};

/// The keys of an `[x.effects]` table.
pub const EFFECT_KEYS: [&str; 9] = [
    "creep_gain_m_per_v",
    "creep_time_constant_s",
    "even_coefficient_m_per_v2",
    "even_center_v",
    "mode_frequency_hz",
    "mode_damping",
    "delay_s",
    "drift_rate_m_per_s",
    "coupling",
];

/// Axis names in the order of the generated `AXES` array.
pub const AXIS_NAMES: [&str; 2] = ["x", "y"];

/// Largest |h| accepted for a range-limited Bouc-Wen set (β + γ ≤ 0) over the output window.
pub const STATE_LIMIT: f32 = 1e6;

/// Volts per step of the virgin loading sweep that gives the linear (uncompensated) gain.
const SWEEP_STEP_V: f32 = 0.01;

/// One validated axis.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AxisSet {
    /// Bouc-Wen parameters.
    pub bouc_wen: BoucWenParams,
    /// Output map.
    pub static_map: StaticMap,
    /// Lowest voltage [V].
    pub output_min_v: f32,
    /// Highest voltage [V].
    pub output_max_v: f32,
    /// Slew limit [V/s].
    pub slew_limit_v_per_s: f32,
    /// Secant gain of the first loading over the window [m/V] (the uncompensated baseline).
    pub linear_gain_m_per_v: f32,
    /// Output at `output_min_v` at rest [m].
    pub rest_output_m: f32,
    /// The effect chain (all zero: none), validated by `Effects::new`.
    pub effects: EffectParams,
}

/// The hysteresis output range the effects are validated over: the first loading's
/// `[y_rest, y_rest + g_lin·(u_max − u_min)]`, sorted [m] (the same formula the firmware uses at
/// boot).
pub fn w_range_m(
    rest_output_m: f32,
    linear_gain_m_per_v: f32,
    output_min_v: f32,
    output_max_v: f32,
) -> (f32, f32) {
    let top = rest_output_m + linear_gain_m_per_v * (output_max_v - output_min_v);
    if top < rest_output_m {
        (top, rest_output_m)
    } else {
        (rest_output_m, top)
    }
}

/// A validated parameter file.
#[derive(Debug, Clone, PartialEq)]
pub struct ParamSet {
    /// `name` and `version` of the file, joined by a space.
    pub version: String,
    /// FNV-1a (32 bit) of the file's bytes.
    pub fnv1a32: u32,
    /// Loop rate [Hz].
    pub loop_rate_hz: f32,
    /// Piezo amplifier gain [V/V].
    pub amplifier_gain_v_per_v: f32,
    /// Displacement sensor gain [m/V].
    pub sensor_m_per_v: f32,
    /// x then y.
    pub axes: [AxisSet; 2],
}

/// FNV-1a, 32 bit (offset basis 0x811c9dc5, prime 0x01000193).
pub fn fnv1a32(bytes: &[u8]) -> u32 {
    bytes.iter().fold(0x811c_9dc5_u32, |hash, &b| {
        (hash ^ u32::from(b)).wrapping_mul(0x0100_0193)
    })
}

fn table<'a>(
    file: &str,
    parent: &'a toml::Table,
    key: &str,
    path: &str,
) -> Result<&'a toml::Table, String> {
    match parent.get(key) {
        Some(toml::Value::Table(t)) => Ok(t),
        Some(_) => Err(format!("{file}: `{path}` must be a table")),
        None => Err(format!("{file}: missing table `{path}`")),
    }
}

fn number(file: &str, t: &toml::Table, key: &str, path: &str) -> Result<f32, String> {
    let value = match t.get(key) {
        Some(toml::Value::Float(f)) => *f,
        Some(toml::Value::Integer(i)) => *i as f64,
        Some(_) => return Err(format!("{file}: `{path}.{key}` must be a number")),
        None => return Err(format!("{file}: missing field `{path}.{key}`")),
    };
    let narrowed = value as f32;
    if !narrowed.is_finite() {
        return Err(format!(
            "{file}: `{path}.{key}` = {value} is not a finite f32"
        ));
    }
    Ok(narrowed)
}

fn text<'a>(file: &str, t: &'a toml::Table, key: &str) -> Result<&'a str, String> {
    match t.get(key) {
        Some(toml::Value::String(s)) => Ok(s),
        Some(_) => Err(format!("{file}: `{key}` must be a string")),
        None => Err(format!("{file}: missing field `{key}`")),
    }
}

fn positive(file: &str, t: &toml::Table, key: &str, path: &str) -> Result<f32, String> {
    let v = number(file, t, key, path)?;
    if v > 0.0 {
        Ok(v)
    } else {
        Err(format!("{file}: `{path}.{key}` = {v} must be > 0"))
    }
}

/// The table path of the field a core error names (`x.bouc_wen.gamma`).
fn core_error(file: &str, axis: &str, section: &str, e: ParamError) -> String {
    let field = match e {
        ParamError::NonFinite { field } | ParamError::OutOfRange { field, .. } => {
            let section = match field {
                "output_min_v" | "output_max_v" | "slew_limit_v_per_s" => "limits",
                "k1_m_per_v" | "k2_m_per_h" | "offset_m" => "static_map",
                "input_min_v" | "input_max_v" => {
                    return format!(
                    "{file}: `{axis}.limits` refused by piezo-core as the Bouc-Wen input range: {e}"
                )
                }
                "sample_period_s" => {
                    return format!("{file}: `loop_rate_hz` refused by piezo-core: {e}")
                }
                _ => section,
            };
            format!("{axis}.{section}.{field}")
        }
        ParamError::UnboundableClass { .. } => format!("{axis}.bouc_wen.beta"),
        ParamError::UnboundedWithoutRange { .. } | ParamError::StateLimitExceeded { .. } => {
            format!("{axis}.bouc_wen (with {axis}.limits)")
        }
        ParamError::NotInvertible { .. } => {
            format!(
                "{axis}.bouc_wen with {axis}.static_map (the compensator's invertibility check)"
            )
        }
        ParamError::Discretisation { .. } => format!("{axis}.{section}"),
    };
    format!("{file}: `{field}` refused by piezo-core: {e}")
}

/// A number or an array of at most [`MAX_CREEP_ELEMENTS`] numbers (missing elements 0).
fn creep_array(
    file: &str,
    t: &toml::Table,
    key: &str,
    path: &str,
) -> Result<[f32; MAX_CREEP_ELEMENTS], String> {
    let mut out = [0.0f32; MAX_CREEP_ELEMENTS];
    let Some(value) = t.get(key) else {
        return Ok(out);
    };
    let toml::Value::Array(items) = value else {
        return Err(format!(
            "{file}: `{path}.{key}` must be an array of at most {MAX_CREEP_ELEMENTS} numbers"
        ));
    };
    if items.len() > MAX_CREEP_ELEMENTS {
        return Err(format!(
            "{file}: `{path}.{key}` has {} elements, at most {MAX_CREEP_ELEMENTS} allowed",
            items.len()
        ));
    }
    for (i, item) in items.iter().enumerate() {
        let value = match item {
            toml::Value::Float(f) => *f,
            toml::Value::Integer(n) => *n as f64,
            _ => return Err(format!("{file}: `{path}.{key}[{i}]` must be a number")),
        };
        let narrowed = value as f32;
        if !narrowed.is_finite() {
            return Err(format!(
                "{file}: `{path}.{key}[{i}]` = {value} is not a finite f32"
            ));
        }
        out[i] = narrowed;
    }
    Ok(out)
}

/// A number, 0 when absent.
fn optional_number(file: &str, t: &toml::Table, key: &str, path: &str) -> Result<f32, String> {
    if t.contains_key(key) {
        number(file, t, key, path)
    } else {
        Ok(0.0)
    }
}

/// The optional `[name.effects]` table (absent: all zero).
fn effects(file: &str, axis_table: &toml::Table, name: &str) -> Result<EffectParams, String> {
    let path = format!("{name}.effects");
    let t = match axis_table.get("effects") {
        None => return Ok(EffectParams::default()),
        Some(toml::Value::Table(t)) => t,
        Some(_) => return Err(format!("{file}: `{path}` must be a table")),
    };
    if let Some(unknown) = t.keys().find(|k| !EFFECT_KEYS.contains(&k.as_str())) {
        return Err(format!(
            "{file}: unknown key `{path}.{unknown}`; valid keys: {}",
            EFFECT_KEYS.join(", ")
        ));
    }
    Ok(EffectParams {
        creep_gain_m_per_v: creep_array(file, t, "creep_gain_m_per_v", &path)?,
        creep_time_constant_s: creep_array(file, t, "creep_time_constant_s", &path)?,
        even_coefficient_m_per_v2: optional_number(file, t, "even_coefficient_m_per_v2", &path)?,
        even_center_v: optional_number(file, t, "even_center_v", &path)?,
        mode_frequency_hz: optional_number(file, t, "mode_frequency_hz", &path)?,
        mode_damping: optional_number(file, t, "mode_damping", &path)?,
        delay_s: optional_number(file, t, "delay_s", &path)?,
        drift_rate_m_per_s: optional_number(file, t, "drift_rate_m_per_s", &path)?,
        coupling: optional_number(file, t, "coupling", &path)?,
    })
}

/// The message for an effect set the core refused (`x.effects.delay_s`).
fn effects_error(file: &str, axis: &str, e: ParamError) -> String {
    match e {
        ParamError::NonFinite { field } | ParamError::OutOfRange { field, .. } => match field {
            "sample_period_s" => format!("{file}: `loop_rate_hz` refused by piezo-core: {e}"),
            "w_range_m" => {
                format!("{file}: `{axis}` gives no valid output range for the effects: {e}")
            }
            _ => format!("{file}: `{axis}.effects.{field}` refused by piezo-core: {e}"),
        },
        ParamError::Discretisation { .. } => format!(
            "{file}: `{axis}.effects.mode_frequency_hz` (with mode_damping) refused by \
             piezo-core: {e}"
        ),
        _ => format!("{file}: `{axis}.effects` refused by piezo-core: {e}"),
    }
}

fn axis(
    file: &str,
    root: &toml::Table,
    name: &str,
    sample_period_s: f32,
) -> Result<AxisSet, String> {
    let t = table(file, root, name, name)?;
    let bw_path = format!("{name}.bouc_wen");
    let bw = table(file, t, "bouc_wen", &bw_path)?;
    let bouc_wen = BoucWenParams {
        a: number(file, bw, "a", &bw_path)?,
        beta: number(file, bw, "beta", &bw_path)?,
        gamma: number(file, bw, "gamma", &bw_path)?,
        n: number(file, bw, "n", &bw_path)?,
    };
    let map_path = format!("{name}.static_map");
    let m = table(file, t, "static_map", &map_path)?;
    let static_map = StaticMap {
        k1_m_per_v: number(file, m, "k1_m_per_v", &map_path)?,
        k2_m_per_h: number(file, m, "k2_m_per_h", &map_path)?,
        offset_m: number(file, m, "offset_m", &map_path)?,
    };
    let lim_path = format!("{name}.limits");
    let l = table(file, t, "limits", &lim_path)?;
    let settings = CompensatorSettings {
        output_min_v: number(file, l, "output_min_v", &lim_path)?,
        output_max_v: number(file, l, "output_max_v", &lim_path)?,
        slew_limit_v_per_s: positive(file, l, "slew_limit_v_per_s", &lim_path)?,
        sample_period_s,
    };
    let hysteresis = BoucWen::with_input_range(
        bouc_wen,
        settings.output_min_v,
        settings.output_max_v,
        STATE_LIMIT,
    )
    .map_err(|e| core_error(file, name, "bouc_wen", e))?;
    let model = StaticModel::new(hysteresis, static_map)
        .map_err(|e| core_error(file, name, "static_map", e))?;
    Compensator::new(model, settings).map_err(|e| core_error(file, name, "limits", e))?;

    // The uncompensated baseline: secant of the first loading from rest over the window.
    let (u0, u1) = (settings.output_min_v, settings.output_max_v);
    let mut state = HysteresisState::at_rest(u0);
    let steps = ((u1 - u0) / SWEEP_STEP_V).ceil() as u32;
    for k in 1..=steps {
        hysteresis.step(&mut state, (u0 + k as f32 * SWEEP_STEP_V).min(u1));
    }
    let rest_output_m = static_map.output(u0, 0.0);
    let top = static_map.output(u1, state.h);
    let linear_gain_m_per_v = (top - rest_output_m) / (u1 - u0);
    if !(linear_gain_m_per_v.is_finite() && linear_gain_m_per_v != 0.0) {
        return Err(format!(
            "{file}: `{name}` gives no stroke over the window (first-loading gain {linear_gain_m_per_v} m/V)"
        ));
    }
    let effects = effects(file, t, name)?;
    Effects::new(
        effects,
        sample_period_s,
        w_range_m(rest_output_m, linear_gain_m_per_v, u0, u1),
    )
    .map_err(|e| effects_error(file, name, e))?;
    Ok(AxisSet {
        bouc_wen,
        static_map,
        output_min_v: u0,
        output_max_v: u1,
        slew_limit_v_per_s: settings.slew_limit_v_per_s,
        linear_gain_m_per_v,
        rest_output_m,
        effects,
    })
}

/// Parses and validates the file `file` (its name, for messages) with contents `bytes`.
pub fn load(file: &str, bytes: &[u8]) -> Result<ParamSet, String> {
    let source = std::str::from_utf8(bytes).map_err(|e| format!("{file}: not UTF-8: {e}"))?;
    let root: toml::Table = source
        .parse()
        .map_err(|e| format!("{file}: not a valid TOML file: {e}"))?;
    let version = format!(
        "{} {}",
        text(file, &root, "name")?,
        text(file, &root, "version")?
    );
    let loop_rate_hz = positive(file, &root, "loop_rate_hz", "")
        .map_err(|e| e.replace("`.loop_rate_hz`", "`loop_rate_hz`"))?;
    let io = table(file, &root, "io", "io")?;
    let amplifier_gain_v_per_v = positive(file, io, "amplifier_gain_v_per_v", "io")?;
    let sensor_m_per_v = positive(file, io, "sensor_m_per_v", "io")?;
    let sample_period_s = 1.0 / loop_rate_hz;
    let axes = [
        axis(file, &root, AXIS_NAMES[0], sample_period_s)?,
        axis(file, &root, AXIS_NAMES[1], sample_period_s)?,
    ];
    Ok(ParamSet {
        version,
        fnv1a32: fnv1a32(bytes),
        loop_rate_hz,
        amplifier_gain_v_per_v,
        sensor_m_per_v,
        axes,
    })
}

/// Rust source of the consts (`{:?}` of an f32 prints a literal that parses back to the same bits).
pub fn generate(set: &ParamSet, file: &str) -> String {
    let mut out = String::new();
    out.push_str(&format!(
        "// Generated by firmware/build.rs from {file}. Do not edit.\n\
         /// The parameter file this image was built from.\n\
         pub const SOURCE: &str = {file:?};\n\
         /// `name` and `version` of the parameter file.\n\
         pub const VERSION: &str = {:?};\n\
         /// FNV-1a (32 bit) of the parameter file's bytes.\n\
         pub const FNV1A32: u32 = {:#010x};\n\
         /// Loop rate \\[Hz\\].\n\
         pub const LOOP_RATE_HZ: f32 = {:?};\n\
         /// Piezo amplifier gain \\[V/V\\].\n\
         pub const AMPLIFIER_GAIN_V_PER_V: f32 = {:?};\n\
         /// Displacement sensor gain \\[m/V\\].\n\
         pub const SENSOR_M_PER_V: f32 = {:?};\n\
         /// Per axis, x then y (validated by piezo-core when built).\n\
         pub const AXES: [AxisParams; 2] = [\n",
        set.version, set.fnv1a32, set.loop_rate_hz, set.amplifier_gain_v_per_v, set.sensor_m_per_v
    ));
    for a in &set.axes {
        let BoucWenParams {
            a: ga,
            beta,
            gamma,
            n,
        } = a.bouc_wen;
        let StaticMap {
            k1_m_per_v,
            k2_m_per_h,
            offset_m,
        } = a.static_map;
        out.push_str(&format!(
            "    AxisParams {{\n\
             \x20       bouc_wen: BoucWenParams {{ a: {ga:?}, beta: {beta:?}, gamma: {gamma:?}, n: {n:?} }},\n\
             \x20       static_map: StaticMap {{ k1_m_per_v: {k1_m_per_v:?}, k2_m_per_h: {k2_m_per_h:?}, offset_m: {offset_m:?} }},\n\
             \x20       output_min_v: {:?},\n\
             \x20       output_max_v: {:?},\n\
             \x20       slew_limit_v_per_s: {:?},\n\
             \x20       linear_gain_m_per_v: {:?},\n\
             \x20       rest_output_m: {:?},\n\
             \x20       effects: EffectParams {{ creep_gain_m_per_v: {:?}, creep_time_constant_s: {:?}, \
             even_coefficient_m_per_v2: {:?}, even_center_v: {:?}, mode_frequency_hz: {:?}, \
             mode_damping: {:?}, delay_s: {:?}, drift_rate_m_per_s: {:?}, coupling: {:?} }},\n\
             \x20   }},\n",
            a.output_min_v,
            a.output_max_v,
            a.slew_limit_v_per_s,
            a.linear_gain_m_per_v,
            a.rest_output_m,
            a.effects.creep_gain_m_per_v,
            a.effects.creep_time_constant_s,
            a.effects.even_coefficient_m_per_v2,
            a.effects.even_center_v,
            a.effects.mode_frequency_hz,
            a.effects.mode_damping,
            a.effects.delay_s,
            a.effects.drift_rate_m_per_s,
            a.effects.coupling,
        ));
    }
    out.push_str("];\n");
    out
}
