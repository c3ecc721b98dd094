//! Error-growth back-off between trials: a learning loop watches each trial's measured error
//! against the trial before, and when it grew by more than [`ERROR_GROWTH_LIMIT`] it does not
//! learn from that trial but steps back halfway to the table before and halves the gain of the
//! learning above Q's cut-off (the step that trusts the trial's own measured response).
//!
//! ```text
//! e_k      the RMS of r − y_k over trial k (what the sensor measured, averaged over its passes)
//! e_k > (1 + g)·e_{k−1} and trial k−1 learned
//!          ⇒  u_{k+1} = u_{k−1} + ½·(u_k − u_{k−1}),   ρ_scale ← ½·ρ_scale   (g = ERROR_GROWTH_LIMIT)
//! otherwise ⇒  u_{k+1} = the learning step's
//! ```
//! A trial that stepped back is always learned from: a stage whose error grows whatever the
//! table (drift, creep without feedback) then still learns every other trial, where comparing
//! with a held error would stop the learning for good.
//!
//! Why: the step's factor |Q·(1 − L·G)| < 1 holds for the linear part of the plants the rule
//! knows; what it does not know (a hysteresis loop the step's linearisation moves, a noise the
//! estimate missed, a harmonic's response misread) can make a trial worse. A trial that is
//! worse is a measurement of that, for any plant: its table is not learned from, the loop
//! returns halfway to the table that was better (for a linear plant, e = r − G·u, the error of
//! the mean of two tables is the mean of their errors, its RMS at most the mean of their RMS), and the learning above the cut-off, the part that trusts the
//! trial most, slows. The held table is the caller's (this module allocates nothing).

/// A trial whose measured RMS error exceeds the trial before's by more than this share backs
/// off.
pub const ERROR_GROWTH_LIMIT: f64 = 0.05;

/// The back-off's state across the trials of one learning run (module doc).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BackOff {
    /// e_{k−1}: the measured RMS error of the trial before \[m\] (NaN before the first trial).
    previous_error_m: f64,
    /// Whether the trial before stepped back.
    stepped_back: bool,
    /// The factor on ρ of the learning above the cut-off, in (0, 1].
    harmonic_scale: f64,
    /// Trials that backed off so far.
    backed_off: usize,
}

impl Default for BackOff {
    fn default() -> Self {
        Self::new()
    }
}

/// What to do after a trial.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Verdict {
    /// The error did not grow (or the trial before stepped back): learn from the trial, and hold
    /// its table.
    Learn,
    /// The error grew: step back halfway to the table before ([`step_back`]).
    StepBack,
}

impl BackOff {
    /// Before the first trial.
    pub const fn new() -> Self {
        Self {
            previous_error_m: f64::NAN,
            stepped_back: false,
            harmonic_scale: 1.0,
            backed_off: 0,
        }
    }

    /// Judges a trial by its measured RMS error `error_m` \[m\] (module doc). A non-finite or
    /// negative error backs off (nothing is learned from a trial that measured nothing).
    pub fn judge(&mut self, error_m: f64) -> Verdict {
        let grew = !(error_m.is_finite() && error_m >= 0.0)
            || error_m > (1.0 + ERROR_GROWTH_LIMIT) * self.previous_error_m;
        self.previous_error_m = if error_m.is_finite() {
            error_m
        } else {
            f64::NAN
        };
        if grew && !self.stepped_back {
            self.harmonic_scale *= 0.5;
            self.backed_off += 1;
            self.stepped_back = true;
            Verdict::StepBack
        } else {
            self.stepped_back = false;
            Verdict::Learn
        }
    }

    /// The factor on ρ of the learning above the cut-off: 1/2 per trial that backed off.
    pub fn harmonic_scale(&self) -> f64 {
        self.harmonic_scale
    }

    /// Trials that backed off so far.
    pub fn backed_off(&self) -> usize {
        self.backed_off
    }

    /// e_{k−1}: the measured error of the last trial judged \[m\] (NaN before the first).
    pub fn previous_error_m(&self) -> f64 {
        self.previous_error_m
    }
}

/// `next[j] = held[j] + ½·(played[j] − held[j])`, `held` the table of the trial before (module
/// doc): between two tables that are
/// inside the window and the slew limit, so is their mean. Samples beyond the shortest slice
/// are left as they are; a non-finite sample of either table keeps the other's.
pub fn step_back(held: &[f32], played: &[f32], next: &mut [f32]) {
    for ((n, &h), &p) in next.iter_mut().zip(held).zip(played) {
        *n = match (h.is_finite(), p.is_finite()) {
            (true, true) => h + 0.5 * (p - h),
            (true, false) => h,
            (false, true) => p,
            (false, false) => *n,
        };
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_trial_that_grew_steps_back_and_halves_the_harmonic_gain() {
        let mut b = BackOff::new();
        assert_eq!(b.judge(10e-9), Verdict::Learn);
        assert_eq!(b.judge(8e-9), Verdict::Learn);
        // Within 5 %: learned.
        assert_eq!(b.judge(8.3e-9), Verdict::Learn);
        assert_eq!(b.previous_error_m(), 8.3e-9);
        assert_eq!(b.judge(9e-9), Verdict::StepBack);
        assert_eq!(b.harmonic_scale(), 0.5);
        // After a step back the next trial learns, even when it grew again (a drift that
        // grows whatever the table must not stop the learning).
        assert_eq!(b.judge(9.9e-9), Verdict::Learn);
        assert_eq!(b.judge(f64::NAN), Verdict::StepBack);
        assert_eq!(b.harmonic_scale(), 0.25);
        assert_eq!(b.judge(7e-9), Verdict::Learn);
        assert_eq!(b.judge(7e-9), Verdict::Learn);
        assert_eq!(b.backed_off(), 2);
        let mut next = [0.0f32; 3];
        step_back(&[1.0, 2.0, f32::NAN], &[3.0, 2.0, 5.0], &mut next);
        assert_eq!(next, [2.0, 2.0, 5.0]);
    }
}
