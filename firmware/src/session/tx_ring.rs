//! The session's transmit buffer: a ring of bytes into which a whole encoded packet is copied
//! with at most two slice copies (the link queues a reply under the session's lock, so the copy
//! is part of that hold; byte by byte it cost ≈ 29 core cycles a byte on the Cortex-M4F).
//!
//! With `N` bytes of storage, `head` the oldest byte and `len` bytes held, byte `i` of the queue
//! is at `(head + i) mod N`; a packet of `n ≤ N − len` bytes goes to `(head + len) mod N`
//! onwards, wrapping to 0.

/// A byte ring of `N` bytes.
pub struct TxRing<const N: usize> {
    bytes: [u8; N],
    head: usize,
    len: usize,
}

impl<const N: usize> TxRing<N> {
    /// An empty ring.
    pub const fn new() -> Self {
        Self {
            bytes: [0; N],
            head: 0,
            len: 0,
        }
    }

    /// Bytes held.
    pub fn len(&self) -> usize {
        self.len
    }

    /// Bytes free.
    pub fn room(&self) -> usize {
        N - self.len
    }

    /// Appends all of `data`, or nothing (false) if it does not fit.
    pub fn push_slice(&mut self, data: &[u8]) -> bool {
        if data.len() > self.room() {
            return false;
        }
        // head < N and len <= N: one subtraction wraps it.
        let tail = self.head + self.len;
        let tail = if tail >= N { tail - N } else { tail };
        let first = data.len().min(N - tail);
        let (a, b) = data.split_at(first);
        if let Some(dst) = self.bytes.get_mut(tail..tail + first) {
            dst.copy_from_slice(a);
        }
        if let Some(dst) = self.bytes.get_mut(..b.len()) {
            dst.copy_from_slice(b);
        }
        self.len += data.len();
        true
    }

    /// Hands the bytes held, oldest first, to `put` until it refuses one (returns false) and
    /// removes those it took; returns how many.
    pub fn drain_with(&mut self, mut put: impl FnMut(u8) -> bool) -> usize {
        let mut taken = 0;
        while self.len > 0 {
            let run = self.len.min(N - self.head);
            let start = self.head;
            let mut n = 0;
            if let Some(bytes) = self.bytes.get(start..start + run) {
                for &b in bytes {
                    if !put(b) {
                        break;
                    }
                    n += 1;
                }
            }
            self.head = if start + n == N { 0 } else { start + n };
            self.len -= n;
            taken += n;
            if n < run {
                break;
            }
        }
        taken
    }
}

impl<const N: usize> Default for TxRing<N> {
    fn default() -> Self {
        Self::new()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn drain<const N: usize>(r: &mut TxRing<N>) -> std::vec::Vec<u8> {
        let mut out = std::vec::Vec::new();
        r.drain_with(|b| {
            out.push(b);
            true
        });
        out
    }

    #[test]
    fn drain_with_stops_where_the_taker_refuses_across_the_wrap() {
        let mut r = TxRing::<8>::new();
        assert!(r.push_slice(&[0; 6]));
        drain(&mut r);
        assert!(r.push_slice(&[1, 2, 3, 4, 5]));
        let mut got = std::vec::Vec::new();
        let n = r.drain_with(|b| {
            if got.len() == 3 {
                return false;
            }
            got.push(b);
            true
        });
        assert_eq!((n, got.as_slice()), (3, [1, 2, 3].as_slice()));
        assert_eq!(r.drain_with(|b| b != 5), 1);
        assert_eq!(drain(&mut r), [5]);
        assert_eq!(r.len(), 0);
        assert_eq!(r.drain_with(|_| true), 0);
    }

    #[test]
    fn packets_come_out_in_order_across_the_wrap() {
        let mut r = TxRing::<8>::new();
        assert!(r.push_slice(&[1, 2, 3, 4, 5]));
        assert!(!r.push_slice(&[6, 7, 8, 9]), "4 bytes into 3 free");
        assert_eq!(r.len(), 5);
        let mut four = 0;
        r.drain_with(|_| {
            four += 1;
            four <= 4
        });
        // head 4, one byte held: 6 bytes go to 5, 6, 7 and 0, 1, 2.
        assert!(r.push_slice(&[6, 7, 8, 9, 10, 11]));
        assert_eq!(r.room(), 1);
        assert_eq!(drain(&mut r), [5, 6, 7, 8, 9, 10, 11]);
        assert_eq!(r.len(), 0);
        assert!(r.push_slice(&[]));
        assert!(r.push_slice(&[1; 8]));
        assert_eq!(drain(&mut r), [1; 8]);
    }
}
