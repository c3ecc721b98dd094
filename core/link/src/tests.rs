use super::*;
use piezo_core::effects::EffectParams;
use piezo_core::{
    Asymmetry, BoucWenParams, Envelope, EnvelopeCounts, EnvelopePolicy, OnTarget, ServoParams,
    StaticMap,
};
use proptest::prelude::*;

fn axis() -> AxisModel {
    AxisModel {
        bouc_wen: BoucWenParams {
            a: 0.185,
            beta: 0.0296,
            gamma: -0.0207,
            n: 1.0,
        },
        static_map: StaticMap {
            k1_m_per_v: 3.2e-7,
            k2_m_per_h: -3.2e-7,
            offset_m: 0.0,
        },
        asymmetry: Asymmetry::default(),
        effects: EffectParams {
            creep_gain_m_per_v: [1e-9, 2e-9, 0.0],
            creep_time_constant_s: [0.1, 1.0, 0.0],
            delay_s: 2e-4,
            coupling: 0.01,
            log_creep_time_s: 0.5,
            relaxation_gain: [0.3, 0.1],
            relaxation_time_constant_s: [1e-3, 1e-2],
            relaxation_linear_m_per_v: 3e-7,
            ..EffectParams::default()
        },
        limits: Limits {
            output_min_v: 0.0,
            output_max_v: 120.0,
            slew_limit_v_per_s: 1e5,
            envelope_policy: EnvelopePolicy::FeedbackOnly,
        },
        servo: Some(ServoParams {
            kp_v_per_m: 0.0,
            ki_v_per_m_s: 2.5e9,
            lowpass_frequency_hz: 3221.0,
            lowpass_q: core::f32::consts::FRAC_1_SQRT_2,
            notch_frequency_hz: 3221.0,
            notch_q: 1.0,
            notch_pole_frequency_hz: 0.0,
            transfer_time_constant_s: 0.02,
        }),
        envelope: Some(Envelope {
            input_range_v: [0.5, 119.5],
            input_rate_max_v_per_s: f32::MAX,
        }),
        on_target: OnTarget {
            tolerance_m: 2.5e-8,
            ticks: u32::MAX,
        },
    }
}

fn model_set() -> ModelSet {
    ModelSet {
        version: heapless::String::try_from("xy-stage 1").unwrap(),
        fnv1a32: 0xdead_beef,
        loop_rate_hz: 10_000.0,
        io: piezo_core::IoChain {
            dac_range_v: [0.0, 5.0],
            amplifier_gain_v_per_v: 24.0,
            adc_range_v: [-10.24, 10.24],
            sensor_range_v: [0.0, 10.0],
            sensor_m_per_v: 1e-5,
        },
        axes: [axis(), axis()],
    }
}

fn round_trip<T>(body: T) -> T
where
    T: Serialize + serde::de::DeserializeOwned + Clone + core::fmt::Debug + PartialEq,
{
    let packet = Packet {
        sequence: 0x1234_5678,
        body,
    };
    let mut out = [0u8; MAX_FRAME];
    let n = encode(&packet, &mut out).unwrap();
    assert!(n <= MAX_FRAME);
    assert_eq!(out[n - 1], 0);
    assert!(
        !out[..n - 1].contains(&0),
        "COBS leaves no delimiter inside"
    );
    let mut decoder = Decoder::new();
    let mut got = None;
    for &b in &out[..n] {
        if let Some(r) = decoder.push::<T>(b) {
            got = Some(r.unwrap());
        }
    }
    let got = got.expect("one packet at the delimiter");
    assert_eq!(got, packet);
    got.body
}

