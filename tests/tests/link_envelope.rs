//! The identified envelope over the command link, against the QEMU image's simulated stage.
//!
//! The built-in stage file with an `[x.identified]` and `[y.identified]` that say the set was
//! identified on 0–40 V (at most 10⁴ V/s) is uploaded; a 19 ± 15 µm, 10 Hz sine (commands up to
//! ≈ 100 V) is tracked with every frame recorded: the status counts per axis the ticks outside
//! and the largest excursion, and the frames flag exactly those ticks. With x's
//! `envelope_policy = "feedback-only"` the servo alone drives x while outside (counted), y
//! (`warn`) is never handed over; tracking 5 ± 3 µm (inside) afterwards, the compensator runs
//! again: no tick flagged once the program has settled and the tracking error is the
//! compensator's.
//!
//! Skipped, with a message, when `qemu-system-arm` or the thumbv7em-none-eabihf target is
//! missing.

mod common;

use common::{build_link_image, connect, firmware_dir, run_link_image, shut_down, TempDir};
use host_sim::link::{upload, Client, Recording};
use integration_tests::qemu::{missing_tools, say};
use piezo_link::{Control, Frame, Program, Request, Response, Status, Wave};

/// The built-in stage file identified on 0–40 V, with x's policy `x_policy`.
fn stage_file(x_policy: &str) -> String {
    let text = std::fs::read_to_string(firmware_dir().join("params/xy-stage.toml")).unwrap();
    let text = text.replacen(
        "slew_limit_v_per_s = 1.0e5\n",
        &format!("slew_limit_v_per_s = 1.0e5\nenvelope_policy = \"{x_policy}\"\n"),
        1,
    );
    let identified = |axis: &str| {
        format!(
            "\n[{axis}.identified]\ndata = \"excite-0-40V.csv\"\nwindow_s = [0.2, 1.2]\n\
             method = \"vp-de-lm\"\nfit_rms_m = 2e-9\ninput_range_v = [0.0, 40.0]\n\
             sample_period_s = 5e-5\ninput_rate_max_v_per_s = 1.0e4\nband_hz = [5.0, 5.0]\n"
        )
    };
    format!("{text}{}{}", identified("x"), identified("y"))
}

/// Tracks `spec` for `duration_s` with every frame recorded, and the status right after (a few
/// ticks later: the program repeats until told otherwise); then holds 5 µm (inside), so that
/// nothing counts until the next recording.
fn track(client: &mut Client, spec: &str, duration_s: f64) -> (Recording, Status) {
    let rec = client.run(spec, duration_s, 1, false).expect("track");
    assert_eq!((rec.gaps, rec.lost), (0, 0));
    let status = client.status().expect("status");
    let hold = Request::Track(Program::PerAxis([Wave::Constant { offset: 5e-6 }; 2]));
    assert!(matches!(
        client.request(hold).unwrap(),
        Response::Started { .. }
    ));
    (rec, status)
}

const OUTSIDE: &str = "sine:amp=15e-6,offset=19e-6,freq=10,phase_deg=-90";
const INSIDE: &str = "sine:amp=3e-6,offset=5e-6,freq=10,phase_deg=-90";

fn flagged(rec: &Recording, axis: usize) -> u32 {
    rec.frames
        .iter()
        .filter(|f| f.flags & Frame::outside_flag(axis) != 0)
        .count() as u32
}

