//! The firmware's end of the command link ([`piezo_link`]): requests in, responses and sample
//! frames out, around the two-axis loop. No hardware: bytes come in through
//! [`Session::receive`] and go out through [`Session::transmit`], so the same code serves the
//! QEMU image's UART, the board's USB link and host tests.
//!
//! # Order of events
//! Requests are handled *between two ticks*, by whoever calls [`Session::receive`] (the QEMU
//! image's main loop; on the board the lower-priority link task, with the loop as a shared
//! resource): a new program, feed-forward or parameter set takes effect at the next tick, and a
//! tick never sees half of one.
//!
//! On the board the link holds the loop only for a request's effect: it decodes and prepares the
//! request outside ([`prepare`]: an upload validated by the core), applies it and copies out
//! its reply under the lock ([`Session::answer`]: the reply is a snapshot, e.g. the `Status` of
//! that moment, with the packet number it goes out under), encodes the reply outside
//! ([`Reply::encode`]) and queues its bytes under the lock again ([`Session::queue_reply`]).
//! Meanwhile the tick keeps its frames in the frame queue, so the packets leave in the order of
//! their numbers; it then sends up to [`FRAMES_PER_TICK`] a tick. [`Session::apply`] does the
//! three steps at once (the QEMU image, host tests).
//!
//! # Requests ([`Request`])
//! - `Track(program)`: reference in metres, in the control mode set by `Control` (feedforward,
//!   the compensator, until told otherwise; open loop: the linear baseline; feedback and
//!   feedforward + feedback: piezo-core's servo on the sensor, which needs `[x.servo]` and
//!   `[y.servo]` in the running set); the tracking error per axis (sensor of tick k minus reference
//!   of tick k − 1) is accumulated from [`SETTLE_S`] after it, reported by `Status`.
//! - `Excite(program)`: stack volts, open loop (compensator off), for identification; the
//!   compensator's model still follows the applied voltage, so going back to `Track` is bumpless.
//! - `TableClear`, `TableAppend`: the wave table ([`TABLE_CAPACITY`] entries); `Stream`: the
//!   streamed setpoint queue ([`STREAM_CAPACITY`] − 1).
//! - `Upload(set)`: each axis validated with piezo-core's constructors exactly as `build.rs`
//!   validates the stage file (`BoucWen::with_input_range`, `StaticModel::new`/`asymmetric`,
//!   `Compensator::new`, `effects::Effects::new`, `Servo::new`, with their plausibility bounds,
//!   and `IoChain::check_limits`: the window inside what the DAC and amplifier drive, a finite
//!   slew limit that leaves a full-window move a few ticks), plus the first-loading gain the
//!   baseline needs; the loop rate and the whole io chain (DAC, amplifier, ADC and sensor ranges
//!   and gains) must be the firmware's. Accepted: swapped in with [`TwoAxisLoop::set_settings`]
//!   (state kept). Refused: nothing changes, the answer carries the core's reason and the axis,
//!   and every refusal is counted in `refused_uploads`.
//! - A request whose sequence number is not ahead of the last one handled is not run: it is
//!   answered with `Replayed { next }` and counted in `replayed_requests` (see [`piezo_link`]).
//! - `Control(mode)`: switches the control mode bumplessly between two ticks
//!   ([`TwoAxisLoop::set_control_mode`]); refused with the axis when a mode with feedback finds
//!   no servo. An upload without a servo is refused while a feedback mode runs.
//! - `LearnedClear`, `LearnedAppend`: the learned voltage table (one `[u_x, u_y]` per wave table
//!   entry, [`TABLE_CAPACITY`]). `Control(Learned | LearnedFeedback)` plays it with the wave
//!   table from the tick after ([`TwoAxisLoop::set_learned_mode`]) and makes it the mode of
//!   `Track`, which then takes table programs only. Both check the table first
//!   ([`crate::reference::ReferenceGenerator::check_learned`]: the wave table's length, every
//!   entry finite and inside each axis's window, every step within the slew limit at the entry
//!   spacing, the wrap of a repeating table) and are refused with the first entry, axis and
//!   limit that fail ([`RefusalKind::Learned`]); a refused table is never played. While the loop
//!   plays it, requests that would change either table, and an upload whose limits the table
//!   fails, are refused. Frames carry the pass over the wave table (`trial`).
//! - `Rearm`, `InjectOverrun` (the next tick is told the previous one overran: a fault drill),
//!   `Frames { decimation }`, `Status`, `Shutdown`.
//!
//! # Frames
//! With frames on, every frame the loop produces is encoded into the transmit buffer
//! ([`TX_CAPACITY`] bytes) if it fits with room to spare for a response; otherwise it is dropped
//! and counted, and the receiver sees the gap in the frame numbers. With frames off they are
//! discarded (the numbers keep counting); a frame produced while frames were on and held back by
//! a reply still goes out.

