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
            envelope_policy: EnvelopePolicy::Warn,
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
        input_rate_max_v_per_s: Some(2400.0),
        band_hz: Some([1.0, 20.0]),
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
fn a_stack_driven_mode_round_trips_and_a_bad_share_names_the_key_and_line() {
    let mut stage = example();
    stage.x.effects.mode_frequency_hz = 3200.0;
    stage.x.effects.mode_damping = 0.035;
    stage.x.effects.mode_relative_damping = 1.0;
    let text = stage.to_toml("");
    let back = StageFile::parse("f.toml", &text).unwrap();
    assert_eq!(back.x.effects, stage.x.effects);
    assert!(back.validate().is_ok());
    let i = text.find("mode_relative_damping").unwrap();
    let end = i + text[i..].find('\n').unwrap();
    for bad_value in ["1.5", "-0.2"] {
        let bad = format!(
            "{}mode_relative_damping = {bad_value}{}",
            &text[..i],
            &text[end..]
        );
        let stage = StageFile::parse("f.toml", &bad).unwrap();
        let e = stage.validate().unwrap_err().located("f.toml", &bad);
        assert_eq!(e.key, "x.effects.mode_relative_damping", "{e}");
        assert!(e.line.is_some(), "{e}");
    }
}

#[test]
fn hysteresis_lag_round_trips_runs_and_its_bad_values_name_the_key_and_line() {
    let mut stage = example();
    stage.x.effects.hysteresis_lag_s = 1e-3;
    let text = stage.to_toml("");
    assert!(text.contains("hysteresis_lag_s"), "{text}");
    let back = StageFile::parse("f.toml", &text).unwrap();
    assert_eq!(back.x.effects, stage.x.effects);
    // The validated chain's model carries the lag, and its compensator inverts it.
    let valid = back.validate().unwrap();
    match valid.axes[0].chain {
        crate::validate::AxisChain::Static { model, .. } => {
            assert_eq!(model.input_lag_s(), 1e-3)
        }
        _ => panic!("static chain expected"),
    }
    assert!(valid.axes[0].compensator.is_some());
    // Shorter than a sample period (the example runs at 10 kHz) or negative: refused by the
    // core, naming the key and its line.
    let i = text.find("hysteresis_lag_s").unwrap();
    let end = i + text[i..].find('\n').unwrap();
    for bad_value in ["1e-6", "-1e-3"] {
        let bad = format!(
            "{}hysteresis_lag_s = {bad_value}{}",
            &text[..i],
            &text[end..]
        );
        let stage = StageFile::parse("f.toml", &bad).unwrap();
        let e = stage.validate().unwrap_err().located("f.toml", &bad);
        assert_eq!(e.key, "x.effects.hysteresis_lag_s", "{e}");
        assert!(e.line.is_some(), "{e}");
    }
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

#[test]
fn the_models_check_skips_only_invertibility_and_the_drive_span() {
    // Refused by the firmware, simulated by a forward model: a window beyond the drive span and a
    // map that turns back after a reversal (k2·dh/du = −1e-6 · 1.2 outweighs k1 = 3.6e-7 there,
    // not near saturation).
    let mut stage = example();
    stage.io.amplifier_gain_v_per_v = 20.0;
    stage.x.static_map.as_mut().unwrap().k2_m_per_h = -1e-6;
    let e = stage.validate().unwrap_err();
    assert!(
        matches!(e.core, Some(ParamError::NotInvertible { .. })),
        "{e}"
    );
    let valid = stage.validate_with(Check::Models).unwrap();
    assert!(valid.axes[0].compensator.is_none() && valid.axes[1].compensator.is_some());
    // Values no check accepts: both refuse them, naming the key and its line.
    let text = example().to_toml("");
    let cases = [
        (
            "sensor_m_per_v = ",
            "sensor_m_per_v = -1e39",
            "io.sensor_m_per_v",
        ),
        (
            "adc_range_v = ",
            "adc_range_v = [nan, 10.24]",
            "io.adc_range_v",
        ),
        (
            "slew_limit_v_per_s = ",
            "slew_limit_v_per_s = nan",
            "x.limits.slew_limit_v_per_s",
        ),
    ];
    for (key, line, path) in cases {
        let i = text.find(key).unwrap();
        let end = i + text[i..].find('\n').unwrap();
        let bad = format!("{}{line}{}", &text[..i], &text[end..]);
        let file = StageFile::parse("f.toml", &bad).unwrap();
        for check in [Check::Models, Check::Firmware] {
            let e = file
                .validate_with(check)
                .unwrap_err()
                .located("f.toml", &bad);
            let at = bad.lines().position(|l| l == line).unwrap() + 1;
            assert_eq!((e.key.as_str(), e.line), (path, Some(at)), "{check:?}: {e}");
        }
    }
    // A servo with a NaN transfer time constant.
    let mut stage = example();
    stage.x.servo = Some(ServoParams {
        kp_v_per_m: 0.0,
        ki_v_per_m_s: 7.1671066e9,
        lowpass_frequency_hz: 3221.0,
        lowpass_q: 0.70710677,
        notch_frequency_hz: 3221.0,
        notch_q: 1.0,
        notch_pole_frequency_hz: 0.0,
        transfer_time_constant_s: f32::NAN,
    });
    let e = stage.validate_with(Check::Models).unwrap_err();
    assert_eq!(e.key, "x.servo.transfer_time_constant_s", "{e}");
}

#[test]
fn fnv1a32_reference_values() {
    // Published FNV-1a 32 test vectors: the empty input is the offset basis.
    assert_eq!(fnv1a32(b""), 0x811c_9dc5);
    assert_eq!(fnv1a32(b"a"), 0xe40c_292c);
    assert_eq!(fnv1a32(b"foobar"), 0xbf9c_f968);
}

/// The envelope keys: a file without them (written before them) still reads and has no rate
/// check; the policy round-trips; `feedback-only` is refused without a servo or without an
/// envelope, naming `x.limits.envelope_policy` and its line.
#[test]
fn envelope_keys_read_round_trip_and_refuse_feedback_only_without_a_servo() {
    let text = example().to_toml("");
    assert!(text.contains("input_rate_max_v_per_s = 2400.0"), "{text}");
    assert!(
        !text.contains("envelope_policy"),
        "warn is the default: {text}"
    );
    let old = text
        .lines()
        .filter(|l| !l.starts_with("input_rate_max_v_per_s") && !l.starts_with("band_hz"))
        .collect::<Vec<_>>()
        .join("\n");
    let file = StageFile::parse("old.toml", &old).unwrap();
    let envelope = file.x.envelope().unwrap();
    assert_eq!(envelope.input_rate_max_v_per_s, f32::MAX);
    assert_eq!(file.x.limits.envelope_policy, EnvelopePolicy::Warn);
    assert!(file.validate().unwrap().axes[0].envelope.is_some());

    let mut stage = example();
    stage.x.limits.envelope_policy = EnvelopePolicy::FeedbackOnly;
    let text = stage.to_toml("");
    assert!(
        text.contains("envelope_policy = \"feedback-only\""),
        "{text}"
    );
    let back = StageFile::parse("f.toml", &text).unwrap();
    assert_eq!(back, stage);
    let e = back.validate().unwrap_err().located("f.toml", &text);
    assert_eq!(e.key, "x.limits.envelope_policy", "{e}");
    assert_eq!(
        e.core,
        Some(ParamError::NeedsServo {
            field: "envelope_policy"
        })
    );
    let at = text
        .lines()
        .position(|l| l.starts_with("envelope_policy"))
        .unwrap()
        + 1;
    assert_eq!(e.line, Some(at), "{e}");
    let mut stage = example();
    stage.x.limits.envelope_policy = EnvelopePolicy::FeedbackOnly;
    stage.x.identified = None;
    let e = stage.validate().unwrap_err();
    assert_eq!(e.key, "x.limits.envelope_policy", "{e}");
    let bad = example().to_toml("").replacen(
        "slew_limit_v_per_s = 100000.0",
        "slew_limit_v_per_s = 100000.0\nenvelope_policy = \"servo\"",
        1,
    );
    let e = StageFile::parse("f.toml", &bad).unwrap_err();
    assert!(e.to_string().contains("feedback-only"), "{e}");
}

/// The band of a record's input: a 5 Hz sine over 2 s at 10 kHz holds its variance at 5 Hz; a
/// constant has none.
#[test]
fn input_band_and_rate_of_a_record() {
    let dt = 1e-4;
    let u: Vec<f64> = (0..20_000)
        .map(|k| 60.0 + 50.0 * (std::f64::consts::TAU * 5.0 * k as f64 * dt).sin())
        .collect();
    let (lo, hi) = input_band_hz(&u, dt).unwrap();
    assert!(
        (lo - 5.0).abs() < 0.6 && (hi - 5.0).abs() < 0.6,
        "{lo}–{hi} Hz"
    );
    let rate = input_rate_max_v_per_s(&u, dt);
    let exact = 50.0 * std::f64::consts::TAU * 5.0;
    assert!((rate - exact).abs() < 1e-3 * exact, "{rate} vs {exact}");
    assert_eq!(input_band_hz(&[3.0; 100], dt), None);
}

/// `[x.on_target]`: absent, the band is the default for `[io]` and the loop rate (8 ADC steps,
/// 1 ms); each key overrides its default alone and round-trips; a bad value is refused naming
/// the key and its line; an unknown key is refused.
#[test]
fn on_target_band_defaults_round_trips_and_refuses_bad_values_at_their_line() {
    let stage = example();
    let valid = stage.validate().unwrap();
    let lsb = (stage.io.adc_range_v[1] - stage.io.adc_range_v[0]) / 65536.0;
    let default = valid.axes[0].on_target;
    assert!((default.tolerance_m - 8.0 * lsb * stage.io.sensor_m_per_v).abs() < 1e-15);
    assert_eq!(default.ticks, 10, "1 ms at 10 kHz");
    assert!(
        !stage.to_toml("").contains("on_target"),
        "absent stays absent"
    );

    let mut stage = example();
    stage.x.on_target = Some(OnTargetBand {
        tolerance_m: Some(5e-9),
        ticks: None,
    });
    let text = stage.to_toml("");
    let back = StageFile::parse("f.toml", &text).unwrap();
    assert_eq!(back.x.on_target, stage.x.on_target);
    let valid = back.validate().unwrap();
    assert_eq!(valid.axes[0].on_target, OnTarget::new(5e-9, 10).unwrap());
    assert_eq!(valid.axes[1].on_target, default, "y keeps the default");
    let set = crate::FirmwareSet::from_bytes("f.toml", text.as_bytes()).unwrap();
    assert_eq!(set.axes[0].on_target, valid.axes[0].on_target);

    for (bad, key) in [
        ("tolerance_m = -5e-9", "x.on_target.tolerance_m"),
        ("tolerance_m = 5e-9\nticks = 0", "x.on_target.ticks"),
    ] {
        let text = example().to_toml("").replacen(
            "[x.limits]",
            &format!("[x.on_target]\n{bad}\n\n[x.limits]"),
            1,
        );
        let e = StageFile::parse("f.toml", &text)
            .unwrap()
            .validate()
            .unwrap_err()
            .located("f.toml", &text);
        assert_eq!(e.key, key, "{e}");
        let field = key.rsplit('.').next().unwrap();
        let lines: Vec<&str> = text.lines().collect();
        let section = lines.iter().position(|l| *l == "[x.on_target]").unwrap();
        let line = section
            + lines[section..]
                .iter()
                .position(|l| l.starts_with(&format!("{field} =")))
                .unwrap()
            + 1;
        assert_eq!(e.line, Some(line), "{e}");
        assert!(e.to_string().contains("f.toml"), "{e}");
    }
    let text = example().to_toml("").replacen(
        "[x.limits]",
        "[x.on_target]\ntolerance = 1e-9\n\n[x.limits]",
        1,
    );
    let e = StageFile::parse("f.toml", &text).unwrap_err();
    assert!(e.to_string().contains("tolerance"), "{e}");
}

/// The firmware's build reads its stage file through [`crate::FirmwareSet::from_bytes`]: the
/// firmware's own file with its gains read a million times too small (an output in µm taken
/// for metres) gives a 40 pm stroke and is refused, naming the key, its line and the stroke.
#[test]
fn the_firmware_refuses_a_stroke_no_piezo_stage_has() {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../firmware/params/xy-stage.toml"
    );
    let text = std::fs::read_to_string(path).unwrap();
    assert!(crate::FirmwareSet::from_bytes(path, text.as_bytes()).is_ok());
    let scaled: String = text
        .lines()
        .map(|line| match line.split_once(" = ") {
            Some((key, value)) if key.starts_with("k1_") || key.starts_with("k2_") => {
                format!("{key} = {:e}\n", value.parse::<f64>().unwrap() * 1e-6)
            }
            _ => format!("{line}\n"),
        })
        .collect();
    let e = crate::FirmwareSet::from_bytes(path, scaled.as_bytes()).unwrap_err();
    assert_eq!(e.key, "x.static_map.k1_m_per_v", "{e}");
    let message = e.to_string();
    assert!(
        message.contains("stroke") && message.contains("xy-stage.toml"),
        "{message}"
    );
}

