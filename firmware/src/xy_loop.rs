//! The two-axis loop: per tick and per axis, reference → `piezo_core::Compensator` → safety guard
//! → DAC, with the sensor read every tick, fault detection, a latched safe state and sample
//! frames. No hardware in here: the converters come in through [`DacWrite`] and
//! [`PositionSensor`], the timer through the `deadline_missed` argument, so the same code runs on
//! the board, under QEMU and in host tests with mock converters.
//!
//! # One tick ([`TwoAxisLoop::tick`])
//!
//! ```text
//! 0. deadline_missed (the previous tick overran)        → fault Overrun
//! 1. per axis: x_meas = sensor.read_both_m()[axis]      Err → fault SensorError
//!                                                       non-finite → fault NonFiniteReading
//!                                                       frozen → fault StuckReading
//! 2. running: [r_x, r_y] = reference.next()
//!              (with effects: r = r[j], w* = inverse chain, see below)
//!    per axis: u_ff  = compensator.compensate(state, r)  (w* with effects; or the linear
//!                                                       baseline u_min + (r − y_rest)/g_lin)
//!              u_req = servo.step(r₋, x_meas, u_ff)     with feedback (see Feedback), else u_ff
//!              u     = guard.apply(u_req)               window, slew, non-finite → hold
//!                                                       (see Output guard)
//!    safe:     u     = last guarded output (hold); reference paused, compensator frozen
//! 3. per axis: DAC code = u / G_amp                     Err → fault DacError; axes not yet
//!                                                       written this tick get their hold value
//! 3b. with effects, per axis: commit(u, w)              u applied (or held), w the
//!                                                       compensator's model output
//! 4. frame {sequence, per axis: r, u, x_meas}           every `decimation`-th tick
//! ```
//!
//! # Feedback
//! With a servo in the parameter file (`[x.servo]`, [`AxisParams::servo`]), the loop runs one of
//! piezo-core's four control modes ([`ServoMode`], [`TwoAxisLoop::set_control_mode`]): open loop
//! (the linear baseline), feedforward (the compensator), feedback (`piezo_core::Servo` alone)
//! and feedforward + feedback. The servo compares the reference of the previous tick r₋ (the
//! voltage written in a tick shows in the next tick's reading) with this tick's reading
//! x_meas, error `e = r₋ − x_meas` \[m\], and adds its correction to the feed-forward
//! `u_ff`; its own window and slew limit are the compensator's, so the guard only acts on a
//! fault. Switching feedback on hands over from the voltage applied, and so does a change of the
//! feed-forward's source under feedback (compensator ↔ learned table: the table carries the
//! correction the servo held, so the servo's correction restarts from the last output instead of
//! being added to it); switching feedback off fades the
//! correction out with the servo's `transfer_time_constant_s` τ over [`HANDOVER_TIME_CONSTANTS`]·τ;
//! after a fault, an excitation, a new parameter set or a tick in which the guard overrode it
//! the servo restarts at rest at the applied voltage. Without feedback and outside a hand-over
//! the servo is not run: the tick is exactly the feed-forward one.
//!
//! # Envelope
//! With an identified envelope in the parameter set ([`AxisParams::envelope`]: the stage
//! file's `[x.identified]` input range and largest input rate, `piezo_core::envelope`), each
//! tracking tick (not an excitation) checks the voltage applied u\[k\] per axis:
//! `e_v = max(u_min − u, u − u_max) > 0` or `|u[k] − u[k−1]| − r_max·T > 0` is a tick outside,
//! counted with the largest excursions ([`TwoAxisLoop::envelope_counts`]) and flagged in the
//! tick's frame. Under the policy `feedback-only` with the compensator's feed-forward, an axis
//! outside is handed to its servo alone from the next tick (`ServoMode::Feedback`, handed over
//! from the voltage applied: the PI's output takes it, so no step) and back to the control
//! mode at the first tick inside again (handed over from the voltage applied; without feedback
//! the servo's correction fades out with τ over [`HANDOVER_TIME_CONSTANTS`]·τ, as when feedback
//! is switched off). A change of control mode, feed-forward or parameter set, and a rearm, end
//! the hand-over (the next tick outside starts it again).
//!
//! # On target
//! While tracking (not in the safe state, not during an excitation) each tick compares per axis
//! the reading y\[k\] with the reference it answers r\[k−1\] (`piezo_core::on_target`): the
//! axis is on target when |y − r| ≤ `tolerance_m` for `ticks` consecutive ticks
//! ([`AxisParams::on_target`]: the stage file's `[x.on_target]`, defaults 8 ADC steps and 1 ms).
//! Per axis one compare and a count since the reference changed; the run and the flag are
//! touched only while a run is going or the reading is inside (a state machine: a tick clearly
//! off target stores nothing else). The settling time of a move (ticks from the
//! reference's change to the start of the in-band run that set the flag) is recorded when the
//! flag rises ([`TwoAxisLoop::on_target`]). The frame's `flags` has bit 2 (x) or bit 3 (y) set in a
//! tick on target. Outside tracking the state is cleared (not on target; the next reference is
//! a move).
//!
//! # Learned table
//! [`Feedforward::Learned`] ([`TwoAxisLoop::set_learned_mode`]) plays a learned voltage table
//! (iterative learning control, computed on the host) with the wave table: per tick
//! `(r, u_ff) = reference.next_learned()`, entry j of both tables at the same tick, linear in
//! between (`crate::reference`); the compensator is not run (its model follows the applied
//! voltage, so a switch back to it is bumpless), no inverse effect chain (the table has the
//! effects in it). With feedback the servo adds its correction on `r₋ − x_meas` as it does to
//! the compensator's `u_ff`. The table is checked before it is played (length, window, slew at
//! the entry spacing, the wrap); the guard still stands after it.
//!
//! # Output guard
//! [`crate::safety`]: per axis, `|u_k − u_{k−1}| ≤ S_r · T` in exact arithmetic (S_r the axis's
//! [`piezo_core::Limits::slew_limit_v_per_s`], T the loop period; the bound is the f32 just
//! below, [`SafetyLimits::from_limits`]) and `u_k`
//! inside the window, whatever the request (NaN, ±∞, 10³⁰, any step). The compensator and the
//! servo run with a slew limit a hair inside ([`piezo_core::CompensatorSettings::inside_guard`]: their
//! largest step 9.99999 V instead of 10 V at 1e5 V/s and 10 kHz), so that their outputs, f32
//! rounding included, pass the guard unchanged: in normal tracking the guard never acts. A new
//! parameter set ([`TwoAxisLoop::set_settings`]) whose window excludes the voltage applied is
//! reached by slewing: the guard moves the output towards the window by at most the new
//! bound per tick (counted in the guard's `window_entry`, per axis in [`Counters::guard`]), the
//! compensator's model follows the voltage applied; a safe loop
//! holds its voltage (no jump) and slews in after the rearm. The bound in force in a tick is the
//! one of the settings of that tick (the new one from the first tick after a swap).
//!
//! # Effects
//! When the parameter file has effects (`[x.effects]`, `[y.effects]`: creep, even term, mode,
//! delay, drift, coupling; [`AxisConfig::effects`]) and the feed-forward is the compensator, the
//! loop runs the inverse of the effect chain around the compensator
//! (`piezo_core::inverse_chain::InverseChain`, re-exported as
//! [`crate::inverse_chain::InverseChain`]; both axes' effects states start at rest at the initial
//! voltages, `EffectsState::at_rest`, as the compensators do): the reference generator is sampled
//! `L = M + max ⌈D⌉` ticks ahead (L ticks of added latency for streamed setpoints and program
//! switches), the desired z of both axes is decoupled, and the compensator is given
//! `w* = Effects::inverse_target_w_window(…)` instead of r; after the DAC write each axis's effects state
//! is advanced with the voltage applied and the w the compensator's model reached (also while
//! safe). When both axes' effects are the identity, or with [`Feedforward::Linear`] (the
//! uncompensated baseline ignores them), the tick is exactly the one without effects.
//!
//! A fault latches the safe state *in the tick that detects it* (the DAC codes written in that
//! tick are already the hold values, except for axes whose new code was written before a later
//! axis's DAC write failed) and counts it ([`Counters`]); the loop stays safe until
//! [`TwoAxisLoop::rearm`]. The safe state holds each actuator at its last guarded voltage: no step
//! on the stage, the compensator's state stays consistent with the voltage actually applied.
//! Stuck detection: the reading bit-identical for [`StuckPolicy::ticks`] ticks while the
//! commanded voltage moved by at least [`StuckPolicy::min_motion_v`] since it froze.
//!
//! # Deadline
//! A tick must have written both DAC codes within one loop period `T = 1/loop_rate_hz` (100 µs at
//! 10 kHz) of the timer update that started it. The caller detects a miss and passes it to the
//! next tick as `deadline_missed`: on the board the TIM2 update flag is already set when the loop
//! comes back to wait for it; under QEMU and on the host the flag is injected. A missed deadline
//! trips the safe state in the tick that is told about it.
//!
//! Never panics (checked mechanically by the `check` image, see `firmware/ci.sh`), no allocation.

