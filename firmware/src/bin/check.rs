//! Check and bench image for QEMU `mps2-an386` (Cortex-M4F), two jobs in one ELF:
//!
//! 1. **No panic reachable** (feature `panic-never`): its panic handler calls
//!    `loop_code_reached_a_panic_path`, a symbol defined nowhere, so the image only links if the
//!    optimiser removed every panic path from everything it contains: boot (building the compensators from the parameter consts), the
//!    two-axis loop [`piezo_firmware::xy_loop::TwoAxisLoop::tick`] on the simulated stage, and the
//!    per-axis compensator + guard steps for n = 1 and n = 1.5. No formatting, no printing.
//!    `firmware/ci.sh` builds it; when the link fails, `firmware/panic-sites.sh` lists the surviving
//!    panic sites (file:line) in the build without the feature, and ci.sh fails unless all of them
//!    are in the files named in `firmware/panic-sites.allowed` (known sites in `core/`;
//!    firmware code may have none).
//! 2. **Instruction counts** with `bench_mark_start`/`bench_mark_end` around known work, for
//!    `/work/shared/tools/qemu-insn-count/count.sh` (`firmware/bench.sh` divides):
//!    window 0: [`BENCH_STEPS`] two-axis steps of `Compensator::compensate` + `SafetyLimits::apply`
//!    with the file's parameters (n = 1); window 1: the same with n = 1.5 (general-n path);
//!    window 2: [`BENCH_TICKS`] full loop ticks (sensor, compensator, guard, DAC code, frame) with
//!    the simulated stage's DAC/ADC and its Euler step; window 3: [`BENCH_STEPS`] two-axis steps
//!    of the compensator + `Servo::step` (feedforward + feedback) + guard, n = 1; windows 4 and
//!    5: [`BENCH_TICKS`] whole control ticks *without* the simulated stage — the ADC replays
//!    readings recorded from the stage beforehand, the DAC keeps the codes — in feedforward and
//!    in feedforward + feedback; window 6: empty; windows 7 … 7 + [`WORST_TICKS`] − 1: one
//!    feedforward + feedback tick each, without the stage (the largest is the tick's worst case
//!    over a run that includes the start from rest).
//!
//! Exits through semihosting (status 0 when everything ran); HardFault and any unhandled
//! exception exit with failure.
#![cfg_attr(target_os = "none", no_std)]
#![cfg_attr(target_os = "none", no_main)]

#[cfg(target_os = "none")]
mod image {
    use core::cell::Cell;
    use core::hint::black_box;

    use cortex_m_rt::{entry, exception, ExceptionFrame};
    use cortex_m_semihosting::debug;

    use piezo_core::{Compensator, CompensatorState, Servo, ServoMode, ServoParams, ServoState};
    use piezo_firmware::codes::{AdcCode, DacCode};
    use piezo_firmware::converter::{AdcRead, DacWrite, ErrorType};
    use piezo_firmware::demo;
    use piezo_firmware::params::{AxisParams, AXES, SAMPLE_PERIOD_S};
    use piezo_firmware::plant::{plant_io, XyPlant};
    use piezo_firmware::reference::ReferenceGenerator;
    use piezo_firmware::safety::{GuardState, SafetyLimits};
    use piezo_firmware::xy_loop::{
        AdcSensor, Axis, AxisConfig, Feedforward, PositionSensor, TwoAxisLoop, XyIo,
    };

    /// Two-axis steps per compensator window.
    pub const BENCH_STEPS: u32 = 1_000;
    /// Loop ticks in the full-tick window.
    pub const BENCH_TICKS: u32 = 500;
    /// Exponent of the general-n window.
    pub const GENERAL_N: f32 = 1.5;
    /// Single-tick windows for the worst case.
    pub const WORST_TICKS: u32 = 1_000;
    /// Stage windows after the single-tick ones ([`stage_windows`]).
    pub const STAGE_WINDOWS: u32 = 10;

    /// The servo benched when the stage file has none (its cost does not depend on the values:
    /// low-pass, notch and PI are three biquads either way).
    const FALLBACK_SERVO: ServoParams = ServoParams {
        kp_v_per_m: 0.0,
        ki_v_per_m_s: 7.0e9,
        lowpass_frequency_hz: 3000.0,
        lowpass_q: core::f32::consts::FRAC_1_SQRT_2,
        notch_frequency_hz: 3000.0,
        notch_q: 1.0,
        notch_pole_frequency_hz: 0.0,
        transfer_time_constant_s: 0.02,
    };

