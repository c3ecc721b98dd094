//! The hybrid controller on the XY stage with creep, drift, sensor noise, DAC and ADC
//! quantisation and the stage's resonances: shortened `servo-bench` runs, and the stage file's
//! `[x.servo]` table.

use host_sim::servo_bench::{run_bench, BenchSettings, Shape};
use piezo_core::servo::{tune, StageDynamics, TuningGoal};
use piezo_core::ServoMode;
use piezo_stage::StageFile;

const STACK_FILE: &str = include_str!("../../firmware/params/xy-stage.toml");

#[test]
fn feedforward_plus_feedback_beats_either_alone_and_every_mode_is_stable() {
    let settings = BenchSettings {
        frequencies_hz: vec![1.0, 100.0],
        shapes: vec![Shape::Triangle],
        periods: 0.6,
        min_scored_s: 0.05,
        chirp_s: 0.0,
        ..Default::default()
    };
    let report = run_bench(&settings, &mut |_: &str| {}).unwrap();
    println!("{}", report.table());
    let rms = |mode, f| report.row(mode, Shape::Triangle, f).unwrap().rms_percent;
    let hybrid = ServoMode::FeedforwardFeedback;
    // Creep and drift at 1 Hz: what the feedforward alone cannot see.
    let at_1 = rms(ServoMode::Feedforward, 1.0) / rms(hybrid, 1.0);
    assert!(at_1 >= 5.0, "feedforward / hybrid at 1 Hz = {at_1}");
    // 100 Hz: beyond what the loop alone can follow.
    let at_100 = rms(ServoMode::Feedback, 100.0) / rms(hybrid, 100.0);
    assert!(at_100 >= 5.0, "feedback / hybrid at 100 Hz = {at_100}");
    // Stable: every mode's error stays bounded (open loop ≈ 7 % of stroke), and with feedback
    // the error never grows past what the transient-free loop allows.
    for row in &report.rows {
        assert!(
            row.rms_percent.is_finite() && row.rms_percent < 15.0 && row.max_percent < 25.0,
            "{row:?}"
        );
    }
    for f in [1.0, 100.0] {
        assert!(report.row(hybrid, Shape::Triangle, f).unwrap().max_percent < 5.0);
    }
    // Steps of 1, 10 and 50 % of the stroke: with feedback every step settles into 2 % of
    // itself within the watch, open loop (creep, hysteresis, no model) never does.
    assert_eq!(report.settling.len(), 4 * 3);
    for st in &report.settling {
        let settled = st.settle_s.iter().all(|t| t.is_some_and(|t| t < 0.05));
        match st.mode {
            ServoMode::Feedback | ServoMode::FeedforwardFeedback => assert!(settled, "{st:?}"),
            ServoMode::OpenLoop => assert_eq!(st.settle_s, [None, None], "{st:?}"),
            ServoMode::Feedforward => {}
        }
    }
    // The last sample of every feedback run is no worse than the RMS over its run allows.
    for t in report.traces.iter().filter(|t| t.mode.feedback()) {
        for a in 0..2 {
            let tail = &t.error_m[a][t.error_m[a].len() - 100..];
            let tail_max = tail.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            assert!(
                tail_max / report.stroke_m[a] < 0.15,
                "{:?} {}",
                t.mode,
                t.freq_hz
            );
        }
    }
}

#[test]
fn servo_table_round_trips_and_is_validated_by_the_core() {
    let mut file = StageFile::parse("xy-stage.toml", STACK_FILE).unwrap();
    let valid = file.validate().unwrap();
    let compensator = valid.axes[0].compensator.unwrap();
    let dynamics = StageDynamics::from_model(compensator.model(), 3200.0, 0.035, 1.5e-4);
    let tuning = tune(&dynamics, &TuningGoal::default(), compensator.settings()).unwrap();
    file.x.servo = Some(tuning.params);
    let text = file.to_toml("servo round trip");
    assert!(text.contains("[x.servo]") && text.contains("ki_v_per_m_s"));
    let back = StageFile::parse("back.toml", &text).unwrap();
    assert_eq!(back, file);
    let valid = back.validate().unwrap();
    assert_eq!(valid.axes[0].servo.unwrap().params(), tuning.params);
    // y keeps the file's own table; without one it has none.
    assert_eq!(
        valid.axes[1].servo.map(|s| s.params()),
        file.y.as_ref().unwrap().servo
    );
    let mut without = back.clone();
    without.y.as_mut().unwrap().servo = None;
    assert!(without.validate().unwrap().axes[1].servo.is_none());
    // A refused table names its key.
    let bad: String = text
        .lines()
        .map(|l| {
            if l.starts_with("ki_v_per_m_s") {
                "ki_v_per_m_s = 0.0\n".to_string()
            } else {
                format!("{l}\n")
            }
        })
        .collect();
    assert_ne!(bad, text);
    let e = StageFile::parse("bad.toml", &bad)
        .unwrap()
        .validate()
        .unwrap_err()
        .to_string();
    assert!(e.contains("x.servo.ki_v_per_m_s"), "{e}");
}

