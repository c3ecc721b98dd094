//! The messages: what a host asks ([`Request`]), what the firmware answers ([`Response`]) and
//! streams ([`Frame`]), and the run-time model upload ([`ModelSet`]). SI units; a field without a
//! unit in its name takes the unit of its request (metres for [`Request::Track`], stack volts for
//! [`Request::Excite`]).

use crate::{Control, Counters, Feedforward, Mode};
use heapless::{String, Vec};
use piezo_core::effects::{EffectParams, MAX_CREEP_ELEMENTS, MAX_RELAXATION_ELEMENTS};
use piezo_core::{
    Asymmetry, AxisParams, BoucWenParams, Envelope, EnvelopeCounts, EnvelopePolicy, Fnv1a32,
    IoChain, Limits, OnTarget, ParamError, Program, ServoParams, StaticMap,
};
use serde::{Deserialize, Serialize};

/// The version of the messages: +1 whenever their bytes change. The first field of
/// [`Status`], so that a host finds it before anything that may have changed.
///
/// 2: the loop's counters with the output guard's per axis and cause, the running set's
/// fingerprint in [`Status`] and [`Response::Loaded`], this version.
///
/// 3: an axis's [`Limits`] are piezo-core's, the stage file's `[x.limits]`, with the envelope
/// policy after the slew limit; [`Program::Raster`] after the other programs.
///
/// 4: an axis's servo carries the notch's pole frequency (`notch_pole_frequency_hz`, a notch
/// with lead) after its Q.
///
/// 5: an axis's effects carry the relaxation's spread (`relaxation_spread_decades`) after the
/// mode's relative damping.
///
/// 6: an axis's effects carry the hysteresis's rate-dependent gain
/// (`hysteresis_rate_gain_s_per_v`) after the relaxation's spread.
pub const PROTOCOL_VERSION: u16 = 6;

/// Setpoints per [`Request::TableAppend`], [`Request::Stream`] or [`Request::LearnedAppend`]
/// message.
pub const SETPOINT_CHUNK: usize = 32;
/// Bytes of a refusal's reason.
pub const REASON_BYTES: usize = 160;
/// Bytes of a parameter set's version string.
pub const VERSION_BYTES: usize = 48;

/// Setpoints `[x, y]`, one per tick (or per table entry; stack volts for the learned table).
pub type Setpoints = Vec<[f32; 2], SETPOINT_CHUNK>;

/// `text` cut to the first `N` bytes that end a character (for versions and reasons).
pub fn truncated<const N: usize>(text: &str) -> String<N> {
    let mut out = String::new();
    for c in text.chars() {
        if out.push(c).is_err() {
            break;
        }
    }
    out
}

/// One axis of a parameter set: piezo-core's own parameter structs. On the wire as protocol 3
/// laid it out (`AxisWire`): the fields in this order, the envelope followed by the policy
/// outside it, which is the limits' ([`Limits::envelope_policy`], written there too and not
/// read back from there).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(from = "AxisWire", into = "AxisWire")]
pub struct AxisModel {
    /// Bouc-Wen parameters.
    pub bouc_wen: BoucWenParams,
    /// y = k1·u + k2·h + y0.
    pub static_map: StaticMap,
    /// δ and φ (zero: the symmetric model).
    pub asymmetry: Asymmetry,
    /// The effects around the model (all zero: none).
    pub effects: EffectParams,
    /// Output limits (the stage file's `[x.limits]`): the window, the slew limit and the policy
    /// outside the envelope.
    pub limits: Limits,
    /// The feedback servo (the stage file's `[x.servo]`; `None`: feed-forward only).
    pub servo: Option<ServoParams>,
    /// The identified envelope (the stage file's `[x.identified]`; `None`: nothing checked),
    /// run under `limits.envelope_policy`.
    pub envelope: Option<Envelope>,
    /// The on-target band (the stage file's `[x.on_target]` with its defaults).
    pub on_target: OnTarget,
}

impl AxisModel {
    /// The axis `p` as the link carries it: its rest output and baseline gain are not carried
    /// (the firmware computes them on upload, [`AxisModel::params`]).
    pub fn from_params(p: &AxisParams) -> Self {
        Self {
            bouc_wen: p.bouc_wen,
            static_map: p.static_map,
            asymmetry: p.asymmetry,
            effects: p.effects,
            limits: p.limits,
            servo: p.servo,
            envelope: p.envelope,
            on_target: p.on_target,
        }
    }

