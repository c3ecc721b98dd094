//! Round trips and error locations of the stage file.

use super::*;
use piezo_core::ParamError;

fn example() -> StageFile {
    let mut x = Axis::static_model(
        BoucWenParams {
            a: 0.18522,
            beta: 0.029586,
            gamma: -0.02071,
            n: 1.0,
        },
        StaticMap {
            k1_m_per_v: 3.573939e-7,
            k2_m_per_h: -3.573939e-7,
            offset_m: 0.0,
        },
        Asymmetry::default(),
        Limits {
            output_min_v: 0.0,
            output_max_v: 120.0,
            slew_limit_v_per_s: 1.0e5,
        },
    );
    x.effects.creep_gain_m_per_v[0] = 1.0e-8;
    x.effects.creep_time_constant_s[0] = 0.2;
    x.identified = Some(Provenance {
        data: "record.csv".into(),
        window_s: [0.5, 3.0],
        method: "vp-de-lm".into(),
        fit_rms_m: 2.1e-9,
        input_range_v: [0.0, 120.0],
        sample_period_s: 1e-4,
    });
    let mut y = x.clone();
    y.effects = EffectParams::default();
    let mut io = Io::placeholder();
    io.placeholder = false;
    StageFile {
        stage: Stage {
            name: "example".into(),
            version: "2".into(),
            loop_rate_hz: 10_000.0,
        },
        io,
        x,
        y: Some(y),
    }
}

fn temp_dir(tag: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("piezo_stage_{tag}_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

#[test]
fn write_then_read_is_the_same_set_and_validates() {
    let stage = example();
    let dir = temp_dir("roundtrip");
    let path = dir.join("stage.toml");
    stage.write(&path, "an example").unwrap();
    let (back, valid) = StageFile::load(&path).unwrap();
    std::fs::remove_dir_all(&dir).unwrap();
    assert_eq!(back, stage);
    assert_eq!(valid.axes.len(), 2);
    assert!(valid.axes.iter().all(|a| a.compensator.is_some()));
    assert!(valid.axes[0].linear_gain_m_per_v > 0.0);
}

#[test]
fn unknown_keys_are_refused_with_the_valid_ones_and_a_location() {
    let text = example().to_toml("");
    let bad = text.replacen("gamma = ", "gama = ", 1);
    let e = StageFile::parse("f.toml", &bad).unwrap_err();
    assert_eq!(e.kind, StageErrorKind::Syntax);
    let shown = e.to_string();
    assert!(shown.starts_with("f.toml:"), "{shown}");
    assert!(shown.contains("gama") && shown.contains("gamma"), "{shown}");
    assert!(e.line.is_some(), "{shown}");
    assert!(e.key.starts_with("x.bouc_wen"), "{shown}");
    let bad = text.replacen("[x.effects]", "[x.effects]\ncreeep = 1.0", 1);
    let e = StageFile::parse("f.toml", &bad).unwrap_err();
    assert!(e.to_string().contains("creep_gain_m_per_v"), "{e}");
}

#[test]
fn relaxation_round_trips_and_its_bad_values_name_the_field() {
    let mut stage = example();
    stage.x.effects.relaxation_gain = [0.4, 0.0];
    stage.x.effects.relaxation_time_constant_s = [1.5e-3, 0.0];
    let text = stage.to_toml("");
    assert!(text.contains("relaxation_gain"), "{text}");
    let back = StageFile::parse("f.toml", &text).unwrap();
    assert_eq!(back.x.effects, stage.x.effects);
    // A short array is padded; a negative gain is refused by the core, naming the field.
    let i = text.find("relaxation_gain").unwrap();
    let end = i + text[i..].find('\n').unwrap();
    let short = format!("{}relaxation_gain = [0.4]{}", &text[..i], &text[end..]);
    let back = StageFile::parse("f.toml", &short).unwrap();
    assert_eq!(back.x.effects.relaxation_gain, [0.4, 0.0]);
    let bad = format!("{}relaxation_gain = [-0.4]{}", &text[..i], &text[end..]);
    let stage = StageFile::parse("f.toml", &bad).unwrap();
    let e = stage.validate().unwrap_err().located("f.toml", &bad);
    let shown = e.to_string();
    assert!(shown.contains("relaxation_gain[0]"), "{shown}");
    assert!(e.line.is_some(), "{shown}");
}

#[test]
fn short_creep_arrays_are_padded_and_long_ones_refused() {
    let text = example().to_toml("");
    let stage = StageFile::parse("f.toml", &text).unwrap();
    assert_eq!(stage.x.effects.creep_gain_m_per_v, [1.0e-8, 0.0, 0.0]);
    let i = text.find("creep_gain_m_per_v").unwrap();
    let end = i + text[i..].find('\n').unwrap();
    let bad = format!(
        "{}creep_gain_m_per_v = [1.0, 2.0, 3.0, 4.0]{}",
        &text[..i],
        &text[end..]
    );
    let e = StageFile::parse("f.toml", &bad).unwrap_err();
    assert!(e.to_string().contains("at most 3"), "{e}");
}

#[test]
fn core_refusals_name_the_key_and_line() {
    let text = example().to_toml("");
    let bad = text.replacen("beta = 0.029586", "beta = -1.0", 1);
    let stage = StageFile::parse("f.toml", &bad).unwrap();
    let e = stage.validate().unwrap_err().located("f.toml", &bad);
    assert_eq!(e.kind, StageErrorKind::Invalid);
    assert!(
        matches!(
            e.core,
            Some(ParamError::UnboundableClass { .. }) | Some(ParamError::OutOfRange { .. })
        ),
        "{e}"
    );
    assert!(e.key.starts_with("x.bouc_wen"), "{e}");
    let line = bad
        .lines()
        .position(|l| l.starts_with("beta = -1.0"))
        .unwrap()
        + 1;
    assert_eq!(e.line, Some(line), "{e}");
}

#[test]
fn output_window_beyond_the_drive_chain_is_refused() {
    let mut stage = example();
    stage.io.amplifier_gain_v_per_v = 20.0; // 0-5 V x 20 = 0-100 V < 120 V
    let e = stage.validate().unwrap_err();
    assert!(e.key.contains("limits"), "{e}");
    assert!(e.message.contains("amplifier"), "{e}");
    let mut stage = example();
    stage.io.sensor_range_v = [0.0, 12.0];
    let e = stage.validate().unwrap_err();
    assert_eq!(e.key, "io.sensor_range_v", "{e}");
}