use piezo_core::effects::Effects;
use piezo_core::{
    CommandStatus, Compensator, CompensatorState, EnvelopeCounts, EnvelopeMonitor, EnvelopePolicy,
    OnTarget, OnTargetState, ParamError, Servo, ServoMode, ServoState, ServoStatus, ZeroReach,
};

use crate::codes::{DacCode, SensorScale};
use crate::converter::{AdcRead, DacWrite, Error, ErrorKind, ErrorType};
use crate::frames::{AxisSample, FrameQueue};
use crate::inverse_chain::InverseChain;
use crate::params::AxisParams;
use crate::reference::{LearnedError, LearnedLimits, Program, ReferenceGenerator};
use crate::safety::{GuardState, LimitsError, SafetyLimits};

/// The loop's state types are the link's: one definition, carried as they are.
pub use piezo_link::{Axis, Counters, Fault, Feedforward, GuardCounters, Mode};

/// Something that measures each axis's displacement in metres.
pub trait PositionSensor: ErrorType {
    /// The displacement of `axis` now \[m\].
    fn read_m(&mut self, axis: Axis) -> Result<f32, Self::Error>;

    /// Both displacements, x then y \[m\]: what the tick reads. By default `read_m(X)` then
    /// `read_m(Y)`; a sensor that reads both axes at once (the board's two ADCs on two buses,
    /// [`crate::concurrent_adc`]) overrides it.
    #[inline]
    fn read_both_m(&mut self) -> [Result<f32, Self::Error>; 2] {
        let x = self.read_m(Axis::X);
        [x, self.read_m(Axis::Y)]
    }
}

/// A [`PositionSensor`] made of an ADC (one channel per axis) and the sensor gain.
#[derive(Debug)]
pub struct AdcSensor<A: AdcRead> {
    /// The converter.
    pub adc: A,
    /// Its channel for x and for y.
    pub channels: [A::Channel; 2],
    /// Metres per volt at the ADC input.
    pub scale: SensorScale,
}

impl<A: AdcRead> ErrorType for AdcSensor<A> {
    type Error = A::Error;
}

impl<A: AdcRead> PositionSensor for AdcSensor<A> {
    #[inline]
    fn read_m(&mut self, axis: Axis) -> Result<f32, A::Error> {
        let code = self.adc.read_code(self.channels[axis.index()])?;
        Ok(self.scale.metres(code.to_volts()))
    }
}

/// A [`PositionSensor`] made of two single-channel ADCs of possibly different types (the board:
/// one ADS8681 per axis on separate buses).
#[derive(Debug)]
pub struct AdcPair<X: AdcRead<Channel = ()>, Y: AdcRead<Channel = ()>> {
    /// x-axis converter.
    pub x: X,
    /// y-axis converter.
    pub y: Y,
    /// Metres per volt at the ADC input (both axes).
    pub scale: SensorScale,
}

/// Error of an [`AdcPair`]: which converter failed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PairError<EX, EY> {
    /// The x converter.
    X(EX),
    /// The y converter.
    Y(EY),
}

impl<EX: Error, EY: Error> Error for PairError<EX, EY> {
    fn kind(&self) -> ErrorKind {
        match self {
            PairError::X(e) => e.kind(),
            PairError::Y(e) => e.kind(),
        }
    }
}

impl<X: AdcRead<Channel = ()>, Y: AdcRead<Channel = ()>> ErrorType for AdcPair<X, Y> {
    type Error = PairError<X::Error, Y::Error>;
}

impl<X: AdcRead<Channel = ()>, Y: AdcRead<Channel = ()>> PositionSensor for AdcPair<X, Y> {
    #[inline]
    fn read_m(&mut self, axis: Axis) -> Result<f32, Self::Error> {
        let code = match axis {
            Axis::X => self.x.read_code(()).map_err(PairError::X)?,
            Axis::Y => self.y.read_code(()).map_err(PairError::Y)?,
        };
        Ok(self.scale.metres(code.to_volts()))
    }
}

/// The converters the loop drives.
#[derive(Debug)]
pub struct XyIo<D: DacWrite, S: PositionSensor> {
    /// Drives both piezo amplifiers.
    pub dac: D,
    /// DAC channel of x and of y.
    pub dac_channels: [D::Channel; 2],
    /// Reads both displacements.
    pub sensor: S,
}

/// When a frozen sensor reading counts as stuck.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StuckPolicy {
    /// Consecutive ticks with a bit-identical reading.
    pub ticks: u32,
    /// Least change of the commanded voltage since the reading froze \[V\].
    pub min_motion_v: f32,
}

impl StuckPolicy {
    /// 10 ticks and 1 V: at ≈ 0.35 µm/V the stage moves ≥ 0.04 µm (≥ 13 sensor LSB) for 1 V even
    /// on the steepest unloading branch.
    pub const DEFAULT: StuckPolicy = StuckPolicy {
        ticks: 10,
        min_motion_v: 1.0,
    };
}

/// Settings of one axis.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AxisConfig {
    compensator: Compensator,
    servo: Option<Servo>,
    envelope: Option<EnvelopeMonitor>,
    on_target: OnTarget,
    effects: Effects,
    limits: SafetyLimits,
    linear_gain_m_per_v: f32,
    rest_output_m: f32,
}

/// Why an axis could not be configured.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ConfigError {
    /// The core refused the model or the compensator limits.
    Core(ParamError),
    /// The safety guard refused the limits.
    Limits(LimitsError),
    /// Amplifier gain or linear gain not finite and positive / nonzero.
    Gain,
}

