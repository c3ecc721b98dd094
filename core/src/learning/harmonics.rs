//! Learning at a periodic trial's harmonics above Q's cut-off from the stage's response
//! measured on the trial itself (model-less inversion-based iterative control: Kim & Zou 2008,
//! "A novel model-less inversion-based iterative control (MIIC)"; Tien, Zou & Devasia 2005,
//! "Iterative control of dynamics-coupling-caused errors in piezoscanners").
//!
//! # The update (one period of n samples, harmonic h at f_h = h/(nT), f_c < f_h < 1/(2T))
//! ```text
//! X(h)       = (1/n)·Σ_j x[j]·e^(−j2πhj/n)          for x = u_k, y_k, r, and the next command
//! Ĝ(h)       = ḡ·Y(h)/Ŵ(h)                           the stage's response on this trial
//! U_next(h)  = U(h) + ρ·s_h·(R(h) − Y(h))/Ĝ(h),       s_h = max(0, 1 − (σ_y²/n)/|R(h) − Y(h)|²)
//! ```
//! ŵ is the hysteresis model's own output for u_k and ḡ its mean slope dy/du along u_k: for a
//! linear model Ŵ = ḡ·U and Ĝ = Y/U, the ratio of the MIIC papers. A piezo stack is not
//! linear: its hysteresis turns the trajectory's fundamental into harmonics of its own, which
//! reach Y(h) whatever U(h) is, and Y/U then reads them as the stage's response (on the XY stage
//! the update at the y mode swung the ring from 28 nm to 67 nm and back); Y/Ŵ leaves them out,
//! as far as the model holds, and keeps what is linear: the stage's dynamics after the stack.
//! The next command's component at h (what Q left there: about the compensator's own) is
//! replaced by U_next(h), its conjugate at n − h with it, so the command stays real.
//! U is the command the trial reports: for the voltage applied (table + servo correction) Ĝ is
//! the stage's own response; for a table under a servo the trial does not see, Ĝ is the
//! table → output response G·S. Either way the update is in the same signal as Ĝ, which is what
//! makes it exact for a linear stage: R − Y_next = (1 − ρ·s_h·G/Ĝ)·(R − Y).
//!
//! **Gates** (a harmonic that passes them all learns; one that passes them widened twofold, SNR
//! 4, factor 4, 90°, keeps the command's own component, so that a harmonic on a gate's edge does
//! not swing between learned and Q's from one trial to the next; any other is left to Q):
//! * SNR: `|G_model(h)|·|U(h)| ≥ 8·σ_y/√n` (for the G_model that agrees, below) and `|U(h)| ≥ 8·σ_u/√n` ([`HARMONIC_SNR`]; σ/√n is
//!   the RMS of a white noise's DFT coefficient; σ_y, σ_u from the spread between the trial's
//!   passes, so the step runs only on trials that average several). Then the noise moves Ĝ by
//!   at most ¼ of itself, |ε| ≤ 0.25, and the factor |1 − ρ·s_h/(1 + ε)| stays ≤
//!   1 − ρ·s_h·(1 − 1/3) < 1.
//! * The model: `1/2 ≤ |Ĝ/G_model| ≤ 2` and `|arg(Ĝ/G_model)| ≤ 45°`
//!   ([`HARMONIC_MODEL_FACTOR`], [`HARMONIC_MODEL_PHASE_RAD`]) for some G_model of the set the
//!   cut-off rule trusts: G_model(f) = ḡ·M_μ(f)·e^(−j2πfDT), ḡ the model's mean slope dy/du
//!   along u_k, M_μ the stage file's mode at μ·f_mode, μ at 33 values across (1 ± t), D its
//!   delay (a file without a mode: none, or one at the rule's 33 frequencies from f_u up, damping
//!   [`super::UNMODELLED_MODE_DAMPING`]). A lightly damped mode turns the phase by 180° within a
//!   few harmonics, so the stage file's own mode frequency alone would refuse the harmonics at
//!   it that ring most. A ratio the hysteresis's own harmonics or a disturbance made, far from
//!   every model of the set, is refused.
//! * A cap: |U_next(h) − U(h)| ≤ [`HARMONIC_STEP_CAP`] of the output window.
//!
//! At most [`MAX_HARMONICS`] harmonics, the lowest above f_c, are examined per step.

use super::C;
use core::f64::consts::PI;

/// The SNR a harmonic's U and predicted output need (module doc).
pub const HARMONIC_SNR: f64 = 8.0;
/// Ĝ/G_model's magnitude within \[1/factor, factor\].
pub const HARMONIC_MODEL_FACTOR: f64 = 2.0;
/// |arg(Ĝ/G_model)| at most this \[rad\] (45°).
pub const HARMONIC_MODEL_PHASE_RAD: f64 = PI / 4.0;
/// Largest change of a harmonic's amplitude per step, as a share of the output window.
pub const HARMONIC_STEP_CAP: f64 = 0.01;
/// Harmonics examined per step (the lowest above the cut-off).
pub const MAX_HARMONICS: usize = 512;

