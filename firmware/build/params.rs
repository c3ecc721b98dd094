//! The stage file the image is built from: read and validated by `piezo-stage` (the one reader
//! every tool uses, with piezo-core's constructors), checked against what this firmware drives,
//! and emitted as Rust consts.
//!
//! Shared by `build.rs` (which turns `firmware/params/xy-stage.toml`, or the file named by the
//! environment variable `PIEZO_PARAMS`, into `OUT_DIR/params.rs`) and by the host test
//! `firmware/tests/params_file.rs`. Every refusal names the file, line, column and key path
//! (`x.bouc_wen.gamma`), so a bad file gives a build error that says what to change.
//!
//! On top of `StageFile::validate` (the core's constructors with their plausibility bounds, and
//! `piezo_core::IoChain::check_limits`: the output window inside `dac_range_v ×
//! amplifier_gain_v_per_v`, a finite slew limit that leaves a full-window move a few ticks, the
//! sensor span inside the ADC's — the same function the firmware's session calls on an upload),
//! the image needs:
//! - models the firmware's chain runs: `symmetric` or `asymmetric` static models;
//! - `io.dac_part = "DAC8563"` with `dac_range_v = [0, 5]` (internal reference, gain 2);
//! - `io.adc_part = "ADS8681"` with `adc_range_v` one of its input ranges (±12.288, ±10.24,
//!   ±6.144, ±5.12, ±2.56, 0–12.288, 0–10.24, 0–6.144, 0–5.12 V);
//! - a loop rate the board's TIM2 runs and its tick budget allows: a whole number of hertz in
//!   [`MIN_LOOP_RATE_HZ`, `MAX_LOOP_RATE_HZ`] (the board timer is set from it).
//!
//! A one-axis file drives both channels with its `x` set (said as a build warning).

use piezo_core::effects::EffectParams;
use piezo_core::{Asymmetry, BoucWenParams, IoChain, ServoParams, StaticMap};
use piezo_stage::{AxisChain, StageError, StageErrorKind, StageFile, ValidAxis};

/// Lowest loop rate the image runs \[Hz\].
pub const MIN_LOOP_RATE_HZ: f32 = 10.0;
/// Highest loop rate the image runs \[Hz\]: 50 kHz, a 20 µs period, 3 360 cycles at 168 MHz.
/// `firmware/bench.sh`'s worst compensator + servo tick of 1 000 from rest takes 2 490
/// instructions (74 % of that period; with the example effects chain 5 390, for 20 kHz), plus
/// the four SPI frames of the converters.
pub const MAX_LOOP_RATE_HZ: f32 = 50_000.0;

/// The ADS8681 input ranges \[V\].
pub const ADC_RANGES_V: [[f32; 2]; 9] = [
    [-12.288, 12.288],
    [-10.24, 10.24],
    [-6.144, 6.144],
    [-5.12, 5.12],
    [-2.56, 2.56],
    [0.0, 12.288],
    [0.0, 10.24],
    [0.0, 6.144],
    [0.0, 5.12],
];

/// One validated axis, as the image needs it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AxisSet {
    /// Bouc-Wen parameters.
    pub bouc_wen: BoucWenParams,
    /// Output map.
    pub static_map: StaticMap,
    /// δ and φ (zero for the symmetric model).
    pub asymmetry: Asymmetry,
    /// Lowest voltage \[V\].
    pub output_min_v: f32,
    /// Highest voltage \[V\].
    pub output_max_v: f32,
    /// Slew limit \[V/s\].
    pub slew_limit_v_per_s: f32,
    /// Secant gain of the first loading over the window \[m/V\] (the uncompensated baseline).
    pub linear_gain_m_per_v: f32,
    /// Output at `output_min_v` at rest \[m\].
    pub rest_output_m: f32,
    /// The effect chain (all zero: none).
    pub effects: EffectParams,
    /// The feedback servo (`None`: none).
    pub servo: Option<ServoParams>,
}