    /// The firmware's view of an uploaded axis at the loop period `sample_period_s` \[s\]: the
    /// core's axis with these limits and its first loading from rest at the lower end of the
    /// window ([`AxisParams::with_first_loading`]). The core's refusal if it does not build.
    pub fn params(&self, sample_period_s: f32) -> Result<AxisParams, ParamError> {
        AxisParams {
            bouc_wen: self.bouc_wen,
            static_map: self.static_map,
            asymmetry: self.asymmetry,
            limits: self.limits,
            linear_gain_m_per_v: 0.0,
            rest_output_m: 0.0,
            effects: self.effects,
            servo: self.servo,
            envelope: self.envelope,
            on_target: self.on_target,
        }
        .with_first_loading(sample_period_s)
    }
}

/// A whole parameter set, validated on the firmware exactly as the stage file's build validates
/// it — piezo-core's constructors with their plausibility bounds, and each axis's window and slew
/// limit against the chain (`IoChain::check_limits`) — and swapped in between two ticks if it is
/// accepted.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ModelSet {
    /// `name version` of the stage file.
    pub version: String<VERSION_BYTES>,
    /// FNV-1a (32 bit) of the stage file's bytes.
    pub fnv1a32: u32,
    /// The stage file's loop rate \[Hz\] (must be the firmware's).
    pub loop_rate_hz: f32,
    /// The stage file's DAC, amplifier, ADC and sensor chain (must be the firmware's, field by
    /// field: the chain is hardware).
    pub io: IoChain,
    /// x, y.
    pub axes: [AxisModel; 2],
}

impl ModelSet {
    /// The content-derived version of the set: FNV-1a 32 ([`piezo_core::fnv`]) of the postcard
    /// bytes of `(loop_rate_hz, io, axes)`, the set as the firmware runs it (its name, version
    /// and file hash left out). Two sets with this fingerprint drive the stage alike; a set that
    /// differs in any carried number has another one (up to FNV's collisions).
    pub fn fingerprint(&self) -> u32 {
        fingerprint(self.loop_rate_hz, &self.io, &self.axes)
    }
}

/// [`ModelSet::fingerprint`] of the set with these parts (the firmware's built-in set).
pub fn fingerprint(loop_rate_hz: f32, io: &IoChain, axes: &[AxisModel; 2]) -> u32 {
    struct Hash(Fnv1a32);
    impl postcard::ser_flavors::Flavor for Hash {
        type Output = u32;
        fn try_push(&mut self, byte: u8) -> postcard::Result<()> {
            self.0.push(byte);
            Ok(())
        }
        fn finalize(self) -> postcard::Result<u32> {
            Ok(self.0.value())
        }
    }
    // The hashing flavour cannot fail, nor can serde's derives on plain numbers.
    postcard::serialize_with_flavor(&(loop_rate_hz, io, axes), Hash(Fnv1a32::new())).unwrap_or(0)
}

/// What a host asks.
// An upload is the large variant; no_std without allocation cannot box it, and a request is
// built and moved once, never stored in bulk.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Request {
    /// Answered with [`Response::Status`].
    Status,
    /// Track a reference in metres in the control mode chosen by [`Request::Control`]
    /// (feedforward, the compensator, unless switched). Answered with [`Response::Started`].
    Track(Program),
    /// Open-loop excitation: the program in stack volts goes to the guard and the DAC, no
    /// compensator (for identification). Answered with [`Response::Started`].
    Excite(Program),
    /// Empties the wave table. Answered with [`Response::Queued`].
    TableClear,
    /// Appends entries to the wave table. Answered with [`Response::Queued`], or refused when it
    /// would overflow (nothing appended).
    TableAppend(Setpoints),
    /// Queues streamed setpoints. Answered with [`Response::Queued`], or refused when they do not
    /// all fit (nothing queued).
    Stream(Setpoints),
    /// The control mode of [`Request::Track`], switched bumplessly between two ticks (during an
    /// excitation: the mode to return to). Answered with [`Response::Done`], or refused
    /// ([`RefusalKind::Program`]) for a mode with feedback when an axis has no servo.
    Control(Control),
    /// Leaves the safe state. Answered with [`Response::Done`].
    Rearm,
    /// Tells the next tick that the previous one missed its deadline (a fault drill).
    InjectOverrun,
    /// Loads a parameter set. Answered with [`Response::Loaded`], or refused with the core's
    /// reason, the running set untouched.
    Upload(ModelSet),
    /// Sample frames: one every `decimation` ticks, 0 for none. Answered with
    /// [`Response::Streaming`].
    Frames {
        /// Ticks per frame (0: off).
        decimation: u32,
    },
    /// Ends the run (the QEMU image exits). Answered with [`Response::Done`].
    Shutdown,
    /// Empties the learned voltage table. Answered with [`Response::Queued`], or refused
    /// ([`RefusalKind::Learned`]) while the loop plays it.
    LearnedClear,
    /// Appends `[ux, uy]` stack voltages \[V\] to the learned voltage table: entry j is the
    /// command for wave table entry j (same ticks per entry, same phase, linear in between).
    /// Answered with [`Response::Queued`], or refused when it would overflow (nothing appended)
    /// or while the loop plays the table. Checked when a learned control mode is switched on or
    /// a table program starts in one, never played unchecked.
    LearnedAppend(Setpoints),
}

