//! The loop's counters are the status's (the output guard's per axis and cause), and the
//! running set's fingerprint follows its content through uploads.

use super::*;

fn excite(x_v: Wave, y_v: Wave) -> Request {
    Request::Excite(Program::PerAxis([x_v, y_v]))
}

/// x excited above its window (clamped, then held there), y by steps larger than the slew limit
/// allows per tick: the status splits the guard's interventions by axis and cause, and they are
/// the loop's own guard counts.
#[test]
fn the_guard_is_counted_per_axis_and_cause() {
    let (mut s, plant) = session();
    let mut host = Host::new();
    let max_v = params::AXES[0].limits.output_max_v;
    let window = params::AXES[1].limits.output_max_v - params::AXES[1].limits.output_min_v;
    host.ask(
        &mut s,
        excite(
            Wave::Constant {
                offset: max_v + 80.0,
            },
            Wave::Steps {
                offset: params::AXES[1].limits.output_min_v + window / 2.0,
                amplitude: window / 2.0,
                frequency_hz: 50.0,
            },
        ),
    );
    run(&mut s, &plant, &mut host, 1_000);
    let st = host.status(&mut s);
    let [x, y] = st.counters.guard;
    // x: every tick's request is outside the window (clamped); the first ones, the slew from
    // the lower end to the upper, are slew-limited as well (each cause counts).
    assert_eq!(x.window_clamped, 1_000, "{x:?}");
    assert!((1..100).contains(&x.slew_limited), "{x:?}");
    assert_eq!((x.non_finite, x.window_entry), (0, 0));
    // y: inside the window, a full-window step every 10 ms; slewed over several ticks each.
    assert_eq!((y.window_clamped, y.non_finite, y.window_entry), (0, 0, 0));
    let steps = 1_000 / (params::LOOP_RATE_HZ as u32 / 100);
    assert!(y.slew_limited >= steps, "{y:?}");
    for axis in Axis::ALL {
        assert_eq!(
            st.counters.guard[axis.index()],
            s.lp.guard(axis).counters(),
            "{axis:?}"
        );
    }
    assert_eq!(st.counters.guard_interventions(), x.total() + y.total());
    // The loop's counters are the status's, the link's added.
    let mut from_loop = s.lp.counters();
    assert_eq!(from_loop.requests, 0);
    from_loop.frames_sent = st.counters.frames_sent;
    from_loop.requests = st.counters.requests;
    assert_eq!(st.counters, from_loop);
}

/// Boot: the built-in set's fingerprint. An upload with other numbers changes it even when the
/// set claims the same stage file hash and version; an upload of the built-in numbers brings it
/// back; a refused upload leaves it.
#[test]
fn the_fingerprint_is_the_running_sets_content() {
    let (mut s, _plant) = session();
    let mut host = Host::new();
    let boot = host.status(&mut s);
    assert_eq!(boot.params_fingerprint, built_in_fingerprint());
    assert_eq!(boot.protocol, PROTOCOL_VERSION);
    let mut slower = built_in_set();
    slower.version = truncated(params::VERSION);
    slower.fnv1a32 = params::FNV1A32;
    slower.axes[0].limits.slew_limit_v_per_s *= 0.5;
    let loaded = host.ask(&mut s, Request::Upload(slower.clone()));
    assert_eq!(
        loaded,
        Response::Loaded {
            params_fnv1a32: params::FNV1A32,
            params_fingerprint: slower.fingerprint(),
        }
    );
    let after = host.status(&mut s);
    assert_eq!(after.params_fnv1a32, boot.params_fnv1a32);
    assert_eq!(after.params_version, boot.params_version);
    assert_ne!(after.params_fingerprint, boot.params_fingerprint);
    assert_eq!(after.params_fingerprint, slower.fingerprint());
    let mut refused = built_in_set();
    refused.loop_rate_hz = 5_000.0;
    assert!(matches!(
        host.ask(&mut s, Request::Upload(refused)),
        Response::Refused(_)
    ));
    assert_eq!(host.status(&mut s).params_fingerprint, slower.fingerprint());
    assert!(matches!(
        host.ask(&mut s, Request::Upload(built_in_set())),
        Response::Loaded { .. }
    ));
    assert_eq!(
        host.status(&mut s).params_fingerprint,
        boot.params_fingerprint
    );
}

/// A table excitation that has finished holds its last entry; the next table, a track's
/// metres, is loaded while it holds. The output stays where the excitation left it, with no
/// guard intervention, until the track starts: the new entries are never played as volts.
#[test]
fn a_table_loaded_after_a_finished_excitation_is_not_played() {
    let (mut s, plant) = session();
    let mut host = Host::new();
    let mid_v = [0, 1]
        .map(|i| 0.5 * (params::AXES[i].limits.output_min_v + params::AXES[i].limits.output_max_v));
    let ramp: Setpoints = (0..=16)
        .map(|j| {
            let f = j as f32 / 16.0;
            [0, 1].map(|i| {
                params::AXES[i].limits.output_min_v
                    + f * (mid_v[i] - params::AXES[i].limits.output_min_v)
            })
        })
        .collect();
    host.ask(&mut s, Request::TableClear);
    host.ask(&mut s, Request::TableAppend(ramp));
    let program = Program::Table {
        ticks_per_entry: 100,
        repeat: false,
    };
    assert!(matches!(
        host.ask(&mut s, Request::Excite(program)),
        Response::Started { .. }
    ));
    run(&mut s, &plant, &mut host, 2_000);
    let guard_before = host.status(&mut s).counters.guard;
    host.ask(&mut s, Request::Frames { decimation: 1 });
    host.frames.clear();
    host.ask(&mut s, Request::TableClear);
    run(&mut s, &plant, &mut host, 50);
    let track: Setpoints = (0..32).map(|j| [19e-6 + j as f32 * 1e-8; 2]).collect();
    host.ask(&mut s, Request::TableAppend(track));
    run(&mut s, &plant, &mut host, 50);
    assert_eq!(host.frames.len(), 100);
    for f in &host.frames {
        for (i, (&v, &held)) in f.commanded_v.iter().zip(&mid_v).enumerate() {
            assert!((v - held).abs() < 1e-3, "axis {i}: {v} V, held at {held} V");
        }
    }
    assert_eq!(host.status(&mut s).counters.guard, guard_before);
}
