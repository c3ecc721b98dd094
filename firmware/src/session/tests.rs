use core::cell::Cell;

use super::*;
use crate::codes::SensorScale;
use crate::demo;
use crate::plant::{PlantAdc, PlantDac, XyPlant};
use crate::reference::ReferenceGenerator;
use crate::xy_loop::AdcSensor;
use piezo_link::{Limits, Mode as WireMode};

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
        let mut out = [0u8; MAX_FRAME];
        let n = piezo_link::encode(
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
        Program::PerAxis([Waveform::Constant { offset_m: 0.0 }; 2]),
        params::SAMPLE_PERIOD_S,
        [0.0; 2],
    );
    let initial = [params::AXES[0].output_min_v, params::AXES[1].output_min_v];
    let lp = TwoAxisLoop::new(settings, Feedforward::Compensator, reference, initial);
    let plant = Cell::new(XyPlant::from_params(params::SAMPLE_PERIOD_S).unwrap());
    (Session::new(lp, params::VERSION, params::FNV1A32), plant)
}

fn built_in_set() -> ModelSet {
    let axis = |p: &AxisParams| AxisModel {
        bouc_wen: p.bouc_wen,
        static_map: p.static_map,
        asymmetry: p.asymmetry,
        effects: p.effects,
        limits: Limits {
            output_min_v: p.output_min_v,
            output_max_v: p.output_max_v,
            slew_limit_v_per_s: p.slew_limit_v_per_s,
        },
        servo: p.servo,
    };
    ModelSet {
        version: String::try_from("uploaded 2").unwrap(),
        fnv1a32: 0x1234_5678,
        loop_rate_hz: params::LOOP_RATE_HZ,
        amplifier_gain_v_per_v: params::AMPLIFIER_GAIN_V_PER_V,
        sensor_m_per_v: params::SENSOR_M_PER_V,
        axes: [axis(&params::AXES[0]), axis(&params::AXES[1])],
    }
}

fn sine_track() -> Request {
    Request::Track(WireProgram::PerAxis([
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

#[test]
fn status_names_the_built_in_set() {
    let (mut s, _plant) = session();
    let mut host = Host::new();
    let st = host.status(&mut s);
    assert_eq!(st.params_fnv1a32, params::FNV1A32);
    assert_eq!(st.params_version.as_str(), params::VERSION);
    assert_eq!(st.mode, WireMode::Running);
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
    let excite = Request::Excite(WireProgram::PerAxis(
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
    for t in st.tracking {
        assert_eq!(t.count, 3000);
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
            params_fnv1a32: 0x1234_5678
        }
    );
    // The same numbers: the same settings, the baseline gain as build.rs computed it.
    for (a, b) in s.lp.settings().axes.iter().zip(before.iter()) {
        assert_eq!(a.compensator(), b.compensator());
    }
    let st = host.status(&mut s);
    assert_eq!(st.params_fnv1a32, 0x1234_5678);
    assert_eq!((st.counters.uploads, st.counters.refused_uploads), (1, 1));
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
    assert_eq!(st.mode, WireMode::Safe(piezo_link::Fault::Overrun));
    assert_eq!(st.applied_v, held);
    assert_eq!(st.counters.overruns, 1);
    host.ask(&mut s, Request::Rearm);
    run(&mut s, &plant, &mut host, 10);
    assert_eq!(host.status(&mut s).mode, WireMode::Running);
}

#[test]
fn table_and_stream_report_their_room() {
    let (mut s, plant) = session();
    let mut host = Host::new();
    assert!(matches!(
        host.ask(
            &mut s,
            Request::Track(WireProgram::Table {
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
        Request::Track(WireProgram::Table {
            ticks_per_entry: 2,
            repeat: false,
        }),
    );
    host.ask(&mut s, Request::Frames { decimation: 1 });
    run(&mut s, &plant, &mut host, 8);
    let r: std::vec::Vec<f32> = host.frames.iter().map(|f| f.reference_m[0]).collect();
    assert!((r[3] - 1.5e-7).abs() < 1e-12, "{r:?}");
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
                params_fnv1a32: 0x1234_5678
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