/// A validated stage file.
#[derive(Debug, Clone, PartialEq)]
pub struct ParamSet {
    /// `name` and `version` of the stage, joined by a space.
    pub version: String,
    /// FNV-1a (32 bit) of the file's bytes.
    pub fnv1a32: u32,
    /// Loop rate \[Hz\].
    pub loop_rate_hz: f32,
    /// Piezo amplifier gain \[V/V\].
    pub amplifier_gain_v_per_v: f32,
    /// Displacement sensor gain \[m/V\].
    pub sensor_m_per_v: f32,
    /// ADC input range \[V\].
    pub adc_range_v: [f32; 2],
    /// The whole chain (DAC, amplifier, ADC, sensor), as an upload must carry it.
    pub io: IoChain,
    /// x then y.
    pub axes: [AxisSet; 2],
    /// Notes for the build log (a one-axis file, a placeholder io chain).
    pub warnings: Vec<String>,
}

/// The stage file's hash, piezo-stage's (the one host-sim's upload carries).
pub use piezo_stage::fnv1a32;

fn axis_set(file: &StageFile, valid: &ValidAxis) -> AxisSet {
    let axis = if valid.name == "x" {
        &file.x
    } else {
        file.y.as_ref().unwrap_or(&file.x)
    };
    let asymmetry = match valid.chain {
        AxisChain::Static { model, .. } => model.asymmetry(),
        _ => Asymmetry::default(),
    };
    AxisSet {
        bouc_wen: axis.bouc_wen.unwrap_or(BoucWenParams {
            a: 0.0,
            beta: 0.0,
            gamma: 0.0,
            n: 1.0,
        }),
        static_map: axis.static_map.unwrap_or(StaticMap {
            k1_m_per_v: 0.0,
            k2_m_per_h: 0.0,
            offset_m: 0.0,
        }),
        asymmetry,
        output_min_v: axis.limits.output_min_v,
        output_max_v: axis.limits.output_max_v,
        slew_limit_v_per_s: axis.limits.slew_limit_v_per_s,
        linear_gain_m_per_v: valid.linear_gain_m_per_v,
        rest_output_m: valid.rest_output_m,
        effects: axis.effects,
        servo: axis.servo,
    }
}

/// Parses and validates the stage file `file` (its name, for messages) with contents `bytes`.
pub fn load(file: &str, bytes: &[u8]) -> Result<ParamSet, String> {
    let text = std::str::from_utf8(bytes).map_err(|e| format!("{file}: not UTF-8: {e}"))?;
    let stage = StageFile::parse(file, text).map_err(|e| e.to_string())?;
    for (name, axis) in stage.axes() {
        if !axis.model.runs_on_firmware() {
            let message = format!(
                "\"{}\": the firmware runs the static models (symmetric, asymmetric) only",
                axis.model.name()
            );
            return Err(StageError::new(
                file,
                StageErrorKind::Invalid,
                &format!("{name}.model"),
                message,
            )
            .located(file, text)
            .to_string());
        }
    }
    let valid = stage
        .validate()
        .map_err(|e| e.located(file, text).to_string())?;
    let io = &stage.io;
    if io.dac_part != "DAC8563" || io.dac_range_v != [0.0, 5.0] {
        return Err(format!(
            "{file}: `io.dac_part`/`io.dac_range_v` = {:?} {:?}: this firmware drives a DAC8563 \
             with its internal reference, range [0.0, 5.0] V",
            io.dac_part, io.dac_range_v
        ));
    }
    if io.adc_part != "ADS8681" || !ADC_RANGES_V.contains(&io.adc_range_v) {
        return Err(format!(
            "{file}: `io.adc_part`/`io.adc_range_v` = {:?} {:?}: this firmware drives an ADS8681; \
             its input ranges are {ADC_RANGES_V:?} V",
            io.adc_part, io.adc_range_v
        ));
    }
    let rate = stage.stage.loop_rate_hz;
    if !(MIN_LOOP_RATE_HZ..=MAX_LOOP_RATE_HZ).contains(&rate) || rate.fract() != 0.0 {
        return Err(format!(
            "{file}: `stage.loop_rate_hz` = {rate}: the image runs whole-hertz loop rates from \
             {MIN_LOOP_RATE_HZ} to {MAX_LOOP_RATE_HZ} Hz (board TIM2 at 84 MHz, tick budget at \
             168 MHz)"
        ));
    }
    let mut warnings = Vec::new();
    if stage.y.is_none() {
        warnings.push(format!(
            "{file} has one axis: both channels run its `x` set"
        ));
    }
    if io.placeholder {
        warnings.push(format!(
            "{file}: `io.placeholder = true`: the io chain was not measured; set it to the real \
             DAC, amplifier, ADC and sensor"
        ));
    }
    let x = axis_set(&stage, &valid.axes[0]);
    let y = valid.axes.get(1).map_or(x, |a| axis_set(&stage, a));
    Ok(ParamSet {
        version: format!("{} {}", stage.stage.name, stage.stage.version),
        fnv1a32: fnv1a32(bytes),
        loop_rate_hz: rate,
        amplifier_gain_v_per_v: io.amplifier_gain_v_per_v,
        sensor_m_per_v: io.sensor_m_per_v,
        adc_range_v: io.adc_range_v,
        io: io.chain(),
        axes: [x, y],
        warnings,
    })
}