/// What the harmonic step reads.
pub(super) struct HarmonicInputs<'a> {
    /// r, y_k, u_k at sample j (non-finite samples already replaced).
    pub reference: &'a dyn Fn(usize) -> f64,
    pub measured: &'a dyn Fn(usize) -> f64,
    pub command: &'a dyn Fn(usize) -> f64,
    /// ŵ: the hysteresis model's own output along u_k, called for j = 0, 1, …, n − 1 in turn
    /// (the caller restarts at j = 0) \[m\].
    pub predicted: &'a mut dyn FnMut(usize) -> f64,
    /// ḡ: the model's mean slope dy/du along u_k \[m/V\].
    pub slope: f64,
    /// T \[s\], f_c \[Hz\].
    pub sample_period_s: f64,
    pub cutoff_hz: f64,
    /// σ_y \[m\] and σ_u \[V\]: the noise of one sample of the record.
    pub noise_measured_m: f64,
    pub noise_command_v: f64,
    /// The model's set of responses at a frequency \[m/V\]: `model(f, i)` for
    /// i < `model_count` (i = 0 the stage file's own).
    pub model: &'a dyn Fn(f64, usize) -> C,
    pub model_count: usize,
    /// ρ in (0, 1].
    pub gain: f64,
    /// Largest |ΔU(h)| \[V\].
    pub cap_v: f64,
}

/// The DFT coefficient's rotation e^(−j2π·h·j/n).
pub(super) fn twiddle(h: usize, j: usize, n: usize) -> (f64, f64) {
    let m = (h as u64 * j as u64 % n as u64) as f64;
    let phase = -2.0 * PI * m / n as f64;
    (libm::cos(phase), libm::sin(phase))
}

/// Replaces `next`'s component at each gated harmonic (module doc); returns how many.
pub(super) fn learn_harmonics(inp: &mut HarmonicInputs<'_>, next: &mut [f32]) -> usize {
    let n = next.len();
    if n < 4 || inp.gain.is_nan() || inp.gain <= 0.0 {
        return 0;
    }
    let t = inp.sample_period_s;
    let first = libm::floor(inp.cutoff_hz * n as f64 * t) as usize + 1;
    // Below the Nyquist frequency (its component has no phase to learn).
    let last = (n - 1) / 2;
    let scale = 1.0 / n as f64;
    let bin_noise_y = inp.noise_measured_m / libm::sqrt(n as f64);
    let bin_noise_u = inp.noise_command_v / libm::sqrt(n as f64);
    let mut learned = 0;
    for h in (first..=last).take(MAX_HARMONICS) {
        let (mut u, mut y, mut r, mut x) = (C(0.0, 0.0), C(0.0, 0.0), C(0.0, 0.0), C(0.0, 0.0));
        let mut w = C(0.0, 0.0);
        for (j, &next_j) in next.iter().enumerate() {
            let (c, s) = twiddle(h, j, n);
            let add = |acc: &mut C, v: f64| {
                acc.0 += v * c;
                acc.1 += v * s;
            };
            add(&mut u, (inp.command)(j));
            add(&mut y, (inp.measured)(j));
            add(&mut r, (inp.reference)(j));
            add(&mut x, f64::from(next_j));
            add(&mut w, (inp.predicted)(j));
        }
        let [u, y, r, x, w] = [u, y, r, x, w].map(|v| C(v.0 * scale, v.1 * scale));
        let f = h as f64 / (n as f64 * t);
        let target = match gated_step(inp, u, y, r, w, f, bin_noise_y, bin_noise_u, 1.0) {
            Some(step) => {
                learned += 1;
                C(u.0 + step.0, u.1 + step.1)
            }
            // Near the gates: held (so that a harmonic on a gate's edge does not swing between
            // learned and Q's trial after trial); far from them: Q's.
            None if gated_step(inp, u, y, r, w, f, bin_noise_y, bin_noise_u, 2.0).is_some() => u,
            None => continue,
        };
        let delta = C(target.0 - x.0, target.1 - x.1);
        if !(delta.0.is_finite() && delta.1.is_finite()) {
            continue;
        }
        // x[j] += 2·Re(Δ·e^(+j2πhj/n)): the harmonic and its conjugate at n − h.
        for (j, v) in next.iter_mut().enumerate() {
            let (c, s) = twiddle(h, j, n);
            // e^(+jφ) = (c, −s).
            *v += (2.0 * (delta.0 * c + delta.1 * s)) as f32;
        }
    }
    learned
}

