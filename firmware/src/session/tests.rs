use core::cell::Cell;

use super::*;
use crate::codes::SensorScale;
use crate::demo;
use crate::plant::{PlantAdc, PlantDac, XyPlant};
use crate::reference::ReferenceGenerator;
use crate::xy_loop::AdcSensor;

/// The host's side: numbered requests in, decoded uplinks out.
struct Host {
    sequence: u32,
    decoder: Decoder,
    frames: std::vec::Vec<Frame>,
    frame_numbers: SequenceChecker,
}

impl Host {
    fn new() -> Self {
        Self {
            sequence: 0,
            decoder: Decoder::new(),
            frames: std::vec::Vec::new(),
            frame_numbers: SequenceChecker::default(),
        }
    }

    fn ask(&mut self, s: &mut Session, request: Request) -> Response {
        let mut out = [0u8; MAX_FRAME + 1];
        let n = piezo_link::encode_request(
            &Packet {
                sequence: self.sequence,
                body: request,
            },
            &mut out,
        )
        .unwrap();
        s.receive(&out[..n]);
        let asked = self.sequence;
        self.sequence += 1;
        let mut answer = None;
        for uplink in self.drain(s) {
            match uplink {
                Uplink::Response { request, response } => {
                    assert_eq!(request, asked);
                    answer = Some(response);
                }
                Uplink::Frame(_) => unreachable!("drain keeps frames"),
            }
        }
        answer.expect("one response")
    }

    fn drain(&mut self, s: &mut Session) -> std::vec::Vec<Uplink> {
        let mut bytes = std::vec::Vec::new();
        s.transmit(|b| {
            bytes.push(b);
            true
        });
        let mut out = std::vec::Vec::new();
        for b in bytes {
            if let Some(r) = self.decoder.push::<Uplink>(b) {
                match r.unwrap().body {
                    Uplink::Frame(f) => {
                        self.frame_numbers.accept(f.sequence);
                        self.frames.push(f);
                    }
                    other => out.push(other),
                }
            }
        }
        out
    }

    fn status(&mut self, s: &mut Session) -> Status {
        match self.ask(s, Request::Status) {
            Response::Status(st) => st,
            other => panic!("{other:?}"),
        }
    }
}

/// Runs `ticks` ticks of the session on the simulated stage.
fn run(s: &mut Session, plant: &Cell<XyPlant>, host: &mut Host, ticks: u32) {
    let mut io = XyIo {
        dac: PlantDac(plant),
        dac_channels: Axis::ALL,
        sensor: AdcSensor {
            adc: PlantAdc(plant),
            channels: Axis::ALL,
            scale: SensorScale::new(params::SENSOR_M_PER_V).unwrap(),
        },
    };
    for _ in 0..ticks {
        s.tick(&mut io, false);
        let mut p = plant.get();
        p.advance();
        plant.set(p);
        host.drain(s);
    }
}

fn session() -> (Session, Cell<XyPlant>) {
    let settings = demo::settings().unwrap();
    let reference = ReferenceGenerator::new(
        Program::PerAxis([Wave::Constant { offset: 0.0 }; 2]),
        params::SAMPLE_PERIOD_S,
        [0.0; 2],
    );
    let initial = [
        params::AXES[0].limits.output_min_v,
        params::AXES[1].limits.output_min_v,
    ];
    let lp = TwoAxisLoop::new(settings, Feedforward::Compensator, reference, initial);
    let plant = Cell::new(XyPlant::from_params(params::SAMPLE_PERIOD_S).unwrap());
    (
        Session::new(
            lp,
            params::VERSION,
            params::FNV1A32,
            super::built_in_fingerprint(),
        ),
        plant,
    )
}

fn built_in_set() -> ModelSet {
    ModelSet {
        version: String::try_from("uploaded 2").unwrap(),
        fnv1a32: 0x1234_5678,
        loop_rate_hz: params::LOOP_RATE_HZ,
        io: params::IO,
        axes: params::AXES.each_ref().map(AxisModel::from_params),
    }
}

fn sine_track() -> Request {
    Request::Track(Program::PerAxis([
        Wave::Sine {
            offset: 19e-6,
            amplitude: 15e-6,
            frequency_hz: 10.0,
        },
        Wave::Triangle {
            offset: 19e-6,
            amplitude: 15e-6,
            frequency_hz: 10.0,
        },
    ]))
}