use heapless::String;
use piezo_core::ServoMode;
use piezo_link::{
    truncated, AxisModel, Control, Counters, Decoder, EnvelopeStatus, Frame, ModelSet,
    OnTargetStatus, Packet, Program, Refusal, RefusalKind, Request, Response, SequenceChecker,
    Setpoints, Status, Tracking, Uplink, Wave, MAX_FRAME, PROTOCOL_VERSION, REASON_BYTES,
    VERSION_BYTES,
};

use crate::control::TrackingStats;
use crate::converter::DacWrite;
use crate::params;
use crate::reference::{LearnedError, STREAM_CAPACITY, TABLE_CAPACITY};
use crate::xy_loop::{
    Axis, AxisConfig, ConfigError, ControlError, Feedforward, Mode, PositionSensor, TickReport,
    TwoAxisLoop, XyIo,
};

/// [`SETTLE_S`] in ticks of the loop's period.
fn settle_ticks(lp: &TwoAxisLoop) -> u32 {
    let ticks = libm::roundf(SETTLE_S / lp.sample_period_s());
    if ticks.is_finite() && ticks >= 0.0 {
        ticks.min(u32::MAX as f32) as u32
    } else {
        0
    }
}

/// The [`ModelSet::fingerprint`] of the set built into the image ([`params`]): the boot log's
/// and the first `Status`'s.
pub fn built_in_fingerprint() -> u32 {
    piezo_link::fingerprint(
        params::LOOP_RATE_HZ,
        &params::IO,
        &params::AXES.each_ref().map(AxisModel::from_params),
    )
}

/// Bytes of the transmit buffer.
pub const TX_CAPACITY: usize = 8 * MAX_FRAME;
/// Time after a `Track` before the tracking error counts (the start-up transient) \[s\]: 1 000
/// ticks at 10 kHz, 2 000 at 20 kHz.
pub const SETTLE_S: f32 = 0.1;

/// The link endpoint around the loop.
pub struct Session {
    /// The loop (public: the image ticks it through [`Session::tick`] and reads its state).
    pub lp: TwoAxisLoop,
    /// The control mode of `Track`.
    control: Control,
    tick_cycles_max: u32,
    inject_overrun: bool,
    decoder: Decoder,
    requests: SequenceChecker,
    tx: TxRing<TX_CAPACITY>,
    tx_sequence: u32,
    frame_decimation: u32,
    /// The link's counters (frames, requests, uploads); the loop keeps its own.
    link: Counters,
    tracking: [TrackingStats; 2],
    previous_reference_m: [f32; 2],
    settle_left: u32,
    last: Option<TickReport>,
    version: String<VERSION_BYTES>,
    fnv1a32: u32,
    /// The running set's [`ModelSet::fingerprint`].
    fingerprint: u32,
    shutdown: bool,
    /// A [`Reply`] has been taken and its bytes not yet queued: the tick leaves its frames in
    /// the loop's frame queue meanwhile, so that the reply keeps its packet number's place.
    reply_out: bool,
}

/// Frames the tick encodes at most per tick: one produced (decimation 1) and one of a backlog
/// left while a [`Reply`] was being encoded, so a backlog drains one per tick.
pub const FRAMES_PER_TICK: usize = 2;

/// The answer to a request, taken out of the session under its lock by [`Session::answer`]:
/// the response (a copy of the state it reports, e.g. `Status`) and the packet number reserved
/// for it. Encoded outside the lock ([`Reply::encode`]) and queued under it
/// ([`Session::queue_reply`]), so that the lock is held for the request's effect and a copy, not
/// for the encoding (postcard, CRC-32, COBS: ≈ 6 800 core cycles for a 102-byte status answer).
#[derive(Clone, Debug, PartialEq)]
pub struct Reply {
    packet: u32,
    request: u32,
    response: Response,
}

impl Reply {
    /// The packet number the reply goes out under.
    pub fn packet(&self) -> u32 {
        self.packet
    }

    /// The response.
    pub fn response(&self) -> &Response {
        &self.response
    }

    /// Encodes the reply's packet (`{packet, Uplink::Response {request, response}}`, as
    /// [`piezo_link::encode`]) into `out`; its length, or `None` if it does not fit (no response
    /// is longer than [`MAX_FRAME`]: the link's tests check every message).
    pub fn encode(&self, out: &mut [u8; MAX_FRAME]) -> Option<usize> {
        let packet = Packet {
            sequence: self.packet,
            body: Uplink::Response {
                request: self.request,
                response: self.response.clone(),
            },
        };
        piezo_link::encode(&packet, out).ok()
    }
}

