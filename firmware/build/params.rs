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
//! ```
//!
//! Validation per axis, in this order: `BoucWen::with_input_range(bouc_wen, output_min_v,
//! output_max_v, 1e6)` (the window is the only input the model will see), `StaticModel::new`,
//! `Compensator::new` with the limits and `sample_period_s = 1 / loop_rate_hz`.

use piezo_core::{
    BoucWen, BoucWenParams, Compensator, CompensatorSettings, HysteresisState, ParamError,
    StaticMap, StaticModel,
};

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
    Ok(AxisSet {
        bouc_wen,
        static_map,
        output_min_v: u0,
        output_max_v: u1,
        slew_limit_v_per_s: settings.slew_limit_v_per_s,
        linear_gain_m_per_v,
        rest_output_m,
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
         /// Loop rate [Hz].\n\
         pub const LOOP_RATE_HZ: f32 = {:?};\n\
         /// Piezo amplifier gain [V/V].\n\
         pub const AMPLIFIER_GAIN_V_PER_V: f32 = {:?};\n\
         /// Displacement sensor gain [m/V].\n\
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
             \x20   }},\n",
            a.output_min_v,
            a.output_max_v,
            a.slew_limit_v_per_s,
            a.linear_gain_m_per_v,
            a.rest_output_m
        ));
    }
    out.push_str("];\n");
    out
}
