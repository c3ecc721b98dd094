//! The output guard over the command link, on the firmware's simulated stage (`plant::XyPlant`):
//! a parameter set whose output window excludes the voltage applied, uploaded while the stage
//! rests or moves, is reached by slewing; guard-limited excitation (NaN, ±10³⁰, full-scale
//! steps) and the compensator at its own slew limit never step further than the stage file's
//! slew limit per tick.
//!
//! The bound is checked as an outside observer would: `|u_k − u_{k−1}|` in f64 from the f32
//! voltages applied, against `slew_limit_v_per_s · T` in f64, with T both the firmware's f32
//! period and `1/loop_rate_hz` exactly (the smaller of the two).

use std::cell::Cell;

use piezo_firmware::codes::SensorScale;
use piezo_firmware::demo;
use piezo_firmware::params::{self, AxisParams};
use piezo_firmware::plant::{PlantAdc, PlantDac, XyPlant};
use piezo_firmware::reference::ReferenceGenerator;
use piezo_firmware::session::Session;
use piezo_firmware::xy_loop::{AdcSensor, Axis, Feedforward, TickReport, TwoAxisLoop, XyIo};
use piezo_link::{
    AxisModel, Control, Decoder, Limits, Mode, ModelSet, Packet, Program, Request, Response,
    Setpoints, Uplink, Wave, MAX_FRAME,
};

/// `slew · T` in f64, the smaller of T = the firmware's f32 period and T = 1/rate.
fn bound_v(slew_v_per_s: f32) -> f64 {
    let slew = f64::from(slew_v_per_s);
    (slew * f64::from(params::SAMPLE_PERIOD_S)).min(slew / f64::from(params::LOOP_RATE_HZ))
}

/// How far `v` lies outside `window` \[V\] (0 inside).
fn distance(window: (f32, f32), v: f32) -> f64 {
    let v = f64::from(v);
    (f64::from(window.0) - v)
        .max(v - f64::from(window.1))
        .max(0.0)
}

/// The session on the simulated stage, driven through the link's bytes.
struct Bench {
    session: Session,
    plant: Cell<XyPlant>,
    sequence: u32,
    decoder: Decoder,
    /// The voltages applied in the last tick.
    applied_v: [f32; 2],
    /// The windows and slew limits in force.
    windows: [(f32, f32); 2],
    slew_v_per_s: [f32; 2],
    /// Largest step seen per axis \[V\].
    largest_step_v: [f64; 2],
}

impl Bench {
    /// At rest at the lower end of the windows, compensator on, reference 0 m.
    fn new() -> Self {
        let reference = ReferenceGenerator::new(
            Program::PerAxis([Wave::Constant { offset: 0.0 }; 2]),
            params::SAMPLE_PERIOD_S,
            [0.0; 2],
        );
        let initial = [
            params::AXES[0].limits.output_min_v,
            params::AXES[1].limits.output_min_v,
        ];
        let lp = TwoAxisLoop::new(
            demo::settings().unwrap(),
            Feedforward::Compensator,
            reference,
            initial,
        );
        Self {
            session: Session::new(
                lp,
                params::VERSION,
                params::FNV1A32,
                piezo_firmware::session::built_in_fingerprint(),
            ),
            plant: Cell::new(XyPlant::from_params(params::SAMPLE_PERIOD_S).unwrap()),
            sequence: 0,
            decoder: Decoder::new(),
            applied_v: initial,
            windows: params::AXES.map(|a| (a.limits.output_min_v, a.limits.output_max_v)),
            slew_v_per_s: params::AXES.map(|a| a.limits.slew_limit_v_per_s),
            largest_step_v: [0.0; 2],
        }
    }

    fn ask(&mut self, request: Request) -> Response {
        let mut out = [0u8; MAX_FRAME];
        let packet = Packet {
            sequence: self.sequence,
            body: request,
        };
        let n = piezo_link::encode(&packet, &mut out).unwrap();
        self.session.receive(&out[..n]);
        self.sequence += 1;
        let mut answer = None;
        for uplink in self.drain() {
            if let Uplink::Response { response, .. } = uplink {
                answer = Some(response);
            }
        }
        answer.expect("one response")
    }

    fn drain(&mut self) -> Vec<Uplink> {
        let mut bytes = Vec::new();
        self.session.transmit(|b| {
            bytes.push(b);
            true
        });
        bytes
            .into_iter()
            .filter_map(|b| self.decoder.push::<Uplink>(b))
            .map(|r| r.unwrap().body)
            .collect()
    }

    /// Uploads `set`; it must be accepted. Its windows and slew limits are in force from the
    /// next tick.
    fn upload(&mut self, set: ModelSet) {
        let windows = set
            .axes
            .each_ref()
            .map(|a| (a.limits.output_min_v, a.limits.output_max_v));
        let slew = set.axes.each_ref().map(|a| a.limits.slew_limit_v_per_s);
        assert!(matches!(
            self.ask(Request::Upload(set)),
            Response::Loaded { .. }
        ));
        self.windows = windows;
        self.slew_v_per_s = slew;
    }