/// The bench at another loop rate runs the stack file's compensator, the servo and the DAC at
/// that rate and tunes the servo for it: at 20 kHz the shorter latency gives a higher crossover
/// than at 10 kHz with the phase margin kept, and feedforward + feedback stays the best mode.
#[test]
fn the_bench_runs_and_tunes_at_the_rate_it_is_given() {
    let at = |rate: f64| {
        let modes = [ServoMode::Feedforward, ServoMode::FeedforwardFeedback];
        run_bench(&triangle_bench(rate, &modes, true), &mut |_: &str| {}).unwrap()
    };
    let slow = at(10_000.0);
    let fast = at(20_000.0);
    assert!(
        host_sim::servo_bench::default_plant_effects(20_000.0)
            .iter()
            .any(|e| e.starts_with("dac:") && e.ends_with("rate_hz=20000")),
        "the DAC updates at the loop rate"
    );
    for a in 0..2 {
        let (s, f) = (&slow.tunings[a], &fast.tunings[a]);
        assert!(f.crossover_hz > 1.1 * s.crossover_hz, "{s:?} {f:?}");
        assert!(
            f.phase_margin_deg >= 60.0 && f.sensitivity_peak <= 1.6,
            "{f:?}"
        );
    }
    for report in [&slow, &fast] {
        let rms = |mode| triangle_rms(report, mode);
        assert!(rms(ServoMode::FeedforwardFeedback) < rms(ServoMode::Feedforward));
    }
    println!(
        "{}",
        host_sim::servo_bench::rates_table(&[(10_000.0, slow), (20_000.0, fast)])
    );
}

/// The feedforward that inverts the identified first mode pre-shapes the drive, so a
/// triangle's corners do not ring the stage: at 20 kHz (the firmware's rate) feedforward +
/// feedback at the 100 Hz triangle is at most half of what the same loop leaves with the
/// compensator aiming at the reference itself, and the feedforward alone improves as well.
#[test]
fn inverting_the_mode_in_the_feedforward_halves_the_triangles_error() {
    let at = |mode_feedforward: bool| {
        let modes = [ServoMode::Feedforward, ServoMode::FeedforwardFeedback];
        let settings = triangle_bench(20_000.0, &modes, mode_feedforward);
        let report = run_bench(&settings, &mut |_: &str| {}).unwrap();
        let rms = |mode| triangle_rms(&report, mode);
        (
            rms(ServoMode::Feedforward),
            rms(ServoMode::FeedforwardFeedback),
        )
    };
    let (ff_with, hybrid_with) = at(true);
    let (ff_without, hybrid_without) = at(false);
    println!("with the mode's inverse: {ff_with} / {hybrid_with} %; without: {ff_without} / {hybrid_without} %");
    assert!(
        hybrid_with <= 0.5 * hybrid_without,
        "{hybrid_with} vs {hybrid_without}"
    );
    assert!(ff_with < 0.9 * ff_without, "{ff_with} vs {ff_without}");
}

/// A faster loop never does worse at the triangle's corners: the mode's inverse asks for each
/// corner's impulse over ≈ 90 µs whatever the rate, inside the slew limit (2 V per tick at
/// 50 kHz), so at 50 kHz feedforward + feedback at the 100 Hz triangle is at most half of what
/// the 10 kHz loop leaves. And when the tuning may hold the mode by phase (a notch with lead),
/// the shorter latency lets it: each axis's crossover is at least twice the 10 kHz one at ≥ 60°
/// of phase margin, and the triangle's error falls further, on this plant, which is not the
/// tuning's model.
#[test]
fn a_fifty_kilohertz_loop_halves_the_ten_kilohertz_triangles_error() {
    let at = |rate: f64, by_phase: bool| {
        let settings = triangle_bench_by(rate, &[ServoMode::FeedforwardFeedback], true, by_phase);
        let report = run_bench(&settings, &mut |_: &str| {}).unwrap();
        (
            triangle_rms(&report, ServoMode::FeedforwardFeedback),
            report,
        )
    };
    let (slow, slow_report) = at(10_000.0, false);
    let (fast, fast_report) = at(50_000.0, false);
    let (held, held_report) = at(50_000.0, true);
    let (slow_tunings, held_tunings) = (slow_report.tunings, held_report.tunings);
    println!(
        "{}",
        host_sim::servo_bench::rates_table(&[(10_000.0, slow_report), (50_000.0, fast_report)])
    );
    assert!(fast <= 0.5 * slow, "50 kHz {fast} % vs 10 kHz {slow} %");
    assert!(held < fast, "held by phase {held} % vs by gain {fast} %");
    for (s, f) in slow_tunings.iter().zip(&held_tunings) {
        assert!(
            f.crossover_hz >= 2.0 * s.crossover_hz && f.phase_margin_deg >= 60.0,
            "50 kHz {f:?} vs 10 kHz {s:?}"
        );
        assert!(f.params.notch_pole_frequency_hz > f.params.notch_frequency_hz);
    }
}

/// A shortened bench at `rate`: two periods of the 100 Hz triangle in `modes`, no chirp and no
/// steps, the plant's effects at that rate, the identified mode in the feedforward or not.
fn triangle_bench(rate: f64, modes: &[ServoMode], mode_feedforward: bool) -> BenchSettings {
    triangle_bench_by(rate, modes, mode_feedforward, false)
}

/// [`triangle_bench`], the tuning allowed to hold the mode by phase or not.
fn triangle_bench_by(
    rate: f64,
    modes: &[ServoMode],
    mode_feedforward: bool,
    mode_by_phase: bool,
) -> BenchSettings {
    BenchSettings {
        loop_rate_hz: rate,
        plant_effects: host_sim::servo_bench::default_plant_effects(rate),
        frequencies_hz: vec![100.0],
        shapes: vec![Shape::Triangle],
        modes: modes.to_vec(),
        periods: 2.0,
        min_scored_s: 0.02,
        chirp_s: 0.0,
        step_fractions: Vec::new(),
        mode_feedforward,
        mode_by_phase,
        ..Default::default()
    }
}

/// The 100 Hz triangle's RMS error in `mode` (% of stroke, worse axis).
fn triangle_rms(report: &host_sim::servo_bench::BenchReport, mode: ServoMode) -> f64 {
    report
        .row(mode, Shape::Triangle, 100.0)
        .unwrap()
        .rms_percent
}