    /// The file's axes, each with its servo or [`FALLBACK_SERVO`].
    fn with_servo(mut axes: [AxisParams; 2]) -> [AxisParams; 2] {
        for a in &mut axes {
            a.servo = a.servo.or(Some(FALLBACK_SERVO));
        }
        axes
    }

    struct Axes {
        compensator: [Compensator; 2],
        limits: [SafetyLimits; 2],
        servo: [Option<Servo>; 2],
    }

    fn axes(params: [AxisParams; 2]) -> Option<Axes> {
        let a = AxisConfig::from_params(&params[0], SAMPLE_PERIOD_S).ok()?;
        let b = AxisConfig::from_params(&params[1], SAMPLE_PERIOD_S).ok()?;
        Some(Axes {
            compensator: [*a.compensator(), *b.compensator()],
            limits: [*a.limits(), *b.limits()],
            servo: [a.servo().copied(), b.servo().copied()],
        })
    }

    /// Readings recorded from the simulated stage, replayed one per tick and axis.
    struct ReplayAdc {
        codes: [[AdcCode; 2]; RECORDED],
        next: usize,
    }

    /// Ticks recorded for [`ReplayAdc`].
    const RECORDED: usize = (BENCH_TICKS + WORST_TICKS) as usize + 8;

    impl ErrorType for ReplayAdc {
        type Error = core::convert::Infallible;
    }

    impl AdcRead for ReplayAdc {
        type Channel = Axis;
        #[inline]
        fn read_code(&mut self, channel: Axis) -> Result<AdcCode, Self::Error> {
            let row = self
                .codes
                .get(self.next)
                .copied()
                .unwrap_or([AdcCode(0); 2]);
            if channel == Axis::Y {
                self.next += 1;
            }
            Ok(row[channel.index()])
        }
    }

    /// A DAC that keeps the codes.
    struct KeptDac([DacCode; 2]);

    impl ErrorType for KeptDac {
        type Error = core::convert::Infallible;
    }

    impl DacWrite for KeptDac {
        type Channel = Axis;
        #[inline]
        fn write_code(&mut self, channel: Axis, code: DacCode) -> Result<(), Self::Error> {
            self.0[channel.index()] = code;
            Ok(())
        }
    }

    /// The reference of step k: 10 Hz sine-like triangle, 4–34 µm (cheap to compute, realistic
    /// increments of ≤ 0.06 µm per step).
    #[inline(always)]
    fn reference_m(k: u32) -> f32 {
        let phase = (k % 1_000) as f32 * 1e-3;
        let tri = if phase < 0.5 {
            4.0 * phase - 1.0
        } else {
            3.0 - 4.0 * phase
        };
        19e-6 + 15e-6 * tri
    }

    /// One axis-step: the compensator, then the guard on its voltage.
    #[inline(always)]
    fn axis_step(
        compensator: &Compensator,
        limits: &SafetyLimits,
        state: &mut CompensatorState,
        guard: &mut GuardState,
        reference: f32,
    ) -> f32 {
        let c = compensator.compensate(state, reference);
        limits.apply(guard, c.voltage_v)
    }

    #[inline(never)]
    fn compensator_window(axes: &Axes) -> f32 {
        let mut state = [
            CompensatorState::at_rest(55.0),
            CompensatorState::at_rest(55.0),
        ];
        let mut guard: [GuardState; 2] = [axes.limits[0].state(55.0), axes.limits[1].state(55.0)];
        // Settle onto the reference outside the window.
        for _ in 0..20 {
            for i in 0..2 {
                let c = axes.compensator[i].compensate(&mut state[i], reference_m(0));
                axes.limits[i].apply(&mut guard[i], c.voltage_v);
            }
        }
        // The references are computed before the window (they are not compensator work); the
        // window loads one per step. The two axes are written out: no axis-index arithmetic.
        let mut references = [0.0f32; BENCH_STEPS as usize];
        for (k, r) in references.iter_mut().enumerate() {
            *r = reference_m(k as u32);
        }
        let references = black_box(references);
        let [c0, c1] = &axes.compensator;
        let [l0, l1] = &axes.limits;
        let [s0, s1] = &mut state;
        let [g0, g1] = &mut guard;
        let mut sum = 0.0;
        bench_mark_start();
        for &r in references.iter() {
            sum += axis_step(c0, l0, s0, g0, r);
            sum += axis_step(c1, l1, s1, g1, r);
        }
        bench_mark_end();
        sum
    }

