//! The learned voltage table over the link: checked before it is played, played in phase with
//! the wave table, refused with the entry, axis and limit that fail, and never changed while
//! it plays.

use super::*;
use piezo_link::SETPOINT_CHUNK;

/// One period of a 20 Hz sine, 19 ± 12 µm on both axes (y a quarter period later), one entry
/// per tick: 500 entries at 10 kHz, 1 000 at 20 kHz.
const ENTRIES: usize = (crate::params::LOOP_RATE_HZ / 20.0) as usize;

fn wave() -> std::vec::Vec<[f32; 2]> {
    (0..ENTRIES)
        .map(|j| {
            let phase = j as f64 / ENTRIES as f64;
            let at = |p: f64| (19e-6 - 12e-6 * (std::f64::consts::TAU * p).cos()) as f32;
            [at(phase), at(phase + 0.25)]
        })
        .collect()
}

const PROGRAM: Program = Program::Table {
    ticks_per_entry: 1,
    repeat: true,
};

fn load(host: &mut Host, s: &mut Session, entries: &[[f32; 2]], learned: bool) {
    let clear = if learned {
        Request::LearnedClear
    } else {
        Request::TableClear
    };
    assert!(matches!(
        host.ask(s, clear),
        Response::Queued { held: 0, .. }
    ));
    for chunk in entries.chunks(SETPOINT_CHUNK) {
        let chunk: Setpoints = chunk.iter().copied().collect();
        let request = if learned {
            Request::LearnedAppend(chunk)
        } else {
            Request::TableAppend(chunk)
        };
        assert!(matches!(host.ask(s, request), Response::Queued { .. }));
    }
}

/// The wave table tracked with the compensator for two passes; its commands of the second pass
/// (frames with trial 1) are a table the learned mode can play.
fn compensator_table(host: &mut Host, s: &mut Session, plant: &Cell<XyPlant>) -> Vec2 {
    load(host, s, &wave(), false);
    host.ask(s, Request::Frames { decimation: 1 });
    assert!(matches!(
        host.ask(s, Request::Track(PROGRAM)),
        Response::Started { .. }
    ));
    host.frames.clear();
    run(s, plant, host, 2 * ENTRIES as u32);
    let table: Vec2 = host
        .frames
        .iter()
        .filter(|f| f.trial == 1)
        .map(|f| f.commanded_v)
        .collect();
    assert_eq!(table.len(), ENTRIES);
    table
}

type Vec2 = std::vec::Vec<[f32; 2]>;

/// `table` with y's last 20 entries ramped to 40 V from its first entry: every step within the
/// slew limit but the wrap.
fn wrap_broken(table: &[[f32; 2]]) -> Vec2 {
    let mut t = table.to_vec();
    let first = t[0][1];
    let last = if first > 60.0 {
        first - 40.0
    } else {
        first + 40.0
    };
    let from = t[ENTRIES - 21][1];
    for k in 0..20 {
        t[ENTRIES - 20 + k][1] = from + (last - from) * (k + 1) as f32 / 20.0;
    }
    t
}

/// Played entry by entry: every frame's applied voltage is the learned entry of its reference
/// entry (the same phase), frames count the passes, and the stage tracks as with the
/// compensator whose commands the table holds.
#[test]
fn a_checked_table_plays_in_phase_with_the_wave_table() {
    let (mut s, plant) = session();
    let mut host = Host::new();
    let table = compensator_table(&mut host, &mut s, &plant);
    run(&mut s, &plant, &mut host, 2000);
    let compensated = host.status(&mut s).tracking;
    load(&mut host, &mut s, &table, true);
    assert_eq!(
        host.ask(&mut s, Request::Control(Control::Learned)),
        Response::Done
    );
    assert!(matches!(
        host.ask(&mut s, Request::Track(PROGRAM)),
        Response::Started { .. }
    ));
    host.frames.clear();
    run(&mut s, &plant, &mut host, 3 * ENTRIES as u32 + 1500);
    let st = host.status(&mut s);
    assert_eq!(st.feedforward, piezo_link::Feedforward::Learned);
    assert_eq!(st.control, Control::Learned);
    assert_eq!(st.learned, [ENTRIES as u32, TABLE_CAPACITY as u32]);
    let wave = wave();
    for (k, f) in host.frames.iter().enumerate() {
        let j = k % ENTRIES;
        assert_eq!(f.trial as usize, k / ENTRIES, "frame {k}");
        assert_eq!(f.reference_m, wave[j], "frame {k}");
        assert_eq!(f.commanded_v, table[j], "frame {k}: entry {j}");
    }
    for (axis, (t, c)) in st.tracking.iter().zip(&compensated).enumerate() {
        println!("axis {axis}: learned {t:?}, compensator {c:?}");
        assert!(
            t.rms_m < 1.5 * c.rms_m + 2e-9,
            "axis {axis}: {t:?} vs {c:?}"
        );
    }
    assert_eq!(st.counters.guard_interventions(), 0);
}

