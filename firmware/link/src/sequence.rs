//! Gap counting on a receiver: the sender numbers what it produces +1 each (wrapping at 2³²), so
//! a receiver sees a gap exactly where something was lost, in the sender's queue or on the link.

/// Receiver side: finds gaps in sequence numbers.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SequenceChecker {
    expected: Option<u32>,
    /// Gaps seen.
    pub gaps: u32,
    /// Numbers missing in those gaps.
    pub lost: u32,
}

impl SequenceChecker {
    /// Takes one received sequence number; returns how many are missing before it (0 if none).
    /// A number that goes backwards restarts the count (a reboot) without a gap.
    pub fn accept(&mut self, sequence: u32) -> u32 {
        let missing = match self.expected {
            Some(e) => {
                let ahead = sequence.wrapping_sub(e);
                if ahead < u32::MAX / 2 {
                    ahead
                } else {
                    0
                }
            }
            None => 0,
        };
        if missing > 0 {
            self.gaps = self.gaps.saturating_add(1);
            self.lost = self.lost.saturating_add(missing);
        }
        self.expected = Some(sequence.wrapping_add(1));
        missing
    }

    /// Expects `sequence` next (e.g. the first frame of a stream that was off), without a gap.
    pub fn expect(&mut self, sequence: u32) {
        self.expected = Some(sequence);
    }
}
