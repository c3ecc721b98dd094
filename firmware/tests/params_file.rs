//! The stage file and its build-time validation (`firmware/build/params.rs`, the code `build.rs`
//! runs, on piezo-stage): the built-in set matches the file, d gives the 38 µm free stroke, and
//! every refusal names the file, line and key.

#[path = "../build/params.rs"]
#[allow(dead_code)]
mod params;

use piezo_core::{BoucWen, HysteresisState};

const DEFAULT: &str = "params/xy-stage.toml";

fn read(name: &str) -> Vec<u8> {
    std::fs::read(std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join(name)).unwrap()
}

/// `DEFAULT` with `from` replaced by `to` (exactly once).
fn edited(from: &str, to: &str) -> Vec<u8> {
    let text = String::from_utf8(read(DEFAULT)).unwrap();
    assert_eq!(text.matches(from).count(), 1, "{from}");
    text.replacen(from, to, 1).into_bytes()
}

fn refusal(bytes: &[u8]) -> String {
    params::load("test.toml", bytes).unwrap_err()
}

#[test]
fn built_in_consts_are_the_default_file() {
    let bytes = read(DEFAULT);
    let set = params::load(DEFAULT, &bytes).unwrap();
    assert_eq!(set.fnv1a32, piezo_firmware::params::FNV1A32);
    assert_eq!(set.version, piezo_firmware::params::VERSION);
    assert_eq!(piezo_firmware::params::SOURCE, DEFAULT);
    for i in 0..2 {
        let built = piezo_firmware::params::AXES[i];
        assert_eq!(set.axes[i].bouc_wen, built.bouc_wen);
        assert_eq!(set.axes[i].static_map, built.static_map);
        assert_eq!(set.axes[i].linear_gain_m_per_v, built.linear_gain_m_per_v);
    }
    let source = params::generate(&set, DEFAULT);
    assert!(source.contains("pub const AXES: [AxisParams; 2]"));
}

/// The build takes the example stage files at 50 kHz, the highest rate (a 20 µs period, the
/// effects' 200 µs delay 10 samples) and refuses one hertz more.
#[test]
fn stage_files_build_at_50_khz() {
    for file in [
        DEFAULT,
        "params/xy-stage-effects.toml",
        "params/xy-stage-lag.toml",
    ] {
        let text = String::from_utf8(read(file)).unwrap();
        // The file's own rate line (20 kHz in the default file, 10 kHz in the others).
        let line = text
            .lines()
            .find(|l| l.starts_with("loop_rate_hz = "))
            .unwrap();
        let at = |rate: &str| text.replacen(line, rate, 1);
        let set = params::load(file, at("loop_rate_hz = 50000.0").as_bytes())
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(set.loop_rate_hz, 50_000.0);
        let source = params::generate(&set, file);
        assert!(source.contains("pub const AXES: [AxisParams; 2]"));
        let refused = params::load(file, at("loop_rate_hz = 50001.0").as_bytes()).unwrap_err();
        assert!(refused.contains("whole-hertz loop rates"), "{refused}");
    }
}

/// d = 38 µm / (120 V − h(120 V)) on the virgin loading curve simulated with the core, for the
/// default file (host-sim's exact XY stack sets).
#[test]
fn d_gives_38_um_free_stroke_on_first_loading() {
    for file in [DEFAULT] {
        let text = String::from_utf8(read(file)).unwrap();
        let stage = piezo_stage::StageFile::parse(file, &text).unwrap();
        for (axis, set) in stage.axes() {
            let p = set.bouc_wen.unwrap();
            let map = set.static_map.unwrap();
            let bw = BoucWen::new(p).unwrap();
            let mut s = HysteresisState::at_rest(0.0);
            for k in 1..=12_000 {
                bw.step(&mut s, k as f32 * 0.01);
            }
            let d = 38e-6 / (120.0 - f64::from(s.h));
            let k1 = f64::from(map.k1_m_per_v);
            let k2 = f64::from(map.k2_m_per_h);
            assert!(
                (k1 - d).abs() < 1e-6 * d,
                "{file} {axis}: k1 {k1:e}, d {d:e}"
            );
            assert_eq!(k2, -k1, "{file} {axis}");
        }
    }
}