/// A reason in words, cut to the link's size.
fn reason(args: core::fmt::Arguments<'_>) -> String<REASON_BYTES> {
    struct Cut(String<REASON_BYTES>);
    impl core::fmt::Write for Cut {
        fn write_str(&mut self, s: &str) -> core::fmt::Result {
            for c in s.chars() {
                if self.0.push(c).is_err() {
                    break;
                }
            }
            Ok(())
        }
    }
    let mut cut = Cut(String::new());
    let _ = core::fmt::write(&mut cut, args);
    cut.0
}

fn refused(kind: RefusalKind, axis: Option<u8>, why: core::fmt::Arguments<'_>) -> Response {
    Response::Refused(Refusal {
        kind,
        axis,
        reason: reason(why),
    })
}

/// An upload's axis checked against the firmware's chain and built by the core, as the build does.
fn axis_config(m: &AxisModel) -> Result<AxisConfig, ConfigError> {
    let p = m
        .params(params::SAMPLE_PERIOD_S)
        .map_err(ConfigError::Core)?;
    p.check_chain(&params::IO, params::SAMPLE_PERIOD_S)
        .map_err(ConfigError::Core)?;
    AxisConfig::from_params(&p, params::SAMPLE_PERIOD_S)
}

/// A request ready for [`Session::apply`]: an upload already validated.
#[allow(clippy::large_enum_variant)] // moved once per request, never stored in bulk
pub enum Prepared {
    /// Any request but an upload.
    Request(Request),
    /// An upload with its axes validated.
    Upload(PreparedUpload),
}

/// An uploaded set and the outcome of its validation.
pub struct PreparedUpload {
    /// The set as received.
    pub set: ModelSet,
    /// Both axes' loop settings, or the first axis the core refused and why.
    pub axes: Result<[AxisConfig; 2], (usize, ConfigError)>,
    /// The set's [`ModelSet::fingerprint`] (postcard and FNV-1a over the whole set: computed
    /// here, outside the board's lock).
    pub fingerprint: u32,
}

/// The part of handling a request that does not need the loop: an upload's validation by the
/// core's constructors (and the first-loading sweep of its baseline gain), which takes several
/// loop periods on the Cortex-M4F, and its fingerprint. Pure: it reads only the built-in loop period.
pub fn prepare(request: Request) -> Prepared {
    match request {
        Request::Upload(set) => Prepared::Upload(prepare_upload(set)),
        other => Prepared::Request(other),
    }
}

fn prepare_upload(set: ModelSet) -> PreparedUpload {
    let config = |i: usize| axis_config(&set.axes[i]).map_err(|e| (i, e));
    let axes = config(0).and_then(|x| config(1).map(|y| [x, y]));
    let fingerprint = set.fingerprint();
    PreparedUpload {
        set,
        axes,
        fingerprint,
    }
}

/// The refusal of a learned voltage table that fails its check, `what` saying when.
fn learned_refusal(what: &str, e: LearnedError) -> Response {
    let name = |axis: usize| ["x", "y"][axis & 1];
    let axis = |axis: usize| Some((axis & 1) as u8);
    match e {
        LearnedError::Length { learned, wave } => refused(
            RefusalKind::Learned,
            None,
            format_args!(
                "{what}: the learned table has {learned} entries, the wave table {wave}: one per wave table entry"
            ),
        ),
        LearnedError::NotFinite { entry, axis: a } => refused(
            RefusalKind::Learned,
            axis(a),
            format_args!(
                "{what}: learned table entry {entry}, {}: not a finite voltage",
                name(a)
            ),
        ),
        LearnedError::Window {
            entry,
            axis: a,
            value_v,
            window_v,
        } => refused(
            RefusalKind::Learned,
            axis(a),
            format_args!(
                "{what}: learned table entry {entry}, {}: {value_v} V outside the window [{}, {}] V",
                name(a),
                window_v[0],
                window_v[1]
            ),
        ),
        LearnedError::Slew {
            entry,
            axis: a,
            step_v,
            limit_v,
            ticks_per_entry,
        } => refused(
            RefusalKind::Learned,
            axis(a),
            format_args!(
                "{what}: learned table entry {entry}{}, {}: step {step_v} V over the slew limit's {limit_v} V at {ticks_per_entry} ticks per entry",
                if entry == 0 { " (wrap)" } else { "" },
                name(a)
            ),
        ),
    }
}