fn full_status() -> Status {
    Status {
        protocol: u16::MAX,
        params_fingerprint: u32::MAX,
        params_fnv1a32: u32::MAX,
        params_version: heapless::String::try_from("x".repeat(VERSION_BYTES).as_str()).unwrap(),
        loop_rate_hz: 10_000.0,
        mode: Mode::Safe(Fault::StuckReading(Axis::Y)),
        feedforward: Feedforward::OpenLoop,
        control: Control::FeedforwardFeedback,
        tick_cycles_max: u32::MAX,
        counters: Counters {
            ticks: u32::MAX,
            frames_sent: u32::MAX,
            guard: [GuardCounters {
                non_finite: u32::MAX,
                window_clamped: u32::MAX,
                slew_limited: u32::MAX,
                window_entry: u32::MAX,
            }; 2],
            ..Counters::default()
        },
        tracking: [Tracking {
            count: u32::MAX,
            rms_m: 1e-9,
            max_abs_m: f32::NAN,
        }; 2],
        applied_v: [1.0, 2.0],
        measured_m: [3.0, 4.0],
        frame_decimation: 10,
        next_frame: u32::MAX,
        table: [2048, 2048],
        stream: [0, 63],
        learned: [2048, 2048],
        envelope: [EnvelopeStatus {
            known: true,
            feedback_only: true,
            outside: true,
            counts: EnvelopeCounts {
                ticks_outside: u32::MAX,
                max_voltage_excursion_v: f32::MAX,
                max_rate_excursion_v_per_s: f32::NAN,
            },
            feedback_only_ticks: u32::MAX,
        }; 2],
        on_target: [OnTargetStatus {
            on_target: true,
            ticks_since_change: u32::MAX,
            settle_ticks: Some(u32::MAX),
            tolerance_m: f32::MAX,
            ticks: u32::MAX,
        }; 2],
    }
}

#[test]
fn every_message_round_trips_and_fits() {
    round_trip(Request::Status);
    round_trip(Request::Upload(model_set()));
    round_trip(Request::TableAppend(
        (0..SETPOINT_CHUNK).map(|i| [i as f32, -1e-6]).collect(),
    ));
    round_trip(Request::Track(Program::PerAxis([
        Wave::Sine {
            offset: 19e-6,
            amplitude: 15e-6,
            frequency_hz: 10.0,
        },
        Wave::Constant { offset: 0.0 },
    ])));
    round_trip(Request::Excite(Program::Table {
        ticks_per_entry: 5,
        repeat: false,
    }));
    round_trip(Request::Frames { decimation: 10 });
    for control in Control::ALL {
        round_trip(Request::Control(control));
    }
    let reason = "r".repeat(REASON_BYTES);
    round_trip(Uplink::Response {
        request: u32::MAX,
        response: Response::Refused(Refusal {
            kind: RefusalKind::Model,
            axis: Some(1),
            reason: heapless::String::try_from(reason.as_str()).unwrap(),
        }),
    });
    // NaN does not compare equal: check the status's bytes instead.
    let status = Uplink::Response {
        request: 7,
        response: Response::Status(full_status()),
    };
    let mut out = [0u8; MAX_FRAME];
    let n = encode(
        &Packet {
            sequence: 1,
            body: &status,
        },
        &mut out,
    )
    .unwrap();
    let back: Packet<Uplink> = decode(&mut out[..n - 1]).unwrap();
    match back.body {
        Uplink::Response {
            response: Response::Status(s),
            ..
        } => {
            assert_eq!(s.counters.ticks, u32::MAX);
            assert!(s.tracking[0].max_abs_m.is_nan());
        }
        other => panic!("{other:?}"),
    }
    round_trip(Uplink::Frame(Frame {
        sequence: 42,
        reference_m: [1e-6, 2e-6],
        commanded_v: [60.0, 0.5],
        sensor_m: [1.1e-6, -0.0],
        trial: u32::MAX,
        flags: Frame::OUTSIDE_X | Frame::OUTSIDE_Y,
    }));
    round_trip(Request::LearnedClear);
    round_trip(Request::LearnedAppend(
        (0..SETPOINT_CHUNK).map(|i| [i as f32, 120.0]).collect(),
    ));
    for control in Control::LEARNED {
        round_trip(Request::Control(control));
    }
}