/// Why a request was refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum RefusalKind {
    /// piezo-core refused the parameter set (the reason is the core's).
    Model,
    /// The set's loop rate or io chain is not the firmware's.
    Chain,
    /// The wave table or the stream queue has no room.
    Full,
    /// A table program with an empty table, or zero ticks per entry.
    Program,
    /// The learned voltage table: missing, not the wave table's length, an entry outside an
    /// axis's window or not finite, a step beyond the slew limit at the entry spacing; or a
    /// request that would change a table the loop plays.
    Learned,
}

/// A refusal: its kind, the axis if one, and a sentence.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Refusal {
    /// What was wrong.
    pub kind: RefusalKind,
    /// 0 for x, 1 for y, when it is one axis's.
    pub axis: Option<u8>,
    /// Why, in words (for a model: piezo-core's `ParamError` message).
    pub reason: String<REASON_BYTES>,
}

/// One axis's identified envelope as the loop checks it (piezo-core's `envelope`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct EnvelopeStatus {
    /// The running set has an envelope for this axis (otherwise nothing is checked).
    pub known: bool,
    /// The policy is `feedback-only`.
    pub feedback_only: bool,
    /// The last tick's command was outside.
    pub outside: bool,
    /// Ticks outside, and the largest voltage \[V\] and rate \[V/s\] excursions, since boot.
    pub counts: EnvelopeCounts,
    /// Ticks the servo alone drove the axis under `feedback-only`, since boot.
    pub feedback_only_ticks: u32,
}

/// One axis's on-target state (piezo-core's `on_target`): |sensor − reference| ≤ `tolerance_m`
/// for `ticks` consecutive ticks.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct OnTargetStatus {
    /// On target in the last tick.
    pub on_target: bool,
    /// Ticks since the reference last changed.
    pub ticks_since_change: u32,
    /// Settling time of the last move that settled \[ticks\]: from the reference's change to the
    /// first tick of the in-band run that set the flag (`None`: none has since boot).
    pub settle_ticks: Option<u32>,
    /// The band \[m\].
    pub tolerance_m: f32,
    /// Consecutive ticks inside the band.
    pub ticks: u32,
}

/// Tracking error of one axis since the last [`Request::Track`]: the sensor reading of tick k
/// minus the reference of tick k − 1 (the command it answers), after a settling time.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Tracking {
    /// Samples.
    pub count: u32,
    /// RMS error \[m\].
    pub rms_m: f32,
    /// Largest |error| \[m\].
    pub max_abs_m: f32,
}

/// The firmware's state, answered to [`Request::Status`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Status {
    /// The firmware's [`PROTOCOL_VERSION`] (first: a host reads it before the rest).
    pub protocol: u16,
    /// The running set's [`ModelSet::fingerprint`]: what the loop runs, changed by every upload
    /// of a set that differs.
    pub params_fingerprint: u32,
    /// FNV-1a of the running parameter set's stage file (as its upload or the build said).
    pub params_fnv1a32: u32,
    /// `name version` of the running set.
    pub params_version: String<VERSION_BYTES>,
    /// Loop rate \[Hz\].
    pub loop_rate_hz: f32,
    /// Running or safe.
    pub mode: Mode,
    /// Feed-forward in use.
    pub feedforward: Feedforward,
    /// Control mode of tracking (during an excitation: the mode it returns to).
    pub control: Control,
    /// Largest cost of one control tick measured by the image \[CPU cycles\] (the board's DWT
    /// cycle counter; 0 where nothing measures it, as under QEMU).
    pub tick_cycles_max: u32,
    /// Counters.
    pub counters: Counters,
    /// Per axis, since the last [`Request::Track`].
    pub tracking: [Tracking; 2],
    /// Voltages applied in the last tick \[V\].
    pub applied_v: [f32; 2],
    /// Sensor readings of the last tick \[m\].
    pub measured_m: [f32; 2],
    /// Ticks per frame (0: frames off).
    pub frame_decimation: u32,
    /// The number the next frame will carry.
    pub next_frame: u32,
    /// Wave table entries held, and its capacity.
    pub table: [u32; 2],
    /// Streamed setpoints queued, and the queue's capacity.
    pub stream: [u32; 2],
    /// Learned voltage table entries held, and its capacity.
    pub learned: [u32; 2],
    /// Per axis, the identified envelope's check.
    pub envelope: [EnvelopeStatus; 2],
    /// Per axis, on target and settling.
    pub on_target: [OnTargetStatus; 2],
}