/// `mode NAME`, as refusals name a control mode.
fn mode_name(control: Control) -> String<24> {
    let mut name = String::new();
    let _ = name.push_str("mode ");
    let _ = name.push_str(control.name());
    name
}

/// The refusal of a control mode.
fn control_refusal(control: Control, e: ControlError) -> Response {
    match e {
        ControlError::NoServo(axis) => {
            let name = ["x", "y"][axis.index()];
            refused(
                RefusalKind::Program,
                Some(axis.index() as u8),
                format_args!(
                    "{} needs a servo: the running set has no [{name}.servo]",
                    control.name()
                ),
            )
        }
        ControlError::NotTable => refused(
            RefusalKind::Learned,
            None,
            format_args!(
                "{} plays the wave table: track a table program first",
                control.name()
            ),
        ),
        ControlError::Learned(e) => learned_refusal(mode_name(control).as_str(), e),
    }
}

/// The refusal of a request that would change a table the loop plays.
fn playing_refusal() -> Response {
    refused(
        RefusalKind::Learned,
        None,
        format_args!(
            "the loop plays the learned table with the wave table: switch the control mode first"
        ),
    )
}

fn config_refusal(axis: usize, e: ConfigError) -> Response {
    let name = ["x", "y"][axis & 1];
    let axis = Some(axis as u8);
    match e {
        ConfigError::Core(e) => refused(RefusalKind::Model, axis, format_args!("{name}: {e}")),
        ConfigError::Limits(e) => refused(
            RefusalKind::Model,
            axis,
            format_args!("{name}.limits refused by the output guard: {e:?}"),
        ),
        ConfigError::Gain => refused(
            RefusalKind::Model,
            axis,
            format_args!("{name}: the model gives no stroke over the output window"),
        ),
    }
}

/// The set's loop rate and io chain against the firmware's (the chain is hardware: each field
/// must be the built-in one), or the refusal naming the first that differs.
fn chain_refusal(set: &ModelSet) -> Option<Response> {
    let (io, runs) = (&set.io, &params::IO);
    let differs = |what: &str, given: &dyn core::fmt::Debug, built: &dyn core::fmt::Debug| {
        refused(
            RefusalKind::Chain,
            None,
            format_args!(
                "{what} is {given:?}, the firmware runs {built:?} (build it with this stage file)"
            ),
        )
    };
    if set.loop_rate_hz != params::LOOP_RATE_HZ {
        return Some(differs(
            "stage.loop_rate_hz",
            &set.loop_rate_hz,
            &params::LOOP_RATE_HZ,
        ));
    }
    let fields: [(&str, &dyn core::fmt::Debug, &dyn core::fmt::Debug, bool); 5] = [
        (
            "io.dac_range_v",
            &io.dac_range_v,
            &runs.dac_range_v,
            io.dac_range_v == runs.dac_range_v,
        ),
        (
            "io.amplifier_gain_v_per_v",
            &io.amplifier_gain_v_per_v,
            &runs.amplifier_gain_v_per_v,
            io.amplifier_gain_v_per_v == runs.amplifier_gain_v_per_v,
        ),
        (
            "io.adc_range_v",
            &io.adc_range_v,
            &runs.adc_range_v,
            io.adc_range_v == runs.adc_range_v,
        ),
        (
            "io.sensor_range_v",
            &io.sensor_range_v,
            &runs.sensor_range_v,
            io.sensor_range_v == runs.sensor_range_v,
        ),
        (
            "io.sensor_m_per_v",
            &io.sensor_m_per_v,
            &runs.sensor_m_per_v,
            io.sensor_m_per_v == runs.sensor_m_per_v,
        ),
    ];
    fields
        .into_iter()
        .find(|f| !f.3)
        .map(|(what, given, built, _)| differs(what, given, built))
}

impl Session {
    /// A session around `lp`, which runs the parameter set `version` (FNV-1a of its stage file
    /// `fnv1a32`, content [`ModelSet::fingerprint`] `fingerprint`: [`built_in_fingerprint`] for
    /// the image's own set). Frames start off.
    pub fn new(lp: TwoAxisLoop, version: &str, fnv1a32: u32, fingerprint: u32) -> Self {
        let settle_left = settle_ticks(&lp);
        Self {
            control: Control::new(lp.control_mode(), lp.feedforward() == Feedforward::Learned),
            tick_cycles_max: 0,
            lp,
            inject_overrun: false,
            decoder: Decoder::new(),
            requests: SequenceChecker::default(),
            tx: TxRing::new(),
            tx_sequence: 0,
            frame_decimation: 0,
            link: Counters::default(),
            tracking: [TrackingStats::default(); 2],
            previous_reference_m: [f32::NAN; 2],
            settle_left,
            last: None,
            version: truncated(version),
            fnv1a32,
            fingerprint,
            shutdown: false,
            reply_out: false,
        }
    }

