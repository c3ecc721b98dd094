//! The stage file the image is built from: read and validated by `piezo-stage` (the one reader
//! every tool uses, with piezo-core's constructors), checked against what this firmware drives,
//! and emitted as Rust consts.
//!
//! Shared by `build.rs` (which turns `firmware/params/xy-stage.toml`, or the file named by the
//! environment variable `PIEZO_PARAMS`, into `OUT_DIR/params.rs`) and by the host test
//! `firmware/tests/params_file.rs`. Every refusal names the file, line, column and key path
//! (`x.bouc_wen.gamma`), so a bad file gives a build error that says what to change.
//!
//! The set is piezo-stage's `FirmwareSet::from_bytes` (the one the command link's upload carries
//! too): `StageFile::validate` (the core's constructors with their plausibility bounds, and
//! `piezo_core::IoChain::check_limits`: the output window inside `dac_range_v ×
//! amplifier_gain_v_per_v`, a finite slew limit that leaves a full-window move a few ticks, the
//! sensor span inside the ADC's — the same function the firmware's session calls on an upload),
//! models the firmware's chain runs (`symmetric` or `asymmetric` static models), the version
//! string and the FNV-1a hash. On top, the image needs:
//! - `io.dac_part = "DAC8563"` with `dac_range_v = [0, 5]` (internal reference, gain 2);
//! - `io.adc_part = "ADS8681"` with `adc_range_v` one of its input ranges (±12.288, ±10.24,
//!   ±6.144, ±5.12, ±2.56, 0–12.288, 0–10.24, 0–6.144, 0–5.12 V);
//! - a loop rate the board's TIM2 runs and its tick budget allows: a whole number of hertz in
//!   [`MIN_LOOP_RATE_HZ`, `MAX_LOOP_RATE_HZ`] (the board timer is set from it).
//!
//! A one-axis file drives both channels with its `x` set (said as a build warning).

use piezo_core::IoChain;
use piezo_stage::{AxisParams, FirmwareSet};

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
    pub axes: [AxisParams; 2],
    /// Notes for the build log (a one-axis file, a placeholder io chain).
    pub warnings: Vec<String>,
}

/// Parses and validates the stage file `file` (its name, for messages) with contents `bytes`:
/// piezo-stage's [`FirmwareSet`], then what this image's hardware needs.
pub fn load(file: &str, bytes: &[u8]) -> Result<ParamSet, String> {
    let set = FirmwareSet::from_bytes(file, bytes).map_err(|e| e.to_string())?;
    let io = &set.file.io;
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
    let rate = set.loop_rate_hz;
    if !(MIN_LOOP_RATE_HZ..=MAX_LOOP_RATE_HZ).contains(&rate) || rate.fract() != 0.0 {
        return Err(format!(
            "{file}: `stage.loop_rate_hz` = {rate}: the image runs whole-hertz loop rates from \
             {MIN_LOOP_RATE_HZ} to {MAX_LOOP_RATE_HZ} Hz (board TIM2 at 84 MHz, tick budget at \
             168 MHz)"
        ));
    }
    let mut warnings = Vec::new();
    if set.one_axis() {
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
    Ok(ParamSet {
        amplifier_gain_v_per_v: io.amplifier_gain_v_per_v,
        sensor_m_per_v: io.sensor_m_per_v,
        adc_range_v: io.adc_range_v,
        version: set.version,
        fnv1a32: set.fnv1a32,
        loop_rate_hz: rate,
        io: set.io,
        axes: set.axes,
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
             \x20       limits: {:?},\n\
             \x20       linear_gain_m_per_v: {:?},\n\
             \x20       rest_output_m: {:?},\n\
             \x20       effects: {:?},\n\
             \x20       servo: {:?},\n\
             \x20       envelope: {:?},\n\
             \x20       on_target: {:?},\n\
             \x20   }},\n",
            a.bouc_wen,
            a.static_map,
            a.asymmetry,
            a.limits,
            a.linear_gain_m_per_v,
            a.rest_output_m,
            a.effects,
            a.servo,
            a.envelope,
            a.on_target,
        ));
    }
    out.push_str("];\n");
    out
}