/// An uploaded axis with effects (creep and the hysteresis's input lag) is accepted, and its
/// first loading is the build's: the quasi-static model's, without the lag (as the stage file's
/// validation computes it), so the same set gets the same baseline gain uploaded or built in;
/// the model the compensator runs carries the lag.
#[test]
fn an_uploaded_axis_with_effects_gets_the_builds_first_loading() {
    let mut set = built_in_set();
    for a in &mut set.axes {
        a.effects.creep_gain_m_per_v = [0.03 * a.static_map.k1_m_per_v, 0.0, 0.0];
        a.effects.creep_time_constant_s = [0.2, 0.0, 0.0];
        a.effects.hysteresis_lag_s = 1e-3;
    }
    let prepared = prepare_upload(set.clone());
    assert!(prepared.axes.is_ok(), "{:?}", prepared.axes.err());
    for (i, a) in set.axes.iter().enumerate() {
        let p = a.params(params::SAMPLE_PERIOD_S).unwrap();
        let built = &params::AXES[i];
        assert_eq!(
            (p.rest_output_m, p.linear_gain_m_per_v),
            (built.rest_output_m, built.linear_gain_m_per_v)
        );
        assert_eq!(
            p.model(params::SAMPLE_PERIOD_S).unwrap().input_lag_s(),
            1e-3
        );
    }
}

#[test]
fn status_names_the_built_in_set() {
    let (mut s, _plant) = session();
    let mut host = Host::new();
    let st = host.status(&mut s);
    assert_eq!(st.params_fnv1a32, params::FNV1A32);
    assert_eq!(st.params_version.as_str(), params::VERSION);
    assert_eq!(st.mode, Mode::Running);
    assert_eq!(st.counters.requests, 1);
}

#[test]
fn excite_streams_frames_then_track_is_accurate() {
    let (mut s, plant) = session();
    let mut host = Host::new();
    let first = match host.ask(&mut s, Request::Frames { decimation: 10 }) {
        Response::Streaming { next_frame, .. } => next_frame,
        other => panic!("{other:?}"),
    };
    host.frame_numbers.expect(first);
    let excite = Request::Excite(Program::PerAxis(
        [Wave::Sine {
            offset: 60.0,
            amplitude: 50.0,
            frequency_hz: 20.0,
        }; 2],
    ));
    assert!(matches!(host.ask(&mut s, excite), Response::Started { .. }));
    run(&mut s, &plant, &mut host, 1000);
    assert_eq!(host.frames.len(), 100);
    assert_eq!(host.frame_numbers.gaps, 0);
    let u: std::vec::Vec<f32> = host.frames.iter().map(|f| f.commanded_v[0]).collect();
    let (lo, hi) = u
        .iter()
        .fold((f32::MAX, f32::MIN), |(a, b), &v| (a.min(v), b.max(v)));
    assert!(lo < 15.0 && hi > 105.0, "{lo} {hi}");
    assert!(host.frames.iter().all(|f| f.reference_m[0].is_nan()));

    assert!(matches!(
        host.ask(&mut s, sine_track()),
        Response::Started { .. }
    ));
    run(&mut s, &plant, &mut host, 4000);
    let st = host.status(&mut s);
    assert_eq!(st.feedforward, piezo_link::Feedforward::Compensator);
    // 4 000 ticks, the first 0.1 s of them settling (`SETTLE_S` at the set's loop rate).
    let settle = libm::roundf(SETTLE_S / s.lp.sample_period_s()) as u32;
    for t in st.tracking {
        assert_eq!(t.count, 4000 - settle);
        assert!(t.rms_m < 50e-9 && t.max_abs_m < 150e-9, "{t:?}");
    }
    assert_eq!(st.counters.frames_dropped, 0);
}