    /// Records the measured cost of a tick \[CPU cycles\] (the board's DWT cycle counter); the
    /// largest is reported by `Status`.
    pub fn note_tick_cycles(&mut self, cycles: u32) {
        self.tick_cycles_max = self.tick_cycles_max.max(cycles);
    }

    /// True once a `Shutdown` request was answered.
    pub fn shutdown_requested(&self) -> bool {
        self.shutdown
    }

    /// True if the transmit buffer has room for one more frame besides a response (the QEMU
    /// image waits for this before a tick while frames are on).
    pub fn has_room_for_frame(&self) -> bool {
        self.tx.room() >= 2 * MAX_FRAME
    }

    /// Bytes waiting to be sent.
    pub fn pending_tx(&self) -> usize {
        self.tx.len()
    }

    /// One tick of the loop (an injected overrun, if one was asked for, is passed on), then the
    /// tracking statistics and the frames.
    pub fn tick<D, S>(&mut self, io: &mut XyIo<D, S>, deadline_missed: bool) -> TickReport
    where
        D: DacWrite,
        S: PositionSensor,
    {
        let missed = deadline_missed || core::mem::take(&mut self.inject_overrun);
        let first_new = self.lp.frames.next_sequence();
        let report = self.lp.tick(io, missed);
        let trial = self.lp.reference.pass();
        let tracking = self.lp.feedforward() != Feedforward::OpenLoop;
        if tracking && report.mode == Mode::Running {
            if self.settle_left > 0 {
                self.settle_left -= 1;
            } else {
                for (i, stats) in self.tracking.iter_mut().enumerate() {
                    stats.push(report.measured_m[i] - self.previous_reference_m[i]);
                }
            }
        }
        self.previous_reference_m = report.reference_m;
        self.last = Some(report);
        if self.frame_decimation == 0 {
            // Frames off: this tick's frame goes; one produced while frames were on and held
            // back by a reply still goes out.
            self.lp.frames.discard_from(first_new);
        }
        if !self.reply_out {
            let mut batch = heapless::Vec::<Frame, FRAMES_PER_TICK>::new();
            self.lp.frames.drain_into(&mut batch);
            for f in &mut batch {
                f.trial = trial;
                if self.has_room_for_frame() && self.send(Uplink::Frame(*f)) {
                    self.link.frames_sent = self.link.frames_sent.saturating_add(1);
                } else {
                    self.link.frames_dropped = self.link.frames_dropped.saturating_add(1);
                }
            }
        }
        report
    }

    /// Takes received bytes; each complete request is prepared ([`prepare`]) and applied
    /// ([`Session::apply`]) at once, its response queued.
    pub fn receive(&mut self, bytes: &[u8]) {
        for &byte in bytes {
            match self.decoder.push::<Request>(byte) {
                None => {}
                Some(Ok(Packet { sequence, body })) => self.apply(sequence, prepare(body)),
                Some(Err(_)) => self.note_rejected_packet(),
            }
        }
    }

    /// Applies a request prepared by [`prepare`] (numbered `sequence` by the host) and queues
    /// its response. For a link that decodes and prepares outside the session (the board: an
    /// upload's validation then does not hold the loop), with [`Session::note_rejected_packet`]
    /// for packets its decoder refused.
    pub fn apply(&mut self, sequence: u32, prepared: Prepared) {
        let reply = self.answer(sequence, &prepared);
        let mut out = [0u8; MAX_FRAME];
        let n = reply.encode(&mut out);
        self.queue_reply(&reply, n.map(|n| &out[..n]));
    }

    /// Applies a request prepared by [`prepare`] (numbered `sequence` by the host), exactly as
    /// [`Session::apply`] does, and returns its reply to be encoded outside the session
    /// ([`Reply::encode`]) and queued with [`Session::queue_reply`]; until then the tick holds
    /// its frames back (in the loop's frame queue, [`crate::frames::FRAME_QUEUE_CAPACITY`]
    /// frames), so the reply goes out under the packet number it was given.
    /// `prepared` is borrowed: a request is not moved (copied) under the lock.
    pub fn answer(&mut self, sequence: u32, prepared: &Prepared) -> Reply {
        let response = self.respond(sequence, prepared);
        self.reply_out = true;
        Reply {
            packet: self.tx_sequence,
            request: sequence,
            response,
        }
    }