    /// Compensator + servo (feedforward + feedback) + guard, two axes per step.
    #[inline(never)]
    fn servo_window(axes: &Axes) -> Option<f32> {
        let servo = [axes.servo[0]?, axes.servo[1]?];
        let mut state = [CompensatorState::at_rest(55.0); 2];
        let mut guard: [GuardState; 2] = [axes.limits[0].state(55.0), axes.limits[1].state(55.0)];
        let mut servo_state = [ServoState::at_rest(55.0, ServoMode::FeedforwardFeedback); 2];
        let mut references = [0.0f32; BENCH_STEPS as usize];
        for (k, r) in references.iter_mut().enumerate() {
            *r = reference_m(k as u32);
        }
        let references = black_box(references);
        let [c0, c1] = &axes.compensator;
        let [l0, l1] = &axes.limits;
        let [s0, s1] = &mut state;
        let [g0, g1] = &mut guard;
        let [v0, v1] = &mut servo_state;
        let mut previous = references[0];
        let mut sum = 0.0;
        bench_mark_start();
        for &r in references.iter() {
            // The measurement: the previous reference plus a little error (no plant here).
            let measured = previous + 1e-9;
            let u0 = c0.compensate(s0, r).voltage_v;
            let u0 = servo[0].step(v0, previous, measured, u0).voltage_v;
            sum += l0.apply(g0, u0);
            let u1 = c1.compensate(s1, r).voltage_v;
            let u1 = servo[1].step(v1, previous, measured, u1).voltage_v;
            sum += l1.apply(g1, u1);
            previous = r;
        }
        bench_mark_end();
        Some(sum)
    }

    /// The loop settings of the file, each axis with its servo or [`FALLBACK_SERVO`].
    fn bench_settings() -> Option<piezo_firmware::xy_loop::LoopSettings> {
        piezo_firmware::xy_loop::LoopSettings::from_params(
            &with_servo(AXES),
            piezo_firmware::params::AMPLIFIER_GAIN_V_PER_V,
            SAMPLE_PERIOD_S,
        )
        .ok()
    }

    /// A loop on the demo program in `mode`, from rest at 0 V.
    fn bench_loop(
        settings: piezo_firmware::xy_loop::LoopSettings,
        mode: ServoMode,
    ) -> Option<TwoAxisLoop> {
        let reference = ReferenceGenerator::new(demo::program(), SAMPLE_PERIOD_S, [0.0; 2]);
        let mut lp = TwoAxisLoop::new(settings, Feedforward::Compensator, reference, [0.0; 2]);
        lp.set_control_mode(mode).ok().map(|_| lp)
    }

    /// The simulated stage's readings under the loop in `mode`, one row per tick.
    fn record(
        settings: piezo_firmware::xy_loop::LoopSettings,
        mode: ServoMode,
    ) -> Option<ReplayAdc> {
        let scale = demo::sensor_scale()?;
        let plant = Cell::new(XyPlant::from_params(SAMPLE_PERIOD_S)?);
        let mut io = plant_io(&plant, scale);
        let mut lp = bench_loop(settings, mode)?;
        let mut adc = ReplayAdc {
            codes: [[AdcCode(0); 2]; RECORDED],
            next: 0,
        };
        for row in adc.codes.iter_mut() {
            *row = [
                plant.get().sensor_code(Axis::X),
                plant.get().sensor_code(Axis::Y),
            ];
            lp.tick(&mut io, false);
            let mut p = plant.get();
            p.advance();
            plant.set(p);
            lp.frames.discard();
        }
        Some(adc)
    }

