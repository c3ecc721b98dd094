//! The DAC8563's two frames of a tick sent without the tick waiting for them: the tick stages
//! both channels' codes ([`DmaDac::write_code`]); staging the last one starts frame A, and
//! the end of each frame (on the board: the SPI2 RX DMA stream's transfer-complete interrupt,
//! which fires once the frame's last bit has been clocked, `board::dac_frame_done`) ends it and
//! starts the next one:
//!
//! ```text
//! tick:          write A (staged), write B (staged) → SYNC↓, frame A  (Idle → First)
//! end of A:      SYNC↑, SYNC high ≥ t_SYNC,           SYNC↓, frame B  (First → Second)
//! end of B:      SYNC↑                                                (Second → Idle)
//! next tick:     a write while not Idle → Err(Busy), counted, nothing staged
//! DMA error:     SYNC↑ (the DAC ignores a frame cut before its 24th SCLK edge), Idle; the
//!                next write fails with Timeout, so the loop counts it and holds the outputs
//! ```
//!
//! Each frame is the one [`crate::dac8563::Dac8563::set`] sends (command 011, write and update,
//! [`update_frame`]): the DAC8563 updates channel n at the end of its frame, so x's output
//! changes one frame (1.14 µs at 21 MHz) after the tick starts the pair and y's one frame plus
//! the SYNC high time and the interrupt's latency later; both inside the loop period
//! ([`crate::converter_timing`]).
//!
//! [`DacSequencer`] is the state machine, hardware-free; [`FramePort`] is what it drives (SYNC
//! and the DMA start), implemented on the board by `board::discovery` and by a recorder in the
//! tests.

use crate::codes::DacCode;
use crate::converter::{DacWrite, Error, ErrorKind, ErrorType};
use crate::dac8563::{update_frame, Dac8563Channel};

/// What the sequencer drives: SYNC and a frame's transfer.
pub trait FramePort {
    /// SYNC low, then starts sending `frame` (returns at once; the end is reported through
    /// [`DacSequencer::frame_done`]).
    fn begin_frame(&mut self, frame: [u8; 3]);
    /// SYNC high (ends the frame that was sent, or cuts one short).
    fn end_frame(&mut self);
    /// Waits SYNC's minimum high time between two frames.
    fn hold_sync_high(&mut self);
}

/// Where the pair of frames is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Phase {
    /// No transfer running.
    Idle,
    /// Frame A (channel A, x) is going out.
    First,
    /// Frame B (channel B, y) is going out.
    Second,
}

/// Why a write was refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DmaDacError {
    /// The previous tick's frames were still going out.
    Busy,
    /// The previous transfer was aborted by a DMA error: its codes were not applied.
    Aborted,
    /// The port is in use elsewhere (not reachable on a single core; never panics instead).
    Unavailable,
}

impl Error for DmaDacError {
    fn kind(&self) -> ErrorKind {
        match self {
            DmaDacError::Busy => ErrorKind::Busy,
            DmaDacError::Aborted => ErrorKind::Timeout,
            DmaDacError::Unavailable => ErrorKind::Other,
        }
    }
}

/// What the sequencer has counted.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct DmaDacCounters {
    /// Pairs of frames sent to their end.
    pub pairs_sent: u32,
    /// Writes refused because the previous pair was still going out.
    pub busy_refusals: u32,
    /// Transfers aborted by a DMA error.
    pub aborted: u32,
    /// Frame-end events with no frame going out.
    pub spurious_ends: u32,
}

/// The state machine of the two frames (module docs).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DacSequencer {
    phase: Phase,
    staged: [Option<DacCode>; 2],
    second: [u8; 3],
    aborted: bool,
    counters: DmaDacCounters,
}

impl Default for DacSequencer {
    fn default() -> Self {
        Self::new()
    }
}

impl DacSequencer {
    /// Idle, nothing staged.
    pub const fn new() -> Self {
        Self {
            phase: Phase::Idle,
            staged: [None; 2],
            second: [0; 3],
            aborted: false,
            counters: DmaDacCounters {
                pairs_sent: 0,
                busy_refusals: 0,
                aborted: 0,
                spurious_ends: 0,
            },
        }
    }

    /// Where the pair is.
    pub fn phase(&self) -> Phase {
        self.phase
    }

    /// The counters.
    pub fn counters(&self) -> DmaDacCounters {
        self.counters
    }

    /// Stages `code` for `channel`. Refused while a pair is going out ([`DmaDacError::Busy`]:
    /// the previous tick's transfer did not end within a period) or once after an aborted
    /// transfer ([`DmaDacError::Aborted`]). When both channels are staged, frame A starts.
    pub fn write<P: FramePort>(
        &mut self,
        port: &mut P,
        channel: Dac8563Channel,
        code: DacCode,
    ) -> Result<(), DmaDacError> {
        if self.phase != Phase::Idle {
            self.counters.busy_refusals = self.counters.busy_refusals.saturating_add(1);
            return Err(DmaDacError::Busy);
        }
        if core::mem::take(&mut self.aborted) {
            return Err(DmaDacError::Aborted);
        }
        let slot = match channel {
            Dac8563Channel::A => 0,
            Dac8563Channel::B => 1,
        };
        self.staged[slot] = Some(code);
        if let [Some(a), Some(b)] = self.staged {
            self.staged = [None; 2];
            self.second = update_frame(Dac8563Channel::B, b);
            self.phase = Phase::First;
            port.begin_frame(update_frame(Dac8563Channel::A, a));
        }
        Ok(())
    }