    /// One tick on the stage; asserts the step bound and the window rule on both axes.
    fn tick(&mut self) -> TickReport {
        let mut io = XyIo {
            dac: PlantDac(&self.plant),
            dac_channels: Axis::ALL,
            sensor: AdcSensor {
                adc: PlantAdc(&self.plant),
                channels: Axis::ALL,
                scale: SensorScale::new(params::SENSOR_M_PER_V).unwrap(),
            },
        };
        let report = self.session.tick(&mut io, false);
        let mut p = self.plant.get();
        p.advance();
        self.plant.set(p);
        self.drain();
        for i in 0..2 {
            let (was, now) = (self.applied_v[i], report.applied_v[i]);
            let step = (f64::from(now) - f64::from(was)).abs();
            let bound = bound_v(self.slew_v_per_s[i]);
            assert!(now.is_finite(), "axis {i}: {now}");
            assert!(
                step <= bound,
                "axis {i}: {was} -> {now} V, step {step} > {bound}"
            );
            let w = self.windows[i];
            assert!(
                distance(w, now) <= distance(w, was),
                "axis {i}: {was} -> {now} V moved away from {w:?}"
            );
            if distance(w, was) == 0.0 {
                assert_eq!(
                    distance(w, now),
                    0.0,
                    "axis {i}: {was} -> {now} V left {w:?}"
                );
            }
            self.largest_step_v[i] = self.largest_step_v[i].max(step);
        }
        self.applied_v = report.applied_v;
        report
    }

    fn run(&mut self, ticks: u32) {
        for _ in 0..ticks {
            self.tick();
        }
    }

    fn guard_interventions(&self) -> u32 {
        self.session.status().counters.guard_interventions()
    }

    fn assert_running_without_faults(&self) {
        let st = self.session.status();
        assert_eq!(st.mode, Mode::Running, "{:?}", st.counters);
        assert_eq!(st.counters.stuck_readings, 0);
        assert_eq!(st.counters.safe_entries, 0);
    }
}

/// The built-in set as the link carries it, with other windows.
fn set_with_windows(windows: [(f32, f32); 2]) -> ModelSet {
    set_with_limits(windows, params::AXES.map(|a| a.limits.slew_limit_v_per_s))
}

