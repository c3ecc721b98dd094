//! `host-sim link`: drives the firmware over its command link ([`piezo_link`]: postcard packets
//! with CRC-32, COBS-framed, numbered) on a TCP port (the QEMU image, `firmware/run-qemu.sh
//! --link PORT`) or a serial device (the board).
//!
//! Signals: `excite` and `track` take a signal in `simulate`'s grammar ([`SignalSpec`]; volts
//! for `excite`, metres for `track`), sample it at the loop rate every m ticks into the
//! firmware's wave table (m the smallest that fits the duration into the table; the firmware
//! interpolates linearly between entries), start it, and record every frame the loop produces
//! (one every `--decimation` ticks) until the duration is covered. The record is the CSV that
//! `identify` reads: `t_s, ux_V, uy_V, x_m, y_m` (and `rx_m, ry_m` for `track`), its rows by
//! [`crate::record`]'s rule (each voltage with the reading that answers it, the next frame's),
//! the rule `host-sim capture` follows too; t_s from the frame numbers, so a gap would show as a
//! jump (gaps are counted and refused unless `--allow-gaps`, which adds a `segment_1` column).
//!
//! Every read has a timeout (`--timeout`); a request that is not answered in time is an error.
//! `--wait S` waits for a firmware that is still starting (QEMU not yet listening, or an image
//! whose link drops the bytes it receives before it is up): it connects and asks for the status
//! again, every 0.2 s with a 1 s answer timeout per try, until one is answered or S seconds have
//! passed, and then runs the command on that connection.
//! Every request starts with a 0x00 delimiter (`piezo_link::encode_request`), so half a frame a
//! previous client left in the firmware's decoder does not swallow it. The client starts counting
//! its requests at 0; the firmware answers a number it already handled with `Replayed { next }`,
//! and the client takes `next` and sends the request again (once).
//!
//! A device's answers are checked before they size anything: the loop rate, the wave table's
//! capacity and the number of frames a run asks for are bounded ([`MAX_LOOP_RATE_HZ`],
//! [`MAX_TABLE_ENTRIES`], [`MAX_RECORD_FRAMES`]); a value outside is an error naming the field
//! and the value, never a panic or an allocation the size of the device's number.

use crate::csv::Table;
use crate::record::{record, AxisChoice, LoopFrame, Record, RecordTable, TimeBase};
use crate::signal::{SignalSpec, SIGNAL_HELP};
use piezo_link::{
    AxisModel, Control, DecodeError, Decoder, Frame, ModelSet, Packet, Program, Request, Response,
    SequenceChecker, Status, Uplink, MAX_FRAME, PROTOCOL_VERSION, SETPOINT_CHUNK,
};
use serde::Serialize;
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::sync::mpsc::{self, Receiver, RecvTimeoutError};
use std::time::{Duration, Instant};

/// Highest loop rate accepted from a device \[Hz\] (the firmware runs at most 20 kHz).
pub const MAX_LOOP_RATE_HZ: f64 = 1e6;
/// Largest wave table accepted from a device \[entries\] (the firmware holds 2 048).
pub const MAX_TABLE_ENTRIES: u32 = 1 << 20;
/// Most frames one recording keeps (28 bytes each in memory: 1.9 GB).
pub const MAX_RECORD_FRAMES: u64 = 1 << 26;

/// The parts of a device's status a run is sized by, checked: a finite loop rate in
/// (0, [`MAX_LOOP_RATE_HZ`]] and a table capacity in [2, [`MAX_TABLE_ENTRIES`]].
pub fn run_limits(status: &Status) -> crate::Result<(f64, u32)> {
    let rate = f64::from(status.loop_rate_hz);
    if !(rate > 0.0 && rate <= MAX_LOOP_RATE_HZ) {
        return Err(crate::Error::Link(format!(
            "the device reports loop_rate_hz = {:?}: expected a finite rate in (0, {MAX_LOOP_RATE_HZ}] Hz",
            status.loop_rate_hz
        )));
    }
    let capacity = status.table[1];
    if !(2..=MAX_TABLE_ENTRIES).contains(&capacity) {
        return Err(crate::Error::Link(format!(
            "the device reports a wave table of {capacity} entries (table[1]): expected 2 to {MAX_TABLE_ENTRIES}"
        )));
    }
    Ok((rate, capacity))
}

/// Help after `host-sim link --help`.
pub const HELP: &str = "Connect: tcp:HOST:PORT (the QEMU image: firmware/run-qemu.sh --link PORT ELF) or serial:PATH (the board's USB serial device).\n\
Commands: status (JSON: protocol, params_fingerprint and params_fnv1a32 in hex, params_version, mode, feedforward, control, counters with the output guard's interventions per axis and cause, guard_interventions, tracking, on_target, ...), excite, track, step, upload, rearm, control, inject-overrun, learn, shutdown.\n\
excite --signal SPEC (volts, compensator off) and track --signal SPEC (metres) write --record CSV (t_s, ux_V, uy_V, x_m, y_m[, rx_m, ry_m]) that identify reads with --u ux_V,uy_V --y x_m,y_m.";

/// Arguments of `link`.
#[derive(Debug, clap::Args)]
#[command(after_help = format!("{HELP}\n\n{SIGNAL_HELP}"))]
pub struct LinkArgs {
    /// tcp:HOST:PORT or serial:PATH.
    #[arg(long)]
    pub connect: String,
    /// Longest wait for any answer (s).
    #[arg(long, default_value_t = 10.0)]
    pub timeout: f64,
    /// Wait up to this long (s) for the firmware to answer a status request before the command
    /// (retries the connection and the request; for an image that is still starting).
    #[arg(long, default_value_t = 0.0)]
    pub wait: f64,
    /// What to do.
    #[command(subcommand)]
    pub command: LinkCommand,
}