    /// The frame going out has ended (its last bit clocked): SYNC high; after frame A, frame B
    /// starts.
    pub fn frame_done<P: FramePort>(&mut self, port: &mut P) {
        match self.phase {
            Phase::First => {
                port.end_frame();
                port.hold_sync_high();
                self.phase = Phase::Second;
                port.begin_frame(self.second);
            }
            Phase::Second => {
                port.end_frame();
                self.phase = Phase::Idle;
                self.counters.pairs_sent = self.counters.pairs_sent.saturating_add(1);
            }
            Phase::Idle => {
                self.counters.spurious_ends = self.counters.spurious_ends.saturating_add(1);
            }
        }
    }

    /// The transfer failed (a DMA error): SYNC high, which makes the DAC8563 drop a frame cut
    /// before its 24th SCLK edge; idle; the next write reports it.
    pub fn abort<P: FramePort>(&mut self, port: &mut P) {
        port.end_frame();
        if self.phase != Phase::Idle {
            self.aborted = true;
            self.counters.aborted = self.counters.aborted.saturating_add(1);
        }
        self.phase = Phase::Idle;
        self.staged = [None; 2];
    }
}

/// Exclusive access to the sequencer and its port (on the board: inside a critical section,
/// since the DMA interrupt shares them).
pub trait PortAccess {
    /// The port.
    type Port: FramePort;
    /// Runs `f` on the sequencer and the port; `None` if they are not available.
    fn with_port<R>(
        &mut self,
        f: impl FnOnce(&mut DacSequencer, &mut Self::Port) -> R,
    ) -> Option<R>;
}

/// The loop's DAC on the board: a [`DacWrite`] whose writes go to the sequencer.
#[derive(Debug)]
pub struct DmaDac<A: PortAccess> {
    access: A,
}

impl<A: PortAccess> DmaDac<A> {
    /// Writes through `access`.
    pub fn new(access: A) -> Self {
        Self { access }
    }
}

impl<A: PortAccess> ErrorType for DmaDac<A> {
    type Error = DmaDacError;
}

impl<A: PortAccess> DacWrite for DmaDac<A> {
    type Channel = Dac8563Channel;

