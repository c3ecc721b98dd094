//! The loop's state types, one definition each: the firmware's two-axis loop keeps them and the
//! link carries them as they are ([`Axis`], [`Fault`], [`Mode`], [`Feedforward`], [`Control`],
//! [`Counters`] with the output guard's [`GuardCounters`]).
//!
//! The output guard (the firmware's `safety` module) sets the applied voltage `y` of a tick from
//! the request `u`, the last applied `y₋`, the window `[V_min, V_max]` and the step bound `M`
//! \[V per tick\]; each cause is counted on every tick it applies to (a request above the window
//! that is also more than M away counts as clamped and as slew-limited):
//!
//! ```text
//! u not finite                                → y = y₋ (held)            non_finite
//! u outside [V_min, V_max]                    → target = clamp(u)        window_clamped
//! |target − y₋| > M                           → y = y₋ ± M               slew_limited
//! y₋ outside the window (a new window swapped
//!   in) and y ≠ u                             → the slew into it         window_entry
//! ```

use piezo_core::ServoMode;
use serde::{Deserialize, Serialize};

/// An axis of the stage (on the wire: 0 for x, 1 for y).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Axis {
    /// x (index 0).
    X,
    /// y (index 1).
    Y,
}

impl Axis {
    /// Both axes, in order.
    pub const ALL: [Axis; 2] = [Axis::X, Axis::Y];

    /// 0 for x, 1 for y.
    #[inline]
    pub fn index(self) -> usize {
        match self {
            Axis::X => 0,
            Axis::Y => 1,
        }
    }

    /// `x` or `y`.
    pub fn name(self) -> &'static str {
        match self {
            Axis::X => "x",
            Axis::Y => "y",
        }
    }
}

/// What tripped the safe state.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Fault {
    /// The previous tick missed its deadline.
    Overrun,
    /// Reading an axis's sensor failed (bus error).
    SensorError(Axis),
    /// An axis's sensor gave NaN or ±∞.
    NonFiniteReading(Axis),
    /// An axis's sensor reading froze while the actuator moved.
    StuckReading(Axis),
    /// Writing an axis's DAC code failed.
    DacError(Axis),
}

/// Running or safe (with the fault that tripped it).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Mode {
    /// Tracking the reference.
    Running,
    /// Holding the outputs after a fault, until a rearm.
    Safe(Fault),
}

/// Which feed-forward computes the requested voltage.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Feedforward {
    /// piezo-core's inverse compensator (reference in metres).
    Compensator,
    /// The uncompensated baseline: `u = u_min + (r − y_rest)/g_lin`, with `g_lin` the secant gain
    /// of the first loading over the window (reference in metres).
    Linear,
    /// Open-loop excitation: the reference is the stack voltage itself (for identification).
    OpenLoop,
    /// The learned voltage table played with the wave table: `u_ff` is the table's voltage at
    /// the wave table's position, the compensator is not used (its model follows the applied
    /// voltage); the reference in metres is kept for the record and the servo.
    Learned,
}

/// How the voltage of a tracking tick is made: piezo-core's [`ServoMode`] ([`Control::servo_mode`]),
/// or the learned voltage table in its place.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Control {
    /// The linear baseline, no feedback.
    OpenLoop,
    /// The inverse compensator alone.
    Feedforward,
    /// The servo on the sensor alone.
    Feedback,
    /// The compensator plus the servo's correction.
    FeedforwardFeedback,
    /// The learned voltage table ([`Request::LearnedAppend`](crate::Request::LearnedAppend)) played with the wave table: the
    /// stack voltage of a tick is the table's, the compensator is not used.
    Learned,
    /// The learned voltage table plus the servo's correction on r − y (as
    /// [`Control::FeedforwardFeedback`] adds it to the compensator's command).
    LearnedFeedback,
}

impl Control {
    /// The four of piezo-core's servo, in the order of the servo benchmark's table.
    pub const ALL: [Self; 4] = [
        Self::OpenLoop,
        Self::Feedforward,
        Self::Feedback,
        Self::FeedforwardFeedback,
    ];

    /// The two that play the learned voltage table.
    pub const LEARNED: [Self; 2] = [Self::Learned, Self::LearnedFeedback];