impl AxisConfig {
    /// An axis from the parameter file, at loop period `sample_period_s` T: a guard with the
    /// window of the axis's [`piezo_core::Limits`] whose step never exceeds their slew limit
    /// times T ([`SafetyLimits::from_limits`]); the core's compensator, its effect chain and the servo with
    /// the same window and a slew limit a hair inside the guard's
    /// ([`piezo_core::CompensatorSettings::inside_guard`]: 10 V per tick become 9.99999 V at 1e5 V/s
    /// and 10 kHz), so that their own steps, f32 rounding included, pass the guard unchanged
    /// and the guard acts only on a fault. The core's checks come first: a file it refuses gets
    /// its reason.
    pub fn from_params(p: &AxisParams, sample_period_s: f32) -> Result<Self, ConfigError> {
        let model = p.model(sample_period_s).map_err(ConfigError::Core)?;
        let limits = SafetyLimits::from_limits(&p.limits, sample_period_s);
        let settings = match &limits {
            Ok(_) => p.settings(sample_period_s).inside_guard(),
            Err(_) => p.settings(sample_period_s),
        };
        let compensator = Compensator::new(model, settings).map_err(ConfigError::Core)?;
        let effects = p.effect_chain(sample_period_s).map_err(ConfigError::Core)?;
        let servo = p
            .servo
            .map(|params| Servo::new(params, settings, p.linear_gain_m_per_v))
            .transpose()
            .map_err(ConfigError::Core)?;
        let envelope = p
            .envelope_monitor(sample_period_s)
            .map_err(ConfigError::Core)?;
        let on_target = p.on_target.validated().map_err(ConfigError::Core)?;
        let limits = limits.map_err(ConfigError::Limits)?;
        if !(p.linear_gain_m_per_v.is_finite() && p.linear_gain_m_per_v != 0.0) {
            return Err(ConfigError::Gain);
        }
        Ok(Self {
            compensator,
            servo,
            envelope,
            on_target,
            effects,
            limits,
            linear_gain_m_per_v: p.linear_gain_m_per_v,
            rest_output_m: p.rest_output_m,
        })
    }

    /// The core's compensator.
    pub fn compensator(&self) -> &Compensator {
        &self.compensator
    }

    /// The feedback servo, if the parameter file has one.
    pub fn servo(&self) -> Option<&Servo> {
        self.servo.as_ref()
    }

    /// This axis without its servo (feed-forward only; an envelope policy `feedback-only`
    /// then only counts).
    pub fn without_servo(mut self) -> Self {
        self.servo = None;
        self
    }

    /// The identified envelope's check, if the parameter set has one.
    pub fn envelope(&self) -> Option<&EnvelopeMonitor> {
        self.envelope.as_ref()
    }

    /// The on-target band.
    pub fn on_target(&self) -> &OnTarget {
        &self.on_target
    }

    /// The guard's limits.
    pub fn limits(&self) -> &SafetyLimits {
        &self.limits
    }

    /// The guard's window and step bound, as the learned voltage table is checked against them.
    pub fn learned_limits(&self) -> LearnedLimits {
        LearnedLimits {
            window_v: [self.limits.min_volts(), self.limits.max_volts()],
            max_step_v: self.limits.max_step_volts(),
        }
    }

    /// The effect chain (the identity when the parameter file has none).
    pub fn effects(&self) -> &Effects {
        &self.effects
    }

    /// This axis with another effect chain (e.g. [`Effects`] identity: the loop ignores the
    /// stage's effects). `effects` must be validated for the same loop period.
    pub fn with_effects(mut self, effects: Effects) -> Self {
        self.effects = effects;
        self
    }
}

/// Settings of the loop.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LoopSettings {
    /// x, y.
    pub axes: [AxisConfig; 2],
    /// Actuator volts per DAC volt.
    pub amplifier_gain_v_per_v: f32,
    /// Stuck-sensor detection.
    pub stuck: StuckPolicy,
    /// Frame decimation (one frame every this many ticks).
    pub frame_decimation: u32,
    /// An axis has an identified envelope (the tick checks it): derived from `axes` by
    /// [`LoopSettings::new`], [`LoopSettings::from_params`], [`LoopSettings::with_axes`],
    /// [`TwoAxisLoop::new`] and [`TwoAxisLoop::set_settings`]; read with
    /// [`LoopSettings::any_envelope`].
    any_envelope: bool,
}

impl LoopSettings {
    /// Settings of these axes: the amplifier's gain (finite, > 0, else [`ConfigError::Gain`]),
    /// the stuck-sensor policy and the frame decimation.
    pub fn new(
        axes: [AxisConfig; 2],
        amplifier_gain_v_per_v: f32,
        stuck: StuckPolicy,
        frame_decimation: u32,
    ) -> Result<Self, ConfigError> {
        if !(amplifier_gain_v_per_v.is_finite() && amplifier_gain_v_per_v > 0.0) {
            return Err(ConfigError::Gain);
        }
        Ok(Self {
            axes,
            amplifier_gain_v_per_v,
            stuck,
            frame_decimation,
            any_envelope: false,
        }
        .with_axes_checked())
    }

    /// Whether an axis has an identified envelope (the tick checks it).
    pub fn any_envelope(&self) -> bool {
        self.any_envelope
    }

    /// Both axes of the parameter file at its loop rate, default stuck policy, one frame per tick.
    pub fn from_params(
        axes: &[AxisParams; 2],
        amplifier_gain_v_per_v: f32,
        sample_period_s: f32,
    ) -> Result<Self, ConfigError> {
        if !(amplifier_gain_v_per_v.is_finite() && amplifier_gain_v_per_v > 0.0) {
            return Err(ConfigError::Gain);
        }
        Ok(Self {
            axes: [
                AxisConfig::from_params(&axes[0], sample_period_s)?,
                AxisConfig::from_params(&axes[1], sample_period_s)?,
            ],
            amplifier_gain_v_per_v,
            stuck: StuckPolicy::DEFAULT,
            frame_decimation: 1,
            any_envelope: false,
        }
        .with_axes_checked())
    }

    /// These settings with `axes` (and [`LoopSettings::any_envelope`] from them).
    pub fn with_axes(self, axes: [AxisConfig; 2]) -> Self {
        Self { axes, ..self }.with_axes_checked()
    }

    fn with_axes_checked(mut self) -> Self {
        self.any_envelope = self.axes.iter().any(|a| a.envelope.is_some());
        self
    }
}

#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct StuckDetector {
    last_bits: u32,
    same_ticks: u32,
    volts_at_freeze: f32,
    reported: bool,
}

impl StuckDetector {
    /// True (once per freeze) when the reading has been frozen long enough while the command
    /// moved.
    #[inline]
    fn observe(&mut self, reading_m: f32, commanded_v: f32, policy: &StuckPolicy) -> bool {
        let bits = reading_m.to_bits();
        if bits == self.last_bits {
            self.same_ticks = self.same_ticks.saturating_add(1);
        } else {
            *self = Self {
                last_bits: bits,
                same_ticks: 0,
                volts_at_freeze: commanded_v,
                reported: false,
            };
        }
        let stuck = self.same_ticks >= policy.ticks
            && (commanded_v - self.volts_at_freeze).abs() >= policy.min_motion_v;
        let first = stuck && !self.reported;
        self.reported |= stuck;
        first
    }
}

/// One axis's identified-envelope state in the loop.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct EnvelopeAxis {
    /// Ticks outside and the largest excursions.
    counts: EnvelopeCounts,
    /// The last tick's command was outside.
    outside: bool,
    /// The policy `feedback-only` has handed the axis to its servo alone.
    servo_alone: bool,
    /// Ticks the servo alone drove the axis.
    servo_alone_ticks: u32,
    /// Ticks left of the servo's fade-out after the feed-forward resumed (no feedback).
    handback_ticks: u32,
}

