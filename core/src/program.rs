//! What the loop's reference generator plays: one [`Wave`] per axis, a raster, the streamed
//! setpoints or the wave table ([`Program`]). The one definition: the firmware's generator plays
//! it and the command link carries it (`piezo_link::Request::Track` and `Excite`).
//!
//! A wave is `r(φ) = offset + amplitude · w(φ)`, `w ∈ [−1, 1]`, at the phase φ in cycles that
//! advances by `f·T` per tick of period T and wraps to `[0, 1)`, starting at φ = 0:
//!
//! ```text
//! constant   w = 0                      (r = offset)
//! sine       w = sin(2πφ)
//! triangle   w = 4φ − 1 for φ < ½,  3 − 4φ after   (−1 at φ = 0, +1 at φ = ½)
//! steps      w = −1 for φ < ½,      +1 after
//! ```
//!
//! Values are in the unit of the request that plays them: metres for a tracked reference, stack
//! volts for an open-loop excitation. With the `serde` feature both derive serde; their postcard
//! encoding is the link's wire format (variant index, then the fields in order), so the order of
//! the variants and of their fields is part of it.

/// One axis's periodic waveform, `offset + amplitude · w(φ)` with `w ∈ [−1, 1]` (module doc).
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub enum Wave {
    /// `offset`.
    Constant {
        /// Value.
        offset: f32,
    },
    /// `offset + amplitude · sin(2πφ)`.
    Sine {
        /// Centre.
        offset: f32,
        /// Amplitude.
        amplitude: f32,
        /// Frequency \[Hz\].
        frequency_hz: f32,
    },
    /// `offset + amplitude · tri(φ)`, rising from −1 at φ = 0 to +1 at φ = ½.
    Triangle {
        /// Centre.
        offset: f32,
        /// Amplitude.
        amplitude: f32,
        /// Frequency \[Hz\].
        frequency_hz: f32,
    },
    /// `offset − amplitude` for φ < ½, `offset + amplitude` after.
    Steps {
        /// Centre.
        offset: f32,
        /// Half the step height.
        amplitude: f32,
        /// Frequency \[Hz\].
        frequency_hz: f32,
    },
}

impl Wave {
    /// The frequency f \[Hz\] its phase advances at (0 for a constant).
    #[inline]
    pub fn frequency_hz(&self) -> f32 {
        match *self {
            Wave::Constant { .. } => 0.0,
            Wave::Sine { frequency_hz, .. }
            | Wave::Triangle { frequency_hz, .. }
            | Wave::Steps { frequency_hz, .. } => frequency_hz,
        }
    }
}

/// What the reference generator plays.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub enum Program {
    /// One waveform per axis, `[x, y]`.
    PerAxis([Wave; 2]),
    /// The wave table (filled by the link's `TableAppend`): entry j at tick j·`ticks_per_entry`,
    /// linear in between; after the last entry it is held, or the table starts again (`repeat`,
    /// interpolating from the last entry to the first).
    Table {
        /// Ticks from one entry to the next (≥ 1; the generator takes 0 as 1, the link refuses
        /// it).
        ticks_per_entry: u32,
        /// Start again after the last entry.
        repeat: bool,
    },
    /// Setpoints from a queue (the link's `Stream`), one per tick; the last one is held when the
    /// queue runs dry (counted as an underrun).
    Streamed,
    /// Raster scan: x sweeps a triangle between `x_min` and `x_max`, one line per half period
    /// (`½·line_rate_hz` periods per second); at each turn-around y moves to the next of
    /// `lines` equally spaced rows between `y_min` and `y_max`, then back (boustrophedon).
    Raster {
        /// Left end of a line.
        x_min: f32,
        /// Right end of a line.
        x_max: f32,
        /// First row.
        y_min: f32,
        /// Last row.
        y_max: f32,
        /// Rows (fewer than 2 are taken as 2).
        lines: u16,
        /// Lines per second \[Hz\] (a triangle period is two lines).
        line_rate_hz: f32,
    },
}