    #[inline]
    fn write_code(&mut self, channel: Dac8563Channel, code: DacCode) -> Result<(), DmaDacError> {
        self.access
            .with_port(|seq, port| seq.write(port, channel, code))
            .unwrap_or(Err(DmaDacError::Unavailable))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::params;
    use crate::xy_loop::{Axis, Fault, Mode, PositionSensor, XyIo};

    #[derive(Clone, Debug, PartialEq, Eq)]
    enum Event {
        Begin([u8; 3]),
        End,
        Hold,
    }

    #[derive(Default)]
    struct Recorder(Vec<Event>);

    impl FramePort for Recorder {
        fn begin_frame(&mut self, frame: [u8; 3]) {
            self.0.push(Event::Begin(frame));
        }
        fn end_frame(&mut self) {
            self.0.push(Event::End);
        }
        fn hold_sync_high(&mut self) {
            self.0.push(Event::Hold);
        }
    }

    #[derive(Default)]
    struct Owned {
        seq: DacSequencer,
        port: Recorder,
    }

    impl PortAccess for &mut Owned {
        type Port = Recorder;
        fn with_port<R>(
            &mut self,
            f: impl FnOnce(&mut DacSequencer, &mut Recorder) -> R,
        ) -> Option<R> {
            Some(f(&mut self.seq, &mut self.port))
        }
    }

    #[test]
    fn a_pair_is_frame_a_then_sync_high_then_frame_b() {
        let mut seq = DacSequencer::new();
        let mut port = Recorder::default();
        seq.write(&mut port, Dac8563Channel::A, DacCode(0x8000))
            .unwrap();
        // One channel staged: nothing goes out yet.
        assert!(port.0.is_empty());
        seq.write(&mut port, Dac8563Channel::B, DacCode(0xFFFF))
            .unwrap();
        assert_eq!(port.0, vec![Event::Begin([0x18, 0x80, 0x00])]);
        assert_eq!(seq.phase(), Phase::First);
        seq.frame_done(&mut port);
        assert_eq!(seq.phase(), Phase::Second);
        seq.frame_done(&mut port);
        assert_eq!(
            port.0,
            vec![
                Event::Begin([0x18, 0x80, 0x00]),
                Event::End,
                Event::Hold,
                Event::Begin([0x19, 0xFF, 0xFF]),
                Event::End,
            ]
        );
        assert_eq!(seq.phase(), Phase::Idle);
        assert_eq!(seq.counters().pairs_sent, 1);
    }

    #[test]
    fn frames_are_the_blocking_drivers_frames() {
        // The DMA sends exactly what Dac8563::set sends over the SPI device.
        for (ch, code) in [
            (Dac8563Channel::A, DacCode(0)),
            (Dac8563Channel::B, DacCode(0x1234)),
            (Dac8563Channel::A, DacCode::MAX),
        ] {
            let expected = crate::dac8563::frame(0b011, ch as u8, code.0);
            assert_eq!(update_frame(ch, code), expected);
        }
    }

    #[test]
    fn a_write_while_the_previous_pair_is_going_out_is_refused_and_counted() {
        let mut seq = DacSequencer::new();
        let mut port = Recorder::default();
        seq.write(&mut port, Dac8563Channel::A, DacCode(1)).unwrap();
        seq.write(&mut port, Dac8563Channel::B, DacCode(2)).unwrap();
        // The next tick comes before frame A ended.
        let err = seq
            .write(&mut port, Dac8563Channel::A, DacCode(3))
            .unwrap_err();
        assert_eq!(err, DmaDacError::Busy);
        assert_eq!(err.kind(), ErrorKind::Busy);
        seq.frame_done(&mut port);
        // ... or before frame B ended.
        assert_eq!(
            seq.write(&mut port, Dac8563Channel::B, DacCode(3)),
            Err(DmaDacError::Busy)
        );
        assert_eq!(seq.counters().busy_refusals, 2);
        // Nothing of the refused writes went out.
        assert_eq!(port.0.len(), 4);
        seq.frame_done(&mut port);
        // Once idle, a pair goes out with the new codes.
        seq.write(&mut port, Dac8563Channel::A, DacCode(5)).unwrap();
        seq.write(&mut port, Dac8563Channel::B, DacCode(6)).unwrap();
        assert_eq!(port.0.last(), Some(&Event::Begin([0x18, 0x00, 0x05])));
    }

    #[test]
    fn an_aborted_transfer_raises_sync_and_fails_the_next_write_once() {
        let mut seq = DacSequencer::new();
        let mut port = Recorder::default();
        seq.write(&mut port, Dac8563Channel::A, DacCode(1)).unwrap();
        seq.write(&mut port, Dac8563Channel::B, DacCode(2)).unwrap();
        seq.abort(&mut port);
        assert_eq!(port.0.last(), Some(&Event::End));
        assert_eq!(seq.phase(), Phase::Idle);
        let err = seq
            .write(&mut port, Dac8563Channel::A, DacCode(3))
            .unwrap_err();
        assert_eq!(err.kind(), ErrorKind::Timeout);
        assert_eq!(seq.counters().aborted, 1);
        seq.write(&mut port, Dac8563Channel::A, DacCode(3)).unwrap();
        seq.write(&mut port, Dac8563Channel::B, DacCode(4)).unwrap();
        assert_eq!(seq.phase(), Phase::First);
    }

    #[test]
    fn a_frame_end_with_nothing_going_out_is_counted_and_ignored() {
        let mut seq = DacSequencer::new();
        let mut port = Recorder::default();
        seq.frame_done(&mut port);
        assert!(port.0.is_empty());
        assert_eq!(seq.counters().spurious_ends, 1);
        assert_eq!(seq.phase(), Phase::Idle);
    }

    /// The rest position of each axis, read every tick.
    struct AtRest;

    impl ErrorType for AtRest {
        type Error = core::convert::Infallible;
    }

    impl PositionSensor for AtRest {
        fn read_m(&mut self, axis: Axis) -> Result<f32, Self::Error> {
            Ok(params::AXES[axis.index()].rest_output_m)
        }
    }

    /// The loop on a DMA DAC whose transfer never ends: the first tick starts the pair, the
    /// second tick's writes are refused, the loop counts DAC errors and holds its outputs in
    /// the safe state.
    #[test]
    fn the_loop_trips_on_a_transfer_still_running_at_the_next_tick() {
        let mut owned = Owned::default();
        let mut lp =
            crate::test_support::loop_holding([0, 1].map(|i| params::AXES[i].rest_output_m));
        let mut io = XyIo {
            dac: DmaDac::new(&mut owned),
            dac_channels: [Dac8563Channel::A, Dac8563Channel::B],
            sensor: AtRest,
        };
        lp.tick(&mut io, false);
        assert_eq!(lp.counters().dac_errors, 0);
        assert_eq!(lp.mode(), Mode::Running);
        lp.tick(&mut io, false);
        assert_eq!(lp.counters().dac_errors, 2);
        assert_eq!(lp.mode(), Mode::Safe(Fault::DacError(Axis::X)));
        assert_eq!(owned.seq.counters().busy_refusals, 2);
        // One pair went out (the first tick's), nothing after it.
        assert_eq!(
            owned
                .port
                .0
                .iter()
                .filter(|e| matches!(e, Event::Begin(_)))
                .count(),
            1
        );
    }
}
