//! Sample frames out: what the loop did, per tick (or every `decimation`-th tick), for a host to
//! record.
//!
//! A [`SampleFrame`] is `{sequence, per axis: reference_m, commanded_v, sensor_m}`. The loop pushes
//! frames into a fixed-capacity [`FrameQueue`]; the sender drains them in batches (defmt on the
//! board, semihosting in QEMU) in the 28-byte little-endian wire format of
//! [`SampleFrame::to_bytes`]. The sequence number counts every frame the loop *produced*,
//! including those dropped because the queue was full, so a receiver ([`SequenceChecker`]) sees a
//! gap exactly where frames were lost, in the link or in the queue.
//!
//! **Text form** (what the images print, and what `host-sim capture` reads), one frame per line,
//! owned by [`piezo_link::text`]: [`SampleFrame`]'s `Display` (QEMU, semihosting) and `FromStr`
//! go through [`FrameText`], and the board's `defmt::Format` prints the same words:
//!
//! ```text
//! frame 2000: x ref 0.000018998257 m cmd 58.12863 V sensor 0.000018887498 m | y ref 0.000004001112 m cmd 1.7004242 V sensor 0.0000040718746 m
//! ```
//!
//! The images' boot line gives what turns sequence numbers into time:
//! `parameters <version> (<file>), fnv1a32 0x<hash>, loop <rate> Hz, one frame every <n> ticks`,
//! so frame `k` was produced at t = k·n / rate after boot.

use heapless::Deque;
pub use piezo_link::text::{FrameText, FrameTextError};

/// Frames the queue holds.
pub const FRAME_QUEUE_CAPACITY: usize = 32;

/// One axis of a frame.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(all(target_os = "none", feature = "board"), derive(defmt::Format))]
pub struct AxisSample {
    /// Setpoint of the tick \[m\].
    pub reference_m: f32,
    /// Voltage applied to the actuator (after the safety guard) \[V\].
    pub commanded_v: f32,
    /// Sensor reading at the start of the tick \[m\] (NaN if the read failed).
    pub sensor_m: f32,
}

/// One frame. `Display` and (board) `defmt::Format` give the one-line text form of the module doc.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SampleFrame {
    /// Frame number, +1 per produced frame (wraps at 2³²).
    pub sequence: u32,
    /// x, y.
    pub axes: [AxisSample; 2],
    /// The tick's flags (`piezo_link::Frame::OUTSIDE_X`, `OUTSIDE_Y`: the command left the
    /// axis's identified envelope); carried by the link's frames, not by the text and 28-byte
    /// forms.
    pub flags: u8,
}

/// Size of a frame on the wire.
pub const FRAME_BYTES: usize = 28;

impl SampleFrame {
    /// Wire format: `sequence` (u32), then per axis `reference_m`, `commanded_v`, `sensor_m`
    /// (f32), all little-endian.
    pub fn to_bytes(&self) -> [u8; FRAME_BYTES] {
        let mut out = [0u8; FRAME_BYTES];
        let mut words = [0u32; 7];
        words[0] = self.sequence;
        for (i, a) in self.axes.iter().enumerate() {
            words[1 + 3 * i] = a.reference_m.to_bits();
            words[2 + 3 * i] = a.commanded_v.to_bits();
            words[3 + 3 * i] = a.sensor_m.to_bits();
        }
        for (chunk, word) in out.chunks_exact_mut(4).zip(words) {
            chunk.copy_from_slice(&word.to_le_bytes());
        }
        out
    }

    /// Inverse of [`SampleFrame::to_bytes`].
    pub fn from_bytes(bytes: &[u8; FRAME_BYTES]) -> Self {
        let mut words = [0u32; 7];
        for (word, chunk) in words.iter_mut().zip(bytes.chunks_exact(4)) {
            let mut b = [0u8; 4];
            b.copy_from_slice(chunk);
            *word = u32::from_le_bytes(b);
        }
        let axis = |i: usize| AxisSample {
            reference_m: f32::from_bits(words[1 + 3 * i]),
            commanded_v: f32::from_bits(words[2 + 3 * i]),
            sensor_m: f32::from_bits(words[3 + 3 * i]),
        };
        Self {
            sequence: words[0],
            axes: [axis(0), axis(1)],
            flags: 0,
        }
    }
}