#[test]
fn a_refused_set_leaves_the_running_one_and_a_good_one_is_swapped_in() {
    let (mut s, plant) = session();
    let mut host = Host::new();
    host.ask(&mut s, sine_track());
    run(&mut s, &plant, &mut host, 200);
    let before = s.lp.settings().axes;
    let mut bad = built_in_set();
    bad.axes[1].bouc_wen.beta = -1.0;
    match host.ask(&mut s, Request::Upload(bad)) {
        Response::Refused(r) => {
            assert_eq!(r.kind, RefusalKind::Model);
            assert_eq!(r.axis, Some(1));
            assert!(r.reason.starts_with("y: Bouc-Wen"), "{}", r.reason);
        }
        other => panic!("{other:?}"),
    }
    assert_eq!(s.lp.settings().axes, before);
    let mut other_rate = built_in_set();
    other_rate.loop_rate_hz = 5_000.0;
    assert!(matches!(
        host.ask(&mut s, Request::Upload(other_rate)),
        Response::Refused(Refusal {
            kind: RefusalKind::Chain,
            ..
        })
    ));
    let good = built_in_set();
    assert_eq!(
        host.ask(&mut s, Request::Upload(good)),
        Response::Loaded {
            params_fnv1a32: 0x1234_5678,
            params_fingerprint: built_in_fingerprint(),
        }
    );
    // The same numbers: the same settings, the baseline gain as build.rs computed it.
    for (a, b) in s.lp.settings().axes.iter().zip(before.iter()) {
        assert_eq!(a.compensator(), b.compensator());
    }
    let st = host.status(&mut s);
    assert_eq!(st.params_fnv1a32, 0x1234_5678);
    // Both refusals count: the core's and the chain's.
    assert_eq!((st.counters.uploads, st.counters.refused_uploads), (1, 2));
}

#[test]
fn an_injected_overrun_holds_until_rearm() {
    let (mut s, plant) = session();
    let mut host = Host::new();
    host.ask(&mut s, sine_track());
    run(&mut s, &plant, &mut host, 100);
    assert_eq!(host.ask(&mut s, Request::InjectOverrun), Response::Done);
    run(&mut s, &plant, &mut host, 1);
    let held = s.status().applied_v;
    run(&mut s, &plant, &mut host, 50);
    let st = host.status(&mut s);
    assert_eq!(st.mode, Mode::Safe(crate::xy_loop::Fault::Overrun));
    assert_eq!(st.applied_v, held);
    assert_eq!(st.counters.overruns, 1);
    host.ask(&mut s, Request::Rearm);
    run(&mut s, &plant, &mut host, 10);
    assert_eq!(host.status(&mut s).mode, Mode::Running);
}

#[test]
fn table_and_stream_report_their_room() {
    let (mut s, plant) = session();
    let mut host = Host::new();
    assert!(matches!(
        host.ask(
            &mut s,
            Request::Track(Program::Table {
                ticks_per_entry: 1,
                repeat: false
            })
        ),
        Response::Refused(Refusal {
            kind: RefusalKind::Program,
            ..
        })
    ));
    let chunk: Setpoints = (0..32).map(|i| [i as f32 * 1e-7; 2]).collect();
    assert_eq!(
        host.ask(&mut s, Request::TableAppend(chunk.clone())),
        Response::Queued {
            held: 32,
            capacity: TABLE_CAPACITY as u32
        }
    );
    host.ask(&mut s, Request::Stream(chunk.clone()));
    assert!(matches!(
        host.ask(&mut s, Request::Stream(chunk)),
        Response::Refused(Refusal {
            kind: RefusalKind::Full,
            ..
        })
    ));
    host.ask(
        &mut s,
        Request::Track(Program::Table {
            ticks_per_entry: 2,
            repeat: false,
        }),
    );
    host.ask(&mut s, Request::Frames { decimation: 1 });
    run(&mut s, &plant, &mut host, 8);
    let r: std::vec::Vec<f32> = host.frames.iter().map(|f| f.reference_m[0]).collect();
    assert!((r[3] - 1.5e-7).abs() < 1e-12, "{r:?}");
}