    /// Whole ticks without the stage in `mode`: the averaged window, then (with `worst`)
    /// single-tick windows.
    #[inline(never)]
    fn tick_windows(mode: ServoMode, worst: bool) -> Option<u32> {
        let settings = bench_settings()?;
        let scale = demo::sensor_scale()?;
        let adc = record(settings, mode)?;
        // Replay: the same loop from the start, the readings from the record.
        let mut lp = bench_loop(settings, mode)?;
        let mut io = XyIo {
            dac: KeptDac([DacCode(0); 2]),
            dac_channels: Axis::ALL,
            sensor: AdcSensor {
                adc,
                channels: Axis::ALL,
                scale,
            },
        };
        let mut batch = heapless::Vec::<_, 8>::new();
        if worst {
            for _ in 0..WORST_TICKS {
                bench_mark_start();
                let report = lp.tick(&mut io, black_box(false));
                bench_mark_end();
                black_box(report);
                lp.frames.drain_into(&mut batch);
            }
        } else {
            bench_mark_start();
            for _ in 0..BENCH_TICKS {
                let report = lp.tick(&mut io, black_box(false));
                black_box(report);
                lp.frames.drain_into(&mut batch);
            }
            bench_mark_end();
        }
        Some(lp.counters().faults())
    }

    /// Ticks of the stage windows.
    const STAGE_TICKS: usize = BENCH_TICKS as usize;