/// An answer to one request.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Response {
    /// The state.
    Status(Status),
    /// The program runs from the next tick; the first frame it produces carries this number.
    Started {
        /// Frame number of the first tick under the new program.
        first_frame: u32,
    },
    /// Entries held by the wave table or the stream queue, and its capacity.
    Queued {
        /// Entries held.
        held: u32,
        /// Capacity.
        capacity: u32,
    },
    /// Frames are on (decimation > 0) or off; the next frame carries `next_frame`.
    Streaming {
        /// Ticks per frame (0: off).
        decimation: u32,
        /// Frame number of the next frame.
        next_frame: u32,
    },
    /// The set runs from the next tick.
    Loaded {
        /// Its FNV-1a (the stage file's, as the upload carried it).
        params_fnv1a32: u32,
        /// Its [`ModelSet::fingerprint`], computed by the firmware.
        params_fingerprint: u32,
    },
    /// Done.
    Done,
    /// Not done; nothing changed.
    Refused(Refusal),
    /// Not run, nothing changed: the request's sequence number is not ahead of the last one the
    /// firmware handled (a replayed or duplicated frame, or a host that started counting again).
    /// A host that meant it numbers it `next` and sends it again.
    Replayed {
        /// The lowest sequence number the firmware runs next (the last handled + 1).
        next: u32,
    },
}

/// One sample frame: what the loop did in one tick.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Frame {
    /// Frame number: +1 per frame the loop produced, sent or not (wraps).
    pub sequence: u32,
    /// Reference of the tick \[m\] (NaN during open-loop excitation).
    pub reference_m: [f32; 2],
    /// Voltage applied (after the guard) \[V\].
    pub commanded_v: [f32; 2],
    /// Sensor reading at the start of the tick \[m\] (NaN if the read failed).
    pub sensor_m: [f32; 2],
    /// The trial: passes completed over the wave table since the program started (0 for the
    /// other programs), counted at the entry this tick plays; the host cuts a record of a
    /// repeating table into periods with it.
    pub trial: u32,
    /// The tick's flags: [`Frame::OUTSIDE_X`], [`Frame::OUTSIDE_Y`], [`Frame::ON_TARGET_X`],
    /// [`Frame::ON_TARGET_Y`].
    pub flags: u8,
}

impl Frame {
    /// Flag: x's command was outside its identified envelope in this tick.
    pub const OUTSIDE_X: u8 = 1 << 0;
    /// Flag: y's command was outside its identified envelope in this tick.
    pub const OUTSIDE_Y: u8 = 1 << 1;
    /// Flag: x was on target in this tick (its reading against the reference it answers).
    pub const ON_TARGET_X: u8 = 1 << 2;
    /// Flag: y was on target in this tick.
    pub const ON_TARGET_Y: u8 = 1 << 3;

    /// The on-target flag of axis `i` (0: x, 1: y).
    pub const fn on_target_flag(i: usize) -> u8 {
        1 << (2 + (i & 1))
    }

    /// The envelope flag of axis `i` (0: x, 1: y).
    pub const fn outside_flag(i: usize) -> u8 {
        1 << (i & 1)
    }
}

/// What the firmware sends.
// A status is the large variant; no_std without allocation cannot box it, and an uplink is
// built and encoded once, never stored in bulk.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Uplink {
    /// The answer to the request with packet number `request`.
    Response {
        /// The request's packet number.
        request: u32,
        /// The answer.
        response: Response,
    },
    /// A sample frame.
    Frame(Frame),
}

/// [`AxisModel`] on the wire: its fields in order, the effects as a fixed tuple
/// (`effects_wire`), and the envelope with the policy outside it after its rate (protocol 3).
#[derive(Serialize, Deserialize)]
#[serde(rename = "AxisModel")]
struct AxisWire {
    bouc_wen: BoucWenParams,
    static_map: StaticMap,
    asymmetry: Asymmetry,
    #[serde(with = "effects_wire")]
    effects: EffectParams,
    limits: Limits,
    servo: Option<ServoParams>,
    envelope: Option<EnvelopeWire>,
    on_target: OnTarget,
}

