//! FNV-1a, 32 bit (Fowler–Noll–Vo, offset basis 0x811c9dc5, prime 0x01000193):
//!
//! ```text
//! h₀ = 0x811c9dc5,   h_{i+1} = (h_i ⊕ b_i) · 0x01000193  mod 2³²
//! ```
//!
//! The hash of a stage file's bytes (the version the firmware's build logs and an upload
//! carries) and, fed byte by byte ([`Fnv1a32`]), the fingerprint of a parameter set's content
//! (`piezo_link::ModelSet::fingerprint`).

/// FNV-1a's state, fed one byte at a time.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Fnv1a32(u32);

impl Default for Fnv1a32 {
    fn default() -> Self {
        Self::new()
    }
}

impl Fnv1a32 {
    /// `h₀ = 0x811c9dc5`.
    pub const fn new() -> Self {
        Self(0x811c_9dc5)
    }

    /// `h ← (h ⊕ b) · 0x01000193 mod 2³²`.
    pub fn push(&mut self, byte: u8) {
        self.0 = (self.0 ^ u32::from(byte)).wrapping_mul(0x0100_0193);
    }

    /// The hash of the bytes pushed so far.
    pub const fn value(self) -> u32 {
        self.0
    }
}

/// FNV-1a (32 bit) of `bytes`.
pub fn fnv1a32(bytes: &[u8]) -> u32 {
    let mut h = Fnv1a32::new();
    bytes.iter().for_each(|&b| h.push(b));
    h.value()
}