/// A servo the guard overrode restarts at rest at the voltage applied, its filters and
/// integrator consistent with the stage again (out of line: the guard overrides only on a fault
/// or while slewing into a new window).
#[cold]
#[inline(never)]
fn restart_at(servo: &mut ServoState, applied_v: f32) {
    *servo = ServoState::at_rest(applied_v, servo.mode());
}

/// Time constants of the servo's fade-out after feedback is switched off, after which the servo
/// stops running (the correction is down to e⁻¹⁰ ≈ 4.5·10⁻⁵ of what it was).
pub const HANDOVER_TIME_CONSTANTS: f32 = 10.0;

/// Why a control mode was refused.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ControlError {
    /// The mode needs feedback and this axis has no servo in the parameter set.
    NoServo(Axis),
    /// A learned mode, but the loop does not track a table program.
    NotTable,
    /// A learned mode, but the learned voltage table fails its check.
    Learned(LearnedError),
}

/// What one tick did.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TickReport {
    /// Setpoints used (the last ones while safe) \[m\].
    pub reference_m: [f32; 2],
    /// Sensor readings at the start of the tick \[m\] (NaN where the read failed).
    pub measured_m: [f32; 2],
    /// Voltages written (or attempted) \[V\].
    pub applied_v: [f32; 2],
    /// Mode at the end of the tick.
    pub mode: Mode,
}

/// Which copy of [`TwoAxisLoop::tick`]'s body runs: one load per tick instead of testing the
/// chain and the feed-forward.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Body {
    /// Neither an effect chain nor the learned table.
    Plain,
    /// With the inverse effect chain.
    Effects,
    /// The learned voltage table.
    Learned,
}

impl Body {
    /// The body for this chain and feed-forward: the chain's copy when there is a chain, the
    /// learned table's for [`Feedforward::Learned`], the plain one otherwise.
    fn of(chain: &Option<InverseChain>, feedforward: Feedforward) -> Self {
        if chain.is_some() {
            Body::Effects
        } else if feedforward == Feedforward::Learned {
            Body::Learned
        } else {
            Body::Plain
        }
    }
}

/// The loop: settings, per-axis compensator and guard state, reference, faults, frames.
pub struct TwoAxisLoop {
    settings: LoopSettings,
    feedforward: Feedforward,
    /// Feedback on (the servo's correction added to the feed-forward).
    feedback: bool,
    /// Ticks left of the fade-out after feedback was switched off.
    handover_ticks: u32,
    /// Per axis, the identified envelope's check (see the module docs, Envelope).
    envelope: [EnvelopeAxis; 2],
    /// An axis is handed to its servo alone or fading back (the per-axis servo path runs).
    envelope_handed: bool,
    /// Per axis, on target and settling (see the module docs, On target).
    on_target: [OnTargetState; 2],
    servo: [ServoState; 2],
    compensator: [CompensatorState; 2],
    /// Per axis, the compensator's last step across h = 0 (its Δu₀, for the model's advance).
    zero_reach: [ZeroReach; 2],
    guard: [GuardState; 2],
    stuck: [StuckDetector; 2],
    mode: Mode,
    counters: Counters,
    last_reference_m: [f32; 2],
    /// The inverse effect chain (`None`: no effects, or the linear baseline).
    chain: Option<InverseChain>,
    /// The copy of the tick's body that runs, from `chain` and `feedforward` (`set_body` after
    /// every change of either).
    body: Body,
    /// The reference generator (public: push streamed setpoints, switch programs; with effects
    /// they take effect [`TwoAxisLoop::lead_ticks`] ticks later).
    pub reference: ReferenceGenerator,
    /// Outgoing sample frames (public: the sender drains them).
    pub frames: FrameQueue,
}

impl TwoAxisLoop {
    /// A running loop whose actuators are at `initial_v` (the voltages the DACs hold now): the
    /// compensators and the effect chain start at rest there (the stage's rest voltage, the lower
    /// end of the window, for a stage that was left unpowered).
    pub fn new(
        settings: LoopSettings,
        feedforward: Feedforward,
        reference: ReferenceGenerator,
        initial_v: [f32; 2],
    ) -> Self {
        let settings = settings.with_axes_checked();
        let guard = [
            settings.axes[0].limits.state(initial_v[0]),
            settings.axes[1].limits.state(initial_v[1]),
        ];
        let chain = match feedforward {
            Feedforward::Compensator => InverseChain::new(
                [settings.axes[0].effects, settings.axes[1].effects],
                [guard[0].last_safe_volts(), guard[1].last_safe_volts()],
            ),
            Feedforward::Linear | Feedforward::OpenLoop | Feedforward::Learned => None,
        };
        let mode = if feedforward == Feedforward::Linear {
            ServoMode::OpenLoop
        } else {
            ServoMode::Feedforward
        };
        Self {
            compensator: [
                CompensatorState::at_rest(guard[0].last_safe_volts()),
                CompensatorState::at_rest(guard[1].last_safe_volts()),
            ],
            zero_reach: [ZeroReach::NONE; 2],
            feedback: false,
            handover_ticks: 0,
            envelope: [EnvelopeAxis::default(); 2],
            envelope_handed: false,
            on_target: [OnTargetState::default(); 2],
            servo: [
                ServoState::at_rest(guard[0].last_safe_volts(), mode),
                ServoState::at_rest(guard[1].last_safe_volts(), mode),
            ],
            body: Body::of(&chain, feedforward),
            chain,
            guard,
            stuck: [StuckDetector::default(); 2],
            mode: Mode::Running,
            counters: Counters::default(),
            last_reference_m: [f32::NAN; 2],
            frames: FrameQueue::new(settings.frame_decimation),
            reference,
            feedforward,
            settings,
        }
    }

    /// Running or safe.
    pub fn mode(&self) -> Mode {
        self.mode
    }

    /// The reference of the last tick (volts in open loop, metres otherwise; NaN before the
    /// first tick).
    pub fn last_reference(&self) -> [f32; 2] {
        self.last_reference_m
    }

    /// Event counters: the loop's own, the output guards' per axis and cause, the reference's
    /// underruns, the envelope's excursions (both axes) and the frame queue's drops; the link's
    /// are zero.
    pub fn counters(&self) -> Counters {
        Counters {
            guard: self.guard.map(|g| g.counters()),
            stream_underruns: self.reference.underruns(),
            envelope_excursions: Axis::ALL
                .map(|a| self.envelope_counts(a).ticks_outside)
                .into_iter()
                .fold(0, u32::saturating_add),
            frames_dropped: self.frames.dropped(),
            ..self.counters
        }
    }

    /// An axis's guard state (last output and the guard's fault counters).
    pub fn guard(&self, axis: Axis) -> &GuardState {
        &self.guard[axis.index()]
    }

    /// T: the loop's period \[s\] (the parameter set's).
    pub fn sample_period_s(&self) -> f32 {
        self.settings.axes[0].compensator.settings().sample_period_s
    }

    /// The settings.
    pub fn settings(&self) -> &LoopSettings {
        &self.settings
    }

    /// The inverse effect chain, if the loop runs one.
    pub fn inverse_chain(&self) -> Option<&InverseChain> {
        self.chain.as_ref()
    }

    /// Ticks the reference generator runs ahead of the tick's reference (0 without effects): the
    /// latency added to streamed setpoints and program switches.
    pub fn lead_ticks(&self) -> u32 {
        self.chain.as_ref().map_or(0, InverseChain::lead_ticks)
    }

    /// The feed-forward in use.
    pub fn feedforward(&self) -> Feedforward {
        self.feedforward
    }