/// The built-in set as the link carries it, with other windows and slew limits.
fn set_with_limits(windows: [(f32, f32); 2], slew_v_per_s: [f32; 2]) -> ModelSet {
    let axis = |p: &AxisParams, (min, max): (f32, f32), slew_limit_v_per_s: f32| AxisModel {
        limits: Limits {
            output_min_v: min,
            output_max_v: max,
            slew_limit_v_per_s,
            ..p.limits
        },
        ..AxisModel::from_params(p)
    };
    ModelSet {
        version: piezo_link::truncated("window swap"),
        fnv1a32: 0x5a5a_5a5a,
        loop_rate_hz: params::LOOP_RATE_HZ,
        io: params::IO,
        axes: [
            axis(&params::AXES[0], windows[0], slew_v_per_s[0]),
            axis(&params::AXES[1], windows[1], slew_v_per_s[1]),
        ],
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

/// x held at 0 V and y at 120 V by the compensator; a set with x in 100–120 V and y in 0–20 V:
/// both slew in at the limit (not 0 → 100 V and 120 → 20 V in one tick), every such tick is
/// counted in `guard_interventions`, and the stuck-reading detector does not trip.
#[test]
fn a_window_that_excludes_the_held_voltage_is_slewed_into() {
    let mut b = Bench::new();
    b.ask(Request::Track(Program::PerAxis([
        Wave::Constant { offset: 0.0 },
        Wave::Constant { offset: 50e-6 },
    ])));
    b.run(100);
    assert_eq!(b.applied_v, [0.0, 120.0]);
    let before = b.guard_interventions();
    assert_eq!(before, 0);
    b.upload(set_with_windows([(100.0, 120.0), (0.0, 20.0)]));
    let mut ticks_outside = [0u32; 2];
    for _ in 0..500 {
        let was = b.applied_v;
        b.tick();
        for i in 0..2 {
            if distance(b.windows[i], was[i]) > 0.0 {
                ticks_outside[i] += 1;
            }
        }
    }
    // 100 V at the guard's step (9.999998 V per tick at 10 kHz: 11 ticks begin outside the
    // window; 4.999999 V at 20 kHz: 21).
    let outside = (100.0 / bound_v(params::AXES[0].limits.slew_limit_v_per_s)).ceil() as u32;
    assert_eq!(ticks_outside, [outside; 2]);
    assert_eq!(b.applied_v, [100.0, 20.0]);
    let counted = b.guard_interventions() - before;
    assert!(counted >= 20, "{counted} guard interventions");
    b.assert_running_without_faults();
    // The window reached, the compensator holds its edge: no more guard interventions.
    let settled = b.guard_interventions();
    b.run(500);
    assert_eq!(b.guard_interventions(), settled);
}

/// Mid-motion (x sine, y triangle, 19 ± 15 µm at 10 Hz), at an instant when x lies below 50 V
/// and y above 50 V, a set with x in 60–120 V and y in 0–40 V, at the file's slew limit and at
/// 2 kV/s (0.2 V per tick: about 50 ticks of slewing in): in each control mode the output
/// slews into the new windows, no fault trips, and with the compensator and the servo the
/// guard stops acting once both axes are inside.
#[test]
fn a_window_uploaded_mid_motion_is_slewed_into_in_every_control_mode() {
    let modes = [
        Control::Feedforward,
        Control::FeedforwardFeedback,
        Control::Feedback,
        Control::OpenLoop,
    ];
    for (control, slew) in modes.iter().flat_map(|&c| [(c, 1e5f32), (c, 2e3)]) {
        let mut b = Bench::new();
        assert_eq!(b.ask(Request::Control(control)), Response::Done);
        b.ask(sine_track());
        b.run(1_000);
        let mut waited = 0;
        while !(b.applied_v[0] < 50.0 && b.applied_v[1] > 50.0) {
            b.tick();
            waited += 1;
            assert!(waited < 2_000, "{control:?}: {:?}", b.applied_v);
        }
        b.upload(set_with_limits([(60.0, 120.0), (0.0, 40.0)], [slew; 2]));
        let far = (0..2)
            .map(|i| distance(b.windows[i], b.applied_v[i]))
            .fold(0.0, f64::max);
        // Ticks at the slew limit to cover the distance (the last one may end exactly inside).
        let ticks_needed = (far / bound_v(slew)).ceil() as usize + 1;
        let mut inside_since = None;
        for k in 0..3_000 {
            b.tick();
            let inside = (0..2).all(|i| distance(b.windows[i], b.applied_v[i]) == 0.0);
            if inside && inside_since.is_none() {
                inside_since = Some((k, b.guard_interventions()));
            }
        }
        let (k, at_entry) = inside_since.expect("both axes inside their windows");
        assert!(
            k < ticks_needed,
            "{control:?} {slew}: entered after {k} ticks"
        );
        b.assert_running_without_faults();
        if control != Control::OpenLoop {
            // The linear baseline's requests leave the window (clamped, counted); the
            // compensator's and the servo's do not.
            assert_eq!(b.guard_interventions(), at_entry, "{control:?} {slew}");
        }
    }
}

/// Steps of 30 µm (≈ 90 V) at 100 Hz: the compensator (and the servo on top) move at their own
/// slew limit, each step within the stage file's, and the guard never acts.
#[test]
fn the_compensator_at_its_slew_limit_passes_the_guard_unchanged() {
    for control in [Control::Feedforward, Control::FeedforwardFeedback] {
        let mut b = Bench::new();
        assert_eq!(b.ask(Request::Control(control)), Response::Done);
        b.ask(Request::Track(Program::PerAxis(
            [Wave::Steps {
                offset: 19e-6,
                amplitude: 15e-6,
                frequency_hz: 100.0,
            }; 2],
        )));
        b.run(2_000);
        for i in 0..2 {
            let bound = bound_v(b.slew_v_per_s[i]);
            assert!(
                b.largest_step_v[i] > 0.999_99 * bound,
                "{control:?} axis {i}: largest step {} V",
                b.largest_step_v[i]
            );
        }
        assert_eq!(b.guard_interventions(), 0, "{control:?}");
        b.assert_running_without_faults();
    }
}

/// Excitation (open loop, volts) streamed with full-scale steps, NaN, ±∞ and ±10³⁰: the guard
/// limits every step, within the stage file's bound.
#[test]
fn guard_limited_excitation_stays_within_the_slew_bound() {
    let mut b = Bench::new();
    b.ask(Request::Excite(Program::Streamed));
    let values = [
        120.0,
        0.0,
        f32::NAN,
        1e30,
        -1e30,
        f32::INFINITY,
        60.0,
        f32::NEG_INFINITY,
        119.999_99,
        0.000_01,
    ];
    let mut k = 0usize;
    for _ in 0..40 {
        let chunk: Setpoints = (0..32)
            .map(|j| {
                let v = values[(k + j) / 3 % values.len()];
                [v, values[(k + j) / 7 % values.len()]]
            })
            .collect();
        k += 32;
        assert!(matches!(
            b.ask(Request::Stream(chunk)),
            Response::Queued { .. }
        ));
        b.run(32);
    }
    for i in 0..2 {
        // The limit is reached: these are slew-limited ramps.
        assert!(b.largest_step_v[i] > 0.999_99 * bound_v(b.slew_v_per_s[i]));
    }
    assert!(b.guard_interventions() > 0);
}