/// Every failure is refused with what failed, and the loop keeps playing what it played.
#[test]
fn a_table_that_fails_its_check_is_refused_and_never_played() {
    let (mut s, plant) = session();
    let mut host = Host::new();
    // No learned table; then one on a program that is not a table.
    let r = refusal(host.ask(&mut s, Request::Control(Control::Learned)));
    assert_eq!(r.kind, RefusalKind::Learned);
    assert!(r.reason.contains("track a table program"), "{}", r.reason);
    let table = compensator_table(&mut host, &mut s, &plant);
    let r = refusal(host.ask(&mut s, Request::Control(Control::Learned)));
    assert!(
        r.reason.contains(&std::format!(
            "learned table has 0 entries, the wave table {ENTRIES}"
        )),
        "{}",
        r.reason
    );
    load(&mut host, &mut s, &table[..ENTRIES - 1], true);
    let r = refusal(host.ask(&mut s, Request::Control(Control::Learned)));
    assert!(
        r.reason.contains(&std::format!("{} entries", ENTRIES - 1)),
        "{}",
        r.reason
    );

    let bad = |j: usize, axis: usize, v: f32| {
        let mut t = table.clone();
        t[j][axis] = v;
        t
    };
    let cases: [(Vec2, Option<u8>, &str); 5] = [
        (
            bad(123, 1, f32::NAN),
            Some(1),
            "learned table entry 123, y: not a finite",
        ),
        (
            bad(7, 0, 120.5),
            Some(0),
            "learned table entry 7, x: 120.5 V outside the window [0, 120] V",
        ),
        (
            bad(300, 1, -0.25),
            Some(1),
            "learned table entry 300, y: -0.25 V outside",
        ),
        // A 30 V spike: the step into entry 200 is over the 9.999998 V of one tick.
        (
            {
                let mut t = table.clone();
                t[200][0] = (t[199][0] + 30.0).min(119.0);
                t
            },
            Some(0),
            "learned table entry 200, x: step",
        ),
        // The wrap of a repeating table: the last entry 40 V from the first.
        (
            wrap_broken(&table),
            Some(1),
            "learned table entry 0 (wrap), y: step",
        ),
    ];
    for (t, axis, expected) in cases {
        load(&mut host, &mut s, &t, true);
        let r = refusal(host.ask(&mut s, Request::Control(Control::Learned)));
        assert_eq!((r.kind, r.axis), (RefusalKind::Learned, axis), "{expected}");
        assert!(r.reason.contains(expected), "{} / {expected}", r.reason);
        // The compensator plays on.
        host.frames.clear();
        run(&mut s, &plant, &mut host, 50);
        assert!(host.frames.iter().all(|f| f.commanded_v[0] < 120.0
            && f.commanded_v[1] > 0.0
            && f.commanded_v[1].is_finite()));
        assert_eq!(
            host.status(&mut s).feedforward,
            piezo_link::Feedforward::Compensator
        );
    }
    // The wrap only counts for a repeating table: the same table plays once through.
    load(&mut host, &mut s, &wrap_broken(&table), true);
    let single = Program::Table {
        ticks_per_entry: 1,
        repeat: false,
    };
    assert!(matches!(
        host.ask(&mut s, Request::Track(single)),
        Response::Started { .. }
    ));
    assert_eq!(
        host.ask(&mut s, Request::Control(Control::Learned)),
        Response::Done
    );
    // In the learned mode, Track takes a checked table program only.
    let r = refusal(host.ask(&mut s, Request::Track(PROGRAM)));
    assert!(
        r.reason.contains("learned table entry 0 (wrap), y"),
        "{}",
        r.reason
    );
    let r = refusal(host.ask(&mut s, sine_track()));
    assert!(r.reason.contains("track a table program"), "{}", r.reason);
    // A step of 1.5 guard steps (15 V at 10 kHz, 7.5 V at 20 kHz) is over the slew limit at 1
    // tick per entry, within it at 2 (2 × 9.999998 V at 10 kHz).
    host.ask(&mut s, Request::Control(Control::Feedforward));
    let guard_step =
        crate::params::AXES[0].limits.slew_limit_v_per_s * crate::params::SAMPLE_PERIOD_S;
    let mut spike = table.clone();
    spike[200][0] = (spike[199][0] + 1.5 * guard_step).min(119.0);
    spike[201][0] = spike[200][0];
    load(&mut host, &mut s, &spike, true);
    let r = refusal(host.ask(&mut s, Request::Control(Control::Learned)));
    assert!(r.reason.contains("at 1 ticks per entry"), "{}", r.reason);
    let slow = Program::Table {
        ticks_per_entry: 2,
        repeat: true,
    };
    assert!(matches!(
        host.ask(&mut s, Request::Track(slow)),
        Response::Started { .. }
    ));
    assert_eq!(
        host.ask(&mut s, Request::Control(Control::Learned)),
        Response::Done
    );
}