/// The program a `Track` carries is the one the generator plays, bit for bit: each frame's
/// reference is a stand-alone generator's for the same program (per-axis waves, and the raster,
/// which the link carries from protocol 3 on).
#[test]
fn a_tracked_program_plays_as_the_link_carries_it() {
    let raster = Program::Raster {
        x_min: 5e-6,
        x_max: 30e-6,
        y_min: 2e-6,
        y_max: 20e-6,
        lines: 4,
        line_rate_hz: 1_000.0,
    };
    let steps = Program::PerAxis([
        Wave::Steps {
            offset: 19e-6,
            amplitude: 3e-6,
            frequency_hz: 700.0,
        },
        Wave::Sine {
            offset: 12e-6,
            amplitude: 5e-6,
            frequency_hz: 310.0,
        },
    ]);
    for program in [raster, steps] {
        let (mut s, plant) = session();
        let mut host = Host::new();
        host.ask(&mut s, Request::Frames { decimation: 1 });
        assert!(matches!(
            host.ask(&mut s, Request::Track(program)),
            Response::Started { .. }
        ));
        run(&mut s, &plant, &mut host, 400);
        let mut own = ReferenceGenerator::new(program, params::SAMPLE_PERIOD_S, [0.0; 2]);
        let want: std::vec::Vec<[u32; 2]> = (0..400)
            .map(|_| own.next_setpoint().map(f32::to_bits))
            .collect();
        let got: std::vec::Vec<[u32; 2]> = host
            .frames
            .iter()
            .map(|f| f.reference_m.map(f32::to_bits))
            .collect();
        assert_eq!(got, want, "{program:?}");
        // The raster visits its 4 rows: 1 000 lines a second, at least 8 lines in 400 ticks up
        // to a 50 kHz loop.
        if program == raster {
            let rows: std::collections::BTreeSet<u32> = host
                .frames
                .iter()
                .map(|f| f.reference_m[1].to_bits())
                .collect();
            assert_eq!(rows.len(), 4, "{rows:?}");
        }
    }
}

#[test]
fn corrupted_requests_are_counted_not_answered() {
    let (mut s, _plant) = session();
    let mut host = Host::new();
    s.receive(&[1, 2, 3, 0, 0xff, 0xff, 0]);
    assert!(host.drain(&mut s).is_empty());
    host.sequence = 5;
    let st = host.status(&mut s);
    assert_eq!(st.counters.rejected_packets, 2);
    assert_eq!(st.counters.requests, 1);
    host.status(&mut s);
    host.sequence = 9;
    assert_eq!(host.status(&mut s).counters.request_gaps, 1);
}

/// The board's way: the link decodes and prepares an upload outside the session while the loop
/// keeps ticking, then applies it between two ticks; the answer is the same as through
/// `receive`.
#[test]
fn an_upload_prepared_outside_the_session_is_applied_between_two_ticks() {
    let (mut s, plant) = session();
    let mut host = Host::new();
    host.ask(&mut s, sine_track());
    let prepared = prepare(Request::Upload(built_in_set()));
    assert!(matches!(&prepared, Prepared::Upload(u) if u.axes.is_ok()));
    run(&mut s, &plant, &mut host, 50);
    let ticks = s.status().counters.ticks;
    s.apply(host.sequence, prepared);
    host.sequence += 1;
    let answers = host.drain(&mut s);
    assert_eq!(
        answers,
        [Uplink::Response {
            request: host.sequence - 1,
            response: Response::Loaded {
                params_fnv1a32: 0x1234_5678,
                params_fingerprint: built_in_fingerprint(),
            }
        }]
    );
    let st = host.status(&mut s);
    assert_eq!(st.counters.ticks, ticks, "applied between two ticks");
    assert_eq!((st.counters.uploads, st.counters.request_gaps), (1, 0));
    // A refused set prepared the same way leaves the running one.
    let mut bad = built_in_set();
    bad.axes[0].bouc_wen.beta = -1.0;
    let before = s.lp.settings().axes;
    s.apply(host.sequence, prepare(Request::Upload(bad)));
    host.sequence += 1;
    assert!(matches!(
        host.drain(&mut s).as_slice(),
        [Uplink::Response {
            response: Response::Refused(Refusal { axis: Some(0), .. }),
            ..
        }]
    ));
    assert_eq!(s.lp.settings().axes, before);
}

fn refusal(response: Response) -> Refusal {
    match response {
        Response::Refused(r) => r,
        other => panic!("accepted: {other:?}"),
    }
}