    /// Queues the encoded `bytes` of `reply` (from [`Session::answer`]) and lets the tick send
    /// frames again; false if they were not queued: `None` (not encoded), no room in the transmit
    /// buffer, or a reply whose packet number is no longer the next one (another reply went out
    /// first). A reply not queued is lost as a packet that did not fit always was (the host
    /// times out; its packet number is not used).
    pub fn queue_reply(&mut self, reply: &Reply, bytes: Option<&[u8]>) -> bool {
        self.reply_out = false;
        match bytes {
            Some(b) if reply.packet == self.tx_sequence => self.queue_packet(b),
            _ => false,
        }
    }

    fn respond(&mut self, sequence: u32, prepared: &Prepared) -> Response {
        let c = &mut self.link;
        c.requests = c.requests.saturating_add(1);
        match self.requests.admit(sequence) {
            Err(next) => {
                c.replayed_requests = c.replayed_requests.saturating_add(1);
                Response::Replayed { next }
            }
            Ok(missing) => {
                if missing > 0 {
                    c.request_gaps = c.request_gaps.saturating_add(1);
                }
                match prepared {
                    Prepared::Request(request) => self.handle(request),
                    Prepared::Upload(upload) => self.upload(upload),
                }
            }
        }
    }

    /// Counts a packet the link's decoder refused (COBS, CRC, length, body).
    pub fn note_rejected_packet(&mut self) {
        let c = &mut self.link;
        c.rejected_packets = c.rejected_packets.saturating_add(1);
    }

    /// Hands queued bytes to `put` until it refuses one (returns false); returns how many went.
    pub fn transmit(&mut self, put: impl FnMut(u8) -> bool) -> usize {
        self.tx.drain_with(put)
    }

    /// Encodes and queues one packet; false if it did not fit.
    fn send(&mut self, body: Uplink) -> bool {
        let mut out = [0u8; MAX_FRAME];
        let packet = Packet {
            sequence: self.tx_sequence,
            body,
        };
        let Ok(n) = piezo_link::encode(&packet, &mut out) else {
            return false;
        };
        self.queue_packet(&out[..n])
    }

    /// Queues one encoded packet numbered `tx_sequence`; false if it did not fit.
    fn queue_packet(&mut self, bytes: &[u8]) -> bool {
        if !self.tx.push_slice(bytes) {
            return false;
        }
        self.tx_sequence = self.tx_sequence.wrapping_add(1);
        true
    }

    /// A table program still running (held at its last entry or repeating) would play the
    /// entries of the next table as they arrive, in the last program's units (a track's metres
    /// as an excitation's volts): the reference holds where it is instead, until the next
    /// program starts. Before the first tick there is nothing to hold and nothing changes.
    fn hold_before_table_clear(&mut self) {
        if let Program::Table { .. } = self.lp.reference.program() {
            let last = self.lp.last_reference();
            if last.iter().all(|r| r.is_finite()) {
                self.lp.reference.set_program(Program::PerAxis(
                    last.map(|offset| Wave::Constant { offset }),
                ));
            }
        }
    }

    fn start(&mut self, program: Program, feedforward: Feedforward) -> Response {
        if let Program::Table {
            ticks_per_entry, ..
        } = program
        {
            if ticks_per_entry == 0 || self.lp.reference.table_len() == 0 {
                return refused(
                    RefusalKind::Program,
                    None,
                    format_args!(
                        "a table program needs ticks_per_entry >= 1 and a filled table ({} entries)",
                        self.lp.reference.table_len()
                    ),
                );
            }
        }
        self.lp.set_feedforward(feedforward);
        self.lp.reference.set_program(program);
        self.tracking = [TrackingStats::default(); 2];
        self.settle_left = settle_ticks(&self.lp);
        Response::Started {
            first_frame: self.lp.frames.next_sequence(),
        }
    }

    /// `Track` in a learned control mode: a table program whose learned table passes its check,
    /// played from its start; otherwise refused, nothing changed.
    fn start_learned(&mut self, program: Program) -> Response {
        let control = Control::new(self.control.servo_mode(), true);
        let Program::Table {
            ticks_per_entry,
            repeat,
        } = program
        else {
            return refused(
                RefusalKind::Learned,
                None,
                format_args!(
                    "the control mode {} plays the wave table: track a table program",
                    control.name()
                ),
            );
        };
        let limits = self.lp.learned_limits();
        if let Err(e) = self
            .lp
            .reference
            .check_learned(ticks_per_entry, repeat, &limits)
        {
            return learned_refusal(mode_name(control).as_str(), e);
        }
        self.start(program, Feedforward::Learned)
    }