/// While the loop plays the learned table, requests that would change either table and an
/// upload whose window the table leaves are refused; leaving the mode lets them through.
#[test]
fn a_playing_table_is_not_changed_under_the_loop() {
    let (mut s, plant) = session();
    let mut host = Host::new();
    let table = compensator_table(&mut host, &mut s, &plant);
    load(&mut host, &mut s, &table, true);
    assert_eq!(
        host.ask(&mut s, Request::Control(Control::LearnedFeedback)),
        Response::Done
    );
    run(&mut s, &plant, &mut host, 100);
    let chunk: Setpoints = (0..4).map(|_| [60.0; 2]).collect();
    for request in [
        Request::TableClear,
        Request::TableAppend(chunk.clone()),
        Request::LearnedClear,
        Request::LearnedAppend(chunk),
    ] {
        let r = refusal(host.ask(&mut s, request));
        assert_eq!(r.kind, RefusalKind::Learned);
        assert!(r.reason.contains("switch the control mode"), "{}", r.reason);
    }
    assert_eq!(s.lp.reference.learned_len(), ENTRIES);
    assert_eq!(s.lp.reference.table_len(), ENTRIES);
    // A set whose window ends below the table's highest voltage.
    let top = table.iter().map(|u| u[0]).fold(0.0f32, f32::max);
    let mut narrow = built_in_set();
    narrow.axes[0].limits.output_max_v = top - 1.0;
    let r = refusal(host.ask(&mut s, Request::Upload(narrow.clone())));
    assert!(
        r.reason
            .starts_with("this set's limits: learned table entry"),
        "{}",
        r.reason
    );
    assert_eq!(s.lp.settings().axes[0].limits().max_volts(), 120.0);
    // A set without a servo while learned + feedback runs.
    let mut no_servo = built_in_set();
    no_servo.axes[1].servo = None;
    assert!(refusal(host.ask(&mut s, Request::Upload(no_servo.clone())))
        .reason
        .contains("no [y.servo]"));
    assert_eq!(
        host.ask(&mut s, Request::Control(Control::FeedforwardFeedback)),
        Response::Done
    );
    assert!(matches!(
        host.ask(&mut s, Request::Upload(narrow)),
        Response::Loaded { .. }
    ));
    assert!(matches!(
        host.ask(&mut s, Request::LearnedClear),
        Response::Queued { held: 0, .. }
    ));
    // Without a servo, learned + feedback is refused naming the axis.
    host.ask(&mut s, Request::Control(Control::Feedforward));
    host.ask(&mut s, Request::Upload(no_servo));
    load(&mut host, &mut s, &table, true);
    let r = refusal(host.ask(&mut s, Request::Control(Control::LearnedFeedback)));
    assert_eq!((r.kind, r.axis), (RefusalKind::Program, Some(1)));
}

/// The compensator's table 2 V too high on both axes (≈ 0.7 µm off), loaded as the learned
/// table.
fn load_table_too_high(host: &mut Host, s: &mut Session, plant: &Cell<XyPlant>) {
    let table = compensator_table(host, s, plant);
    let high: Vec2 = table
        .iter()
        .map(|u| u.map(|v| (v + 2.0).min(120.0)))
        .collect();
    load(host, s, &high, true);
}