/// `link` subcommands.
#[derive(Debug, clap::Subcommand)]
pub enum LinkCommand {
    /// Prints the firmware's state as one JSON object.
    Status,
    /// Open-loop excitation in stack volts (compensator off); records the answer.
    Excite(RunArgs),
    /// Tracks a reference in metres in the control mode set by `control` (feedforward unless
    /// switched); records it.
    Track(RunArgs),
    /// Sends a stage file's model; exits non-zero with the core's reason if it is refused.
    Upload {
        /// Stage file (TOML).
        #[arg(long)]
        params: PathBuf,
    },
    /// Leaves the safe state.
    Rearm,
    /// The control mode of `track`, switched bumplessly: open-loop (the linear baseline),
    /// feedforward (the compensator), feedback (the servo alone), feedforward+feedback; learned
    /// and learned+feedback play the learned voltage table with the wave table (while it tracks
    /// a table program; `learn` loads one). The modes with feedback need
    /// `[x.servo]`/`[y.servo]` in the running set.
    Control {
        /// open-loop | feedforward | feedback | feedforward+feedback | learned | learned+feedback.
        #[arg(value_parser = ["open-loop", "feedforward", "feedback", "feedforward+feedback", "learned", "learned+feedback"])]
        mode: String,
    },
    /// Tells the next tick that the previous one overran (a fault drill: the safe state).
    InjectOverrun,
    /// Iterative learning control over the link: learns a voltage table for a periodic
    /// reference, trial by trial, and leaves the best one playing.
    Learn(crate::link_learn::LinkLearnArgs),
    /// Moves to a position (metres) and waits until both axes are on target; prints the
    /// settling time (JSON).
    Step(crate::link_step::StepArgs),
    /// Ends the firmware's run (the QEMU image exits).
    Shutdown,
}

/// Arguments of `excite` and `track`.
#[derive(Debug, clap::Args)]
pub struct RunArgs {
    /// Signal (simulate's grammar): volts for excite, metres for track.
    #[arg(long)]
    pub signal: String,
    /// Length (s).
    #[arg(long)]
    pub duration: f64,
    /// CSV to write.
    #[arg(long)]
    pub record: PathBuf,
    /// One frame every this many ticks (1: each reading paired with the voltage it answers).
    #[arg(long, default_value_t = 1)]
    pub decimation: u32,
    /// Write the record even if frames were lost (t_s stays true; the gaps are reported).
    #[arg(long)]
    pub allow_gaps: bool,
    /// Figure of the record (`.svg` or `.png`): track: reference and sensor, commanded voltage
    /// and tracking error (sensor − reference) per axis; excite: commanded voltage, sensor and
    /// the loop sensor against voltage per axis.
    #[arg(long)]
    pub plot: Option<PathBuf>,
}

/// Puts a serial device in raw mode without echo (`stty -F PATH raw -echo`): the terminal's
/// default line handling would echo bytes back and rewrite newlines inside the packets. A path
/// that is not a terminal (a pipe, a file) is left as it is.
fn raw_mode(path: &str) -> crate::Result<()> {
    let out = std::process::Command::new("stty")
        .args(["-F", path, "raw", "-echo"])
        .output()
        .map_err(|e| crate::Error::Link(format!("stty (to set raw mode): {e}")))?;
    let err = String::from_utf8_lossy(&out.stderr);
    if out.status.success() || err.contains("Inappropriate ioctl") || err.contains("not a tty") {
        Ok(())
    } else {
        Err(crate::Error::Link(format!(
            "stty -F {path} raw -echo: {}",
            err.trim()
        )))
    }
}

/// The error for a firmware that speaks link protocol `theirs`.
fn protocol_error(theirs: u16) -> crate::Error {
    crate::Error::Link(format!(
        "the firmware speaks link protocol {theirs}, this host-sim {PROTOCOL_VERSION}: build both from one commit"
    ))
}

/// A connection to the firmware: numbered requests, answers matched by number, frames kept.
pub struct Client {
    writer: Box<dyn Write + Send>,
    bytes: Receiver<Vec<u8>>,
    pending: std::collections::VecDeque<u8>,
    decoder: Decoder,
    /// The bytes of the frame the decoder collects (to read a refused status's version).
    raw: Vec<u8>,
    sequence: u32,
    timeout: Duration,
    /// Gaps in the firmware's packet numbers.
    pub packets: SequenceChecker,
    /// Frames received since the last [`Client::take_frames`].
    frames: Vec<Frame>,
    /// Frames refused (COBS, CRC, body).
    pub rejected: u32,
    /// The TCP connection, shut down when the client is dropped (its reader thread holds a
    /// clone, which alone would keep it open: QEMU serves one connection at a time).
    tcp: Option<std::net::TcpStream>,
}

impl Drop for Client {
    fn drop(&mut self) {
        if let Some(stream) = &self.tcp {
            let _ = stream.shutdown(std::net::Shutdown::Both);
        }
    }
}

/// A recorded run.
#[derive(Debug, Clone, Serialize)]
pub struct Recording {
    /// Loop rate \[Hz\].
    pub loop_rate_hz: f64,
    /// Ticks per frame.
    pub decimation: u32,
    /// Number of the first frame.
    pub first_frame: u32,
    /// Frames, in order.
    #[serde(skip)]
    pub frames: Vec<Frame>,
    /// Gaps in the frame numbers, and frames lost in them.
    pub gaps: u32,
    /// Frames lost in the gaps.
    pub lost: u32,
    /// Wave table: ticks per entry, entries.
    pub table: [u32; 2],
}