impl From<&SampleFrame> for FrameText {
    fn from(f: &SampleFrame) -> Self {
        let axis = |a: &AxisSample| [a.reference_m, a.commanded_v, a.sensor_m];
        Self {
            sequence: f.sequence,
            axes: [axis(&f.axes[0]), axis(&f.axes[1])],
        }
    }
}

impl From<FrameText> for SampleFrame {
    fn from(t: FrameText) -> Self {
        let axis = |[reference_m, commanded_v, sensor_m]: [f32; 3]| AxisSample {
            reference_m,
            commanded_v,
            sensor_m,
        };
        Self {
            sequence: t.sequence,
            axes: t.axes.map(axis),
            flags: 0,
        }
    }
}

/// The text form of [`piezo_link::text`].
impl core::fmt::Display for SampleFrame {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        FrameText::from(self).fmt(f)
    }
}

/// Reads the text form of [`piezo_link::text`] (what `Display` writes).
impl core::str::FromStr for SampleFrame {
    type Err = FrameTextError;

    fn from_str(text: &str) -> Result<Self, FrameTextError> {
        text.parse::<FrameText>().map(Self::from)
    }
}

/// The words of `Display` (host-sim capture reads either); defmt needs the format as a literal.
#[cfg(all(target_os = "none", feature = "board"))]
impl defmt::Format for SampleFrame {
    fn format(&self, f: defmt::Formatter<'_>) {
        let [x, y] = &self.axes;
        defmt::write!(
            f,
            "frame {=u32}: x ref {=f32} m cmd {=f32} V sensor {=f32} m | y ref {=f32} m cmd {=f32} V sensor {=f32} m",
            self.sequence,
            x.reference_m,
            x.commanded_v,
            x.sensor_m,
            y.reference_m,
            y.commanded_v,
            y.sensor_m
        );
    }
}

/// The loop's outgoing frames: decimation, sequence numbers, a bounded queue.
#[derive(Debug)]
pub struct FrameQueue {
    frames: Deque<SampleFrame, FRAME_QUEUE_CAPACITY>,
    decimation: u32,
    countdown: u32,
    next_sequence: u32,
    dropped: u32,
}