/// With feedback the servo corrects what the table gets wrong: a table 2 V too high on both
/// axes (≈ 0.7 µm off) tracks within 1 % of that error with learned + feedback.
#[test]
fn learned_feedback_adds_the_servos_correction() {
    let (mut s, plant) = session();
    let mut host = Host::new();
    load_table_too_high(&mut host, &mut s, &plant);
    let mut tracked = |control: Control| {
        assert_eq!(host.ask(&mut s, Request::Control(control)), Response::Done);
        host.ask(&mut s, Request::Track(PROGRAM));
        // 0.4 s, whatever the loop rate (the servo's integral settles in time, not in ticks).
        run(
            &mut s,
            &plant,
            &mut host,
            (0.4 / crate::params::SAMPLE_PERIOD_S) as u32,
        );
        host.status(&mut s).tracking
    };
    let learned = tracked(Control::Learned);
    let corrected = tracked(Control::LearnedFeedback);
    for axis in 0..2 {
        println!(
            "axis {axis}: learned {:?}, learned + feedback {:?}",
            learned[axis], corrected[axis]
        );
        assert!(learned[axis].rms_m > 500e-9, "{:?}", learned[axis]);
        assert!(
            corrected[axis].rms_m < 0.01 * learned[axis].rms_m,
            "{:?}",
            corrected[axis]
        );
    }
}

/// Between the learned table and the compensator with feedback on, the servo hands its
/// correction over: the applied voltage moves at the switch by what the wave moves in a tick,
/// not by the 2 V the servo held against a table 2 V too high.
#[test]
fn switching_between_table_and_compensator_under_feedback_does_not_jump() {
    let (mut s, plant) = session();
    let mut host = Host::new();
    load_table_too_high(&mut host, &mut s, &plant);
    assert_eq!(
        host.ask(&mut s, Request::Control(Control::LearnedFeedback)),
        Response::Done
    );
    host.ask(&mut s, Request::Track(PROGRAM));
    run(&mut s, &plant, &mut host, 4000);
    // The largest step between frames k − 1 and k over `frames`.
    let steps = |frames: &[piezo_link::Frame]| -> std::vec::Vec<f32> {
        frames
            .windows(2)
            .map(|w| {
                (0..2)
                    .map(|a| (w[1].commanded_v[a] - w[0].commanded_v[a]).abs())
                    .fold(0.0f32, f32::max)
            })
            .collect()
    };
    for control in [Control::FeedforwardFeedback, Control::LearnedFeedback] {
        host.frames.clear();
        run(&mut s, &plant, &mut host, 200);
        assert_eq!(host.ask(&mut s, Request::Control(control)), Response::Done);
        run(&mut s, &plant, &mut host, 200);
        let d = steps(&host.frames);
        let before = d[..190].iter().fold(0.0f32, |m, &v| m.max(v));
        let at_switch = d[195..210].iter().fold(0.0f32, |m, &v| m.max(v));
        println!("{control:?}: largest step before {before} V, at the switch {at_switch} V");
        assert!(
            at_switch < before + 0.5,
            "{control:?}: {at_switch} V vs {before} V"
        );
    }
}

/// The learned copy of the tick behind the output guard: whatever the table holds (it is
/// switched on here without its check), every output is finite, inside the window and at most
/// one step from the one before.
#[test]
fn an_unchecked_table_cannot_drive_an_unsafe_voltage() {
    let (mut s, plant) = session();
    let mut host = Host::new();
    load(&mut host, &mut s, &wave(), false);
    host.ask(&mut s, Request::Track(PROGRAM));
    let wild: Vec2 = (0..ENTRIES)
        .map(|j| match j % 5 {
            0 => [f32::NAN, 1e30],
            1 => [-1e30, f32::INFINITY],
            2 => [130.0, -5.0],
            3 => [0.0, 120.0],
            _ => [120.0, f32::NEG_INFINITY],
        })
        .collect();
    s.lp.reference.learned_append(&wild[..300]).unwrap();
    s.lp.set_feedforward(Feedforward::Learned);
    host.ask(&mut s, Request::Frames { decimation: 1 });
    host.frames.clear();
    run(&mut s, &plant, &mut host, 2000);
    let step = s.lp.settings().axes[0].limits().max_step_volts();
    let mut previous = [0.0f32; 2];
    for f in &host.frames {
        for (&u, last) in f.commanded_v.iter().zip(&mut previous) {
            assert!((0.0..=120.0).contains(&u), "{f:?}");
            assert!((u - *last).abs() <= step, "{f:?}");
            *last = u;
        }
    }
    assert!(host.status(&mut s).counters.guard_interventions() > 0);
}