/// ρ·s_h·(R − Y)/Ĝ at one harmonic, or `None` where a gate refuses it (module doc).
#[allow(clippy::too_many_arguments)]
fn gated_step(
    inp: &HarmonicInputs<'_>,
    u: C,
    y: C,
    r: C,
    w: C,
    f: f64,
    bin_noise_y: f64,
    bin_noise_u: f64,
    widen: f64,
) -> Option<C> {
    {
        let snr = HARMONIC_SNR / widen;
        let factor = HARMONIC_MODEL_FACTOR * widen;
        let phase = (HARMONIC_MODEL_PHASE_RAD * widen).min(PI);
        if !(u.abs() > 0.0 && w.abs() > 0.0) || u.abs() < snr * bin_noise_u {
            return None;
        }
        // The dynamics the trial shows, Y/Ŵ, times the model's small-signal slope.
        let dynamics = y.div(w);
        let estimate = C(dynamics.0 * inp.slope, dynamics.1 * inp.slope);
        let agrees = |model: C| {
            let ratio = estimate.div(model);
            let magnitude = ratio.abs();
            model.abs() * w.abs() / libm::fabs(inp.slope) >= snr * bin_noise_y
                && magnitude >= 1.0 / factor
                && magnitude <= factor
                && libm::fabs(libm::atan2(ratio.1, ratio.0)) <= phase
        };
        if !(0..inp.model_count.max(1)).any(|i| agrees((inp.model)(f, i))) {
            return None;
        }
        let error = C(r.0 - y.0, r.1 - y.1);
        let power = error.0 * error.0 + error.1 * error.1;
        let share = if power > 0.0 {
            (1.0 - bin_noise_y * bin_noise_y / power).max(0.0)
        } else {
            0.0
        };
        let mut step = error.div(estimate);
        step = C(step.0 * inp.gain * share, step.1 * inp.gain * share);
        let size = step.abs();
        if size > inp.cap_v {
            let k = inp.cap_v / size;
            step = C(step.0 * k, step.1 * k);
        }
        Some(step)
    }
}

#[cfg(test)]
#[allow(clippy::needless_range_loop)] // sample and harmonic indices over parallel arrays
mod tests {
    use super::*;

    /// A linear stage y = G·u with a resonance between two harmonics the model places 10 % off:
    /// one step with ρ = 1 removes the error at every harmonic above the cut-off (the stage's
    /// own response, measured), where the model's inverse would leave a share.
    #[test]
    fn a_linear_stage_is_inverted_at_its_harmonics_in_one_step() {
        const N: usize = 100;
        let t = 1e-4;
        let plant = |f: f64, fm: f64| {
            let (w, wm) = (2.0 * PI * f, 2.0 * PI * fm);
            C(wm * wm, 0.0).div(C(wm * wm - w * w, 0.04 * wm * w))
        };
        let harmonic = |h: usize, j: usize| libm::sin(2.0 * PI * (h * j) as f64 / N as f64);
        // Command: a 100 Hz wave plus content at harmonics 15 and 22 (1.5 and 2.2 kHz).
        let u: [f64; N] =
            core::array::from_fn(|j| 60.0 + 40.0 * harmonic(1, j) + 0.2 * harmonic(15, j));
        // The response of G = plant(f, 2200) to u (harmonics one by one).
        let respond = |x: &[f64; N]| -> [f64; N] {
            let mut y = [0.0f64; N];
            for h in 0..N / 2 {
                let (mut re, mut im) = (0.0, 0.0);
                for j in 0..N {
                    let (c, s) = twiddle(h, j, N);
                    re += x[j] * c / N as f64;
                    im += x[j] * s / N as f64;
                }
                let g = if h == 0 {
                    C(1.0, 0.0)
                } else {
                    plant(h as f64 * 100.0, 2200.0)
                };
                let out = C(re, im).mul(g);
                for j in 0..N {
                    let (c, s) = twiddle(h, j, N);
                    let k = if h == 0 { 1.0 } else { 2.0 };
                    y[j] += k * (out.0 * c + out.1 * s);
                }
            }
            y
        };
        let y = respond(&u);
        // The reference: the same wave without the content at 15, and 2 mV worth at 22.
        let wanted: [f64; N] =
            core::array::from_fn(|j| 60.0 + 40.0 * harmonic(1, j) + 0.002 * harmonic(22, j));
        let r = respond(&wanted);
        let model = |f: f64, _: usize| plant(f, 2000.0);
        let mut next: [f32; N] = core::array::from_fn(|j| u[j] as f32);
        let learned = learn_harmonics(
            &mut HarmonicInputs {
                reference: &|j| r[j],
                measured: &|j| y[j],
                command: &|j| u[j],
                predicted: &mut |j| u[j],
                slope: 1.0,
                sample_period_s: t,
                cutoff_hz: 1000.0,
                noise_measured_m: 1e-9,
                noise_command_v: 1e-6,
                model: &model,
                model_count: 1,
                gain: 1.0,
                cap_v: 1.0,
            },
            &mut next,
        );
        // Harmonics 11 … 49 with content: 15 (in u and y) only; 22 has none in u (no estimate).
        assert_eq!(learned, 1);
        let after = respond(&core::array::from_fn(|j| f64::from(next[j])));
        let rms = |a: &[f64; N], b: &[f64; N]| {
            libm::sqrt(a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum::<f64>() / N as f64)
        };
        // The error left is the 22nd harmonic's alone (nothing to estimate it from).
        let only_22: [f64; N] = core::array::from_fn(|j| 60.0 + 40.0 * harmonic(1, j));
        let left = rms(&r, &respond(&only_22));
        assert!(rms(&r, &y) > 5.0 * left, "{} vs {left}", rms(&r, &y));
        assert!(
            (rms(&r, &after) - left).abs() < 1e-4 * rms(&r, &y),
            "{}",
            rms(&r, &after)
        );
    }
}