impl FrameQueue {
    /// One frame every `decimation` ticks (0 is taken as 1).
    pub fn new(decimation: u32) -> Self {
        Self {
            frames: Deque::new(),
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

    /// [`FrameQueue::offer`] with the tick's flags ([`SampleFrame::flags`]).
    #[inline]
    pub fn offer_flagged(&mut self, make: impl FnOnce() -> [AxisSample; 2], flags: u8) {
        if self.countdown > 0 {
            self.countdown -= 1;
            return;
        }
        self.countdown = self.decimation - 1;
        let frame = SampleFrame {
            sequence: self.next_sequence,
            axes: make(),
            flags,
        };
        self.next_sequence = self.next_sequence.wrapping_add(1);
        if self.frames.push_back(frame).is_err() {
            self.dropped = self.dropped.saturating_add(1);
        }
    }

    /// Moves up to `N` frames, oldest first, into `batch` (cleared first); returns how many.
    pub fn drain_into<const N: usize>(
        &mut self,
        batch: &mut heapless::Vec<SampleFrame, N>,
    ) -> usize {
        batch.clear();
        while batch.len() < N {
            match self.frames.pop_front() {
                Some(f) => {
                    // Cannot fail: the length was checked above.
                    let _ = batch.push(f);
                }
                None => break,
            }
        }
        batch.len()
    }

    /// Drops the queued frames numbered `first` and after (those produced since
    /// [`Self::next_sequence`] was `first`), keeping older ones; not counted as dropped.
    pub fn discard_from(&mut self, first: u32) {
        let produced = self.next_sequence.wrapping_sub(first);
        while let Some(f) = self.frames.back() {
            if self.next_sequence.wrapping_sub(f.sequence) > produced {
                break;
            }
            self.frames.pop_back();
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
        self.frames.clear();
    }

    /// Frames waiting.
    pub fn len(&self) -> usize {
        self.frames.len()
    }

    /// True if no frame is waiting.
    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
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
    fn wire_format_round_trips_bit_exactly() {
        let f = SampleFrame {
            sequence: 0xdead_beef,
            axes: axes(1.5e-6),
            flags: 0,
        };
        let bytes = f.to_bytes();
        assert_eq!(&bytes[..4], &[0xef, 0xbe, 0xad, 0xde]);
        let back = SampleFrame::from_bytes(&bytes);
        assert_eq!(back.to_bytes(), bytes);
        assert_eq!(back.sequence, f.sequence);
        assert!(back.axes[0].sensor_m.is_nan());
    }

    #[test]
    fn text_form_round_trips() {
        let f = SampleFrame {
            sequence: 2000,
            axes: axes(1.5e-5),
            flags: 0,
        };
        let mut s = heapless::String::<256>::new();
        core::fmt::write(&mut s, format_args!("{f}")).unwrap();
        assert_eq!(
            s.as_str(),
            "frame 2000: x ref 0.000015 m cmd 0.00003 V sensor NaN m | y ref -0.000015 m cmd 3 V sensor 0.000001 m"
        );
        let back: SampleFrame = s.parse().unwrap();
        assert_eq!(back.sequence, f.sequence);
        let bits = |f: &SampleFrame| f.to_bytes();
        // NaN reads back as NaN (the sensor field of x); every other value bit for bit.
        assert!(back.axes[0].sensor_m.is_nan());
        let mut nan_cleared = [back, f];
        for g in &mut nan_cleared {
            g.axes[0].sensor_m = 0.0;
        }
        assert_eq!(bits(&nan_cleared[0]), bits(&nan_cleared[1]));
        let odd = SampleFrame {
            sequence: u32::MAX,
            axes: [
                AxisSample {
                    reference_m: 1.9094246e-5,
                    commanded_v: -0.0,
                    sensor_m: f32::from_bits(1),
                },
                AxisSample {
                    reference_m: f32::MAX,
                    commanded_v: f32::INFINITY,
                    sensor_m: core::f32::consts::PI,
                },
            ],
            flags: 0,
        };
        s.clear();
        core::fmt::write(&mut s, format_args!("{odd}")).unwrap();
        assert_eq!(s.parse::<SampleFrame>().unwrap().to_bytes(), odd.to_bytes());
    }

    #[test]
    fn decimation_and_batches() {
        let mut q = FrameQueue::new(4);
        for k in 0..40 {
            q.offer(|| axes(k as f32));
        }
        assert_eq!(q.len(), 10);
        let mut batch = heapless::Vec::<SampleFrame, 8>::new();
        assert_eq!(q.drain_into(&mut batch), 8);
        assert_eq!(batch[0].axes[0].reference_m, 0.0);
        assert_eq!(batch[1].axes[0].reference_m, 4.0);
        assert_eq!(batch[7].sequence, 7);
        assert_eq!(q.drain_into(&mut batch), 2);
        assert!(q.is_empty());
    }

    #[test]
    fn overflow_drops_and_the_receiver_sees_the_gap() {
        let mut q = FrameQueue::new(1);
        let mut rx = SequenceChecker::default();
        let mut batch = heapless::Vec::<SampleFrame, 16>::new();
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
        let mut batch = heapless::Vec::<SampleFrame, 8>::new();
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