#[test]
fn excursions_are_counted_and_feedback_only_hands_over_outside() {
    if let Some(why) = missing_tools() {
        say(&format!("link_envelope: SKIPPED: {why}"));
        return;
    }
    let elf = build_link_image();
    let dir = TempDir(std::env::temp_dir().join(format!("link_envelope_{}", std::process::id())));
    std::fs::create_dir_all(&dir.0).expect("temporary directory");
    let (mut qemu, port) = run_link_image(&elf);
    let mut client = connect(port);
    let before = client.status().unwrap();
    assert!(
        before.envelope.iter().all(|e| !e.known),
        "built-in set: none"
    );

    // 1. warn on both axes: counted and flagged, nothing else changes.
    let warn = dir.0.join("warn.toml");
    std::fs::write(&warn, stage_file("warn")).unwrap();
    upload(&mut client, &warn).expect("upload warn");
    let (rec, st) = track(&mut client, OUTSIDE, 0.5);
    for axis in 0..2 {
        let e = st.envelope[axis];
        assert!(e.known && !e.feedback_only);
        let peak = rec
            .frames
            .iter()
            .map(|f| f.commanded_v[axis])
            .fold(f32::MIN, f32::max);
        let above = rec
            .frames
            .iter()
            .filter(|f| f.commanded_v[axis] > 40.0)
            .count() as u32;
        say(&format!(
            "link_envelope: warn, axis {axis}: {} ticks outside of {}, largest excursion {} V \
             (peak command {peak} V), {} V/s over the rate",
            e.counts.ticks_outside,
            rec.frames.len(),
            e.counts.max_voltage_excursion_v,
            e.counts.max_rate_excursion_v_per_s
        ));
        assert!(peak > 80.0, "{peak}");
        assert_eq!(e.counts.max_voltage_excursion_v, peak - 40.0);
        // The only steps over the rate are the start's: the reference jumps to the sine's
        // first value and the compensator slews there at the slew limit (1e5 V/s).
        assert!(e.counts.max_rate_excursion_v_per_s <= 1.0e5 - 1.0e4 + 1.0);
        // The status comes a few ticks after the last frame.
        let counted = e.counts.ticks_outside;
        assert!(
            counted >= above && counted <= above + 50,
            "{counted} vs {above}"
        );
        let flags = flagged(&rec, axis);
        assert!(
            flags <= counted && counted <= flags + 50,
            "{counted} vs {flags}"
        );
        assert_eq!(e.feedback_only_ticks, 0);
    }
    assert_eq!(
        st.counters.envelope_excursions,
        st.envelope[0].counts.ticks_outside + st.envelope[1].counts.ticks_outside
    );

    // 2. feedback-only on x (the built-in set has a servo on both axes), feed-forward mode.
    let feedback_only = dir.0.join("feedback-only.toml");
    std::fs::write(&feedback_only, stage_file("feedback-only")).unwrap();
    upload(&mut client, &feedback_only).expect("upload feedback-only");
    let start = client.status().unwrap();
    assert_eq!(start.control, Control::Feedforward);
    let (rec, st) = track(&mut client, OUTSIDE, 0.5);
    let [x, y] = st.envelope;
    let x_outside = x.counts.ticks_outside - start.envelope[0].counts.ticks_outside;
    let alone = x.feedback_only_ticks - start.envelope[0].feedback_only_ticks;
    say(&format!(
        "link_envelope: feedback-only, x: {x_outside} ticks outside, the servo alone {alone} ticks"
    ));
    assert!(x.feedback_only);
    let flags = flagged(&rec, 0);
    assert!(
        flags <= x_outside && x_outside <= flags + 50,
        "{x_outside} vs {flags}"
    );
    assert!(x_outside > 1000, "{x_outside}");
    assert!(
        alone <= x_outside && alone + 20 >= x_outside,
        "{alone} vs {x_outside}"
    );
    assert!(y.counts.ticks_outside > start.envelope[1].counts.ticks_outside);
    assert_eq!(y.feedback_only_ticks, 0, "y's policy is warn");
    // Bumpless: x's largest step per tick stays the size of a tracking step.
    let largest = rec
        .frames
        .windows(2)
        .map(|w| (w[1].commanded_v[0] - w[0].commanded_v[0]).abs())
        .fold(0.0, f32::max);
    say(&format!(
        "link_envelope: largest x step {largest} V per tick"
    ));
    assert!(largest < 1.0, "{largest} V in one tick");

    // 3. Inside again: the compensator runs, no tick outside once the program has settled.
    let (rec, st) = track(&mut client, INSIDE, 0.5);
    let late = rec.frames.len() / 2;
    assert!(rec.frames[late..]
        .iter()
        .all(|f| f.flags & (Frame::OUTSIDE_X | Frame::OUTSIDE_Y) == 0));
    assert!(!st.envelope[0].outside);
    let more = st.envelope[0].feedback_only_ticks - x.feedback_only_ticks;
    say(&format!(
        "link_envelope: inside: the servo alone {more} more ticks, x rms {:.1} nm",
        st.tracking[0].rms_m * 1e9
    ));
    assert!(more < 200, "{more}");
    assert!(st.tracking[0].rms_m < 100e-9, "{}", st.tracking[0].rms_m);
    shut_down(&mut client, &mut qemu);
}
