//! Sample frames out: what the loop did, per tick (or every `decimation`-th tick), for a host to
//! record.
//!
//! A frame is the link's [`Frame`] (`{sequence, per axis reference_m, commanded_v, sensor_m,
//! trial, flags}`), one type from the loop to the host's CSV: the loop pushes frames into a
//! fixed-capacity [`FrameQueue`]; the command link ([`crate::session`]) sends them as
//! [`piezo_link::Uplink::Frame`] (with the pass over the wave table, `trial`), the QEMU
//! self-check prints them over semihosting in the text form of [`piezo_link::text`]. The
//! sequence number counts every frame the loop *produced*, including those dropped because the
//! queue was full, so a receiver ([`SequenceChecker`]) sees a gap exactly where frames were lost,
//! in the link or in the queue.
//!
//! **Text form** (what the QEMU self-check prints, and what `host-sim capture` reads), one frame
//! per line, `Display` and `FromStr` of [`Frame`] ([`piezo_link::text`]):
//!
//! ```text
//! frame 2000: x ref 0.000018998257 m cmd 58.12863 V sensor 0.000018887498 m | y ref 0.000004001112 m cmd 1.7004242 V sensor 0.0000040718746 m
//! ```
//!
//! The images' boot line gives what turns sequence numbers into time:
//! `parameters <version> (<file>), fnv1a32 0x<hash>, fingerprint 0x<hash>, loop <rate> Hz, one
//! frame every <n> ticks`, so frame `k` was produced at t = k·n / rate after boot.

pub use piezo_link::text::FrameTextError;
pub use piezo_link::Frame;

/// Frames the queue holds (a power of two: a slot is the write count modulo it).
pub const FRAME_QUEUE_CAPACITY: usize = 32;
const _: () = assert!(FRAME_QUEUE_CAPACITY.is_power_of_two());

/// One axis of a tick as the loop offers it to [`FrameQueue::offer_flagged`].
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct AxisSample {
    /// Setpoint of the tick \[m\].
    pub reference_m: f32,
    /// Voltage applied to the actuator (after the safety guard) \[V\].
    pub commanded_v: f32,
    /// Sensor reading at the start of the tick \[m\] (NaN if the read failed).
    pub sensor_m: f32,
}

/// The loop's outgoing frames: decimation, sequence numbers, a bounded queue.
///
/// A ring of [`FRAME_QUEUE_CAPACITY`] frames written in place: the tick stores its fields into
/// the next free slot (no frame built on the stack and copied in), `written − read` frames wait
/// (both counts free-running, wrapping), slot `written mod capacity` is the next one written.
/// A slot's `trial` stays 0 (the link sets its own copy's), so the tick never writes it.
#[derive(Debug)]
pub struct FrameQueue {
    slots: [Frame; FRAME_QUEUE_CAPACITY],
    /// Frames put into the ring (wraps).
    written: u32,
    /// Frames taken out or discarded (wraps); `written − read` ≤ capacity.
    read: u32,
    decimation: u32,
    countdown: u32,
    next_sequence: u32,
    dropped: u32,
}

impl FrameQueue {
    /// One frame every `decimation` ticks (0 is taken as 1).
    pub fn new(decimation: u32) -> Self {
        Self {
            slots: [Frame::default(); FRAME_QUEUE_CAPACITY],
            written: 0,
            read: 0,
            decimation: decimation.max(1),
            countdown: 0,
            next_sequence: 0,
            dropped: 0,
        }
    }

    /// Called once per tick: `make` builds the frame only on the ticks that produce one.
    /// A frame that finds the queue full is dropped (and counted); its sequence number is used.
    #[inline]
    pub fn offer(&mut self, make: impl FnOnce() -> [AxisSample; 2]) {
        self.offer_flagged(make, 0);
    }

