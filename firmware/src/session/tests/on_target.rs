//! On target over the link: an uploaded set carries its band, a step's frames carry the flag
//! (bits 2 and 3) exactly when the last N readings were inside the band around the reference
//! they answer, the status reports the flag and the settling time, the safe state clears it,
//! and a band the core refuses is refused on upload.

use super::*;
use piezo_core::OnTarget;

fn hold(to_m: f32) -> Request {
    Request::Track(Program::PerAxis([Wave::Constant { offset: to_m }; 2]))
}

#[test]
fn a_step_is_flagged_on_target_after_n_ticks_inside_the_band() {
    let (mut s, plant) = session();
    let mut host = Host::new();
    let mut set = built_in_set();
    let band = OnTarget::new(20e-9, 7).unwrap();
    set.axes[0].on_target = band;
    set.axes[1].on_target = OnTarget::new(1e-6, 3).unwrap();
    assert!(matches!(
        host.ask(&mut s, Request::Upload(set)),
        Response::Loaded { .. }
    ));
    assert!(matches!(
        host.ask(&mut s, hold(2e-6)),
        Response::Started { .. }
    ));
    run(&mut s, &plant, &mut host, 400);
    let st = host.status(&mut s);
    assert!(
        st.on_target.iter().all(|a| a.on_target),
        "{:?}",
        st.on_target
    );
    assert_eq!(
        (st.on_target[0].tolerance_m, st.on_target[0].ticks),
        (20e-9, 7)
    );
    assert_eq!(st.on_target[1].ticks, 3);

    host.ask(&mut s, Request::Frames { decimation: 1 });
    host.frames.clear();
    assert!(matches!(
        host.ask(&mut s, hold(15e-6)),
        Response::Started { .. }
    ));
    run(&mut s, &plant, &mut host, 200);
    let frames = host.frames.clone();
    assert!(frames.len() >= 199, "{}", frames.len());
    // x: the flag is the rule on the frames, frame k's reading against k − 1's reference.
    let mut run_inside = 0u32;
    let mut first_flag = None;
    let mut first_inside_of_run = 0;
    for k in 1..frames.len() {
        let e = frames[k].sensor_m[0] - frames[k - 1].reference_m[0];
        if e.abs() <= band.tolerance_m {
            if run_inside == 0 {
                first_inside_of_run = k;
            }
            run_inside += 1;
        } else {
            run_inside = 0;
        }
        let flagged = frames[k].flags & Frame::ON_TARGET_X != 0;
        assert_eq!(flagged, run_inside >= 7, "frame {k}: error {e:e} m");
        if flagged && first_flag.is_none() {
            first_flag = Some(first_inside_of_run);
        }
    }
    let first_inside = first_flag.expect("x settles");
    assert!(first_inside > 2, "the step leaves the band first");
    let st = host.status(&mut s);
    assert!(st.on_target[0].on_target);
    // The change is seen at frame 1 (the first reading answering 15 µm).
    assert_eq!(st.on_target[0].settle_ticks, Some(first_inside as u32 - 1));
    assert!(st.on_target[0].ticks_since_change >= 190);
    // y's wide band: flagged earlier than x.
    let y_first = frames
        .iter()
        .position(|f| f.flags & Frame::ON_TARGET_Y != 0);
    assert!(y_first.unwrap() < first_inside + 7);

    // The safe state clears the flag.
    host.ask(&mut s, Request::InjectOverrun);
    run(&mut s, &plant, &mut host, 5);
    let st = host.status(&mut s);
    assert!(st.on_target.iter().all(|a| !a.on_target));
    assert!(host.frames.last().unwrap().flags & (Frame::ON_TARGET_X | Frame::ON_TARGET_Y) == 0);
}

#[test]
fn a_band_the_core_refuses_is_refused_on_upload() {
    let (mut s, _plant) = session();
    let mut host = Host::new();
    for (tolerance_m, ticks) in [(0.0, 5), (f32::NAN, 5), (1e-8, 0)] {
        let mut set = built_in_set();
        set.axes[1].on_target = OnTarget { tolerance_m, ticks };
        let r = refusal(host.ask(&mut s, Request::Upload(set)));
        assert_eq!(r.axis, Some(1), "{r:?}");
        assert!(
            r.reason.contains("tolerance_m") || r.reason.contains("ticks"),
            "{}",
            r.reason
        );
    }
    assert_eq!(host.status(&mut s).counters.refused_uploads, 3);
}