    /// Switches the feed-forward between two ticks. Bumpless: the compensator's model has been
    /// advanced with the applied voltages all along; switching to the compensator starts the
    /// inverse effect chain at rest at the applied voltages (the effects' memory of the time
    /// before is not kept).
    pub fn set_feedforward(&mut self, feedforward: Feedforward) {
        if feedforward == self.feedforward {
            return;
        }
        let from_excitation = self.feedforward == Feedforward::OpenLoop;
        self.feedforward = feedforward;
        self.chain = self.chain_at_applied();
        self.set_body();
        if from_excitation {
            self.restart_servo();
        } else {
            let mode = self.control_mode();
            self.servo.iter_mut().for_each(|s| s.set_mode(mode));
            self.hand_over_if(true);
            self.release_servo_alone();
        }
    }

    /// The control mode of [`Feedforward::Compensator`]/[`Feedforward::Linear`] with feedback on
    /// or off (feedback alone runs the linear feed-forward, which the servo ignores, so that the
    /// compensator's model only follows the applied voltage). During an excitation, the mode the
    /// loop returns to. [`Feedforward::Learned`] runs the servo as the compensator's feed-forward
    /// does: feedforward, or feedforward + feedback with feedback on.
    pub fn control_mode(&self) -> ServoMode {
        match (self.feedforward, self.feedback) {
            (Feedforward::Linear, false) => ServoMode::OpenLoop,
            (_, false) => ServoMode::Feedforward,
            (Feedforward::Linear, true) => ServoMode::Feedback,
            (_, true) => ServoMode::FeedforwardFeedback,
        }
    }

    /// `Ok` unless `feedback` is asked for and an axis has no servo.
    fn servos_for(&self, feedback: bool) -> Result<(), ControlError> {
        if feedback {
            for axis in Axis::ALL {
                if self.settings.axes[axis.index()].servo.is_none() {
                    return Err(ControlError::NoServo(axis));
                }
            }
        }
        Ok(())
    }

    /// The servos after a mode change from `was_feedback` to `self.feedback` in `mode`: started
    /// from the voltage applied when feedback comes on, faded out when it goes off.
    fn switch_servo(&mut self, was_feedback: bool, mode: ServoMode) {
        if self.feedback && !was_feedback {
            self.restart_servo();
        } else {
            self.servo.iter_mut().for_each(|s| s.set_mode(mode));
            if was_feedback && !self.feedback {
                self.handover_ticks = self.handover_length();
            }
        }
    }

    /// Switches the control mode between two ticks, bumplessly (see the module docs, Feedback).
    /// A mode with feedback needs a servo on both axes; refused, nothing changes. During an
    /// excitation only the mode to return to changes.
    pub fn set_control_mode(&mut self, mode: ServoMode) -> Result<(), ControlError> {
        self.servos_for(mode.feedback())?;
        let was_feedback = self.feedback;
        self.feedback = mode.feedback();
        let mut source_changed = false;
        if self.feedforward != Feedforward::OpenLoop {
            let feedforward = if matches!(
                mode,
                ServoMode::Feedforward | ServoMode::FeedforwardFeedback
            ) {
                Feedforward::Compensator
            } else {
                Feedforward::Linear
            };
            if feedforward != self.feedforward {
                self.feedforward = feedforward;
                self.chain = self.chain_at_applied();
                self.set_body();
                source_changed = true;
            }
        }
        self.switch_servo(was_feedback, mode);
        self.hand_over_if(source_changed && was_feedback);
        self.release_servo_alone();
        Ok(())
    }

    /// With feedback on before and after a change of the feedforward's source, the servo hands
    /// over from the last output (its correction belonged to the old feedforward: a learned
    /// table carries what the servo held for the compensator, and back).
    fn hand_over_if(&mut self, source_changed_under_feedback: bool) {
        if source_changed_under_feedback && self.feedback {
            self.servo.iter_mut().for_each(ServoState::hand_over);
        }
    }

    /// Each axis's window and guard step bound, as the learned voltage table is checked against
    /// them ([`ReferenceGenerator::check_learned`]).
    pub fn learned_limits(&self) -> [LearnedLimits; 2] {
        self.settings.axes.map(|a| a.learned_limits())
    }

    /// Switches to the learned voltage table ([`Feedforward::Learned`]), with the servo's
    /// correction added when `feedback`, between two ticks, from the wave table's current
    /// position (the same phase: entry j with reference entry j). Refused, nothing changed,
    /// unless the loop tracks a table program ([`Program::Table`], not an excitation), the
    /// learned table passes [`ReferenceGenerator::check_learned`] for that program and this
    /// set's limits, and, with `feedback`, both axes have a servo. A switch from the
    /// compensator hands over from the voltage applied: the guard slews to the table's voltage
    /// should they differ by more than a step.
    pub fn set_learned_mode(&mut self, feedback: bool) -> Result<(), ControlError> {
        self.servos_for(feedback)?;
        let Program::Table {
            ticks_per_entry,
            repeat,
        } = self.reference.program()
        else {
            return Err(ControlError::NotTable);
        };
        if self.feedforward == Feedforward::OpenLoop {
            return Err(ControlError::NotTable);
        }
        self.reference
            .check_learned(ticks_per_entry, repeat, &self.learned_limits())
            .map_err(ControlError::Learned)?;
        let was_feedback = self.feedback;
        self.feedback = feedback;
        let source_changed = self.feedforward != Feedforward::Learned;
        if source_changed {
            self.feedforward = Feedforward::Learned;
            self.chain = None;
            self.set_body();
        }
        let mode = self.control_mode();
        self.switch_servo(was_feedback, mode);
        self.hand_over_if(source_changed && was_feedback);
        self.release_servo_alone();
        Ok(())
    }

    /// Ticks of the fade-out: [`HANDOVER_TIME_CONSTANTS`] of the slower axis's τ.
    fn handover_length(&self) -> u32 {
        let ticks = |a: &AxisConfig| {
            a.servo.map_or(0.0, |s| {
                HANDOVER_TIME_CONSTANTS * s.params().transfer_time_constant_s / s.sample_period_s()
            })
        };
        let [x, y] = &self.settings.axes;
        libm::ceilf(ticks(x).max(ticks(y))).clamp(0.0, u32::MAX as f32) as u32
    }

    /// The servo of each axis at rest at its applied voltage in the current mode (no fade-out).
    fn restart_servo(&mut self) {
        let mode = self.control_mode();
        for (servo, guard) in self.servo.iter_mut().zip(&self.guard) {
            *servo = ServoState::at_rest(guard.last_safe_volts(), mode);
        }
        self.handover_ticks = 0;
        for e in &mut self.envelope {
            e.servo_alone = false;
            e.handback_ticks = 0;
        }
        self.envelope_handed = false;
    }

    /// After the servos were set to the control mode (their next tick hands over from the last
    /// output), an axis the envelope policy had handed to its servo alone goes back to the
    /// mode: the servo keeps running until its correction has faded out when the mode has no
    /// feedback ([`HANDOVER_TIME_CONSTANTS`]·τ), and is handed over again at the next tick
    /// still outside.
    fn release_servo_alone(&mut self) {
        let fade = if self.feedback {
            0
        } else {
            self.handover_length()
        };
        for e in &mut self.envelope {
            if e.servo_alone {
                e.servo_alone = false;
                e.handback_ticks = fade;
            }
        }
        self.envelope_handed = self.envelope.iter().any(|e| e.handback_ticks > 0);
    }