    /// `open-loop`, `feedforward`, `feedback`, `feedforward+feedback` (as piezo-core names them),
    /// `learned`, `learned+feedback`.
    pub fn name(self) -> &'static str {
        match self {
            Self::Learned => "learned",
            Self::LearnedFeedback => "learned+feedback",
            servo => servo.servo_mode().name(),
        }
    }

    /// True for the modes that play the learned voltage table.
    pub fn learned(self) -> bool {
        matches!(self, Self::Learned | Self::LearnedFeedback)
    }

    /// piezo-core's mode of the servo: the learned modes run it as the compensator's
    /// feed-forward does (`Learned`: none, `LearnedFeedback`: the correction on r − y added).
    pub fn servo_mode(self) -> ServoMode {
        match self {
            Self::OpenLoop => ServoMode::OpenLoop,
            Self::Feedforward | Self::Learned => ServoMode::Feedforward,
            Self::Feedback => ServoMode::Feedback,
            Self::FeedforwardFeedback | Self::LearnedFeedback => ServoMode::FeedforwardFeedback,
        }
    }

    /// The mode that runs the servo as `mode`, with the learned voltage table in the
    /// compensator's place if `learned` (the inverse of [`Control::servo_mode`] and
    /// [`Control::learned`]; a learned mode has feed-forward, so `Feedback` with `learned` is
    /// `LearnedFeedback` and `OpenLoop` with `learned` is `Learned`).
    pub fn new(mode: ServoMode, learned: bool) -> Self {
        match (mode, learned) {
            (ServoMode::OpenLoop, false) => Self::OpenLoop,
            (ServoMode::Feedforward, false) => Self::Feedforward,
            (ServoMode::Feedback, false) => Self::Feedback,
            (ServoMode::FeedforwardFeedback, false) => Self::FeedforwardFeedback,
            (ServoMode::FeedforwardFeedback | ServoMode::Feedback, true) => Self::LearnedFeedback,
            (ServoMode::OpenLoop | ServoMode::Feedforward, true) => Self::Learned,
        }
    }
}

/// The output guard's interventions on one axis, per cause (saturating; see the module doc):
/// a tick counts under every cause that applies to it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct GuardCounters {
    /// Requests that were NaN or ±∞ (output held, or the slew into a new window continued).
    pub non_finite: u32,
    /// Requests outside the window (clamped).
    pub window_clamped: u32,
    /// Requests further than the step bound from the last output (slew-limited).
    pub slew_limited: u32,
    /// Ticks that began with the last output outside the window (a window swapped in while the
    /// output lay outside it) and on which the guard, not the request, set the output: the slew
    /// into the new window.
    pub window_entry: u32,
}

impl GuardCounters {
    /// Interventions of all causes (saturating; a tick with two causes counts twice).
    pub fn total(&self) -> u32 {
        self.non_finite
            .saturating_add(self.window_clamped)
            .saturating_add(self.slew_limited)
            .saturating_add(self.window_entry)
    }
}

/// Event counts since boot (saturating): the loop's own (ticks, faults, the compensator's, the
/// servo's and the guard's limits, the reference's underruns, the envelope's excursions, the
/// frame queue's drops) and the link's (frames, requests, uploads). The loop fills its part
/// and leaves the link's at zero; the link's endpoint adds its own.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Counters {
    /// Ticks run.
    pub ticks: u32,
    /// Missed deadlines.
    pub overruns: u32,
    /// Failed sensor reads.
    pub sensor_errors: u32,
    /// Non-finite sensor readings.
    pub non_finite_readings: u32,
    /// Stuck-sensor detections.
    pub stuck_readings: u32,
    /// Failed DAC writes.
    pub dac_errors: u32,
    /// Transitions Running → Safe.
    pub safe_entries: u32,
    /// Samples where the compensator's window or slew limit stopped it short (both axes).
    pub compensator_limited: u32,
    /// Samples with a non-finite reference, held by the compensator (both axes).
    pub held_references: u32,
    /// Samples where the servo's window or slew limit stopped the feedback short, or it held its
    /// correction over a non-finite input (both axes).
    pub servo_limited: u32,
    /// Per axis (x, y), the output guard's interventions by cause.
    pub guard: [GuardCounters; 2],
    /// Ticks of a streamed program that found the queue empty.
    pub stream_underruns: u32,
    /// Ticks whose command left an axis's identified envelope (both axes; per axis in
    /// [`Status::envelope`](crate::Status::envelope)).
    pub envelope_excursions: u32,
    /// Frames produced but not sent (the loop's queue, or the link's transmit buffer, full).
    pub frames_dropped: u32,
    /// Frames sent.
    pub frames_sent: u32,
    /// Requests received (CRC good).
    pub requests: u32,
    /// Frames refused by the receiver (COBS, CRC, length, body).
    pub rejected_packets: u32,
    /// Gaps in the request sequence numbers.
    pub request_gaps: u32,
    /// Requests not run because their sequence number was already handled
    /// ([`Response::Replayed`](crate::Response::Replayed)).
    pub replayed_requests: u32,
    /// Parameter sets loaded at run time ([`Request::Upload`](crate::Request::Upload)).
    pub uploads: u32,
    /// Parameter sets refused (by the core, the chain or the control mode).
    pub refused_uploads: u32,
}

impl Counters {
    /// Faults of all kinds (overruns, sensor errors, non-finite and stuck readings, DAC errors).
    pub fn faults(&self) -> u32 {
        self.overruns
            .saturating_add(self.sensor_errors)
            .saturating_add(self.non_finite_readings)
            .saturating_add(self.stuck_readings)
            .saturating_add(self.dac_errors)
    }

    /// The output guard's interventions, all causes, both axes.
    pub fn guard_interventions(&self) -> u32 {
        self.guard
            .iter()
            .map(GuardCounters::total)
            .fold(0, u32::saturating_add)
    }
}
