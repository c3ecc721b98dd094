//! Gap counting on a receiver: the sender numbers what it produces +1 each (wrapping at 2³²), so
//! a receiver sees a gap exactly where something was lost, in the sender's queue or on the link.
//!
//! Two readings of a number that is not ahead of the last one (modulo 2³², "ahead" meaning less
//! than 2³¹ further on): for frames ([`SequenceChecker::accept`]) the sender restarted, and the
//! count goes on from there; for requests ([`SequenceChecker::admit`]) it was already handled (a
//! replayed or duplicated frame, or a host that started counting again), and it is not run.

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

    /// Takes one request's sequence number: `Ok(missing)` if it is ahead of every number admitted
    /// so far (the first one always is), counted as [`SequenceChecker::accept`] does; `Err(next)`
    /// if it is not (already handled: equal to or behind the last admitted one), with the lowest
    /// number admitted next. A refused number changes nothing.
    pub fn admit(&mut self, sequence: u32) -> Result<u32, u32> {
        match self.expected {
            Some(e) if sequence.wrapping_sub(e) >= u32::MAX / 2 => Err(e),
            _ => Ok(self.accept(sequence)),
        }
    }

    /// Expects `sequence` next (e.g. the first frame of a stream that was off), without a gap.
    pub fn expect(&mut self, sequence: u32) {
        self.expected = Some(sequence);
    }
}