    /// Axis `i` of a tick whose command `u` was (`outside`) or was not outside its envelope,
    /// under the policy `feedback-only` with the compensator: outside, the servo alone drives
    /// from the next tick (handed over from `u`: the PI's output takes the whole voltage);
    /// inside again, the control mode's feed-forward resumes (handed over from `u`; without
    /// feedback the servo's correction then fades out).
    #[cold]
    #[inline(never)]
    fn envelope_switch(&mut self, i: usize, outside: bool, servo_ran: bool, u: f32) {
        let i = i & 1;
        self.envelope_handed = true;
        if outside {
            self.envelope[i].servo_alone = true;
            self.envelope[i].handback_ticks = 0;
            if servo_ran {
                self.servo[i].set_mode(ServoMode::Feedback);
            } else {
                self.servo[i] = ServoState::at_rest(u, ServoMode::Feedback);
            }
        } else {
            self.envelope[i].servo_alone = false;
            self.servo[i].set_mode(self.control_mode());
            if !self.feedback {
                self.envelope[i].handback_ticks = self.handover_length();
            }
        }
    }

    /// Step 2's envelope check of a running tick (module docs, Envelope): per axis with an
    /// envelope, the voltage applied `applied_v` after `previous_v` counted, and the policy's
    /// hand-over; returns which axes were outside. Out of line: the tick without envelopes
    /// does not carry it.
    #[inline(never)]
    fn envelope_tick(
        &mut self,
        applied_v: [f32; 2],
        previous_v: [f32; 2],
        servo_ran: [bool; 2],
    ) -> [bool; 2] {
        let mut outside = [false; 2];
        // Counted while tracking (an excitation measures one).
        if self.mode != Mode::Running || self.feedforward == Feedforward::OpenLoop {
            self.envelope[0].outside = false;
            self.envelope[1].outside = false;
            return outside;
        }
        for i in 0..2 {
            let axis = &self.settings.axes[i];
            let Some(envelope) = axis.envelope.as_ref() else {
                continue;
            };
            let e = &mut self.envelope[i];
            outside[i] = envelope.observe(&mut e.counts, applied_v[i], previous_v[i]);
            if e.servo_alone {
                e.servo_alone_ticks = e.servo_alone_ticks.saturating_add(1);
            }
            if outside[i] != e.servo_alone
                && envelope.policy() == EnvelopePolicy::FeedbackOnly
                && self.feedforward == Feedforward::Compensator
                && axis.servo.is_some()
            {
                self.envelope_switch(i, outside[i], servo_ran[i], applied_v[i]);
            }
        }
        self.envelope[0].outside = outside[0];
        self.envelope[1].outside = outside[1];
        outside
    }

    /// Per axis, whether its servo runs this tick while the envelope policy has handed an axis
    /// over: the control mode's servo (`servo_runs`), or the policy's (servo alone, or the
    /// fade-out after it), when a servo may run at all (`servo_may_run`).
    #[inline(never)]
    fn envelope_servo_runs(&self, servo_may_run: bool, servo_runs: bool) -> [bool; 2] {
        self.envelope
            .map(|e| servo_may_run && (servo_runs || e.servo_alone || e.handback_ticks > 0))
    }

    /// Step 3a: a servo that ran (`ran`) but whose output was not applied (the guard overrode
    /// it: a fault, or the slew into a new window) restarts at rest at what was (`applied_v`).
    #[inline(always)]
    fn restart_overridden_servos(&mut self, ran: [bool; 2], applied_v: [f32; 2]) {
        for i in 0..2 {
            if ran[i] && self.servo[i].output_v() != applied_v[i] {
                restart_at(&mut self.servo[i], applied_v[i]);
            }
        }
    }

    /// Step 3a for the envelope's hand-overs: a fade-out after the servo alone counts down.
    #[inline(never)]
    fn count_down_handback(&mut self, servo_ran: [bool; 2]) {
        for (e, ran) in self.envelope.iter_mut().zip(servo_ran) {
            if ran {
                e.handback_ticks = e.handback_ticks.saturating_sub(1);
            }
        }
        self.envelope_handed = self
            .envelope
            .iter()
            .any(|e| e.servo_alone || e.handback_ticks > 0);
    }

    /// An axis's on-target state of the last tick (flag, ticks since the reference changed,
    /// settling time of the last move; module docs, On target).
    pub fn on_target(&self, axis: Axis) -> &OnTargetState {
        &self.on_target[axis.index()]
    }

    /// An axis's identified-envelope counts (ticks outside, largest excursions).
    pub fn envelope_counts(&self, axis: Axis) -> EnvelopeCounts {
        self.envelope[axis.index()].counts
    }

    /// Whether an axis's command of the last tick was outside its identified envelope.
    pub fn envelope_outside(&self, axis: Axis) -> bool {
        self.envelope[axis.index()].outside
    }

    /// Whether the envelope policy has handed an axis to its servo alone (from the next tick).
    pub fn servo_alone(&self, axis: Axis) -> bool {
        self.envelope[axis.index()].servo_alone
    }

    /// Ticks the servo alone drove an axis under the policy `feedback-only`.
    pub fn servo_alone_ticks(&self, axis: Axis) -> u32 {
        self.envelope[axis.index()].servo_alone_ticks
    }

    /// An axis's servo state (mode, last output and correction).
    pub fn servo_state(&self, axis: Axis) -> &ServoState {
        &self.servo[axis.index()]
    }

    /// Swaps the settings between two ticks (a new parameter set). The run-time state is kept:
    /// the compensator's model state, each guard's last output and its counters, the counters,
    /// the mode and the reference. Nothing moves here: an output outside the new window is
    /// slewed into it by the guard in the ticks that follow, at most the new slew limit per
    /// tick, each such tick counted (`window_entry`); while the loop is safe it stays held
    /// where it is, and the slew-in follows the rearm. In those ticks the compensator's model is
    /// advanced with the voltage applied and the servo restarts at it, as after any guard
    /// override (see [`TwoAxisLoop::tick`]). The inverse effect chain restarts at rest at the
    /// applied voltages when the effects changed; the servo restarts at rest at them.
    pub fn set_settings(&mut self, settings: LoopSettings) {
        let settings = settings.with_axes_checked();
        let effects_changed =
            (0..2).any(|i| settings.axes[i].effects != self.settings.axes[i].effects);
        self.frames.set_decimation(settings.frame_decimation);
        self.settings = settings;
        // The tick sets `outside` only while a set has an envelope.
        self.envelope.iter_mut().for_each(|e| e.outside = false);
        if effects_changed {
            self.chain = self.chain_at_applied();
            self.set_body();
        }
        if self.feedback && settings.axes.iter().any(|a| a.servo.is_none()) {
            // A set without a servo: feed-forward only from here on.
            self.feedback = false;
        }
        self.restart_servo();
    }

    /// The body's copy again after `chain` or `feedforward` changed.
    fn set_body(&mut self) {
        self.body = Body::of(&self.chain, self.feedforward);
    }

    fn chain_at_applied(&self) -> Option<InverseChain> {
        match self.feedforward {
            Feedforward::Compensator => InverseChain::new(
                [self.settings.axes[0].effects, self.settings.axes[1].effects],
                [
                    self.guard[0].last_safe_volts(),
                    self.guard[1].last_safe_volts(),
                ],
            ),
            Feedforward::Linear | Feedforward::OpenLoop | Feedforward::Learned => None,
        }
    }