/// A rate-dependent gain the slew limit cannot carry is refused by its key with the slew limit
/// that would pass; a map that folds at rest, where the gain is 1, is refused by the static map's
/// key as the same set without the gain is, since no slew limit helps there.
#[test]
fn a_rate_gain_refusal_names_what_would_pass_or_that_nothing_would() {
    let mut stage = example();
    stage.x.effects.hysteresis_rate_gain_s_per_v = 1e-4;
    let e = stage.validate().unwrap_err();
    assert_eq!(e.key, "x.effects.hysteresis_rate_gain_s_per_v", "{e}");
    let fastest: f64 = e
        .message
        .split("at most ")
        .nth(1)
        .and_then(|s| s.split(' ').next())
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| panic!("{e}"));
    assert!(fastest > 0.0 && fastest < 1e5, "{e}");
    stage.x.limits.slew_limit_v_per_s = fastest as f32;
    stage.y = None;
    assert!(stage.validate().is_ok(), "at {fastest} V/s");
    // The hysteretic part ten times the linear one, against it: dy/du changes sign at rest.
    if let Some(map) = stage.x.static_map.as_mut() {
        map.k2_m_per_h = -3.573939e-6;
    }
    let e = stage.validate().unwrap_err();
    assert_eq!(e.key, "x.static_map", "{e}");
    stage.x.effects.hysteresis_rate_gain_s_per_v = 0.0;
    let without_gain = stage.validate().unwrap_err();
    assert_eq!(without_gain.key, "x.static_map", "{without_gain}");
    // The same slopes, to the f32 rounding of the gain's own path at gain 1.
    let slopes = |e: &StageError| match e.core {
        Some(ParamError::NotInvertible {
            min_slope,
            max_slope,
        }) => (min_slope, max_slope),
        _ => panic!("{e}"),
    };
    let ((lo, hi), (lo0, hi0)) = (slopes(&e), slopes(&without_gain));
    assert!((lo - lo0).abs() <= 1e-6 * lo0.abs(), "{e}\n{without_gain}");
    assert!((hi - hi0).abs() <= 1e-6 * hi0.abs(), "{e}\n{without_gain}");
}