#[test]
fn refusals_name_the_file_line_and_key() {
    let cases = [
        ("beta = 0.029586", "beta = -0.029586", "`x.bouc_wen.beta`"),
        (
            "n = 1.0\n\n[x.static_map]",
            "n = 20.0\n\n[x.static_map]",
            "`x.bouc_wen.n`",
        ),
        ("a = 0.16792", "a = \"big\"", "`y.bouc_wen.a`: invalid type"),
        (
            "k1_m_per_v = 3.5739391e-7\nk2_m_per_h = -3.5739391e-7\noffset_m = 0.0",
            "k1_m_per_v = 0.0\nk2_m_per_h = 0.0\noffset_m = 0.0",
            "`x.static_map.k1_m_per_v`",
        ),
        (
            "[x.limits]\noutput_min_v = 0.0\noutput_max_v = 120.0",
            "[x.limits]\noutput_min_v = 0.0\noutput_max_v = -1.0",
            "`x.limits",
        ),
        (
            "loop_rate_hz = 20000.0",
            "loop_rate_hz = 0.0",
            "`stage.loop_rate_hz`",
        ),
        (
            "loop_rate_hz = 20000.0",
            "loop_rate_hz = 100000.0",
            "whole-hertz loop rates",
        ),
        (
            "loop_rate_hz = 20000.0",
            "loop_rate_hz = 20000.5",
            "whole-hertz loop rates",
        ),
        (
            "sensor_m_per_v = 10.0e-6",
            "",
            "missing field `sensor_m_per_v`",
        ),
        (
            "amplifier_gain_v_per_v = 24.0",
            "amplifier_gain_v_per_v = 20.0",
            "exceeds what the DAC and amplifier drive",
        ),
        (
            "sensor_range_v = [0.0, 10.0]",
            "sensor_range_v = [0.0, 12.0]",
            "exceeds the ADC's input span",
        ),
        (
            "adc_range_v = [-10.24, 10.24]",
            "adc_range_v = [-10.0, 10.0]",
            "its input ranges are",
        ),
        ("[y.limits]", "[z.limits]", "`y`: missing field `limits`"),
        ("name = \"xy-stage\"", "name = xy-stage", "test.toml:"),
        (
            "[x]\nmodel = \"symmetric\"",
            "[x]\nmodel = \"dynamic\"",
            "`x.model`: \"dynamic\": the firmware runs the static models",
        ),
    ];
    for (from, to, expected) in cases {
        let e = refusal(&edited(from, to));
        assert!(e.starts_with("test.toml:"), "{e}");
        assert!(e.contains(expected), "{to:?}: {e}");
    }
    // The line of the refused key.
    let e = refusal(&edited("beta = 0.029586", "beta = -0.029586"));
    let text = String::from_utf8(edited("beta = 0.029586", "beta = -0.029586")).unwrap();
    let line = text
        .lines()
        .position(|l| l.starts_with("beta = -0.029586"))
        .unwrap()
        + 1;
    assert!(e.starts_with(&format!("test.toml:{line}:")), "{e}");
}

#[test]
fn a_one_axis_file_drives_both_channels_and_says_so() {
    let text = String::from_utf8(read(DEFAULT)).unwrap();
    let one = &text[..text.find("[y]").unwrap()];
    let set = params::load("one.toml", one.as_bytes()).unwrap();
    assert_eq!(set.axes[0], set.axes[1]);
    assert!(
        set.warnings.iter().any(|w| w.contains("one axis")),
        "{:?}",
        set.warnings
    );
}

const WITH_EFFECTS: &str = "params/xy-stage-effects.toml";

/// `WITH_EFFECTS` with `from` replaced by `to` (exactly once).
fn edited_effects(from: &str, to: &str) -> Vec<u8> {
    let text = String::from_utf8(read(WITH_EFFECTS)).unwrap();
    assert_eq!(text.matches(from).count(), 1, "{from}");
    text.replacen(from, to, 1).into_bytes()
}