    /// Leaves the safe state (after the cause is cleared): tracking resumes from the held
    /// voltages; stuck detection starts afresh.
    pub fn rearm(&mut self) {
        self.mode = Mode::Running;
        self.stuck = [StuckDetector::default(); 2];
        self.restart_servo();
    }

    /// A fault: counted under its cause ([`Counters`]) and latched (`trip`). Out of line, as
    /// `trip`: only a fault calls it, and the tick keeps fewer values live around it.
    #[cold]
    #[inline(never)]
    fn count_fault(&mut self, fault: Fault) {
        let c = &mut self.counters;
        let count = match fault {
            Fault::SensorError(_) => &mut c.sensor_errors,
            Fault::NonFiniteReading(_) => &mut c.non_finite_readings,
            Fault::StuckReading(_) => &mut c.stuck_readings,
            Fault::Overrun => &mut c.overruns,
            Fault::DacError(_) => &mut c.dac_errors,
        };
        *count = count.saturating_add(1);
        self.trip(fault);
    }

    /// Latches the safe state with `fault`, counted once per entry (out of line: only a fault
    /// calls it).
    #[cold]
    #[inline(never)]
    fn trip(&mut self, fault: Fault) {
        if self.mode == Mode::Running {
            self.mode = Mode::Safe(fault);
            self.counters.safe_entries = self.counters.safe_entries.saturating_add(1);
        }
    }

    /// Step 2 for axis `i` of a running tick: the feed-forward (`[target, reference, learned]`:
    /// the compensator's target, the reference, the learned table's voltage), the servo's
    /// correction when it runs on the reference `previous_reference` of the reading
    /// `measured`, the guard, and the compensator's model advanced from `before` by the
    /// voltage applied when that differs from its own command; returns the voltage applied.
    #[inline(always)]
    fn command_axis<const LEARNED: bool>(
        &mut self,
        i: usize,
        [target, reference, learned_v]: [f32; 3],
        previous_reference: f32,
        measured: f32,
        servo_runs: bool,
        before: &CompensatorState,
    ) -> f32 {
        let i = i & 1;
        let axis = &self.settings.axes[i];
        let requested = match self.feedforward {
            _ if LEARNED => learned_v,
            Feedforward::Compensator => {
                let out = axis.compensator.compensate_noting(
                    &mut self.compensator[i],
                    target,
                    &mut self.zero_reach[i],
                );
                let c = &mut self.counters;
                match out.status {
                    CommandStatus::Tracking => {}
                    CommandStatus::Limited => {
                        c.compensator_limited = c.compensator_limited.saturating_add(1)
                    }
                    CommandStatus::HeldInvalidReference => {
                        c.held_references = c.held_references.saturating_add(1)
                    }
                }
                out.voltage_v
            }
            Feedforward::Linear => {
                axis.limits.min_volts()
                    + (reference - axis.rest_output_m) / axis.linear_gain_m_per_v
            }
            // Learned only reaches the learned copy of the body.
            Feedforward::OpenLoop | Feedforward::Learned => reference,
        };
        let feedforward = requested;
        let requested = match axis.servo.as_ref() {
            Some(servo) if servo_runs => {
                let out = servo.step(
                    &mut self.servo[i],
                    previous_reference,
                    measured,
                    feedforward,
                );
                if out.status != ServoStatus::Tracking {
                    let c = &mut self.counters;
                    c.servo_limited = c.servo_limited.saturating_add(1);
                }
                out.voltage_v
            }
            _ => feedforward,
        };
        let u = axis.limits.apply(&mut self.guard[i], requested);
        if u != feedforward || self.feedforward != Feedforward::Compensator {
            // The guard overrode the compensator, or another feed-forward ran: advance the
            // model by what is applied, so that switching to the compensator is bumpless.
            // From the state before the tick, with the command's Δu₀ when it crossed h = 0.
            let state = &mut self.compensator[i];
            *state = *before;
            axis.compensator
                .advance_noted(state, u, &self.zero_reach[i]);
        }
        u
    }

    /// One tick (see the module docs). Never panics.
    #[inline]
    pub fn tick<D, S>(&mut self, io: &mut XyIo<D, S>, deadline_missed: bool) -> TickReport
    where
        D: DacWrite,
        S: PositionSensor,
    {
        // Three copies of the body: without effects it is exactly the tick without the chain,
        // and only the learned table's copy reads it.
        match self.body {
            Body::Plain => self.tick_body::<false, false, D, S>(io, deadline_missed),
            Body::Effects => self.tick_body::<true, false, D, S>(io, deadline_missed),
            Body::Learned => self.tick_body::<false, true, D, S>(io, deadline_missed),
        }
    }