/// Rust source of the consts (`{:?}` of an f32 prints a literal that parses back to the same bits,
/// and `{:?}` of the core's parameter structs prints their struct literal).
pub fn generate(set: &ParamSet, file: &str) -> String {
    let mut out = String::new();
    out.push_str(&format!(
        "// Generated by firmware/build.rs from {file}. Do not edit.\n\
         #[allow(non_upper_case_globals, dead_code)]\n\
         const inf: f32 = f32::INFINITY;\n\
         /// The stage file this image was built from.\n\
         pub const SOURCE: &str = {file:?};\n\
         /// `name` and `version` of the stage.\n\
         pub const VERSION: &str = {:?};\n\
         /// FNV-1a (32 bit) of the stage file's bytes.\n\
         pub const FNV1A32: u32 = {:#010x};\n\
         /// Loop rate \\[Hz\\] (whole hertz: the board timer runs at it).\n\
         pub const LOOP_RATE_HZ: f32 = {:?};\n\
         /// Piezo amplifier gain \\[V/V\\].\n\
         pub const AMPLIFIER_GAIN_V_PER_V: f32 = {:?};\n\
         /// Displacement sensor gain \\[m/V\\].\n\
         pub const SENSOR_M_PER_V: f32 = {:?};\n\
         /// ADC input range \\[V\\].\n\
         pub const ADC_RANGE_V: [f32; 2] = {:?};\n\
         /// The hardware chain (an upload must carry exactly this).\n\
         pub const IO: IoChain = {:?};\n\
         /// Per axis, x then y (validated by piezo-core when built).\n\
         pub const AXES: [AxisParams; 2] = [\n",
        set.version,
        set.fnv1a32,
        set.loop_rate_hz,
        set.amplifier_gain_v_per_v,
        set.sensor_m_per_v,
        set.adc_range_v,
        set.io
    ));
    for a in &set.axes {
        out.push_str(&format!(
            "    AxisParams {{\n\
             \x20       bouc_wen: {:?},\n\
             \x20       static_map: {:?},\n\
             \x20       asymmetry: {:?},\n\
             \x20       output_min_v: {:?},\n\
             \x20       output_max_v: {:?},\n\
             \x20       slew_limit_v_per_s: {:?},\n\
             \x20       linear_gain_m_per_v: {:?},\n\
             \x20       rest_output_m: {:?},\n\
             \x20       effects: {:?},\n\
             \x20       servo: {:?},\n\
             \x20   }},\n",
            a.bouc_wen,
            a.static_map,
            a.asymmetry,
            a.output_min_v,
            a.output_max_v,
            a.slew_limit_v_per_s,
            a.linear_gain_m_per_v,
            a.rest_output_m,
            a.effects,
            a.servo,
        ));
    }
    out.push_str("];\n");
    out
}