    fn queue(&mut self, setpoints: &Setpoints, table: bool) -> Response {
        let reference = &mut self.lp.reference;
        let (held, capacity) = if table {
            if reference.table_append(setpoints).is_err() {
                return refused(
                    RefusalKind::Full,
                    None,
                    format_args!(
                        "the wave table holds {} of {TABLE_CAPACITY} entries: {} more do not fit",
                        reference.table_len(),
                        setpoints.len()
                    ),
                );
            }
            (reference.table_len(), TABLE_CAPACITY)
        } else {
            let room = STREAM_CAPACITY - 1 - reference.queued();
            if setpoints.len() > room {
                return refused(
                    RefusalKind::Full,
                    None,
                    format_args!(
                        "the stream queue has room for {room}, not {}",
                        setpoints.len()
                    ),
                );
            }
            for &s in setpoints {
                // Cannot fail: the room was checked above.
                let _ = reference.push_setpoint(s);
            }
            (reference.queued(), STREAM_CAPACITY - 1)
        };
        Response::Queued {
            held: held as u32,
            capacity: capacity as u32,
        }
    }

    /// Swaps in a set [`prepare`] validated, or says why not (nothing changed), counting every
    /// refusal.
    fn upload(&mut self, upload: &PreparedUpload) -> Response {
        let response = self.try_upload(upload);
        if matches!(response, Response::Refused(_)) {
            let c = &mut self.link;
            c.refused_uploads = c.refused_uploads.saturating_add(1);
        }
        response
    }

    fn try_upload(&mut self, upload: &PreparedUpload) -> Response {
        let set = &upload.set;
        if let Some(refusal) = chain_refusal(set) {
            return refusal;
        }
        if self.control.servo_mode().feedback() {
            if let Some(i) = set.axes.iter().position(|a| a.servo.is_none()) {
                let name = ["x", "y"][i & 1];
                return refused(
                    RefusalKind::Model,
                    Some(i as u8),
                    format_args!(
                        "{name}: no [{name}.servo] while the control mode is {}; switch to feedforward first",
                        self.control.name()
                    ),
                );
            }
        }
        let axes = match upload.axes {
            Ok(valid) => valid,
            Err((i, e)) => return config_refusal(i, e),
        };
        if let (
            Feedforward::Learned,
            Program::Table {
                ticks_per_entry,
                repeat,
            },
        ) = (self.lp.feedforward(), self.lp.reference.program())
        {
            let limits = axes.map(|a| a.learned_limits());
            if let Err(e) = self
                .lp
                .reference
                .check_learned(ticks_per_entry, repeat, &limits)
            {
                return learned_refusal("this set's limits", e);
            }
        }
        let settings = self.lp.settings().with_axes(axes);
        self.lp.set_settings(settings);
        self.version = set.version.clone();
        self.fnv1a32 = set.fnv1a32;
        self.fingerprint = upload.fingerprint;
        self.link.uploads = self.link.uploads.saturating_add(1);
        Response::Loaded {
            params_fnv1a32: set.fnv1a32,
            params_fingerprint: self.fingerprint,
        }
    }

    fn handle(&mut self, request: &Request) -> Response {
        match *request {
            Request::Status => Response::Status(self.status()),
            Request::Track(program) if self.control.learned() => self.start_learned(program),
            Request::Track(program) => {
                let ff = match self.control.servo_mode() {
                    ServoMode::Feedforward | ServoMode::FeedforwardFeedback => {
                        Feedforward::Compensator
                    }
                    ServoMode::OpenLoop | ServoMode::Feedback => Feedforward::Linear,
                };
                self.start(program, ff)
            }
            Request::Excite(program) => self.start(program, Feedforward::OpenLoop),
            Request::TableClear
            | Request::TableAppend(_)
            | Request::LearnedClear
            | Request::LearnedAppend(_)
                if self.lp.feedforward() == Feedforward::Learned =>
            {
                playing_refusal()
            }
            Request::TableClear => {
                self.hold_before_table_clear();
                self.lp.reference.table_clear();
                Response::Queued {
                    held: 0,
                    capacity: TABLE_CAPACITY as u32,
                }
            }
            Request::TableAppend(ref setpoints) => self.queue(setpoints, true),
            Request::Stream(ref setpoints) => self.queue(setpoints, false),
            Request::LearnedClear => {
                self.lp.reference.learned_clear();
                Response::Queued {
                    held: 0,
                    capacity: TABLE_CAPACITY as u32,
                }
            }
            Request::LearnedAppend(ref entries) => {
                let reference = &mut self.lp.reference;
                match reference.learned_append(entries) {
                    Ok(()) => Response::Queued {
                        held: reference.learned_len() as u32,
                        capacity: TABLE_CAPACITY as u32,
                    },
                    Err(_) => refused(
                        RefusalKind::Full,
                        None,
                        format_args!(
                            "the learned table holds {} of {TABLE_CAPACITY} entries: {} more do not fit",
                            reference.learned_len(),
                            entries.len()
                        ),
                    ),
                }
            }
            Request::Control(control) => {
                let mode = control.servo_mode();
                let switched = if control.learned() {
                    self.lp.set_learned_mode(mode.feedback())
                } else {
                    self.lp.set_control_mode(mode)
                };
                match switched {
                    Ok(()) => {
                        self.control = control;
                        Response::Done
                    }
                    Err(e) => control_refusal(control, e),
                }
            }
            Request::Rearm => {
                self.lp.rearm();
                self.settle_left = settle_ticks(&self.lp);
                Response::Done
            }
            Request::InjectOverrun => {
                self.inject_overrun = true;
                Response::Done
            }
            // Not on a link's path: `prepare` makes an upload a `Prepared::Upload`.
            Request::Upload(ref set) => self.upload(&prepare_upload(set.clone())),
            Request::Frames { decimation } => {
                if decimation > 0 {
                    self.lp.frames.set_decimation(decimation);
                }
                self.frame_decimation = decimation;
                Response::Streaming {
                    decimation,
                    next_frame: self.lp.frames.next_sequence(),
                }
            }
            Request::Shutdown => {
                self.shutdown = true;
                Response::Done
            }
        }
    }