/// An [`Envelope`] on the wire: the identified range and rate, then the axis's policy outside it.
#[derive(Serialize, Deserialize)]
#[serde(rename = "Envelope")]
struct EnvelopeWire {
    input_range_v: [f32; 2],
    input_rate_max_v_per_s: f32,
    policy: EnvelopePolicy,
}

impl From<AxisModel> for AxisWire {
    fn from(a: AxisModel) -> Self {
        Self {
            bouc_wen: a.bouc_wen,
            static_map: a.static_map,
            asymmetry: a.asymmetry,
            effects: a.effects,
            limits: a.limits,
            servo: a.servo,
            envelope: a.envelope.map(|e| EnvelopeWire {
                input_range_v: e.input_range_v,
                input_rate_max_v_per_s: e.input_rate_max_v_per_s,
                policy: a.limits.envelope_policy,
            }),
            on_target: a.on_target,
        }
    }
}

impl From<AxisWire> for AxisModel {
    /// The envelope's own policy byte is left: the axis runs under its limits' policy.
    fn from(a: AxisWire) -> Self {
        Self {
            bouc_wen: a.bouc_wen,
            static_map: a.static_map,
            asymmetry: a.asymmetry,
            effects: a.effects,
            limits: a.limits,
            servo: a.servo,
            envelope: a.envelope.map(|e| Envelope {
                input_range_v: e.input_range_v,
                input_rate_max_v_per_s: e.input_rate_max_v_per_s,
            }),
            on_target: a.on_target,
        }
    }
}

/// [`EffectParams`] as a fixed tuple: its own serde reads the creep and relaxation arrays as
/// sequences of up to [`MAX_CREEP_ELEMENTS`] / [`MAX_RELAXATION_ELEMENTS`] (for TOML), which
/// postcard writes as fixed arrays.
mod effects_wire {
    use super::*;
    use serde::{Deserializer, Serializer};

    type Tuple = (
        [f32; MAX_CREEP_ELEMENTS],
        [f32; MAX_CREEP_ELEMENTS],
        [f32; 15],
        [f32; MAX_RELAXATION_ELEMENTS],
        [f32; MAX_RELAXATION_ELEMENTS],
        f32,
    );

    pub fn serialize<S: Serializer>(e: &EffectParams, s: S) -> Result<S::Ok, S::Error> {
        let tuple: Tuple = (
            e.creep_gain_m_per_v,
            e.creep_time_constant_s,
            [
                e.even_coefficient_m_per_v2,
                e.even_center_v,
                e.mode_frequency_hz,
                e.mode_damping,
                e.delay_s,
                e.drift_rate_m_per_s,
                e.coupling,
                e.drift_settling_m,
                e.drift_settling_time_constant_s,
                e.log_creep_gain_m_per_v,
                e.log_creep_time_s,
                e.hysteresis_lag_s,
                e.mode_relative_damping,
                e.relaxation_spread_decades,
                e.hysteresis_rate_gain_s_per_v,
            ],
            e.relaxation_gain,
            e.relaxation_time_constant_s,
            e.relaxation_linear_m_per_v,
        );
        tuple.serialize(s)
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<EffectParams, D::Error> {
        let (
            creep_gain_m_per_v,
            creep_time_constant_s,
            f,
            relaxation_gain,
            relaxation_time_constant_s,
            relaxation_linear_m_per_v,
        ): Tuple = Deserialize::deserialize(d)?;
        Ok(EffectParams {
            creep_gain_m_per_v,
            creep_time_constant_s,
            even_coefficient_m_per_v2: f[0],
            even_center_v: f[1],
            mode_frequency_hz: f[2],
            mode_damping: f[3],
            delay_s: f[4],
            drift_rate_m_per_s: f[5],
            coupling: f[6],
            drift_settling_m: f[7],
            drift_settling_time_constant_s: f[8],
            log_creep_gain_m_per_v: f[9],
            log_creep_time_s: f[10],
            hysteresis_lag_s: f[11],
            mode_relative_damping: f[12],
            relaxation_spread_decades: f[13],
            hysteresis_rate_gain_s_per_v: f[14],
            relaxation_gain,
            relaxation_time_constant_s,
            relaxation_linear_m_per_v,
        })
    }
}
