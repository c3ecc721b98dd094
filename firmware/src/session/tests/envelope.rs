//! The identified envelope over the link: an uploaded set carries it, the loop counts the ticks
//! whose command leaves it (status and frame flags), and the policy `feedback-only` hands the
//! axis to its servo alone while outside and back to the compensator inside, without a jump.

use super::*;
use piezo_core::{Envelope, EnvelopePolicy};

/// The built-in set with an envelope of 0–40 V (any rate) on x under the policy `x` (its
/// limits'), as given on y under the policy `warn`.
fn set_with_envelope(x: EnvelopePolicy, y: Option<Envelope>) -> ModelSet {
    let mut set = built_in_set();
    set.axes[0].envelope = Some(Envelope {
        input_range_v: [0.0, 40.0],
        input_rate_max_v_per_s: f32::MAX,
    });
    set.axes[0].limits.envelope_policy = x;
    set.axes[1].envelope = y;
    set.axes[1].limits.envelope_policy = EnvelopePolicy::Warn;
    set
}

/// 19 ± 15 µm at 10 Hz on both axes: x's command reaches ≈ 100 V, well outside 0–40 V.
fn track_outside(host: &mut Host, s: &mut Session, plant: &Cell<XyPlant>, ticks: u32) {
    assert!(matches!(
        host.ask(s, sine_track()),
        Response::Started { .. }
    ));
    run(s, plant, host, ticks);
}

/// 5 ± 3 µm at 10 Hz: x's command stays inside 0–40 V.
fn track_inside(host: &mut Host, s: &mut Session, plant: &Cell<XyPlant>, ticks: u32) {
    let inside = Request::Track(Program::PerAxis(
        [Wave::Sine {
            offset: 5e-6,
            amplitude: 3e-6,
            frequency_hz: 10.0,
        }; 2],
    ));
    assert!(matches!(host.ask(s, inside), Response::Started { .. }));
    run(s, plant, host, ticks);
}

fn upload(host: &mut Host, s: &mut Session, set: ModelSet) {
    let answer = host.ask(s, Request::Upload(set));
    assert!(matches!(answer, Response::Loaded { .. }), "{answer:?}");
}

#[test]
fn excursions_are_counted_in_status_and_flagged_in_frames() {
    let (mut s, plant) = session();
    let mut host = Host::new();
    upload(
        &mut host,
        &mut s,
        set_with_envelope(EnvelopePolicy::Warn, None),
    );
    host.ask(&mut s, Request::Frames { decimation: 1 });
    host.frames.clear();
    let ticks = (0.2 * params::LOOP_RATE_HZ) as u32;
    track_outside(&mut host, &mut s, &plant, ticks);
    let st = host.status(&mut s);
    let [x, y] = st.envelope;
    assert!(x.known && !x.feedback_only);
    assert!(!y.known, "y has no envelope: nothing checked");
    assert_eq!(y.counts.ticks_outside, 0);
    // Every tick was framed: the flagged frames are the counted ticks.
    assert_eq!(host.frames.len() as u32, ticks);
    let flagged = host
        .frames
        .iter()
        .filter(|f| f.flags & Frame::OUTSIDE_X != 0)
        .count() as u32;
    assert!(host.frames.iter().all(|f| f.flags & Frame::OUTSIDE_Y == 0));
    assert_eq!(flagged, x.counts.ticks_outside);
    assert_eq!(st.counters.envelope_excursions, x.counts.ticks_outside);
    // Outside exactly when the command is above 40 V (the sine's rate is never over f32::MAX).
    let above = host
        .frames
        .iter()
        .filter(|f| f.commanded_v[0] > 40.0)
        .count() as u32;
    assert_eq!(above, flagged);
    assert!(flagged > ticks / 4, "{flagged} of {ticks}");
    // The largest excursion is the largest command minus 40 V.
    let peak = host
        .frames
        .iter()
        .map(|f| f.commanded_v[0])
        .fold(f32::MIN, f32::max);
    assert!(peak > 90.0, "{peak}");
    assert_eq!(x.counts.max_voltage_excursion_v, peak - 40.0);
    assert_eq!(
        x.feedback_only_ticks, 0,
        "warn: the compensator kept running"
    );
    assert_eq!(st.feedforward, piezo_link::Feedforward::Compensator);
}

#[test]
fn a_rate_over_the_identified_one_is_an_excursion() {
    let (mut s, plant) = session();
    let mut host = Host::new();
    let mut set = set_with_envelope(EnvelopePolicy::Warn, None);
    // The whole window, but 1 000 V/s: the 10 Hz sine's ≈ 3 000 V/s is over it.
    set.axes[0].envelope = Some(Envelope {
        input_range_v: [0.0, 120.0],
        input_rate_max_v_per_s: 1000.0,
    });
    upload(&mut host, &mut s, set);
    host.ask(&mut s, Request::Frames { decimation: 1 });
    track_outside(&mut host, &mut s, &plant, 4000);
    let x = host.status(&mut s).envelope[0];
    assert!(x.counts.ticks_outside > 0);
    assert_eq!(x.counts.max_voltage_excursion_v, 0.0);
    let steepest = host
        .frames
        .windows(2)
        .map(|w| (w[1].commanded_v[0] - w[0].commanded_v[0]).abs() * params::LOOP_RATE_HZ)
        .fold(0.0, f32::max);
    let excess = x.counts.max_rate_excursion_v_per_s;
    assert!(
        (excess - (steepest - 1000.0)).abs() < 1e-3 * steepest,
        "{excess} vs {steepest}"
    );
}