impl Client {
    /// Connects to `tcp:HOST:PORT` or `serial:PATH`.
    pub fn connect(spec: &str, timeout: Duration) -> crate::Result<Self> {
        let mut tcp = None;
        let (reader, writer): (Box<dyn Read + Send>, Box<dyn Write + Send>) =
            if let Some(address) = spec.strip_prefix("tcp:") {
                let stream = std::net::TcpStream::connect(address)
                    .map_err(|e| crate::Error::Link(format!("--connect {spec}: {e}")))?;
                let _ = stream.set_nodelay(true);
                let reader = stream.try_clone().map_err(crate::Error::from)?;
                tcp = Some(stream.try_clone().map_err(crate::Error::from)?);
                (Box::new(reader), Box::new(stream))
            } else if let Some(path) = spec.strip_prefix("serial:") {
                raw_mode(path).map_err(|e| crate::Error::Link(format!("--connect {spec}: {e}")))?;
                let file = std::fs::OpenOptions::new()
                    .read(true)
                    .write(true)
                    .open(path)
                    .map_err(|e| crate::Error::Link(format!("--connect {spec}: {e}")))?;
                let reader = file.try_clone().map_err(crate::Error::from)?;
                (Box::new(reader), Box::new(file))
            } else {
                return Err(crate::Error::Link(format!(
                    "--connect {spec}: give tcp:HOST:PORT or serial:PATH"
                )));
            };
        // A reader thread, so that every wait has a timeout (a tty read has none in std).
        let (tx, rx) = mpsc::channel();
        std::thread::spawn(move || {
            let mut reader = reader;
            let mut buffer = [0u8; 4096];
            while let Ok(n) = reader.read(&mut buffer) {
                if n == 0 || tx.send(buffer[..n].to_vec()).is_err() {
                    break;
                }
            }
        });
        Ok(Self {
            writer,
            bytes: rx,
            pending: Default::default(),
            decoder: Decoder::new(),
            raw: Vec::new(),
            sequence: 0,
            timeout,
            packets: SequenceChecker::default(),
            frames: Vec::new(),
            rejected: 0,
            tcp,
        })
    }

    /// Connects as [`Client::connect`] and waits up to `wait` for the firmware to answer a status
    /// request: each try connects, asks with an answer timeout of at most 1 s, and on failure
    /// drops the connection and tries again 0.2 s later. The error after `wait` names the last
    /// failure. The client returned waits `timeout` for every later answer.
    pub fn connect_waiting(spec: &str, timeout: Duration, wait: Duration) -> crate::Result<Self> {
        let deadline = Instant::now() + wait;
        let per_try = timeout.min(Duration::from_secs(1));
        loop {
            let last = match Client::connect(spec, per_try) {
                Ok(mut client) => match client.status() {
                    Ok(_) => {
                        client.timeout = timeout;
                        return Ok(client);
                    }
                    Err(e) => e,
                },
                Err(e) => e,
            };
            if Instant::now() >= deadline {
                return Err(crate::Error::Link(format!(
                    "--connect {spec}: the firmware did not answer within --wait {:.1} s: {last}",
                    wait.as_secs_f64()
                )));
            }
            std::thread::sleep(Duration::from_millis(200));
        }
    }

    /// The next packet from the firmware, by `deadline`.
    /// A frame that does not parse but holds a status of another protocol version is that
    /// error.
    fn next(&mut self, deadline: Instant) -> crate::Result<Uplink> {
        loop {
            while let Some(byte) = self.pending.pop_front() {
                if byte != 0 && self.raw.len() < MAX_FRAME {
                    self.raw.push(byte);
                }
                match self.decoder.push::<Uplink>(byte) {
                    None => {}
                    Some(Ok(packet)) => {
                        self.raw.clear();
                        self.packets.accept(packet.sequence);
                        return Ok(packet.body);
                    }
                    Some(Err(e)) => {
                        self.rejected += 1;
                        let theirs = piezo_link::protocol_of_status(&self.raw);
                        self.raw.clear();
                        match theirs {
                            Some(p) if e == DecodeError::Body && p != PROTOCOL_VERSION => {
                                return Err(protocol_error(p))
                            }
                            _ => {}
                        }
                    }
                }
                if byte == 0 {
                    self.raw.clear();
                }
            }
            let left = deadline.saturating_duration_since(Instant::now());
            match self.bytes.recv_timeout(left) {
                Ok(chunk) => self.pending.extend(chunk),
                Err(RecvTimeoutError::Timeout) => {
                    return Err(crate::Error::Link(format!(
                        "no answer from the firmware within {:.1} s",
                        self.timeout.as_secs_f64()
                    )))
                }
                Err(RecvTimeoutError::Disconnected) => {
                    return Err(crate::Error::Link("the firmware closed the link".into()))
                }
            }
        }
    }

    /// Sends `request` and waits for its answer (frames that arrive meanwhile are kept). A
    /// `Replayed { next }` answer (the firmware handled this number already, e.g. from an earlier
    /// client) moves the count to `next` and sends the request once more.
    pub fn request(&mut self, request: Request) -> crate::Result<Response> {
        match self.send_once(&request)? {
            Response::Replayed { next } => {
                self.sequence = next;
                match self.send_once(&request)? {
                    Response::Replayed { next } => Err(crate::Error::Link(format!(
                        "the firmware refused request {} as already handled (next {next})",
                        self.sequence.wrapping_sub(1)
                    ))),
                    other => Ok(other),
                }
            }
            other => Ok(other),
        }
    }

    fn send_once(&mut self, request: &Request) -> crate::Result<Response> {
        let asked = self.sequence;
        self.sequence = self.sequence.wrapping_add(1);
        let mut out = [0u8; MAX_FRAME + 1];
        let n = piezo_link::encode_request(
            &Packet {
                sequence: asked,
                body: request,
            },
            &mut out,
        )
        .map_err(|e| crate::Error::Link(format!("cannot encode the request: {e}")))?;
        self.writer
            .write_all(&out[..n])
            .and_then(|()| self.writer.flush())
            .map_err(|e| crate::Error::Link(format!("link: {e}")))?;
        let deadline = Instant::now() + self.timeout;
        loop {
            match self.next(deadline)? {
                Uplink::Response { request, response } if request == asked => return Ok(response),
                Uplink::Response { .. } => {}
                Uplink::Frame(f) => self.frames.push(f),
            }
        }
    }

    /// Like [`Client::request`], a refusal as an error carrying the firmware's reason.
    pub fn expect(&mut self, request: Request) -> crate::Result<Response> {
        match self.request(request)? {
            Response::Refused(r) => Err(crate::Error::Link(format!(
                "refused ({:?}): {}",
                r.kind, r.reason
            ))),
            other => Ok(other),
        }
    }