#[test]
fn the_loop_state_keeps_its_bytes() {
    // A fault names its axis as the index 0 / 1, one byte, as before the loop's own types were
    // carried.
    let bytes = |m: &Mode| postcard::to_allocvec(m).unwrap();
    assert_eq!(bytes(&Mode::Running), [0]);
    assert_eq!(bytes(&Mode::Safe(Fault::Overrun)), [1, 0]);
    assert_eq!(bytes(&Mode::Safe(Fault::SensorError(Axis::Y))), [1, 1, 1]);
    assert_eq!(bytes(&Mode::Safe(Fault::DacError(Axis::X))), [1, 4, 0]);
}

#[test]
fn a_status_names_its_protocol_first() {
    let mut status = full_status();
    status.protocol = PROTOCOL_VERSION;
    let frame = |body: Uplink| {
        let mut out = [0u8; MAX_FRAME];
        let n = encode(&Packet { sequence: 9, body }, &mut out).unwrap();
        out[..n - 1].to_vec()
    };
    let ok = frame(Uplink::Response {
        request: 3,
        response: Response::Status(status.clone()),
    });
    assert_eq!(protocol_of_status(&ok), Some(PROTOCOL_VERSION));
    // Another version's status, whatever follows its version, is still read that far.
    status.protocol = 1;
    let mut other = frame(Uplink::Response {
        request: 3,
        response: Response::Status(status),
    });
    assert_eq!(protocol_of_status(&other), Some(1));
    other[5] ^= 0x40;
    assert_eq!(protocol_of_status(&other), None, "CRC");
    assert_eq!(
        protocol_of_status(&frame(Uplink::Frame(Frame::default()))),
        None
    );
    let done = frame(Uplink::Response {
        request: 3,
        response: Response::Done,
    });
    assert_eq!(protocol_of_status(&done), None);
}

#[test]
fn the_fingerprint_follows_the_content() {
    let set = model_set();
    let mut renamed = set.clone();
    renamed.version = heapless::String::try_from("other 9").unwrap();
    renamed.fnv1a32 ^= 0xffff;
    assert_eq!(renamed.fingerprint(), set.fingerprint());
    let mut moved = set.clone();
    moved.axes[1].static_map.k1_m_per_v *= 1.0 + f32::EPSILON;
    assert_ne!(moved.fingerprint(), set.fingerprint());
    let mut slower = set.clone();
    slower.axes[0].limits.slew_limit_v_per_s *= 0.5;
    assert_ne!(slower.fingerprint(), set.fingerprint());
    // FNV-1a 32 of the set's postcard bytes, (loop rate, io, axes).
    let bytes = postcard::to_allocvec(&(set.loop_rate_hz, &set.io, &set.axes)).unwrap();
    assert_eq!(set.fingerprint(), piezo_core::fnv1a32(&bytes));
    assert_eq!(piezo_core::fnv1a32(b"a"), 0xe40c_292c);
}

#[test]
fn effect_parameters_survive_the_wire() {
    let set = round_trip(model_set());
    assert_eq!(set.axes[0].effects, axis().effects);
}

#[test]
fn a_corrupted_frame_is_refused() {
    let packet = Packet {
        sequence: 3,
        body: Request::Upload(model_set()),
    };
    let mut out = [0u8; MAX_FRAME];
    let n = encode(&packet, &mut out).unwrap();
    for i in 0..n - 1 {
        for flip in [0x01u8, 0x80, 0xff] {
            let mut bad = out;
            bad[i] ^= flip;
            if bad[i] == 0 {
                continue; // a new delimiter: two short frames, each refused below
            }
            let r = decode::<Request>(&mut bad[..n - 1]);
            assert!(r.is_err(), "byte {i} ^ {flip:#x} accepted");
        }
    }
    // A byte lost.
    let mut short = [0u8; MAX_FRAME];
    short[..n - 2].copy_from_slice(&out[1..n - 1]);
    assert!(decode::<Request>(&mut short[..n - 2]).is_err());
    // A frame that is not a request.
    let n = encode(
        &Packet {
            sequence: 0,
            body: 200u8,
        },
        &mut out,
    )
    .unwrap();
    assert_eq!(decode::<Request>(&mut out[..n - 1]), Err(DecodeError::Body));
}