#[test]
fn effects_tables_are_parsed_validated_and_emitted() {
    // The default file has none: all zero.
    let plain = params::load(DEFAULT, &read(DEFAULT)).unwrap();
    for a in &plain.axes {
        assert_eq!(a.effects, piezo_core::effects::EffectParams::default());
    }
    let set = params::load(WITH_EFFECTS, &read(WITH_EFFECTS)).unwrap();
    let [x, y] = set.axes.map(|a| a.effects);
    // Shorter creep arrays are padded with 0; absent keys (y's mode) are 0.
    assert_eq!(x.creep_gain_m_per_v, [1.0721817e-8, 0.0, 0.0]);
    assert_eq!(x.creep_time_constant_s, [0.2, 0.0, 0.0]);
    assert_eq!(y.creep_gain_m_per_v, [1.066826e-8, 0.0, 0.0]);
    assert_eq!(
        (x.even_coefficient_m_per_v2, x.even_center_v),
        (1.0e-10, 60.0)
    );
    assert_eq!((x.delay_s, x.drift_rate_m_per_s), (2.0e-4, -2.0e-7));
    assert_eq!((x.coupling, y.coupling), (0.02, -0.015));
    assert_eq!((y.mode_frequency_hz, y.mode_damping), (0.0, 0.0));
    // The same validation as the firmware's boot: the core accepts them at the loop period.
    for a in &set.axes {
        let range = piezo_core::effects::OperatingRange::first_loading(
            a.rest_output_m,
            a.linear_gain_m_per_v,
            (a.limits.output_min_v, a.limits.output_max_v),
        );
        let (w0, w1) = range.output_m;
        assert!(w0 < w1 && w1 > 37e-6, "{range:?}");
        let e =
            piezo_core::effects::Effects::new(a.effects, 1.0 / set.loop_rate_hz, range).unwrap();
        assert!(!e.is_identity());
        assert_eq!(e.lead_samples(), 2);
    }
    // Emitted into the consts, exactly (f32 `{:?}` round-trips).
    let source = params::generate(&set, WITH_EFFECTS);
    assert!(
        source.contains(
            "effects: EffectParams { creep_gain_m_per_v: [1.0721817e-8, 0.0, 0.0], \
             creep_time_constant_s: [0.2, 0.0, 0.0], even_coefficient_m_per_v2: 1e-10, \
             even_center_v: 60.0,"
        ),
        "{source}"
    );
    // The default file's consts carry all-zero effects.
    for axis in piezo_firmware::params::AXES {
        assert_eq!(axis.effects, piezo_core::effects::EffectParams::default());
    }
}

#[test]
fn bad_effects_are_refused_naming_the_file_and_the_field() {
    let cases = [
        // The core's validation, mapped to the table path.
        (
            "coupling = 0.02",
            "coupling = 0.6",
            "`x.effects.coupling`: refused",
        ),
        (
            "delay_s = 2.0e-4\ndrift_rate_m_per_s = -2.0e-7\ncoupling = -0.015",
            "delay_s = 1.0\ndrift_rate_m_per_s = -2.0e-7\ncoupling = -0.015",
            "`y.effects.delay_s`: refused",
        ),
        (
            "creep_time_constant_s = [0.2]",
            "creep_time_constant_s = [-0.2]",
            "`x.effects.creep_time_constant_s[0]`: refused",
        ),
        (
            "creep_time_constant_s = [0.2, 0.0, 0.0]",
            "creep_time_constant_s = [0.2]",
            "",
        ),
        (
            "mode_frequency_hz = 0.0",
            "mode_frequency_hz = 6000.0",
            "`x.effects.mode_frequency_hz`: refused",
        ),
        (
            "mode_frequency_hz = 0.0\nmode_damping = 0.0",
            "mode_frequency_hz = 500.0\nmode_damping = 0.0",
            "`x.effects.mode_damping`: refused",
        ),
        // The parser's own checks.
        (
            "even_center_v = 60.0\nmode",
            "even_centre_v = 60.0\nmode",
            "unknown field `even_centre_v`, expected one of `creep_gain_m_per_v`",
        ),
        (
            "creep_gain_m_per_v = [1.066826e-8, 0.0, 0.0]",
            "creep_gain_m_per_v = [1.066826e-8, 0.0, 0.0, 1e-9]",
            "`y.effects.creep_gain_m_per_v`: invalid length 4, expected an array of at most 3 numbers",
        ),
        (
            "creep_gain_m_per_v = [1.0721817e-8]",
            "creep_gain_m_per_v = 1.0721817e-8",
            "`x.effects.creep_gain_m_per_v`: invalid type: floating point",
        ),
        (
            "creep_gain_m_per_v = [1.0721817e-8]",
            "creep_gain_m_per_v = [\"a\"]",
            "`x.effects.creep_gain_m_per_v[0]`: invalid type: string",
        ),
        (
            "coupling = 0.02",
            "coupling = \"0.02\"",
            "`x.effects.coupling`: invalid type: string",
        ),
        (
            "even_coefficient_m_per_v2 = 1.0e-10\neven_center_v = 60.0\nmode",
            "even_coefficient_m_per_v2 = 1.0e99\neven_center_v = 60.0\nmode",
            "`x.effects.even_coefficient_m_per_v2`: refused by piezo-core",
        ),
    ];
    for (from, to, expected) in cases {
        let bytes = edited_effects(from, to);
        if expected.is_empty() {
            // A shorter array that is still valid.
            params::load("test.toml", &bytes).unwrap();
            continue;
        }
        let e = refusal(&bytes);
        assert!(e.starts_with("test.toml:"), "{e}");
        assert!(e.contains(expected), "{to:?}: {e}");
    }
    // Not a table.
    let e = refusal(&edited(
        "[x]\nmodel = \"symmetric\"",
        "[x]\nmodel = \"symmetric\"\neffects = 3",
    ));
    assert!(e.contains("`x.effects`: invalid type"), "{e}");
}