    /// The firmware's state.
    pub fn status(&mut self) -> crate::Result<Status> {
        match self.request(Request::Status)? {
            Response::Status(s) if s.protocol != PROTOCOL_VERSION => {
                Err(protocol_error(s.protocol))
            }
            Response::Status(s) => Ok(s),
            other => Err(crate::Error::Link(format!(
                "unexpected answer to status: {other:?}"
            ))),
        }
    }

    /// The frames received so far (and forgets them).
    pub fn take_frames(&mut self) -> Vec<Frame> {
        std::mem::take(&mut self.frames)
    }

    /// Fills the wave table (`learned` false) or the learned voltage table with `entries`,
    /// in chunks; a refusal is an error with the firmware's reason.
    pub fn load_table(&mut self, entries: &[[f32; 2]], learned: bool) -> crate::Result<()> {
        let clear = if learned {
            Request::LearnedClear
        } else {
            Request::TableClear
        };
        self.expect(clear)?;
        for chunk in entries.chunks(SETPOINT_CHUNK) {
            let chunk = chunk.iter().copied().collect();
            self.expect(if learned {
                Request::LearnedAppend(chunk)
            } else {
                Request::TableAppend(chunk)
            })?;
        }
        Ok(())
    }

    /// The frames received so far and then as they arrive, up to and including the first for
    /// which `last` is true (each wait bounded by the timeout).
    pub fn frames_through(
        &mut self,
        mut last: impl FnMut(&Frame) -> bool,
    ) -> crate::Result<Vec<Frame>> {
        let mut out = Vec::new();
        for f in self.take_frames() {
            out.push(f);
            if last(&f) {
                return Ok(out);
            }
        }
        loop {
            let deadline = Instant::now() + self.timeout;
            if let Uplink::Frame(f) = self.next(deadline)? {
                out.push(f);
                if last(&f) {
                    return Ok(out);
                }
            }
        }
    }

    /// Waits for frames until `count` numbered from `first` on have arrived (earlier ones are
    /// dropped).
    fn collect(
        &mut self,
        first: u32,
        count: usize,
    ) -> crate::Result<(Vec<Frame>, SequenceChecker)> {
        let mut checker = SequenceChecker::default();
        checker.expect(first);
        // Grown as frames arrive: `count` comes from the device's numbers.
        let mut out = Vec::new();
        let ahead = |f: &Frame| f.sequence.wrapping_sub(first) < u32::MAX / 2;
        let keep = |f: Frame, out: &mut Vec<Frame>, checker: &mut SequenceChecker| {
            if ahead(&f) && out.len() < count {
                checker.accept(f.sequence);
                out.push(f);
            }
        };
        for f in self.take_frames() {
            keep(f, &mut out, &mut checker);
        }
        let mut deadline = Instant::now() + self.timeout;
        while out.len() < count {
            let before = out.len();
            match self.next(deadline)? {
                Uplink::Frame(f) => keep(f, &mut out, &mut checker),
                Uplink::Response { .. } => {}
            }
            if out.len() > before {
                deadline = Instant::now() + self.timeout;
            }
        }
        Ok((out, checker))
    }

    /// Plays `spec` for `duration_s` (open loop in volts if `excite`, else tracking in metres)
    /// and records it.
    pub fn run(
        &mut self,
        spec: &str,
        duration_s: f64,
        decimation: u32,
        excite: bool,
    ) -> crate::Result<Recording> {
        let parsed =
            SignalSpec::parse(spec).map_err(|e| crate::Error::Link(format!("--signal: {e}")))?;
        let signals = parsed
            .build(2)
            .map_err(|e| crate::Error::Link(format!("--signal: {e}")))?;
        if !(duration_s > 0.0 && duration_s.is_finite()) || decimation == 0 {
            return Err(crate::Error::Link(
                "--duration must be > 0 and --decimation >= 1".into(),
            ));
        }
        if let Some(w) = crate::simulate::csv_length_warning(&parsed, duration_s, "--duration ") {
            eprintln!("warning: {w}");
        }
        let status = self.status()?;
        let (rate, capacity) = run_limits(&status)?;
        let ticks = (duration_s * rate).round().max(1.0);
        if !(ticks / f64::from(decimation) <= MAX_RECORD_FRAMES as f64) {
            return Err(crate::Error::Link(format!(
                "--duration {duration_s} s at the device's {rate} Hz and --decimation {decimation} \
                 is more than {MAX_RECORD_FRAMES} frames"
            )));
        }
        let ticks = ticks as u64;
        let per_entry = ticks.div_ceil(u64::from(capacity - 1)).max(1);
        if per_entry > u64::from(u32::MAX) {
            return Err(crate::Error::Link(format!(
                "--duration {duration_s} s needs {per_entry} ticks per table entry, more than the link carries"
            )));
        }
        let entries = ticks / per_entry + 1;
        let table: Vec<[f32; 2]> = (0..entries)
            .map(|j| {
                let t = (j * per_entry) as f64 / rate;
                [signals[0].value(t) as f32, signals[1].value(t) as f32]
            })
            .collect();
        self.expect(Request::TableClear)?;
        for chunk in table.chunks(SETPOINT_CHUNK) {
            let setpoints = chunk.iter().copied().collect();
            self.expect(Request::TableAppend(setpoints))?;
        }
        self.expect(Request::Frames { decimation })?;
        let program = Program::Table {
            ticks_per_entry: per_entry as u32,
            repeat: false,
        };
        let request = if excite {
            Request::Excite(program)
        } else {
            Request::Track(program)
        };
        let first_frame = match self.expect(request)? {
            Response::Started { first_frame } => first_frame,
            other => {
                return Err(crate::Error::Link(format!(
                    "unexpected answer to a program: {other:?}"
                )))
            }
        };
        let count = (ticks / u64::from(decimation)) as usize;
        let (frames, checker) = self.collect(first_frame, count)?;
        self.expect(Request::Frames { decimation: 0 })?;
        self.take_frames();
        Ok(Recording {
            loop_rate_hz: rate,
            decimation,
            first_frame,
            frames,
            gaps: checker.gaps,
            lost: checker.lost,
            table: [per_entry as u32, entries as u32],
        })
    }
}