#[test]
fn the_decoder_resynchronises_after_garbage() {
    let mut decoder = Decoder::new();
    let mut results = std::vec::Vec::new();
    let mut feed = |bytes: &[u8], results: &mut std::vec::Vec<_>| {
        for &b in bytes {
            if let Some(r) = decoder.push::<Request>(b) {
                results.push(r);
            }
        }
    };
    feed(&[7u8; MAX_FRAME + 10], &mut results);
    feed(&[0], &mut results);
    let mut out = [0u8; MAX_FRAME];
    let n = encode(
        &Packet {
            sequence: 9,
            body: Request::Rearm,
        },
        &mut out,
    )
    .unwrap();
    feed(&out[..n], &mut results);
    assert_eq!(results.len(), 2);
    assert_eq!(results[0], Err(DecodeError::TooLong));
    assert_eq!(results[1].as_ref().unwrap().body, Request::Rearm);
}

#[test]
fn cobs_round_trips_every_length_and_zero_pattern() {
    for len in [0usize, 1, 2, 253, 254, 255, 508, 509, 600] {
        for pattern in 0..4u8 {
            let data: std::vec::Vec<u8> = (0..len)
                .map(|i| match pattern {
                    0 => 0,
                    1 => (i % 255 + 1) as u8,
                    2 => (i % 7) as u8,
                    _ => ((i * 31) % 256) as u8,
                })
                .collect();
            let mut out = std::vec![0u8; len + len / 254 + 2];
            let n = cobs::encode(&data, &mut out).unwrap();
            assert!(!out[..n].contains(&0));
            let back = cobs::decode_in_place(&mut out[..n]).unwrap();
            assert_eq!(&out[..back], &data[..], "len {len} pattern {pattern}");
        }
    }
    let mut tiny = [0u8; 2];
    assert_eq!(cobs::encode(&[1, 2, 3], &mut tiny), None);
}

#[test]
fn gaps_are_counted() {
    let mut rx = SequenceChecker::default();
    assert_eq!(rx.accept(10), 0);
    assert_eq!(rx.accept(11), 0);
    assert_eq!(rx.accept(15), 3);
    assert_eq!(rx.accept(16), 0);
    assert_eq!((rx.gaps, rx.lost), (1, 3));
    // Wrap without a gap, a restart without a gap.
    rx.accept(u32::MAX);
    assert_eq!(rx.accept(0), 0);
    assert_eq!(rx.accept(0), 0);
    assert_eq!(rx.gaps, 1);
    rx.expect(100);
    assert_eq!(rx.accept(100), 0);
    assert_eq!(rx.accept(102), 1);
    assert_eq!((rx.gaps, rx.lost), (2, 4));
}

#[test]
fn requests_already_handled_are_refused_with_the_next_number() {
    let mut rx = SequenceChecker::default();
    assert_eq!(rx.admit(7), Ok(0));
    assert_eq!(rx.admit(7), Err(8), "the same number again");
    assert_eq!(rx.admit(3), Err(8), "a number behind");
    assert_eq!(rx.admit(0), Err(8), "a host counting from 0 again");
    assert_eq!(rx.admit(8), Ok(0));
    assert_eq!(rx.admit(10), Ok(1));
    assert_eq!((rx.gaps, rx.lost), (1, 1));
    let mut rx = SequenceChecker::default();
    rx.admit(u32::MAX).unwrap();
    assert_eq!(rx.admit(0), Ok(0), "wraps");
    assert_eq!(rx.admit(u32::MAX), Err(1));
}

/// One encoded frame of `packet`, delimiter included.
fn frame_of<T: Serialize>(sequence: u32, body: T) -> std::vec::Vec<u8> {
    let mut out = [0u8; MAX_FRAME];
    let n = encode(&Packet { sequence, body }, &mut out).unwrap();
    out[..n].to_vec()
}

/// A frame whose CRC holds over `raw` (any bytes), delimiter included.
fn frame_with_crc(raw: &[u8]) -> std::vec::Vec<u8> {
    let mut data = raw.to_vec();
    data.extend_from_slice(&CRC.checksum(raw).to_le_bytes());
    let mut out = std::vec![0u8; data.len() + data.len() / 254 + 2];
    let n = cobs::encode(&data, &mut out).unwrap();
    out.truncate(n);
    out.push(0);
    out
}