/// Every set the stage file's build refuses is refused on upload too, with the core's reason,
/// counted, and the running set left as it was.
#[test]
fn implausible_sets_and_other_chains_are_refused_and_counted() {
    let (mut s, _plant) = session();
    let mut host = Host::new();
    let before = s.lp.settings().axes;
    let servo = piezo_core::ServoParams {
        kp_v_per_m: 0.0,
        ki_v_per_m_s: 2.5e9,
        lowpass_frequency_hz: 3221.0,
        lowpass_q: core::f32::consts::FRAC_1_SQRT_2,
        notch_frequency_hz: 3221.0,
        notch_q: 1.0,
        notch_pole_frequency_hz: 0.0,
        transfer_time_constant_s: 0.02,
    };
    type Edit = fn(&mut ModelSet);
    let model: [(&str, Edit); 9] = [
        ("window 0-200 V", |m| m.axes[0].limits.output_max_v = 200.0),
        ("window -50-120 V", |m| {
            m.axes[1].limits.output_min_v = -50.0
        }),
        ("creep gain 1e6", |m| {
            m.axes[0].effects.creep_gain_m_per_v[0] = 1e6;
            m.axes[0].effects.creep_time_constant_s[0] = 0.1;
        }),
        ("even term 1e30", |m| {
            m.axes[0].effects.even_coefficient_m_per_v2 = 1e30
        }),
        ("drift 1e30", |m| {
            m.axes[1].effects.drift_rate_m_per_s = 1e30
        }),
        ("settling drift 1 m", |m| {
            m.axes[1].effects.drift_settling_m = 1.0;
            m.axes[1].effects.drift_settling_time_constant_s = 1.0;
        }),
        ("slew 1e38", |m| m.axes[0].limits.slew_limit_v_per_s = 1e38),
        ("slew +inf", |m| {
            m.axes[1].limits.slew_limit_v_per_s = f32::INFINITY
        }),
        ("kp 1e38", |m| {
            if let Some(servo) = m.axes[0].servo.as_mut() {
                servo.kp_v_per_m = 1e38;
            }
        }),
    ];
    let chain: [(&str, Edit); 6] = [
        ("loop rate", |m| m.loop_rate_hz = 5_000.0),
        ("amplifier gain", |m| m.io.amplifier_gain_v_per_v = 40.0),
        ("DAC range", |m| m.io.dac_range_v = [0.0, 10.0]),
        ("ADC range", |m| m.io.adc_range_v = [-12.288, 12.288]),
        ("sensor range", |m| m.io.sensor_range_v = [0.0, 5.0]),
        ("sensor gain", |m| m.io.sensor_m_per_v = 2e-5),
    ];
    let mut refused = 0;
    for (what, edit) in model {
        let mut set = built_in_set();
        set.axes[0].servo = Some(servo);
        set.axes[1].servo = Some(servo);
        edit(&mut set);
        let r = refusal(host.ask(&mut s, Request::Upload(set)));
        assert_eq!(r.kind, RefusalKind::Model, "{what}: {}", r.reason);
        assert!(r.axis.is_some(), "{what}");
        refused += 1;
        assert_eq!(s.status().counters.refused_uploads, refused, "{what}");
    }
    for (what, edit) in chain {
        let mut set = built_in_set();
        edit(&mut set);
        let r = refusal(host.ask(&mut s, Request::Upload(set)));
        assert_eq!(r.kind, RefusalKind::Chain, "{what}: {}", r.reason);
        refused += 1;
        assert_eq!(s.status().counters.refused_uploads, refused, "{what}");
    }
    assert_eq!(s.lp.settings().axes, before);
    assert_eq!(s.status().counters.uploads, 0);
    // The reasons are the core's.
    let mut wide = built_in_set();
    wide.axes[0].limits.output_max_v = 200.0;
    let r = refusal(host.ask(&mut s, Request::Upload(wide)));
    assert!(
        r.reason
            .contains("exceeds what the DAC and amplifier drive"),
        "{}",
        r.reason
    );
    let mut creep = built_in_set();
    creep.axes[1].effects.creep_gain_m_per_v[0] = 1e6;
    creep.axes[1].effects.creep_time_constant_s[0] = 0.1;
    let r = refusal(host.ask(&mut s, Request::Upload(creep)));
    assert!(
        r.reason.starts_with("y: field `creep_gain_m_per_v[0]`"),
        "{}",
        r.reason
    );
}

/// A 200 V excitation on the built-in window never commands more than the window's 120 V.
#[test]
fn an_excitation_beyond_the_window_stays_inside_it() {
    let (mut s, plant) = session();
    let mut host = Host::new();
    host.ask(&mut s, Request::Frames { decimation: 1 });
    let excite = Request::Excite(Program::PerAxis([Wave::Constant { offset: 200.0 }; 2]));
    host.ask(&mut s, excite);
    run(&mut s, &plant, &mut host, 200);
    let top = host
        .frames
        .iter()
        .flat_map(|f| f.commanded_v)
        .fold(f32::MIN, f32::max);
    assert!(top <= params::AXES[0].limits.output_max_v, "{top}");
}

