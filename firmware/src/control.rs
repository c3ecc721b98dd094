//! Tracking-error statistics of a loop run: RMS and peak of reference − sensor, accumulated one
//! sample at a time in f32 (the QEMU image's self-check, the command link's `track` report and the
//! servo table).

/// Running tracking-error statistics (RMS and peak).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct TrackingStats {
    count: u32,
    sum_sq_m2: f32,
    max_abs_m: f32,
}

impl TrackingStats {
    /// Adds one error sample (non-finite samples make the RMS and peak infinite).
    pub fn push(&mut self, error_m: f32) {
        let e = if error_m.is_finite() {
            error_m
        } else {
            f32::INFINITY
        };
        self.count = self.count.saturating_add(1);
        self.sum_sq_m2 += e * e;
        self.max_abs_m = self.max_abs_m.max(e.abs());
    }

    /// Number of samples.
    pub fn count(&self) -> u32 {
        self.count
    }

    /// Root mean square error, metres (0 with no samples).
    pub fn rms_m(&self) -> f32 {
        if self.count == 0 {
            0.0
        } else {
            libm::sqrtf(self.sum_sq_m2 / self.count as f32)
        }
    }

    /// Largest absolute error, metres.
    pub fn max_abs_m(&self) -> f32 {
        self.max_abs_m
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tracking_stats() {
        let mut s = TrackingStats::default();
        assert_eq!(s.rms_m(), 0.0);
        s.push(3.0);
        s.push(-4.0);
        assert_eq!(s.count(), 2);
        assert!((s.rms_m() - libm::sqrtf(12.5)).abs() < 1e-6);
        assert_eq!(s.max_abs_m(), 4.0);
        s.push(f32::NAN);
        assert_eq!(s.max_abs_m(), f32::INFINITY);
    }
}
