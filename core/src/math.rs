//! Branch-based `min`, `max` and `clamp` for the per-sample path.
//!
//! On the Cortex-M4F (FPv4, no VMAXNM/VMINNM) `f32::max`/`f32::min` compile to calls of the
//! `fmaxf`/`fminf` library routines, and `f32::clamp` keeps a panic path for `min > max`. These
//! compile to a compare and conditional moves. NaN behaviour is stated per function; callers
//! handle NaN before relying on it.

/// The smaller of `a` and `b`; `b` when either is NaN.
#[inline(always)]
pub(crate) fn min(a: f32, b: f32) -> f32 {
    if a < b {
        a
    } else {
        b
    }
}

/// The larger of `a` and `b`; `b` when either is NaN.
#[inline(always)]
pub(crate) fn max(a: f32, b: f32) -> f32 {
    if a > b {
        a
    } else {
        b
    }
}

/// `x` forced into `[lo, hi]` (`lo ≤ hi` assumed, not checked); NaN gives `lo`.
#[inline(always)]
pub(crate) fn clamp(x: f32, lo: f32, hi: f32) -> f32 {
    if x > hi {
        hi
    } else if x >= lo {
        x
    } else {
        lo
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn semantics_including_nan() {
        assert_eq!(min(1.0, 2.0), 1.0);
        assert_eq!(max(1.0, 2.0), 2.0);
        assert_eq!(clamp(5.0, 0.0, 1.0), 1.0);
        assert_eq!(clamp(-5.0, 0.0, 1.0), 0.0);
        assert_eq!(clamp(0.5, 0.0, 1.0), 0.5);
        assert_eq!(clamp(f32::NAN, 0.0, 1.0), 0.0);
        assert_eq!(clamp(f32::INFINITY, 0.0, 1.0), 1.0);
        assert_eq!(clamp(f32::NEG_INFINITY, 0.0, 1.0), 0.0);
        assert_eq!(clamp(3.0, f32::NEG_INFINITY, f32::INFINITY), 3.0);
        assert_eq!(min(f32::NAN, 2.0), 2.0);
        assert_eq!(max(f32::NAN, 2.0), 2.0);
    }
}
