//! The parameter file and its build-time validation (`firmware/build/params.rs`, the code
//! `build.rs` runs): the built-in set matches the file, d gives the 38 µm free stroke, and every
//! refusal names the file and the field.

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

#[test]
fn fnv1a32_reference_values() {
    // Published FNV-1a 32 test vectors.
    assert_eq!(params::fnv1a32(b""), 0x811c_9dc5);
    assert_eq!(params::fnv1a32(b"a"), 0xe40c_292c);
    assert_eq!(params::fnv1a32(b"foobar"), 0xbf9c_f968);
}

/// d = 38 µm / (120 V − h(120 V)) on the virgin loading curve simulated with the core, for the
/// default file (host-sim's exact XY stack sets).
#[test]
fn d_gives_38_um_free_stroke_on_first_loading() {
    for file in [DEFAULT] {
        let text = String::from_utf8(read(file)).unwrap();
        let root: toml::Table = text.parse().unwrap();
        for axis in ["x", "y"] {
            let t = root[axis].as_table().unwrap();
            let f = |sec: &str, key: &str| t[sec][key].as_float().unwrap() as f32;
            let bw = BoucWen::new(piezo_core::BoucWenParams {
                a: f("bouc_wen", "a"),
                beta: f("bouc_wen", "beta"),
                gamma: f("bouc_wen", "gamma"),
                n: f("bouc_wen", "n"),
            })
            .unwrap();
            let mut s = HysteresisState::at_rest(0.0);
            for k in 1..=12_000 {
                bw.step(&mut s, k as f32 * 0.01);
            }
            let d = 38e-6 / (120.0 - f64::from(s.h));
            let k1 = f64::from(f("static_map", "k1_m_per_v"));
            let k2 = f64::from(f("static_map", "k2_m_per_h"));
            assert!(
                (k1 - d).abs() < 1e-6 * d,
                "{file} {axis}: k1 {k1:e}, d {d:e}"
            );
            assert_eq!(k2, -k1, "{file} {axis}");
        }
    }
}

#[test]
fn refusals_name_the_file_and_the_field() {
    let cases = [
        ("beta = 0.029586", "beta = -0.029586", "`x.bouc_wen.beta`"),
        (
            "n = 1.0\n\n[x.static_map]",
            "n = 20.0\n\n[x.static_map]",
            "`x.bouc_wen.n`",
        ),
        (
            "a = 0.16792",
            "a = \"big\"",
            "`y.bouc_wen.a` must be a number",
        ),
        (
            "k1_m_per_v = 3.5739391e-7\nk2_m_per_h = -3.5739391e-7\noffset_m = 0.0",
            "k1_m_per_v = 0.0\nk2_m_per_h = 0.0\noffset_m = 0.0",
            "`x.static_map.k1_m_per_v`",
        ),
        (
            "output_max_v = 120.0\nslew_limit_v_per_s = 1.0e5\n\n[y",
            "output_max_v = -1.0\nslew_limit_v_per_s = 1.0e5\n\n[y",
            "`x.limits",
        ),
        (
            "loop_rate_hz = 10000.0",
            "loop_rate_hz = 0.0",
            "`loop_rate_hz`",
        ),
        (
            "sensor_m_per_v = 10.0e-6",
            "",
            "missing field `io.sensor_m_per_v`",
        ),
        ("[y.limits]", "[z.limits]", "missing table `y.limits`"),
        (
            "name = \"xy-stage\"",
            "name = xy-stage",
            "not a valid TOML file",
        ),
    ];
    for (from, to, expected) in cases {
        let e = refusal(&edited(from, to));
        assert!(e.starts_with("test.toml: "), "{e}");
        assert!(e.contains(expected), "{to:?}: {e}");
    }
}