/// The control mode named `mode` (`open-loop`, `feedforward`, `feedback`,
/// `feedforward+feedback`, `learned`, `learned+feedback`).
pub fn control_mode(mode: &str) -> crate::Result<Control> {
    Control::ALL
        .into_iter()
        .chain(Control::LEARNED)
        .find(|c| c.name() == mode)
        .ok_or_else(|| crate::Error::Link(format!("unknown control mode {mode:?}")))
}

impl Recording {
    /// Refuses a record with gaps in its frame numbers unless `allow_gaps`.
    pub fn check_gaps(&self, allow_gaps: bool) -> crate::Result<()> {
        if self.gaps > 0 && !allow_gaps {
            return Err(crate::Error::Link(format!(
                "{} gaps ({} frames lost) in the record; --allow-gaps writes it anyway",
                self.gaps, self.lost
            )));
        }
        Ok(())
    }

    /// The frames as a record ([`crate::record`]'s rule: each voltage with the reading that
    /// answers it, the next frame's at decimation 1), t from the first frame of the run.
    pub fn record(&self) -> Record {
        let frames: Vec<LoopFrame> = self
            .frames
            .iter()
            .map(|f| LoopFrame::from_link(f, u64::from(f.sequence.wrapping_sub(self.first_frame))))
            .collect();
        record(
            &frames,
            TimeBase {
                loop_rate_hz: self.loop_rate_hz,
                decimation: self.decimation,
            },
        )
    }

    /// The record's columns as the CSV `identify` reads: `t_s, ux_V, uy_V, x_m, y_m` and, when
    /// tracking, `rx_m, ry_m`; `segment_1` when frames were lost.
    pub fn columns(&self, tracking: bool) -> RecordTable {
        self.record()
            .table(AxisChoice::Both, tracking, self.gaps > 0)
    }

    /// [`Self::columns`] as an f64 [`Table`].
    pub fn table(&self, tracking: bool) -> Table {
        self.columns(tracking).to_table()
    }
}

/// A track's figure scores its samples from this long after the start on \[s\]: the firmware's
/// own tracking statistics start there too (`piezo_firmware::session::SETTLE_S`).
pub const TRACK_SCORED_AFTER_S: f64 = 0.1;

/// Draws a link record (`t_s, ux_V, uy_V, x_m, y_m` and, when `tracking`, `rx_m, ry_m`) to
/// `path`: [`crate::track_plot::tracking_charts`] (sensor against reference) or
/// [`crate::track_plot::excitation_charts`]; errors name `--plot`.
pub fn plot_record(path: &Path, columns: &RecordTable, tracking: bool) -> crate::Result<()> {
    use crate::track_plot::{
        excitation_charts, tracking_charts, write_figure, ExciteAxis, TrackAxis,
    };
    let column = |name: &str| -> crate::Result<Vec<f64>> {
        columns
            .names
            .iter()
            .skip(1)
            .position(|n| n == name)
            .map(|i| columns.data[i].iter().map(|&v| f64::from(v)).collect())
            .ok_or_else(|| crate::Error::Link(format!("--plot: the record has no column {name}")))
    };
    let names = ["x", "y"];
    let traces = names
        .iter()
        .map(|a| {
            Ok((
                column(&format!("u{a}_V"))?,
                column(&format!("{a}_m"))?,
                if tracking {
                    column(&format!("r{a}_m"))?
                } else {
                    Vec::new()
                },
            ))
        })
        .collect::<crate::Result<Vec<_>>>()?;
    let (charts, columns_drawn) = if tracking {
        let axes: Vec<TrackAxis<'_>> = names
            .iter()
            .zip(&traces)
            .map(|(name, (u, y, r))| TrackAxis {
                name,
                reference_m: r,
                position_m: y,
                position: "sensor",
                voltage_v: u,
            })
            .collect();
        // Scored as the firmware scores a track: from its settling time on (the start-up
        // transient shaded); a record too short for it is scored whole.
        let t = &columns.t_s;
        let from = t
            .iter()
            .position(|&ts| ts - t[0] >= TRACK_SCORED_AFTER_S)
            .filter(|&k| k < t.len() / 2)
            .unwrap_or(0);
        (tracking_charts(t, &axes, from), axes.len())
    } else {
        let axes: Vec<ExciteAxis<'_>> = names
            .iter()
            .zip(&traces)
            .map(|(name, (u, y, _))| ExciteAxis {
                name,
                voltage_v: u,
                sensor_m: y,
            })
            .collect();
        (excitation_charts(&columns.t_s, &axes), 3)
    };
    let charts =
        charts.map_err(|e| crate::Error::Link(format!("--plot {}: {e}", path.display())))?;
    write_figure("--plot", path, &charts, columns_drawn)
}

/// FNV-1a, 32 bit, of a stage file's bytes: piezo-stage's, the one the firmware's build logs for
/// the same file.
pub use piezo_stage::fnv1a32;

/// A stage file as the upload message: piezo-stage's [`piezo_stage::FirmwareSet`] (the set the
/// firmware's build makes of the same file: its refusals, a one-axis file driving both axes with
/// x, the version string and the hash), per axis the core's parameter structs.
pub fn model_set(path: &Path) -> crate::Result<ModelSet> {
    let bytes =
        std::fs::read(path).map_err(|e| crate::Error::Link(format!("{}: {e}", path.display())))?;
    model_set_of(path, &bytes)
}

