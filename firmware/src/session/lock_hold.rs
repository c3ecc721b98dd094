//! How long the command link holds the session, per kind of request: on the board the session is
//! a shared resource of the control tick, and every cycle the link spends inside its lock is a
//! cycle the tick may wait at its entry (its latency, [`crate::session`]'s "Order of events").
//!
//! A hold is measured by the link inside the lock, with the board's free-running cycle counter:
//!
//! ```text
//! hold = (c_release − c_acquire) mod 2^b      core cycles; b = 32 (DWT CYCCNT) or 24 (SysTick)
//! ```
//!
//! The tick waits for one hold at most (it preempts the link as soon as the lock is released), so
//! its latency from a request is bounded by the largest single hold, kept here per kind
//! ([`LockHolds::worst_cycles`]).

use piezo_link::Request;

use super::Prepared;

/// The kinds of request the link tells apart when it measures its holds, plus the transmit
/// batches it takes from the session.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RequestKind {
    /// `Status`.
    Status,
    /// `Upload` of a model set.
    Upload,
    /// The wave table, the learned table and the stream queue: `TableClear`, `TableAppend`,
    /// `LearnedClear`, `LearnedAppend`, `Stream`.
    Table,
    /// `Control`.
    Control,
    /// `Track` and `Excite`.
    Track,
    /// `Frames`, `Rearm`, `InjectOverrun`, `Shutdown`, and packets the decoder refused.
    Other,
    /// A batch of bytes out of the transmit buffer.
    Transmit,
}

impl RequestKind {
    /// Every kind, in the order of [`LockHolds::worst_cycles`].
    pub const ALL: [RequestKind; 7] = [
        RequestKind::Status,
        RequestKind::Upload,
        RequestKind::Table,
        RequestKind::Control,
        RequestKind::Track,
        RequestKind::Other,
        RequestKind::Transmit,
    ];

    /// The kind of a request.
    pub fn of(request: &Request) -> Self {
        match request {
            Request::Status => RequestKind::Status,
            Request::Upload(_) => RequestKind::Upload,
            Request::TableClear
            | Request::TableAppend(_)
            | Request::LearnedClear
            | Request::LearnedAppend(_)
            | Request::Stream(_) => RequestKind::Table,
            Request::Control(_) => RequestKind::Control,
            Request::Track(_) | Request::Excite(_) => RequestKind::Track,
            Request::Frames { .. }
            | Request::Rearm
            | Request::InjectOverrun
            | Request::Shutdown => RequestKind::Other,
        }
    }

    /// The kind of a prepared request.
    pub fn of_prepared(prepared: &Prepared) -> Self {
        match prepared {
            Prepared::Request(r) => Self::of(r),
            Prepared::Upload(_) => RequestKind::Upload,
        }
    }

    /// Its name in the figures the images print.
    pub fn name(self) -> &'static str {
        match self {
            RequestKind::Status => "status",
            RequestKind::Upload => "upload",
            RequestKind::Table => "table",
            RequestKind::Control => "control",
            RequestKind::Track => "track",
            RequestKind::Other => "other",
            RequestKind::Transmit => "transmit",
        }
    }

    fn index(self) -> usize {
        self as usize
    }
}

/// The largest hold of the session's lock per [`RequestKind`] \[core cycles\].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LockHolds {
    /// Indexed as [`RequestKind::ALL`].
    pub worst_cycles: [u32; RequestKind::ALL.len()],
}

impl LockHolds {
    /// Notes one hold of `cycles` for `kind`.
    pub fn note(&mut self, kind: RequestKind, cycles: u32) {
        let w = &mut self.worst_cycles[kind.index()];
        *w = (*w).max(cycles);
    }

    /// The largest hold of `kind`.
    pub fn worst(&self, kind: RequestKind) -> u32 {
        self.worst_cycles[kind.index()]
    }

    /// The largest hold of any kind.
    pub fn worst_of_all(&self) -> u32 {
        self.worst_cycles.iter().copied().max().unwrap_or(0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_kind_keeps_its_own_worst() {
        let mut h = LockHolds::default();
        h.note(RequestKind::Status, 300);
        h.note(RequestKind::Status, 200);
        h.note(RequestKind::Transmit, 900);
        assert_eq!(h.worst(RequestKind::Status), 300);
        assert_eq!(h.worst(RequestKind::Upload), 0);
        assert_eq!(h.worst(RequestKind::Transmit), 900);
        assert_eq!(h.worst_of_all(), 900);
        for (i, k) in RequestKind::ALL.iter().enumerate() {
            assert_eq!(k.index(), i);
        }
    }

    #[test]
    fn requests_are_classified_by_what_they_touch() {
        assert_eq!(RequestKind::of(&Request::Status), RequestKind::Status);
        assert_eq!(RequestKind::of(&Request::TableClear), RequestKind::Table);
        assert_eq!(RequestKind::of(&Request::LearnedClear), RequestKind::Table);
        assert_eq!(
            RequestKind::of(&Request::Control(piezo_link::Control::Feedforward)),
            RequestKind::Control
        );
        assert_eq!(
            RequestKind::of(&Request::Frames { decimation: 1 }),
            RequestKind::Other
        );
    }
}