    /// [`FrameQueue::offer`] with the tick's flags ([`Frame::flags`]); `trial` is 0 (the link
    /// sets it). The frame is written into its slot field by field.
    #[inline]
    pub fn offer_flagged(&mut self, make: impl FnOnce() -> [AxisSample; 2], flags: u8) {
        if self.countdown > 0 {
            self.countdown -= 1;
            return;
        }
        self.countdown = self.decimation - 1;
        let sequence = self.next_sequence;
        self.next_sequence = sequence.wrapping_add(1);
        let written = self.written;
        if written.wrapping_sub(self.read) as usize >= FRAME_QUEUE_CAPACITY {
            self.dropped = self.dropped.saturating_add(1);
            return;
        }
        let [x, y] = make();
        let slot = &mut self.slots[written as usize % FRAME_QUEUE_CAPACITY];
        slot.sequence = sequence;
        slot.reference_m = [x.reference_m, y.reference_m];
        slot.commanded_v = [x.commanded_v, y.commanded_v];
        slot.sensor_m = [x.sensor_m, y.sensor_m];
        slot.flags = flags;
        self.written = written.wrapping_add(1);
    }

    /// Moves up to `N` frames, oldest first, into `batch` (cleared first); returns how many.
    pub fn drain_into<const N: usize>(&mut self, batch: &mut heapless::Vec<Frame, N>) -> usize {
        batch.clear();
        let n = self.len().min(N);
        for k in 0..n {
            let slot = self.read.wrapping_add(k as u32) as usize % FRAME_QUEUE_CAPACITY;
            // Cannot fail: n ≤ N.
            let _ = batch.push(self.slots[slot]);
        }
        self.read = self.read.wrapping_add(n as u32);
        n
    }

    /// Drops the queued frames numbered `first` and after (those produced since
    /// [`Self::next_sequence`] was `first`), keeping older ones; not counted as dropped.
    pub fn discard_from(&mut self, first: u32) {
        let produced = self.next_sequence.wrapping_sub(first);
        while self.written != self.read {
            let last = self.written.wrapping_sub(1);
            let f = &self.slots[last as usize % FRAME_QUEUE_CAPACITY];
            if self.next_sequence.wrapping_sub(f.sequence) > produced {
                break;
            }
            self.written = last;
        }
    }

    /// One frame every `decimation` ticks from now on (0 is taken as 1).
    pub fn set_decimation(&mut self, decimation: u32) {
        self.decimation = decimation.max(1);
        self.countdown = self.countdown.min(self.decimation - 1);
    }

    /// Ticks per frame.
    pub fn decimation(&self) -> u32 {
        self.decimation
    }

    /// Drops the waiting frames without counting them as dropped (nobody is listening).
    pub fn discard(&mut self) {
        self.read = self.written;
    }

    /// Frames waiting.
    pub fn len(&self) -> usize {
        self.written.wrapping_sub(self.read) as usize
    }

    /// True if no frame is waiting.
    pub fn is_empty(&self) -> bool {
        self.written == self.read
    }

    /// Frames dropped because the queue was full (saturating).
    pub fn dropped(&self) -> u32 {
        self.dropped
    }

    /// Sequence number the next frame will get.
    pub fn next_sequence(&self) -> u32 {
        self.next_sequence
    }
}

/// Receiver side: finds gaps in the sequence numbers (the link's, one owner for both ends).
pub use piezo_link::SequenceChecker;

#[cfg(test)]
mod tests {
    use super::*;

    fn axes(v: f32) -> [AxisSample; 2] {
        [
            AxisSample {
                reference_m: v,
                commanded_v: 2.0 * v,
                sensor_m: f32::NAN,
            },
            AxisSample {
                reference_m: -v,
                commanded_v: 3.0,
                sensor_m: 1e-6,
            },
        ]
    }

    #[test]
    fn a_frame_holds_what_the_loop_offered() {
        let mut q = FrameQueue::new(1);
        q.offer_flagged(|| axes(1.5e-6), Frame::OUTSIDE_Y);
        let mut batch = heapless::Vec::<Frame, 1>::new();
        q.drain_into(&mut batch);
        let f = batch[0];
        assert_eq!(f.reference_m, [1.5e-6, -1.5e-6]);
        assert_eq!(f.commanded_v, [3e-6, 3.0]);
        assert!(f.sensor_m[0].is_nan());
        assert_eq!(f.sensor_m[1], 1e-6);
        assert_eq!((f.sequence, f.trial, f.flags), (0, 0, Frame::OUTSIDE_Y));
        // The text form is the link's.
        let mut s = heapless::String::<256>::new();
        core::fmt::write(&mut s, format_args!("{f}")).unwrap();
        assert_eq!(
            s.as_str(),
            "frame 0: x ref 0.0000015 m cmd 0.000003 V sensor NaN m | y ref -0.0000015 m cmd 3 V sensor 0.000001 m"
        );
    }