/// The upload message of the stage file `bytes` (validated as the firmware's build validates
/// it), read from `path` (named in errors).
pub fn model_set_of(path: &Path, bytes: &[u8]) -> crate::Result<ModelSet> {
    let set = piezo_stage::FirmwareSet::from_bytes(&path.display().to_string(), bytes)
        .map_err(crate::Error::from)?;
    Ok(ModelSet {
        version: piezo_link::truncated(&set.version),
        fnv1a32: set.fnv1a32,
        loop_rate_hz: set.loop_rate_hz,
        io: set.io,
        axes: set.axes.each_ref().map(AxisModel::from_params),
    })
}

/// Uploads the stage file at `path`; the firmware's refusal (the core's reason) as an error.
pub fn upload(client: &mut Client, path: &Path) -> crate::Result<u32> {
    upload_set(client, model_set(path)?, path)
}

/// Uploads `set` (from the stage file `path`, named in errors); the firmware's refusal (the
/// core's reason) as an error.
/// The firmware's fingerprint of the set it loaded must be the host's
/// ([`ModelSet::fingerprint`]): it runs what was sent.
pub fn upload_set(client: &mut Client, set: ModelSet, path: &Path) -> crate::Result<u32> {
    let fingerprint = set.fingerprint();
    match client.request(Request::Upload(set))? {
        Response::Loaded {
            params_fnv1a32,
            params_fingerprint,
        } if params_fingerprint != fingerprint => Err(crate::Error::Link(format!(
            "{}: the firmware loaded a set with fingerprint {params_fingerprint:#010x}, the file's is \
             {fingerprint:#010x}: it does not run what was sent (fnv1a32 {params_fnv1a32:#010x})",
            path.display()
        ))),
        Response::Loaded { params_fnv1a32, .. } => Ok(params_fnv1a32),
        Response::Refused(r) => Err(crate::Error::Link(format!(
            "{}: refused by the firmware ({:?}): {}",
            path.display(),
            r.kind,
            r.reason
        ))),
        other => Err(crate::Error::Link(format!("unexpected answer to upload: {other:?}"))),
    }
}

fn json<T: Serialize>(value: &T) -> crate::Result<String> {
    serde_json::to_string(value).map_err(crate::Error::from)
}

/// `0x` and 8 hex digits, as host-sim prints an FNV-1a 32.
pub fn hex32(value: u32) -> String {
    format!("{value:#010x}")
}

/// `status` as `link status` prints it: the firmware's [`Status`] with its two hashes
/// (`params_fnv1a32`, `params_fingerprint`) in hex, and `guard_interventions`, the output
/// guard's interventions of all causes on both axes, next to `counters.guard` (per axis: x, y;
/// per cause: `non_finite`, `window_clamped`, `slew_limited`, `window_entry`).
pub fn status_json(status: &Status) -> crate::Result<serde_json::Value> {
    let mut value = serde_json::to_value(status).map_err(crate::Error::from)?;
    if let Some(fields) = value.as_object_mut() {
        fields.insert("params_fnv1a32".into(), hex32(status.params_fnv1a32).into());
        fields.insert(
            "params_fingerprint".into(),
            hex32(status.params_fingerprint).into(),
        );
        fields.insert(
            "guard_interventions".into(),
            status.counters.guard_interventions().into(),
        );
    }
    Ok(value)
}