fn feed(
    decoder: &mut Decoder,
    bytes: &[u8],
) -> std::vec::Vec<Result<Packet<Request>, DecodeError>> {
    bytes
        .iter()
        .filter_map(|&b| decoder.push::<Request>(b))
        .collect()
}

#[test]
fn bytes_after_the_body_are_refused() {
    let packet = Packet {
        sequence: 4,
        body: Request::Rearm,
    };
    let mut body = postcard::to_allocvec(&packet).unwrap();
    assert_eq!(
        feed(&mut Decoder::new(), &frame_with_crc(&body)),
        [Ok(packet.clone())]
    );
    body.push(0x17);
    assert_eq!(
        feed(&mut Decoder::new(), &frame_with_crc(&body)),
        [Err(DecodeError::Trailing)]
    );
}

#[test]
fn a_half_frame_left_in_the_decoder_ends_at_the_next_requests_delimiter() {
    let mut out = [0u8; MAX_FRAME + 1];
    let n = encode_request(
        &Packet {
            sequence: 1,
            body: Request::Status,
        },
        &mut out,
    )
    .unwrap();
    assert_eq!((out[0], out[n - 1]), (0, 0));
    let half = frame_of(0, Request::Upload(model_set()));
    let mut decoder = Decoder::new();
    let mut results = feed(&mut decoder, &half[..half.len() / 2]);
    results.extend(feed(&mut decoder, &out[..n]));
    assert_eq!(results.len(), 2, "{results:?}");
    assert!(results[0].is_err());
    assert_eq!(results[1].as_ref().unwrap().body, Request::Status);
}

#[test]
fn frames_at_the_length_limit() {
    // MAX_FRAME − 1 non-zero bytes plus the delimiter: collected whole (the CRC decides).
    let mut decoder = Decoder::new();
    let mut at_limit = std::vec![1u8; MAX_FRAME - 1];
    at_limit.push(0);
    assert_eq!(feed(&mut decoder, &at_limit), [Err(DecodeError::Crc)]);
    // One more byte: too long, reported once, and the decoder takes the next frame.
    let mut over = std::vec![1u8; MAX_FRAME + 1];
    over.push(0);
    assert_eq!(feed(&mut decoder, &over), [Err(DecodeError::TooLong)]);
    let good = frame_of(2, Request::Status);
    assert_eq!(feed(&mut decoder, &good)[0].as_ref().unwrap().sequence, 2);
    // The largest raw packet encode accepts fits the limit, and decodes.
    let raw = std::vec![0xeeu8; MAX_RAW - 4];
    let frame = frame_with_crc(&raw);
    assert_eq!(frame.len(), MAX_FRAME);
    assert_eq!(feed(&mut decoder, &frame), [Err(DecodeError::Body)]);
}