/// The same upload frame delivered 20 times runs once; the other 19 are answered `Replayed` with
/// the next number, counted, and change nothing.
#[test]
fn a_replayed_request_is_not_run_again() {
    let (mut s, _plant) = session();
    let mut host = Host::new();
    let mut out = [0u8; MAX_FRAME + 1];
    let n = piezo_link::encode_request(
        &Packet {
            sequence: 3,
            body: Request::Upload(built_in_set()),
        },
        &mut out,
    )
    .unwrap();
    for _ in 0..20 {
        s.receive(&out[..n]);
    }
    let answers = host.drain(&mut s);
    assert_eq!(answers.len(), 20);
    assert!(matches!(
        answers[0],
        Uplink::Response {
            request: 3,
            response: Response::Loaded { .. }
        }
    ));
    for a in &answers[1..] {
        assert_eq!(
            *a,
            Uplink::Response {
                request: 3,
                response: Response::Replayed { next: 4 }
            }
        );
    }
    host.sequence = 4;
    let st = host.status(&mut s);
    assert_eq!(st.counters.uploads, 1);
    assert_eq!(st.counters.replayed_requests, 19);
    assert_eq!(st.counters.requests, 21);
    // A host that counts from 0 again is told where to go on.
    host.sequence = 0;
    assert_eq!(
        host.ask(&mut s, Request::Rearm),
        Response::Replayed { next: 5 }
    );
}

/// A request with bytes after its body (CRC over both) is refused as a packet, not run.
#[test]
fn a_request_with_trailing_bytes_is_refused() {
    let (mut s, _plant) = session();
    let mut host = Host::new();
    let packet = Packet {
        sequence: 1,
        body: Request::InjectOverrun,
    };
    let mut raw = [0u8; 64];
    let mut n = postcard::to_slice(&packet, &mut raw).unwrap().len();
    raw[n] = 0x55;
    n += 1;
    let crc = crc::Crc::<u32>::new(&crc::CRC_32_ISO_HDLC).checksum(&raw[..n]);
    raw[n..n + 4].copy_from_slice(&crc.to_le_bytes());
    n += 4;
    // COBS by hand: one block (the packet holds no zero byte).
    assert!(!raw[..n].contains(&0), "{:?}", &raw[..n]);
    let mut frame = std::vec![0u8, n as u8 + 1];
    frame.extend_from_slice(&raw[..n]);
    frame.push(0);
    s.receive(&frame);
    assert!(host.drain(&mut s).is_empty());
    host.sequence = 2;
    let st = host.status(&mut s);
    assert_eq!(st.counters.rejected_packets, 1);
    assert_eq!(st.mode, Mode::Running, "the overrun drill did not run");
}

/// Ticks the session `ticks` times on the simulated stage and returns every packet it queued,
/// decoded, with its packet number.
fn tick_packets(
    s: &mut Session,
    plant: &Cell<XyPlant>,
    ticks: u32,
) -> std::vec::Vec<Packet<Uplink>> {
    let mut io = XyIo {
        dac: PlantDac(plant),
        dac_channels: Axis::ALL,
        sensor: AdcSensor {
            adc: PlantAdc(plant),
            channels: Axis::ALL,
            scale: SensorScale::new(params::SENSOR_M_PER_V).unwrap(),
        },
    };
    for _ in 0..ticks {
        s.tick(&mut io, false);
        let mut p = plant.get();
        p.advance();
        plant.set(p);
    }
    packets(s)
}

/// The packets queued in the session's transmit buffer, decoded.
fn packets(s: &mut Session) -> std::vec::Vec<Packet<Uplink>> {
    let mut decoder = Decoder::new();
    let mut out = std::vec::Vec::new();
    s.transmit(|b| {
        if let Some(p) = decoder.push::<Uplink>(b) {
            out.push(p.unwrap());
        }
        true
    });
    out
}