/// Runs `link`.
pub fn link_cmd(a: &LinkArgs) -> crate::Result<String> {
    if !(a.timeout > 0.0 && a.timeout.is_finite()) {
        return Err(crate::Error::Link("--timeout must be > 0".into()));
    }
    if !(a.wait >= 0.0 && a.wait.is_finite()) {
        return Err(crate::Error::Link("--wait must be ≥ 0".into()));
    }
    if let LinkCommand::Excite(RunArgs { plot: Some(p), .. })
    | LinkCommand::Track(RunArgs { plot: Some(p), .. }) = &a.command
    {
        crate::track_plot::check_plot_path("--plot", p)?;
    }
    let timeout = Duration::from_secs_f64(a.timeout);
    let mut client = if a.wait > 0.0 {
        Client::connect_waiting(&a.connect, timeout, Duration::from_secs_f64(a.wait))?
    } else {
        Client::connect(&a.connect, timeout)?
    };
    match &a.command {
        LinkCommand::Status => json(&status_json(&client.status()?)?),
        LinkCommand::Excite(r) | LinkCommand::Track(r) => {
            let tracking = matches!(a.command, LinkCommand::Track(_));
            let recording = client.run(&r.signal, r.duration, r.decimation, !tracking)?;
            recording.check_gaps(r.allow_gaps)?;
            let record = recording.record();
            if record.rows.is_empty() {
                return Err(crate::Error::Link(format!(
                    "{} frames but no two consecutive ones: no row for the record",
                    recording.frames.len()
                )));
            }
            let comments = [
                format!(
                    "host-sim link {} of {} for {} s: loop {} Hz, one frame every {} ticks: \
                     t_s = (sequence - {}) * {} s",
                    if tracking { "track" } else { "excite" },
                    r.signal,
                    r.duration,
                    recording.loop_rate_hz,
                    recording.decimation,
                    recording.first_frame,
                    f64::from(recording.decimation) / recording.loop_rate_hz
                ),
                format!(
                    "{} frames, {} gaps ({} frames lost); {} rows: {}",
                    recording.frames.len(),
                    recording.gaps,
                    recording.lost,
                    record.rows.len(),
                    record.lead_note().unwrap_or_else(|| {
                        "each voltage with the next frame's reading, the one that answers it".into()
                    })
                ),
            ];
            let columns = record.table(AxisChoice::Both, tracking, recording.gaps > 0);
            columns
                .write(&r.record, &comments)
                .map_err(crate::Error::from)?;
            if let Some(plot) = &r.plot {
                plot_record(plot, &columns, tracking)?;
            }
            let status = client.status()?;
            json(&serde_json::json!({
                "record": r.record.display().to_string(),
                "plot": r.plot.as_ref().map(|p| p.display().to_string()),
                "frames": recording.frames.len(),
                "rows": record.rows.len(),
                "reading_lead_ticks": record.reading_lead_ticks,
                "recording": recording,
                "tracking": tracking.then_some(status.tracking),
                "mode": status.mode,
                "counters": status.counters,
            }))
        }
        LinkCommand::Upload { params } => {
            let set = model_set(params)?;
            let fingerprint = set.fingerprint();
            let fnv = upload_set(&mut client, set, params)?;
            json(&serde_json::json!({
                "loaded": params.display().to_string(),
                "params_fnv1a32": hex32(fnv),
                "params_fingerprint": hex32(fingerprint),
            }))
        }
        LinkCommand::Rearm => json(&client.expect(Request::Rearm)?),
        LinkCommand::Control { mode } => {
            json(&client.expect(Request::Control(control_mode(mode)?))?)
        }
        LinkCommand::InjectOverrun => json(&client.expect(Request::InjectOverrun)?),
        LinkCommand::Learn(l) => crate::link_learn::link_learn_cmd(&mut client, l),
        LinkCommand::Step(s) => crate::link_step::link_step_cmd(&mut client, s),
        LinkCommand::Shutdown => json(&client.expect(Request::Shutdown)?),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A fake device on a loopback port: answers each request with `answer(sequence, request)`,
    /// and hands back every byte it received once the link is quiet for a second.
    fn device(
        answer: impl Fn(u32, &Request) -> Response + Send + 'static,
    ) -> (String, std::thread::JoinHandle<Vec<u8>>) {
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let address = format!("tcp:{}", listener.local_addr().unwrap());
        let handle = std::thread::spawn(move || {
            let (mut stream, _) = listener.accept().unwrap();
            // The client's reader thread keeps the socket open: stop after a quiet second.
            stream
                .set_read_timeout(Some(Duration::from_secs(1)))
                .unwrap();
            let mut decoder = Decoder::new();
            let mut received = Vec::new();
            let mut buffer = [0u8; 1024];
            let mut sequence = 0;
            while let Ok(n) = stream.read(&mut buffer) {
                if n == 0 {
                    break;
                }
                received.extend_from_slice(&buffer[..n]);
                for &b in &buffer[..n] {
                    if let Some(Ok(packet)) = decoder.push::<Request>(b) {
                        let body = Uplink::Response {
                            request: packet.sequence,
                            response: answer(packet.sequence, &packet.body),
                        };
                        let mut out = [0u8; MAX_FRAME];
                        let n = piezo_link::encode(&Packet { sequence, body }, &mut out).unwrap();
                        sequence += 1;
                        if stream.write_all(&out[..n]).is_err() {
                            return received;
                        }
                    }
                }
            }
            received
        });
        (address, handle)
    }

    fn status(loop_rate_hz: f32, table: u32) -> Status {
        Status {
            protocol: PROTOCOL_VERSION,
            params_fingerprint: 0,
            params_fnv1a32: 0,
            params_version: Default::default(),
            loop_rate_hz,
            mode: piezo_link::Mode::Running,
            feedforward: piezo_link::Feedforward::Compensator,
            control: Control::Feedforward,
            tick_cycles_max: 0,
            counters: Default::default(),
            tracking: Default::default(),
            applied_v: [0.0; 2],
            measured_m: [0.0; 2],
            frame_decimation: 0,
            next_frame: 0,
            table: [0, table],
            stream: [0, 63],
            learned: [0, table],
            envelope: Default::default(),
            on_target: Default::default(),
        }
    }

    /// A firmware of another protocol version is named as such: one whose status parses (a
    /// version field of another value), and one whose status does not (other fields after its
    /// version), which before the version's check timed out as an answer never received.
    #[test]
    fn a_firmware_of_another_protocol_is_named() {
        let (address, device) = device(|_, _| {
            Response::Status(Status {
                protocol: PROTOCOL_VERSION + 1,
                ..status(10_000.0, 2048)
            })
        });
        let mut client = Client::connect(&address, Duration::from_secs(5)).unwrap();
        let e = client.status().unwrap_err().to_string();
        let theirs = format!(
            "protocol {}, this host-sim {PROTOCOL_VERSION}",
            PROTOCOL_VERSION + 1
        );
        assert!(e.contains(&theirs), "{e}");
        drop(client);
        device.join().unwrap();

        // A status of protocol 1 laid out otherwise: Uplink::Response (0), the request's number,
        // Response::Status (0), the version, then a field this host does not expect.
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let address = format!("tcp:{}", listener.local_addr().unwrap());
        let old = std::thread::spawn(move || {
            let (mut stream, _) = listener.accept().unwrap();
            let mut decoder = Decoder::new();
            let mut buffer = [0u8; 1024];
            while let Ok(n) = stream.read(&mut buffer) {
                for &b in &buffer[..n] {
                    if let Some(Ok(packet)) = decoder.push::<Request>(b) {
                        let body = (0u32, packet.sequence, 0u32, 1u16, 7u8);
                        let mut out = [0u8; MAX_FRAME];
                        let n =
                            piezo_link::encode(&Packet { sequence: 0, body }, &mut out).unwrap();
                        stream.write_all(&out[..n]).unwrap();
                        return;
                    }
                }
                if n == 0 {
                    return;
                }
            }
        });
        let mut client = Client::connect(&address, Duration::from_secs(5)).unwrap();
        let started = Instant::now();
        let e = client.status().unwrap_err().to_string();
        assert!(
            e.contains(&format!("protocol 1, this host-sim {PROTOCOL_VERSION}")),
            "{e}"
        );
        assert!(started.elapsed() < Duration::from_secs(4), "not a timeout");
        old.join().unwrap();
    }

    /// A device whose status is out of bounds makes `excite` fail with the field and the value,
    /// never a panic or a huge allocation.
    #[test]
    fn bad_device_answers_are_errors() {
        let cases: [(f32, u32, &str); 6] = [
            (1e30, 2048, "loop_rate_hz = 1e30"),
            (f32::INFINITY, 2048, "loop_rate_hz = inf"),
            (f32::NAN, 2048, "loop_rate_hz = NaN"),
            (-10_000.0, 2048, "loop_rate_hz = -10000.0"),
            (10_000.0, u32::MAX, "4294967295 entries"),
            (10_000.0, 0, "0 entries"),
        ];
        for (rate, table, expected) in cases {
            let (address, device) = device(move |_, request| match request {
                Request::Status => Response::Status(status(rate, table)),
                _ => Response::Done,
            });
            let mut client = Client::connect(&address, Duration::from_secs(5)).unwrap();
            let e = client
                .run("sine:amp=1,offset=1,freq=1", 1.0, 1, true)
                .unwrap_err()
                .to_string();
            assert!(e.contains(expected), "{rate} {table}: {e}");
            drop(client);
            device.join().unwrap();
        }
        // A sane device with a duration too long to record.
        let (address, device) = device(|_, request| match request {
            Request::Status => Response::Status(status(20_000.0, 2048)),
            _ => Response::Done,
        });
        let mut client = Client::connect(&address, Duration::from_secs(5)).unwrap();
        let e = client
            .run("sine:amp=1,offset=1,freq=1", 1e9, 1, true)
            .unwrap_err()
            .to_string();
        assert!(e.contains("frames"), "{e}");
        drop(client);
        device.join().unwrap();
    }

    /// Every request starts with a delimiter; a `Replayed` answer moves the count on and the
    /// request is sent again with the number the device asked for.
    #[test]
    fn requests_start_with_a_delimiter_and_follow_a_replayed_answer() {
        let (address, device) = device(|sequence, _| {
            if sequence < 40 {
                Response::Replayed { next: 40 }
            } else {
                Response::Status(status(10_000.0, 2048))
            }
        });
        let mut client = Client::connect(&address, Duration::from_secs(5)).unwrap();
        assert_eq!(client.status().unwrap().loop_rate_hz, 10_000.0);
        assert_eq!(client.sequence, 41);
        drop(client);
        let bytes = device.join().unwrap();
        assert_eq!(bytes[0], 0);
        let starts = bytes.windows(2).filter(|w| w == &[0, 0]).count();
        assert_eq!(
            starts, 1,
            "two requests, the second right after the first's delimiter"
        );
    }

    /// `--wait`: a device that is not listening yet, and whose first connection takes the
    /// request without answering (bytes lost while its link comes up), is reached on a later try.
    #[test]
    fn waiting_connects_once_the_device_answers() {
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .unwrap()
            .port();
        let address = format!("tcp:127.0.0.1:{port}");
        let device = std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(600));
            let listener = std::net::TcpListener::bind(("127.0.0.1", port)).unwrap();
            // First connection: the request is swallowed, no answer.
            let (mut deaf, _) = listener.accept().unwrap();
            let mut buffer = [0u8; 1024];
            let _ = deaf.read(&mut buffer);
            drop(deaf);
            let (mut stream, _) = listener.accept().unwrap();
            stream
                .set_read_timeout(Some(Duration::from_secs(1)))
                .unwrap();
            let mut decoder = Decoder::new();
            let mut answered = 0;
            while let Ok(n) = stream.read(&mut buffer) {
                if n == 0 {
                    break;
                }
                for &b in &buffer[..n] {
                    if let Some(Ok(packet)) = decoder.push::<Request>(b) {
                        let body = Uplink::Response {
                            request: packet.sequence,
                            response: Response::Status(status(10_000.0, 2048)),
                        };
                        let mut out = [0u8; MAX_FRAME];
                        let n = piezo_link::encode(
                            &Packet {
                                sequence: answered,
                                body,
                            },
                            &mut out,
                        )
                        .unwrap();
                        answered += 1;
                        stream.write_all(&out[..n]).unwrap();
                    }
                }
            }
            answered
        });
        let e = Client::connect(&address, Duration::from_secs(5))
            .err()
            .expect("nothing listens yet")
            .to_string();
        assert!(e.contains(&address), "{e}");
        let mut client =
            Client::connect_waiting(&address, Duration::from_secs(5), Duration::from_secs(10))
                .unwrap();
        assert_eq!(client.timeout, Duration::from_secs(5));
        assert_eq!(client.status().unwrap().loop_rate_hz, 10_000.0);
        drop(client);
        assert_eq!(
            device.join().unwrap(),
            2,
            "the waiting status and the command's"
        );
        // Nothing answering: the error after the wait names the last failure.
        let e =
            Client::connect_waiting(&address, Duration::from_secs(5), Duration::from_millis(300))
                .err()
                .expect("nothing listens any more")
                .to_string();
        assert!(e.contains("did not answer within --wait 0.3 s"), "{e}");
    }

    #[test]
    fn the_stage_file_becomes_the_upload_message() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../firmware/params/xy-stage.toml");
        let set = model_set(&path).unwrap();
        assert_eq!(set.loop_rate_hz, 20_000.0);
        assert!(set.version.starts_with("xy-stage"));
        assert_ne!(set.axes[0].bouc_wen, set.axes[1].bouc_wen);
        assert_eq!(set.axes[0].limits.output_max_v, 120.0);
        // The build's own set of the same file: one function makes both.
        let bytes = std::fs::read(&path).unwrap();
        assert_eq!(set.fnv1a32, fnv1a32(&bytes));
    }

    #[test]
    fn a_model_the_firmware_does_not_run_is_refused_at_its_line() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("dynamic.toml");
        let text = std::fs::read_to_string(
            Path::new(env!("CARGO_MANIFEST_DIR")).join("../firmware/params/xy-stage.toml"),
        )
        .unwrap()
        .replacen("model = \"symmetric\"", "model = \"dynamic\"", 1);
        std::fs::write(&path, &text).unwrap();
        let e = model_set(&path).unwrap_err().to_string();
        let line = 1 + text[..text.find("model = \"dynamic\"").unwrap()]
            .matches('\n')
            .count();
        assert!(
            e.contains(&format!("dynamic.toml:{line}:"))
                && e.contains("`x.model`")
                && e.contains("the firmware runs the static models (symmetric, asymmetric) only"),
            "{e}"
        );
    }
}