proptest! {
    /// Any byte stream: the decoder never panics, reports at most one result per delimiter, and
    /// a valid request sent after a delimiter still decodes.
    #[test]
    fn the_decoder_survives_any_byte_stream(
        bytes in prop::collection::vec(any::<u8>(), 0..2000),
    ) {
        let mut decoder = Decoder::new();
        let results = feed(&mut decoder, &bytes);
        let delimiters = bytes.iter().filter(|&&b| b == 0).count();
        prop_assert!(results.len() <= delimiters);
        let mut out = [0u8; MAX_FRAME + 1];
        let n = encode_request(&Packet { sequence: 9, body: Request::Rearm }, &mut out).unwrap();
        let after = feed(&mut decoder, &out[..n]);
        prop_assert_eq!(after.last().cloned(), Some(Ok(Packet { sequence: 9, body: Request::Rearm })));
    }

    /// Bodies with a correct CRC that are not a request (or have bytes after one) are refused,
    /// never accepted as something else and never a panic.
    #[test]
    fn correct_crc_bad_bodies_are_refused(
        raw in prop::collection::vec(any::<u8>(), 0..600),
    ) {
        let results = feed(&mut Decoder::new(), &frame_with_crc(&raw));
        prop_assert_eq!(results.len(), 1);
        match &results[0] {
            Ok(packet) => {
                // Then it is exactly a request's bytes: re-encoding gives them back.
                prop_assert_eq!(postcard::to_allocvec(packet).unwrap(), raw);
            }
            Err(e) => prop_assert!(matches!(e, DecodeError::Body | DecodeError::Trailing)),
        }
    }

    /// Broken COBS: a random non-zero run claims more than it holds, or holds a frame cut short.
    #[test]
    fn malformed_cobs_is_refused(
        sequence in any::<u32>(),
        cut in 1usize..30,
        code in 2u8..=255,
    ) {
        let frame = frame_of(sequence, Request::Frames { decimation: sequence });
        let body = &frame[..frame.len() - 1];
        let mut cut_short = body[..body.len().saturating_sub(cut).max(1)].to_vec();
        cut_short.push(0);
        let r = feed(&mut Decoder::new(), &cut_short);
        prop_assert!(r.iter().all(|r| r.is_err()), "{:?}", r);
        let mut overrun = std::vec![code];
        overrun.extend(std::iter::repeat_n(1u8, usize::from(code) - 2));
        overrun.push(0);
        let r = feed(&mut Decoder::new(), &overrun);
        prop_assert!(r.iter().all(|r| r.is_err()), "{:?}", r);
    }
}

#[test]
fn control_modes_map_to_the_cores_and_back() {
    let all: Vec<Control> = Control::ALL.into_iter().chain(Control::LEARNED).collect();
    for &c in &all {
        assert_eq!(Control::new(c.servo_mode(), c.learned()), c);
    }
    let names: Vec<&str> = all.iter().map(|c| c.name()).collect();
    assert_eq!(
        names,
        [
            "open-loop",
            "feedforward",
            "feedback",
            "feedforward+feedback",
            "learned",
            "learned+feedback"
        ]
    );
    assert_eq!(
        Control::LearnedFeedback.servo_mode(),
        piezo_core::ServoMode::FeedforwardFeedback
    );
}

/// `x` as postcard writes an f32: 4 bytes, little-endian.
fn f32_bytes(x: f32) -> [u8; 4] {
    x.to_le_bytes()
}