    /// Where a feedforward + feedback tick's time goes: its stages one after the other, each
    /// over [`STAGE_TICKS`] ticks in a window of its own, in the order of the tick, with the
    /// inputs of the same run (the readings recorded from the stage, the reference program, the
    /// targets, feed-forward voltages and outputs each stage before produced):
    /// 0 reference generator; 1 reference generator + inverse effect chain's targets (the same
    /// as 0 without effects); 2 both sensor reads (code → volts → metres); 3 both compensators;
    /// 4 both servos; 5 both models advanced by the applied voltage (what the tick does when the
    /// servo moved the output); 6 both guards; 7 both DAC codes written; 8 the effect chain's
    /// commit of both axes (with the model's output w; nothing without effects); 9 the frame.
    /// What the tick costs beyond their sum is its bookkeeping (fault checks, counters, copies).
    #[inline(never)]
    fn stage_windows() -> Option<()> {
        let settings = bench_settings()?;
        let scale = demo::sensor_scale()?;
        let adc = record(settings, ServoMode::FeedforwardFeedback)?;
        let [ax, ay] = settings.axes;
        let compensator = [*ax.compensator(), *ay.compensator()];
        let servo = [*ax.servo()?, *ay.servo()?];
        let limits = [*ax.limits(), *ay.limits()];
        let new_chain = || {
            piezo_firmware::inverse_chain::InverseChain::new(
                [*ax.effects(), *ay.effects()],
                [0.0; 2],
            )
        };
        let program = || ReferenceGenerator::new(demo::program(), SAMPLE_PERIOD_S, [0.0; 2]);
        let mut reference = [[0.0f32; 2]; STAGE_TICKS];
        let mut target = [[0.0f32; 2]; STAGE_TICKS];
        let mut measured = [[0.0f32; 2]; STAGE_TICKS];
        let mut feedforward = [[0.0f32; 2]; STAGE_TICKS];
        let mut requested = [[0.0f32; 2]; STAGE_TICKS];
        let mut applied = [[0.0f32; 2]; STAGE_TICKS];
        let mut w = [[0.0f32; 2]; STAGE_TICKS];

        // 0: the reference generator.
        let mut generator = program();
        bench_mark_start();
        for r in reference.iter_mut() {
            *r = generator.next_setpoint();
        }
        bench_mark_end();
        // 1: the generator and the chain's targets.
        let mut generator = program();
        let mut chain = new_chain();
        bench_mark_start();
        for (r, t) in reference.iter_mut().zip(target.iter_mut()) {
            (*r, *t) = match chain.as_mut() {
                Some(c) => c.next_targets(|| generator.next_setpoint()),
                None => {
                    let r = generator.next_setpoint();
                    (r, r)
                }
            };
        }
        bench_mark_end();
        // 2: the sensor reads.
        let mut sensor = AdcSensor {
            adc,
            channels: Axis::ALL,
            scale,
        };
        bench_mark_start();
        for m in measured.iter_mut() {
            *m = [
                sensor.read_m(Axis::X).unwrap_or(f32::NAN),
                sensor.read_m(Axis::Y).unwrap_or(f32::NAN),
            ];
        }
        bench_mark_end();
        // 3: the compensators (their states as the tick leaves them are rebuilt in 5).
        let mut state = [CompensatorState::at_rest(0.0); 2];
        let mut before = [[CompensatorState::at_rest(0.0); 2]; STAGE_TICKS];
        for k in 0..STAGE_TICKS {
            before[k] = state;
            for i in 0..2 {
                let mut s = state[i];
                feedforward[k][i] = compensator[i].compensate(&mut s, target[k][i]).voltage_v;
                // The tick's model follows the applied voltage, which the servo moves; here
                // the feed-forward's.
                state[i] = s;
            }
        }
        let mut state = [CompensatorState::at_rest(0.0); 2];
        let [c0, c1] = &compensator;
        bench_mark_start();
        for (t, u) in target.iter().zip(feedforward.iter_mut()) {
            u[0] = c0.compensate(&mut state[0], t[0]).voltage_v;
            u[1] = c1.compensate(&mut state[1], t[1]).voltage_v;
        }
        bench_mark_end();
        // 4: the servos.
        let mut servo_state = [ServoState::at_rest(0.0, ServoMode::FeedforwardFeedback); 2];
        let [v0, v1] = &servo;
        let mut previous = [f32::NAN; 2];
        bench_mark_start();
        for k in 0..STAGE_TICKS {
            let (m, u) = (measured[k], feedforward[k]);
            requested[k] = [
                v0.step(&mut servo_state[0], previous[0], m[0], u[0])
                    .voltage_v,
                v1.step(&mut servo_state[1], previous[1], m[1], u[1])
                    .voltage_v,
            ];
            previous = reference[k];
        }
        bench_mark_end();
        // 5: the models advanced by the requested voltage from the state before the tick
        // (`Compensator::advance`, as the tick); the states before each tick are those of a
        // model that followed the requested voltages.
        let mut state = [CompensatorState::at_rest(0.0); 2];
        for (b, u) in before.iter_mut().zip(requested.iter()) {
            *b = state;
            for i in 0..2 {
                compensator[i].model().step(&mut state[i].model, u[i]);
            }
        }
        let [m0, m1] = [c0.model(), c1.model()];
        bench_mark_start();
        for (b, u) in before.iter_mut().zip(requested.iter()) {
            c0.advance(&mut b[0], u[0]);
            c1.advance(&mut b[1], u[1]);
        }
        bench_mark_end();
        // 6: the guards.
        let mut guard = [limits[0].state(0.0), limits[1].state(0.0)];
        let [l0, l1] = &limits;
        bench_mark_start();
        for (u, a) in requested.iter().zip(applied.iter_mut()) {
            *a = [l0.apply(&mut guard[0], u[0]), l1.apply(&mut guard[1], u[1])];
        }
        bench_mark_end();
        // 7: the DAC codes.
        let mut dac = KeptDac([DacCode(0); 2]);
        let gain = settings.amplifier_gain_v_per_v;
        bench_mark_start();
        for a in applied.iter() {
            let _ = dac.write_code(Axis::X, DacCode::from_volts(a[0] / gain));
            let _ = dac.write_code(Axis::Y, DacCode::from_volts(a[1] / gain));
        }
        bench_mark_end();
        black_box(dac.0);
        // 8: the chain's commit, with the models' output.
        let mut chain = new_chain();
        bench_mark_start();
        if let Some(c) = chain.as_mut() {
            for k in 0..STAGE_TICKS {
                w[k] = [
                    m0.output(&before[k][0].model),
                    m1.output(&before[k][1].model),
                ];
                c.commit(0, applied[k][0], w[k][0]);
                c.commit(1, applied[k][1], w[k][1]);
            }
        }
        bench_mark_end();
        black_box(chain);
        // 9: the frame.
        let mut frames = piezo_firmware::frames::FrameQueue::new(1);
        let mut batch = heapless::Vec::<_, 8>::new();
        bench_mark_start();
        for k in 0..STAGE_TICKS {
            frames.offer(|| {
                [0, 1].map(|i| piezo_firmware::frames::AxisSample {
                    reference_m: reference[k][i],
                    commanded_v: applied[k][i],
                    sensor_m: measured[k][i],
                })
            });
            frames.drain_into(&mut batch);
            batch.clear();
        }
        bench_mark_end();
        black_box((&w, &batch, &guard, &servo_state));
        Some(())
    }