/// The board's link answers a request in two holds of the session's lock, encoding in between
/// while ticks run: the reply keeps the packet number it was given, frames produced meanwhile
/// wait in the frame queue and follow it, none lost, and the backlog drains at most
/// [`FRAMES_PER_TICK`] a tick.
#[test]
fn a_reply_encoded_between_ticks_keeps_its_place_and_no_frame_is_lost() {
    let (mut s, plant) = session();
    let mut host = Host::new();
    host.ask(&mut s, Request::Frames { decimation: 1 });
    host.ask(&mut s, sine_track());
    let mut all = tick_packets(&mut s, &plant, 5);
    assert_eq!(all.len(), 5);

    let prepared = prepare(Request::Status);
    let reply = s.answer(host.sequence, &prepared);
    let Response::Status(snapshot) = reply.response().clone() else {
        panic!("{:?}", reply.response());
    };
    // Three ticks while the reply is encoded: their frames wait.
    assert!(tick_packets(&mut s, &plant, 3).is_empty());
    let mut out = [0u8; MAX_FRAME];
    let n = reply.encode(&mut out).unwrap();
    assert!(s.queue_reply(&reply, Some(&out[..n])));
    // The status is the state when the request was applied, not when it was sent.
    assert_eq!(snapshot.counters.ticks, 5);
    all.extend(packets(&mut s));
    for k in 0..3 {
        let p = tick_packets(&mut s, &plant, 1);
        // Three held and one new a tick: two go a tick until the backlog is gone.
        assert_eq!(p.len(), 2, "tick {k}");
        all.extend(p);
    }
    let numbers: std::vec::Vec<u32> = all.iter().map(|p| p.sequence).collect();
    assert_eq!(
        numbers,
        (numbers[0]..numbers[0] + 12).collect::<std::vec::Vec<_>>()
    );
    assert_eq!(
        all[5].body,
        Uplink::Response {
            request: host.sequence,
            response: Response::Status(snapshot)
        }
    );
    let frames: std::vec::Vec<u32> = all
        .iter()
        .filter_map(|p| match p.body {
            Uplink::Frame(f) => Some(f.sequence),
            _ => None,
        })
        .collect();
    assert_eq!(
        frames,
        (frames[0]..frames[0] + 11).collect::<std::vec::Vec<_>>()
    );
    host.sequence += 1;
    assert_eq!(s.lp.frames.len(), 0);
    assert_eq!(host.status(&mut s).counters.frames_dropped, 0);
}

/// Frames produced while frames were on still go out when a request turns them off before the
/// tick could send them (held back by a reply); the ones after it do not.
#[test]
fn frames_held_back_by_a_reply_still_go_out_after_frames_off() {
    let (mut s, plant) = session();
    let mut host = Host::new();
    host.ask(&mut s, Request::Frames { decimation: 1 });
    host.ask(&mut s, sine_track());
    tick_packets(&mut s, &plant, 2);
    let reply = s.answer(host.sequence, &prepare(Request::Status));
    host.sequence += 1;
    assert!(tick_packets(&mut s, &plant, 3).is_empty());
    let mut out = [0u8; MAX_FRAME];
    let n = reply.encode(&mut out).unwrap();
    assert!(s.queue_reply(&reply, Some(&out[..n])));
    packets(&mut s);
    let next = match host.ask(&mut s, Request::Frames { decimation: 0 }) {
        Response::Streaming { next_frame, .. } => next_frame,
        other => panic!("{other:?}"),
    };
    let frames: std::vec::Vec<u32> = tick_packets(&mut s, &plant, 4)
        .iter()
        .filter_map(|p| match p.body {
            Uplink::Frame(f) => Some(f.sequence),
            _ => None,
        })
        .collect();
    assert_eq!(frames, [next - 3, next - 2, next - 1]);
}

/// A reply whose packet number is no longer the next (another packet went out under it) is not
/// queued: two packets never carry one number.
#[test]
fn a_stale_reply_is_not_queued() {
    let (mut s, _plant) = session();
    let first = s.answer(0, &prepare(Request::Status));
    let second = s.answer(1, &prepare(Request::Rearm));
    assert_eq!(first.packet(), second.packet());
    let mut out = [0u8; MAX_FRAME];
    let n = second.encode(&mut out).unwrap();
    assert!(s.queue_reply(&second, Some(&out[..n])));
    let n = first.encode(&mut out).unwrap();
    assert!(!s.queue_reply(&first, Some(&out[..n])));
    assert!(!s.queue_reply(&first, None));
    let sent = packets(&mut s);
    assert_eq!(sent.len(), 1);
    assert_eq!(sent[0].sequence, second.packet());
}

mod counters;
mod envelope;
mod learned;
mod on_target;