    /// The state as the link reports it.
    pub fn status(&self) -> Status {
        let link = &self.link;
        let loop_counters = self.lp.counters();
        let counters = Counters {
            frames_dropped: loop_counters
                .frames_dropped
                .saturating_add(link.frames_dropped),
            frames_sent: link.frames_sent,
            requests: link.requests,
            rejected_packets: link.rejected_packets,
            request_gaps: link.request_gaps,
            replayed_requests: link.replayed_requests,
            uploads: link.uploads,
            refused_uploads: link.refused_uploads,
            ..loop_counters
        };
        let last = self.last;
        Status {
            protocol: PROTOCOL_VERSION,
            params_fingerprint: self.fingerprint,
            params_fnv1a32: self.fnv1a32,
            params_version: self.version.clone(),
            loop_rate_hz: params::LOOP_RATE_HZ,
            mode: self.lp.mode(),
            feedforward: self.lp.feedforward(),
            control: self.control,
            tick_cycles_max: self.tick_cycles_max,
            counters,
            tracking: self.tracking.map(|s| Tracking {
                count: s.count(),
                rms_m: s.rms_m(),
                max_abs_m: s.max_abs_m(),
            }),
            applied_v: last.map_or(
                [
                    self.lp.guard(Axis::X).last_safe_volts(),
                    self.lp.guard(Axis::Y).last_safe_volts(),
                ],
                |r| r.applied_v,
            ),
            measured_m: last.map_or([f32::NAN; 2], |r| r.measured_m),
            frame_decimation: self.frame_decimation,
            next_frame: self.lp.frames.next_sequence(),
            table: [self.lp.reference.table_len() as u32, TABLE_CAPACITY as u32],
            stream: [
                self.lp.reference.queued() as u32,
                (STREAM_CAPACITY - 1) as u32,
            ],
            learned: [
                self.lp.reference.learned_len() as u32,
                TABLE_CAPACITY as u32,
            ],
            envelope: Axis::ALL.map(|a| {
                let envelope = self.lp.settings().axes[a.index()].envelope();
                EnvelopeStatus {
                    known: envelope.is_some(),
                    feedback_only: envelope
                        .is_some_and(|e| e.policy() == piezo_core::EnvelopePolicy::FeedbackOnly),
                    outside: self.lp.envelope_outside(a),
                    counts: self.lp.envelope_counts(a),
                    feedback_only_ticks: self.lp.servo_alone_ticks(a),
                }
            }),
            on_target: Axis::ALL.map(|a| {
                let state = self.lp.on_target(a);
                let band = self.lp.settings().axes[a.index()].on_target();
                let settle = state.settle_ticks();
                OnTargetStatus {
                    on_target: state.on_target(),
                    ticks_since_change: state.ticks_since_change(),
                    settle_ticks: (settle != piezo_core::on_target::NOT_SETTLED).then_some(settle),
                    tolerance_m: band.tolerance_m,
                    ticks: band.ticks,
                }
            }),
        }
    }
}

mod lock_hold;
mod tx_ring;
pub use lock_hold::{LockHolds, RequestKind};
use tx_ring::TxRing;

#[cfg(test)]
mod tests;