    #[test]
    fn decimation_and_batches() {
        let mut q = FrameQueue::new(4);
        for k in 0..40 {
            q.offer(|| axes(k as f32));
        }
        assert_eq!(q.len(), 10);
        let mut batch = heapless::Vec::<Frame, 8>::new();
        assert_eq!(q.drain_into(&mut batch), 8);
        assert_eq!(batch[0].reference_m[0], 0.0);
        assert_eq!(batch[1].reference_m[0], 4.0);
        assert_eq!(batch[7].sequence, 7);
        assert_eq!(q.drain_into(&mut batch), 2);
        assert!(q.is_empty());
    }

    #[test]
    fn overflow_drops_and_the_receiver_sees_the_gap() {
        let mut q = FrameQueue::new(1);
        let mut rx = SequenceChecker::default();
        let mut batch = heapless::Vec::<Frame, 16>::new();
        for k in 0..(FRAME_QUEUE_CAPACITY + 5) {
            q.offer(|| axes(k as f32));
        }
        assert_eq!(q.dropped(), 5);
        for _ in 0..3 {
            q.drain_into(&mut batch);
            for f in &batch {
                assert_eq!(rx.accept(f.sequence), 0);
            }
        }
        q.offer(|| axes(0.0));
        q.drain_into(&mut batch);
        assert_eq!(rx.accept(batch[0].sequence), 5);
        assert_eq!((rx.gaps, rx.lost), (1, 5));
    }

    #[test]
    fn discard_from_keeps_the_older_frames() {
        let mut q = FrameQueue::new(1);
        for _ in 0..3 {
            q.offer(|| axes(1.0));
        }
        let first_new = q.next_sequence();
        for _ in 0..2 {
            q.offer(|| axes(2.0));
        }
        q.discard_from(first_new);
        let mut batch = heapless::Vec::<Frame, 8>::new();
        assert_eq!(q.drain_into(&mut batch), 3);
        assert_eq!(
            batch
                .iter()
                .map(|f| f.sequence)
                .collect::<heapless::Vec<u32, 8>>(),
            [0, 1, 2]
        );
        // Nothing new: nothing dropped.
        q.offer(|| axes(3.0));
        q.discard_from(q.next_sequence());
        assert_eq!(q.len(), 1);
        assert_eq!(q.dropped(), 0);
    }

    #[test]
    fn the_ring_keeps_order_and_fields_over_many_passes() {
        // Frames go through the ring's slots many times over, drained in uneven batches and
        // discarded from the back across the slots' wrap: every frame comes out once, in
        // order, with its own fields, and `trial` stays 0.
        let mut q = FrameQueue::new(1);
        let mut batch = heapless::Vec::<Frame, 5>::new();
        let mut next = 0u32;
        for round in 0..(4 * FRAME_QUEUE_CAPACITY) {
            for k in 0..(1 + round % 7) {
                q.offer_flagged(|| axes(k as f32 + round as f32 * 0.5), (round % 16) as u8);
            }
            if round % 5 == 4 {
                // The newest frame goes again (as a refused reply would drop it).
                q.discard_from(q.next_sequence() - 1);
            }
            while q.drain_into(&mut batch) > 0 {
                for f in &batch {
                    assert!(f.sequence >= next, "{} after {next}", f.sequence);
                    next = f.sequence + 1;
                    assert_eq!(f.commanded_v[0], 2.0 * f.reference_m[0]);
                    assert_eq!(f.reference_m[1], -f.reference_m[0]);
                    assert_eq!(f.trial, 0);
                }
            }
            assert!(q.is_empty());
        }
        assert_eq!(q.dropped(), 0);
        assert_eq!(next, q.next_sequence());
    }

    #[test]
    fn sequence_wraps_without_a_gap() {
        let mut rx = SequenceChecker::default();
        rx.accept(u32::MAX - 1);
        assert_eq!(rx.accept(u32::MAX), 0);
        assert_eq!(rx.accept(0), 0);
        assert_eq!(rx.accept(2), 1);
        // Backwards: a restart, not a gap.
        assert_eq!(rx.accept(0), 0);
        assert_eq!(rx.gaps, 1);
    }
}