/// The bytes of the reference programs on the wire: the variant's index (one varint byte), then
/// the fields in order (f32: 4 bytes LE; u32, u16: varint; bool: 1 byte). Written out here from
/// postcard's format, not from the types: the programs of protocol 2 (per axis, table, streamed;
/// the four waves) keep their bytes now that the wire carries piezo-core's types, and the
/// raster and the limits are laid out as protocol 3 says.
#[test]
fn programs_and_limits_keep_their_wire_bytes() {
    let bytes = |v: &[&[u8]]| v.concat();
    let (o, a, f) = (f32_bytes(1.5e-5), f32_bytes(-2.0), f32_bytes(10.0));
    let waves = [
        (Wave::Constant { offset: 1.5e-5 }, bytes(&[&[0], &o])),
        (
            Wave::Sine {
                offset: 1.5e-5,
                amplitude: -2.0,
                frequency_hz: 10.0,
            },
            bytes(&[&[1], &o, &a, &f]),
        ),
        (
            Wave::Triangle {
                offset: 1.5e-5,
                amplitude: -2.0,
                frequency_hz: 10.0,
            },
            bytes(&[&[2], &o, &a, &f]),
        ),
        (
            Wave::Steps {
                offset: 1.5e-5,
                amplitude: -2.0,
                frequency_hz: 10.0,
            },
            bytes(&[&[3], &o, &a, &f]),
        ),
    ];
    for (wave, want) in &waves {
        assert_eq!(&postcard::to_allocvec(wave).unwrap(), want, "{wave:?}");
        let per_axis = Program::PerAxis([*wave, waves[0].0]);
        let want = bytes(&[&[0], want, &waves[0].1]);
        assert_eq!(
            postcard::to_allocvec(&per_axis).unwrap(),
            want,
            "{per_axis:?}"
        );
        // As a request: Track is variant 1, Excite 2.
        let track = postcard::to_allocvec(&Request::Track(per_axis)).unwrap();
        assert_eq!(track, bytes(&[&[1], &want]));
        let excite = postcard::to_allocvec(&Request::Excite(per_axis)).unwrap();
        assert_eq!(excite, bytes(&[&[2], &want]));
    }
    let table = Program::Table {
        ticks_per_entry: 300,
        repeat: true,
    };
    // 300 = 0b10_0101100: varint 0xAC 0x02.
    assert_eq!(postcard::to_allocvec(&table).unwrap(), [1, 0xAC, 0x02, 1]);
    assert_eq!(postcard::to_allocvec(&Program::Streamed).unwrap(), [2]);
    let raster = Program::Raster {
        x_min: 1.0,
        x_max: 2.0,
        y_min: 3.0,
        y_max: 4.0,
        lines: 200,
        line_rate_hz: 5.0,
    };
    let want = bytes(&[
        &[3],
        &f32_bytes(1.0),
        &f32_bytes(2.0),
        &f32_bytes(3.0),
        &f32_bytes(4.0),
        &[0xC8, 0x01],
        &f32_bytes(5.0),
    ]);
    assert_eq!(postcard::to_allocvec(&raster).unwrap(), want);
    for program in [table, Program::Streamed, raster] {
        assert_eq!(round_trip(Request::Track(program)), Request::Track(program));
    }
    for (policy, byte) in [(EnvelopePolicy::Warn, 0), (EnvelopePolicy::FeedbackOnly, 1)] {
        let limits = Limits {
            output_min_v: -10.0,
            output_max_v: 120.0,
            slew_limit_v_per_s: 1e5,
            envelope_policy: policy,
        };
        let want = bytes(&[
            &f32_bytes(-10.0),
            &f32_bytes(120.0),
            &f32_bytes(1e5),
            &[byte],
        ]);
        assert_eq!(postcard::to_allocvec(&limits).unwrap(), want);
        assert_eq!(postcard::from_bytes::<Limits>(&want).unwrap(), limits);
    }
}

/// An uploaded axis runs with its limits' envelope policy, and an axis taken from the core's
/// parameters carries the same limits: the policy travels in the limits.
#[test]
fn the_envelope_policy_travels_in_the_limits() {
    let mut a = axis();
    let p = a.params(1e-4).unwrap();
    assert_eq!(p.limits.envelope_policy, EnvelopePolicy::FeedbackOnly);
    assert_eq!(AxisModel::from_params(&p), a);
    a.limits.envelope_policy = EnvelopePolicy::Warn;
    let p = a.params(1e-4).unwrap();
    assert_eq!(p.limits, a.limits);
    assert_eq!(AxisModel::from_params(&p).limits, a.limits);
}

/// An axis's identified envelope on the wire, written out from postcard's format: `Some` (1),
/// the input range and the largest rate (f32 LE), then the axis's envelope policy (its limits',
/// one varint byte), then the on-target band; and the reference set's fingerprint, the FNV-1a
/// of all its bytes, as protocol 6 lays them out (its servo with the notch's pole frequency, its
/// effects with the relaxation's spread and the hysteresis's rate-dependent gain).
#[test]
fn an_axis_keeps_its_wire_bytes() {
    let on_target = [&f32_bytes(2.5e-8)[..], &[0xFF, 0xFF, 0xFF, 0xFF, 0x0F]].concat();
    for (policy, byte) in [(EnvelopePolicy::Warn, 0), (EnvelopePolicy::FeedbackOnly, 1)] {
        let mut a = axis();
        a.limits.envelope_policy = policy;
        let want = [
            &[1][..],
            &f32_bytes(0.5),
            &f32_bytes(119.5),
            &f32_bytes(f32::MAX),
            &[byte],
            &on_target,
        ]
        .concat();
        let got = postcard::to_allocvec(&a).unwrap();
        assert!(got.ends_with(&want), "{policy:?}: {got:?}");
        assert_eq!(postcard::from_bytes::<AxisModel>(&got).unwrap(), a);
    }
    assert_eq!(model_set().fingerprint(), 0x466c_9258);
}