#[test]
fn feedback_only_runs_the_servo_alone_outside_and_the_compensator_inside() {
    let warn_y = Some(Envelope {
        input_range_v: [0.0, 40.0],
        input_rate_max_v_per_s: f32::MAX,
    });
    // The same session twice: x with `feedback-only`, then with `warn`, feed-forward only.
    let mut runs = std::vec::Vec::new();
    for policy in [EnvelopePolicy::FeedbackOnly, EnvelopePolicy::Warn] {
        let (mut s, plant) = session();
        let mut host = Host::new();
        upload(&mut host, &mut s, set_with_envelope(policy, warn_y));
        host.ask(&mut s, Request::Frames { decimation: 1 });
        host.frames.clear();
        track_outside(&mut host, &mut s, &plant, 4000);
        let outside = host.status(&mut s);
        let frames_outside = core::mem::take(&mut host.frames);
        // Inside again for 0.5 s: the servo's correction fades out (10 τ = 0.2 s), the
        // compensator alone tracks.
        track_inside(
            &mut host,
            &mut s,
            &plant,
            (0.5 * params::LOOP_RATE_HZ) as u32,
        );
        let inside = host.status(&mut s);
        runs.push((
            outside,
            frames_outside,
            inside,
            core::mem::take(&mut host.frames),
        ));
    }
    let (fb_out, fb_frames, fb_in, fb_in_frames) = &runs[0];
    let (warn_out, warn_frames, warn_in, _) = &runs[1];
    // The servo alone drove x in (nearly) every tick outside: from the tick after each exit to
    // the tick the command came back inside.
    let [x, y] = fb_out.envelope;
    assert!(x.feedback_only);
    assert!(x.counts.ticks_outside > 1000, "{x:?}");
    assert!(
        x.feedback_only_ticks + 10 >= x.counts.ticks_outside,
        "{x:?}"
    );
    assert!(x.feedback_only_ticks <= x.counts.ticks_outside, "{x:?}");
    // y's policy is `warn`: counted, never handed over.
    assert!(y.counts.ticks_outside > 0);
    assert_eq!(y.feedback_only_ticks, 0);
    assert_eq!(warn_out.envelope[0].feedback_only_ticks, 0);
    // Outside, the voltages differ from the compensator's (the servo's, not the inverse's);
    // y's are the same in both sessions.
    let differs = fb_frames
        .iter()
        .zip(warn_frames.iter())
        .filter(|(a, b)| a.commanded_v[0] != b.commanded_v[0])
        .count();
    assert!(differs > 1000, "{differs}");
    assert!(fb_frames
        .iter()
        .zip(warn_frames.iter())
        .all(|(a, b)| a.commanded_v[1] == b.commanded_v[1]));
    // Bumpless: no step in x's command larger than the compensator's own largest step.
    let largest_step = |frames: &[Frame]| {
        frames
            .windows(2)
            .map(|w| (w[1].commanded_v[0] - w[0].commanded_v[0]).abs())
            .fold(0.0, f32::max)
    };
    let (fb_step, warn_step) = (largest_step(fb_frames), largest_step(warn_frames));
    assert!(fb_step <= 1.5 * warn_step, "{fb_step} V vs {warn_step} V");
    // Inside again: the servo alone drives only until the command is back inside (a few ticks
    // after the switch of program), no excursion once the start-up is over, and the compensator
    // tracks as in the session that never handed over.
    let more = fb_in.envelope[0].feedback_only_ticks - x.feedback_only_ticks;
    assert!(more < 100, "{more} ticks more of the servo alone");
    assert!(!fb_in.envelope[0].outside);
    assert!(fb_in_frames
        .iter()
        .skip(fb_in_frames.len() / 2)
        .all(|f| f.flags & Frame::OUTSIDE_X == 0));
    let (fb_rms, warn_rms) = (fb_in.tracking[0].rms_m, warn_in.tracking[0].rms_m);
    assert!(
        (fb_rms - warn_rms).abs() <= 0.05 * warn_rms + 1e-9,
        "x rms inside: {fb_rms} (after feedback-only) vs {warn_rms} (warn)"
    );
}

#[test]
fn feedback_only_without_a_servo_is_refused_with_the_field() {
    let (mut s, _plant) = session();
    let mut host = Host::new();
    let mut set = set_with_envelope(EnvelopePolicy::FeedbackOnly, None);
    set.axes[0].servo = None;
    match host.ask(&mut s, Request::Upload(set)) {
        Response::Refused(r) => {
            assert_eq!(r.kind, RefusalKind::Model);
            assert_eq!(r.axis, Some(0));
            assert!(r.reason.contains("envelope_policy"), "{}", r.reason);
        }
        other => panic!("{other:?}"),
    }
    assert!(!host.status(&mut s).envelope[0].known);
}