    /// The tick's steps 0–4 (module docs), written as one function on purpose: split into named
    /// helpers (sensors, commands, DAC, effects, frame; all `#[inline(always)]`) the tick cost
    /// 6–7 % more instructions under `firmware/bench.sh` (2519 → 2670 per tick with the
    /// simulated stage), the state copies the DAC-failure path needs no longer staying in
    /// registers. The exception is step 2's per-axis work ([`TwoAxisLoop::command_axis`]),
    /// called once per axis instead of in an axis loop: the worst tick of `bench.sh` with a
    /// 50 kHz copy of the stage file went from 2106 to 1967 instructions (a sensor step
    /// written the same way cost 35 more, so it stays a loop).
    #[inline(always)]
    fn tick_body<const EFFECTS: bool, const LEARNED: bool, D, S>(
        &mut self,
        io: &mut XyIo<D, S>,
        deadline_missed: bool,
    ) -> TickReport
    where
        D: DacWrite,
        S: PositionSensor,
    {
        let c = &mut self.counters;
        c.ticks = c.ticks.saturating_add(1);
        if deadline_missed {
            self.count_fault(Fault::Overrun);
        }

        // 1. Sensors, every tick.
        let mut measured_m = [f32::NAN; 2];
        let readings = io.sensor.read_both_m();
        for (axis, reading) in Axis::ALL.into_iter().zip(readings) {
            let i = axis.index();
            match reading {
                Ok(m) if m.is_finite() => {
                    measured_m[i] = m;
                    let commanded = self.guard[i].last_safe_volts();
                    if self.stuck[i].observe(m, commanded, &self.settings.stuck) {
                        self.count_fault(Fault::StuckReading(axis));
                    }
                }
                Ok(_) => self.count_fault(Fault::NonFiniteReading(axis)),
                Err(_) => self.count_fault(Fault::SensorError(axis)),
            }
        }

        // 2. Commands.
        let answered_reference = self.last_reference_m;
        let before_compensator = self.compensator;
        let before_guard = self.guard;
        let before_servo = self.servo;
        let mut applied_v = [
            self.guard[0].last_safe_volts(),
            self.guard[1].last_safe_volts(),
        ];
        let servo_may_run = self.mode == Mode::Running && self.feedforward != Feedforward::OpenLoop;
        let servo_runs = servo_may_run && (self.feedback || self.handover_ticks > 0);
        // Per axis: the control mode's servo, or the envelope policy's (servo alone, or the
        // fade-out after it).
        let axis_servo_runs = if self.envelope_handed {
            self.envelope_servo_runs(servo_may_run, servo_runs)
        } else {
            [servo_runs; 2]
        };
        if self.mode == Mode::Running {
            let previous_reference = self.last_reference_m;
            let mut learned_v = [f32::NAN; 2];
            let (reference, target) = match self.chain.as_mut() {
                Some(chain) if EFFECTS => {
                    let reference = &mut self.reference;
                    chain.next_targets(|| reference.next_setpoint())
                }
                _ if LEARNED => {
                    let (r, u) = self.reference.next_learned();
                    learned_v = u;
                    (r, r)
                }
                _ => {
                    let r = self.reference.next_setpoint();
                    (r, r)
                }
            };
            self.last_reference_m = reference;
            // The two axes written out (no axis loop: its counter and indexing cost more than
            // the second copy).
            applied_v[0] = self.command_axis::<LEARNED>(
                0,
                [target[0], reference[0], learned_v[0]],
                previous_reference[0],
                measured_m[0],
                axis_servo_runs[0],
                &before_compensator[0],
            );
            applied_v[1] = self.command_axis::<LEARNED>(
                1,
                [target[1], reference[1], learned_v[1]],
                previous_reference[1],
                measured_m[1],
                axis_servo_runs[1],
                &before_compensator[1],
            );
        }
        // The identified envelope: counted while tracking (an excitation measures one).
        let outside = if self.settings.any_envelope() {
            let previous_v = [
                before_guard[0].last_safe_volts(),
                before_guard[1].last_safe_volts(),
            ];
            self.envelope_tick(applied_v, previous_v, axis_servo_runs)
        } else {
            [false; 2]
        };
        // On target: each reading against the reference it answers, while tracking.
        let mut on_target = [false; 2];
        if self.mode == Mode::Running && self.feedforward != Feedforward::OpenLoop {
            let [x, y] = &self.settings.axes;
            let [sx, sy] = &mut self.on_target;
            on_target = [
                x.on_target
                    .observe(sx, measured_m[0], answered_reference[0]),
                y.on_target
                    .observe(sy, measured_m[1], answered_reference[1]),
            ];
        } else {
            self.on_target.iter_mut().for_each(OnTargetState::reset);
        }

        // 3. DAC.
        let gain = self.settings.amplifier_gain_v_per_v;
        for axis in Axis::ALL {
            let i = axis.index();
            let code = DacCode::from_volts(applied_v[i] / gain);
            if io.dac.write_code(io.dac_channels[i], code).is_err() {
                let c = &mut self.counters;
                c.dac_errors = c.dac_errors.saturating_add(1);
                if self.mode == Mode::Running {
                    self.trip(Fault::DacError(axis));
                    // This axis's DAC kept its previous code; so does the model.
                    self.compensator[i] = before_compensator[i];
                    self.guard[i] = before_guard[i];
                    self.servo[i] = before_servo[i];
                    applied_v[i] = before_guard[i].last_safe_volts();
                    // Axes after it have not been written yet: hold them too.
                    for j in (i + 1)..2 {
                        self.compensator[j] = before_compensator[j];
                        self.guard[j] = before_guard[j];
                        self.servo[j] = before_servo[j];
                        applied_v[j] = before_guard[j].last_safe_volts();
                    }
                }
            }
        }

        // 3a. Servo: a fade-out counts down; a servo that did not run this tick (safe,
        // excitation, feed-forward only) restarts at rest at the applied voltage when it runs
        // again (see `restart_servo`: rearm, set_feedforward, set_control_mode).
        if servo_runs && !self.feedback {
            self.handover_ticks = self.handover_ticks.saturating_sub(1);
        }
        if self.envelope_handed {
            self.restart_overridden_servos(axis_servo_runs, applied_v);
            self.count_down_handback(axis_servo_runs);
        } else if servo_runs {
            self.restart_overridden_servos([true; 2], applied_v);
        }

        // 3b. Effects: the stage saw `applied_v` this tick (the held value if safe or if the
        // write failed); the compensator's model is at the w it gives.
        if EFFECTS {
            if let Some(chain) = self.chain.as_mut() {
                for (i, (axis, state)) in self
                    .settings
                    .axes
                    .iter()
                    .zip(self.compensator.iter())
                    .enumerate()
                {
                    let w = axis.compensator.model().output(&state.model);
                    chain.commit(i, applied_v[i], w);
                }
            }
        }

        // 4. Frame (open loop: the reference is in volts, not metres).
        let reference_m = if self.feedforward == Feedforward::OpenLoop {
            [f32::NAN; 2]
        } else {
            self.last_reference_m
        };
        let flags = u8::from(outside[0])
            | (u8::from(outside[1]) << 1)
            | (u8::from(on_target[0]) << 2)
            | (u8::from(on_target[1]) << 3);
        self.frames.offer_flagged(
            || {
                [0, 1].map(|i| AxisSample {
                    reference_m: reference_m[i],
                    commanded_v: applied_v[i],
                    sensor_m: measured_m[i],
                })
            },
            flags,
        );
        TickReport {
            reference_m,
            measured_m,
            applied_v,
            mode: self.mode,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::params::{AxisParams, AMPLIFIER_GAIN_V_PER_V, AXES, SAMPLE_PERIOD_S};
    use crate::test_support::loop_holding;
    use piezo_core::effects::EffectParams;

    /// The tick's body (plain, effects, learned) stays the one of the loop's chain and
    /// feed-forward through every call that changes either: feed-forward switches, control
    /// modes, a set with effects and one without, the learned table and back.
    #[test]
    fn the_tick_body_follows_the_chain_and_the_feedforward() {
        let check = |lp: &TwoAxisLoop, want: Body| {
            assert_eq!(lp.body, Body::of(&lp.chain, lp.feedforward));
            assert_eq!(lp.body, want);
        };
        let mut lp = loop_holding([5e-6, 5e-6]);
        check(&lp, Body::Plain);
        lp.set_feedforward(Feedforward::OpenLoop);
        check(&lp, Body::Plain);
        lp.set_feedforward(Feedforward::Compensator);
        check(&lp, Body::Plain);

        // A set with effects: the chain's copy, in every mode that runs the compensator.
        let mut axes: [AxisParams; 2] = AXES;
        for a in &mut axes {
            a.effects = EffectParams {
                creep_gain_m_per_v: [0.03 * a.static_map.k1_m_per_v, 0.0, 0.0],
                creep_time_constant_s: [0.2, 0.0, 0.0],
                ..EffectParams::default()
            };
        }
        let with_effects =
            LoopSettings::from_params(&axes, AMPLIFIER_GAIN_V_PER_V, SAMPLE_PERIOD_S).unwrap();
        let without = *lp.settings();
        lp.set_settings(with_effects);
        check(&lp, Body::Effects);
        lp.set_control_mode(ServoMode::OpenLoop).unwrap();
        check(&lp, Body::Plain);
        lp.set_control_mode(ServoMode::Feedforward).unwrap();
        check(&lp, Body::Effects);
        lp.set_feedforward(Feedforward::OpenLoop);
        check(&lp, Body::Plain);
        lp.set_feedforward(Feedforward::Compensator);
        check(&lp, Body::Effects);
        lp.set_settings(without);
        check(&lp, Body::Plain);

        // The learned table over a table program, then the compensator again.
        let entries = [[5e-6, 5e-6], [6e-6, 6e-6], [7e-6, 7e-6], [6e-6, 6e-6]];
        let volts = [[10.0, 10.0], [10.1, 10.1], [10.2, 10.2], [10.1, 10.1]];
        lp.reference.table_append(&entries).unwrap();
        lp.reference.learned_append(&volts).unwrap();
        lp.reference.set_program(Program::Table {
            ticks_per_entry: 8,
            repeat: true,
        });
        lp.set_learned_mode(false).unwrap();
        check(&lp, Body::Learned);
        lp.set_control_mode(ServoMode::Feedforward).unwrap();
        check(&lp, Body::Plain);
    }
}