    #[inline(never)]
    fn loop_window() -> Option<u32> {
        let settings = demo::settings().ok()?;
        let plant = Cell::new(XyPlant::from_params(SAMPLE_PERIOD_S)?);
        let mut io = plant_io(&plant, demo::sensor_scale()?);
        let reference = ReferenceGenerator::new(demo::program(), SAMPLE_PERIOD_S, [0.0; 2]);
        let mut lp = TwoAxisLoop::new(settings, Feedforward::Compensator, reference, [0.0; 2]);
        let mut batch = heapless::Vec::<_, 8>::new();
        for _ in 0..200 {
            lp.tick(&mut io, false);
            let mut p = plant.get();
            p.advance();
            plant.set(p);
            lp.frames.drain_into(&mut batch);
        }
        bench_mark_start();
        for _ in 0..BENCH_TICKS {
            let report = lp.tick(&mut io, black_box(false));
            black_box(report);
            let mut p = plant.get();
            p.advance();
            plant.set(p);
            lp.frames.drain_into(&mut batch);
        }
        bench_mark_end();
        Some(lp.counters().faults())
    }

    #[entry]
    fn main() -> ! {
        let general = [
            AXES[0].with_exponent(GENERAL_N),
            AXES[1].with_exponent(GENERAL_N),
        ];
        let ok = match (axes(with_servo(AXES)), axes(general)) {
            (Some(n1), Some(nx)) => {
                black_box(compensator_window(&n1));
                black_box(compensator_window(&nx));
                matches!(loop_window(), Some(0))
                    && black_box(servo_window(&n1)).is_some()
                    && matches!(tick_windows(ServoMode::Feedforward, false), Some(0))
                    && matches!(tick_windows(ServoMode::FeedforwardFeedback, false), Some(0))
            }
            _ => false,
        };
        bench_mark_start();
        bench_mark_end();
        let ok = ok && matches!(tick_windows(ServoMode::FeedforwardFeedback, true), Some(0));
        let ok = ok && stage_windows().is_some();
        black_box(STAGE_WINDOWS);
        debug::exit(if ok {
            debug::EXIT_SUCCESS
        } else {
            debug::EXIT_FAILURE
        });
        #[allow(clippy::empty_loop)]
        loop {}
    }

    // The markers are found by name (`nm`), so they must keep their symbol and not be merged.
    #[allow(unsafe_code)] // `no_mangle` only; no unsafe operation.
    #[no_mangle]
    #[inline(never)]
    extern "C" fn bench_mark_start() {
        black_box(0x5741_5254_u32);
    }

    #[allow(unsafe_code)] // `no_mangle` only; no unsafe operation.
    #[no_mangle]
    #[inline(never)]
    extern "C" fn bench_mark_end() {
        black_box(0x0045_4e44_u32);
    }

    /// Without `panic-never` (the bench build): a panic exits QEMU with failure.
    #[cfg(not(feature = "panic-never"))]
    #[panic_handler]
    fn panic(_: &core::panic::PanicInfo<'_>) -> ! {
        debug::exit(debug::EXIT_FAILURE);
        #[allow(clippy::empty_loop)]
        loop {}
    }

    /// With `panic-never`: the link fails if this handler is reachable.
    #[cfg(feature = "panic-never")]
    #[panic_handler]
    fn panic(_: &core::panic::PanicInfo<'_>) -> ! {
        #[allow(unsafe_code)] // declares the link-time trap; never defined.
        extern "C" {
            /// Defined nowhere: referencing it makes the link fail if any panic path survives
            /// optimisation.
            fn loop_code_reached_a_panic_path() -> !;
        }
        // SAFETY: never runs; if this call survives optimisation the image does not link.
        #[allow(unsafe_code)]
        unsafe {
            loop_code_reached_a_panic_path()
        }
    }

    #[allow(unsafe_code)] // cortex-m-rt requires HardFault to be an `unsafe fn`.
    #[exception]
    unsafe fn HardFault(_frame: &ExceptionFrame) -> ! {
        debug::exit(debug::EXIT_FAILURE);
        #[allow(clippy::empty_loop)]
        loop {}
    }

    #[allow(unsafe_code)] // cortex-m-rt requires DefaultHandler to be an `unsafe fn`.
    #[exception]
    unsafe fn DefaultHandler(_irqn: i16) {
        debug::exit(debug::EXIT_FAILURE);
    }
}

#[cfg(not(target_os = "none"))]
fn main() {
    eprintln!("the check image runs on thumbv7em-none-eabihf: see firmware/ci.sh and bench.sh");
}
