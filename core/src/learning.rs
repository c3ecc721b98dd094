//! Iterative learning control (ILC) for repeated trajectories: one trial's reference r, command
//! u_k and measured output y_k (same length: one period of a periodic trajectory, or one whole
//! trial from rest) give the next trial's command. Caller-supplied slices, no allocation.
//!
//! # The learning step (per axis, sample period T)
//! ```text
//! e_k[j]     = r[j] − y_k[j]                                       error of trial k [m]
//! z[j]       = e_k(j + D)          the error D samples later (linear interpolation between
//!                                  e[j + ⌊D⌋] and e[j + ⌊D⌋ + 1]): u[j] shows at output sample j + D
//! s[j]       = z[j] + ((1 − ρ)ζ/(ωT))·(z[j+1] − z[j−1]) + (z[j+1] − 2z[j] + z[j−1])/(ωT)²
//!                                  inverse of the mode z̈ + 2ζω·(ż − ρ·ṡ) + ω²·(z − s) = 0
//!                                  (central differences, as the inverse chain; s = z without
//!                                  a mode)
//! (L·e_k)[j] = λ · s[j] / g[j]     g[j] = dy/du of the hysteresis model at step j along u_k
//! u_{k+1}    = u_0 + Q·(u_k − u_0 + L·e_k),   then limited to the window and the slew limit
//! ```
//! u_0 is the compensator's command for r (iteration 0); with u_0 = 0 this is the textbook
//! `Q·(u_k + L·e_k)`. Q acts on what was learned, not on the compensator's own command, so the
//! error outside Q's band is the compensator's rather than the whole reference. The contraction
//! is the same: with δ_k = u_k − u_0 and e_k = e_0 − G·δ_k, δ_{k+1} = Q·((1 − L·G)·δ_k + L·e_0).
//! A base the output window held (u_0 at `output_min_v` or `output_max_v` over at least
//! [`LIMITED_BASE_SHARE`] of the trial: the model asks for more than the window, its gain is off)
//! has corners that are the window's, not the stage's, and above Q's cut-off nothing would ever
//! remove them; such a base is filtered too, `u_{k+1} = Q·(u_k + L·e_k)` (the textbook form).
//! Sign convention: e = r − y; for a stage whose output rises with voltage (g > 0) a positive
//! error raises the command.
//!
//! * **Rate-dependent hysteresis**: L inverts the model's linearised dynamics along u_k, not only
//!   its one-sample slope g. With the operator's input lag (`hysteresis_lag_s`, v\[j\] =
//!   v\[j−1\] + c·(u\[j−1\] − v\[j−1\]) + b·(u\[j\] − u\[j−1\])) a correction Δu moves the
//!   output by `g[j]·Δu[j] + k2·(dh/dv)[j]·Δv⁻[j]`, Δv⁻\[j\] = Δv\[j−1\] + c·(Δu\[j−1\] − Δv\[j−1\])
//!   − b·Δu\[j−1\] (the lag's memory of earlier corrections); with the relaxation of the effects
//!   (Σ g_wᵢ·vᵢ, vᵢ a lag of p = w − k_r·u) it also moves by Σ g_wᵢ·Δvᵢ\[j\], Δvᵢ\[j+1\] = Δvᵢ\[j\] +
//!   (1 − bᵢ)·(Δp\[j\] − Δvᵢ\[j\]). `(L·e)[j] = λ·Δu[j]` with Δu solved sample by sample so that
//!   the model moves by s\[j\]; a periodic trial runs this recursion over the period twice and
//!   keeps the second pass (its memory in the periodic state). Without either, Δu = s/g as above.
//! * **Learning gain** λ = 2/(γ_min + γ_max): the plant's gain is γ times the model's, γ in
//!   `[gain_min, gain_max]`; λ balances the two ends, max|1 − λγ| = (γ_max − γ_min)/(γ_max + γ_min).
//! * **Q** is a zero-phase low-pass: a 4th-order Butterworth (two biquads, bilinear transform
//!   with prewarping) run forward and then backward, so
//!   `|Q(f)| = 1/(1 + (tan(πfT)/tan(πf_cT))⁸)` and its phase is 0. Periodic trials are filtered
//!   circularly (each pass starts from its periodic steady state, solved exactly); a trial from
//!   rest starts each pass in the steady state of its first sample.
//! * **The cut-off rule** (monotone convergence with a margin m): with the model's
//!   `G(f) = γ·g·M_μ(f)·e^(−j2πfDT)` (M_μ the continuous mode at μ·f_mode, damping ζ, the share ρ
//!   of it on the relative motion) and L's own frequency response (the interpolated shift and the
//!   central-difference inverse above),
//!   `W(f) = max |1 − λ·γ·M_μ(f)·M̂⁻¹(f)·S_D(f)·e^(−j2πfDT)|` over γ ∈ {γ_min, γ_max} and
//!   μ ∈ [1 − t, 1 + t] (t = `mode_frequency_tolerance`; 33 values and μ = f/f_mode);
//!   **without a mode in the effects** the model claims no dynamics, which nothing checked: the
//!   plant may still have a lightly damped mode it lacks. The set then holds, besides no mode,
//!   every mode at or above f_u = `unmodelled_mode_fraction`/T with damping
//!   [`UNMODELLED_MODE_DAMPING`] (f_u itself, f itself when f ≥ f_u, and 33 frequencies spaced
//!   geometrically from f_u to 2/T), with M̂⁻¹ = 1 (L inverts no mode);
//!   f_c is the largest cut-off with `|Q(f)|·W(f) ≤ 1 − m` at 2048 frequencies across
//!   (0, 1/(2T)), in closed form per frequency:
//!   `f_c = min over f with W(f) > 1 − m of atan(tan(πfT)/(W(f)/(1 − m) − 1)^(1/8))/(πT)`,
//!   at most 0.4/T. Then ‖e_{k+1}‖ ≤ (1 − m)·‖e_k‖ for every plant in that set (the linear
//!   part, on a periodic trial). With a feedback servo whose sensitivity is S, learning on the
//!   applied command gives the factor |S·Q·(1 − L·G)| instead.
//! * **Under a servo** (a periodic trial with [`Trial::table_v`]): the command measured is the
//!   voltage applied U, the table T plus the servo's correction. The step starts from T and
//!   learns the same share of the correction U − T as of L·e, harmonic by harmonic:
//!   `T_next = u₀ + Q·(T − u₀ + s_h·(U − T + L·e))`, and for a linear stage
//!   `ε_next = (1 − s_h + s_h·S·(1 − L·G))·ε`: the factor S·(1 − L·G) at s_h = 1, and a
//!   harmonic at the noise (s_h ≈ 0) held. Started from U, the whole correction was handed
//!   over whatever s_h, `ε_next = S·(1 − s_h·L·G)·ε`, and a harmonic at the noise near the
//!   servo's crossover grew by |S| (up to 1.6 on the XY stage).
//! * **Sensor noise**: the measured error carries the sensor's noise, and L passes it into the
//!   next command: at full gain the table gathers noise trial after trial, and once the error is
//!   down at the noise the trials rise and fall with it. Each step therefore learns the share
//!   `s = max(0, 1 − σ̂²·b/⟨(Q·e)²⟩)` of L·e (a Wiener gain: the error inside Q's band against the
//!   noise expected there), `(L·e)[j] = s·λ·Δu[j]`. σ̂ is the white noise's standard deviation,
//!   estimated robustly from the fourth differences of e (a smooth error has none; a white noise
//!   has `var(Δ⁴n) = 70σ²`): `σ̂ = P25(|Δ⁴e|)/(0.3186·√70)`, the 25th percentile so that rings and
//!   corners over up to three quarters of the trial do not count as noise; `b = ⟨|Q(f)|²⟩` over
//!   (0, 1/(2T)) is the share of a white noise Q passes. s ≤ 1 keeps the contraction
//!   (|1 − s·z| ≤ (1 − s) + s·|1 − z|). A trial far above the noise learns with s ≈ 1.
//!   On a periodic trial the share is set **harmonic by harmonic** where Q passes
//!   (h ≤ 2·f_c·nT, the lowest [`SHARED_HARMONICS`]): the component of L·e at harmonic h is
//!   scaled by `s_h = max(0, 1 − (σ̂²/n)/|E(h)|²)` (E(h) the error's DFT coefficient, σ̂²/n a
//!   white noise's power in one), the rest by s. One share for the whole band learned the noise
//!   of every harmonic as soon as a few carried error (a 100 Hz sine at the noise: s ≈ 0.94 with
//!   nearly all of its error at two harmonics), and the table then carried each trial's noise
//!   into the next; with s_h a harmonic at the noise learns (almost) nothing and one far above
//!   it all. Each s_h ≤ 1, so the contraction holds harmonic by harmonic.
//! * **The model's gain, from the trial** ([`Learning::gain_ratio`]): the measured output against
//!   the model's own output for the trial's command, `y_k ≈ γ̂·ŷ(u_k) + ĉ` (least squares; ŷ from
//!   the model's state at rest, or in its periodic state for a periodic trial). Given when the
//!   model explains the trial (R² ≥ [`GAIN_FIT_MIN_R2`]): a caller may re-solve u_0 for
//!   (r − ĉ)/γ̂ and learn with L's gain λ/γ̂ ([`Learning::with_model_gain`]): a stage file
//!   whose gain is off then starts each step from a base that fits the stage, and learns as fast
//!   as a right one. Q is not changed: the rule's gain set then bounds the estimate's error.
//! * **Limits**: the result is clamped to `[output_min_v, output_max_v]` and to the slew limit S_r:
//!   a forward pass `u[j] ∈ u[j−1] ± S_r·T` (from rest at `output_min_v` for a trial from rest),
//!   and for a periodic table a backward pass from the first sample, which also holds the wrap
//!   from the last sample to the first (a learned table is safe to play in a loop).
//!
//! * **Above Q's cut-off** (periodic trials that average several passes, [`Trial::noise`]):
//!   at each harmonic of the period the stage's response is read from the trial itself and the
//!   command learns there, `U_next(h) = U(h) + ρ·s_h·(R(h) − Y(h))/Ĝ(h)`, behind an SNR, a model
//!   and an amplitude gate (module `harmonics`: the equation, the gates, the sources; ρ =
//!   `harmonic_gain`). The rule's set of plants forbids L there; the measured response need not.
//!   It learns only from a trial whose error inside Q's band has settled,
//!   `⟨(Q·e)²⟩ ≤ ½·⟨e²⟩` ([`IN_BAND_SETTLED_SHARE`]): while the error Q passes dominates, what
//!   lies above the cut-off is its transient (with feedback, the servo's correction of that
//!   error; with a base the window held, its corners), not the stage's response to the table.
//!   Learned into the table, it stays there: each step moves a harmonic by at most ρ of its
//!   error, and once its command falls to the SNR gate it is held. With a stage file whose gain
//!   is 0.6× the stage's (the first trial 5.7 % of the stroke off, the servo fighting it) the
//!   100 Hz sine with ρ = 0.5 ended at 0.114 % of the stroke, 38× the nominal file's; now at
//!   0.0021 % (`cargo test --release -p host-sim --test learn_bench harmonic`).
//! * **Mixing into the band**: a harmonic learned above the cut-off adds reversals to the path
//!   the stack's hysteresis follows, and a Bouc-Wen state integrates |du|: a fraction of a volt
//!   near the Nyquist frequency shifts the whole loop, which shows at the trajectory's first
//!   harmonics, inside Q's band, on the next trial. The step cancels what the model predicts
//!   there: with Δ the harmonic step's changes in time and, along one period of each from its
//!   periodic state, `M = Ŵ(u + Δ) − Ŵ(u) − ḡ·Δ` (ḡ the mean slope along u),
//!   `U_next(h) −= λ·M(h)/G_model(f_h)` at every harmonic h below the first the harmonic step
//!   examines (each at most the harmonic step's cap). On the XY stage with the stage file's
//!   mode ×0.85 the 100 Hz triangle with feedback rose up to 1.31× from one trial to the next,
//!   each time in the trial after a first step at a harmonic near the Nyquist frequency, the
//!   error gathered at the sample after each corner; `host-sim learn-bench --freq 100` gives
//!   today's figures (README)
//!   (`cargo test -p piezo-core a_learned_harmonic_s_mixing`: a 4 kHz change alone leaves
//!   209 nm in the band, 36 nm with the cancellation).
//! * **Mixing above the band**: the same mixing reaches the harmonics above the cut-off, where
//!   the stage's mode amplifies it and the step cannot cancel it (there the stage's response is
//!   the measured one, not the model's). On the XY stage with the stage file's mode ×1.15 the
//!   100 Hz triangle with feedback rose 1.15× in the trial after two first steps at 3.3 and
//!   3.5 kHz: the error there fell, and the y mode's harmonics near 2.1 kHz grew by more (a
//!   per-harmonic trace of the bench's error). The step is therefore scaled, all harmonics by
//!   one factor α ≤ 1, so that the mixing the model predicts there through the stage file's
//!   dynamics stays within κ of the trial's error RMS ([`LearningParams::collateral_share`], default 0.12):
//!   `c² = Σ_h 2·|G(f_h)/ḡ|²·|M(h)|²` over the harmonics the step examines, `α = min(1, κ·e/c)`
//!   (`cargo test -p piezo-core a_learned_harmonic_s_mixing_above_the_band`). It trades speed
//!   for monotony; `host-sim learn-bench --collateral-share 0` runs without it, and the README
//!   gives both.
//! * **Noise from the passes**: a trial that averages m passes of a periodic trajectory gives
//!   the averaged record's noise directly, `σ² = ⟨var_p(x_pj)⟩_j / m` ([`pass_noise_rms`]),
//!   without the fourth differences' assumption that the error is smooth: they mistake a ring
//!   above the cut-off for noise, and noise for a ring. The caller passes it as [`Trial::noise`].
//!
//! Never panics, for any slices: a non-finite reference or measured sample counts as no error,
//! a non-finite command sample as the compensator's.

pub mod back_off;
mod harmonics;

pub use back_off::{step_back, BackOff, Verdict, ERROR_GROWTH_LIMIT};
pub use harmonics::{
    HARMONIC_MODEL_FACTOR, HARMONIC_MODEL_PHASE_RAD, HARMONIC_SNR, HARMONIC_STEP_CAP, MAX_HARMONICS,
};

use crate::compensator::{Compensator, CompensatorSettings};
use crate::effects::{Effects, RELAXATION_LAGS};
use crate::error::{finite, ParamError};
use crate::math::clamp;
use crate::static_model::{ModelState, StaticModel};
use crate::Limits;
use core::f64::consts::PI;

/// A base held at a window bound over at least this share of the trial is filtered by Q with the
/// learned part (module doc).
pub const LIMITED_BASE_SHARE: f64 = 0.01;
/// The harmonic step learns from a trial whose error Q passes carries at most this share of its
/// mean square, ⟨(Q·e)²⟩ ≤ share·⟨e²⟩ (module doc, "Above Q's cut-off").
pub const IN_BAND_SETTLED_SHARE: f64 = 0.5;
/// Harmonics of a periodic trial whose learned share is set one by one (module doc, "Sensor
/// noise"); above them the band's share.
pub const SHARED_HARMONICS: usize = 512;
/// Frequencies at which the cut-off rule checks the convergence condition.
pub const RULE_FREQUENCIES: usize = 2048;
/// Mode frequencies (relative, spread over the tolerance) the rule checks per frequency.
pub const RULE_MODE_SAMPLES: usize = 33;

/// Modes of the set the harmonic step's model gate accepts (module `harmonics`, "The model"): the
/// rule's span sampled this densely. A mode of damping ζ moves its response by ×2 or 45° within
/// about ζ of its frequency at the harmonics that ring most: the rule's 33 frequencies from f_u
/// (12 % apart over 500 Hz – 20 kHz at 10 kHz) left a stage's 740 Hz mode between two of them,
/// and its harmonic at 700 Hz, the error's largest, was refused every step; now 1 % apart
/// (at the default `unmodelled_mode_fraction`).
pub const HARMONIC_MODEL_SAMPLES: usize = 385;

/// Damping ratio of the mode a model without one may lack (module doc): light, as a flexure's.
pub const UNMODELLED_MODE_DAMPING: f64 = 0.02;
/// Least R² of `y ≈ γ̂·ŷ + c` for [`Learning::gain_ratio`] to give γ̂.
pub const GAIN_FIT_MIN_R2: f64 = 0.9;
/// Fourth differences of a white noise: var(Δ⁴n) = C(8, 4)·σ² = 70·σ².
const FOURTH_DIFFERENCE_VARIANCE: f64 = 70.0;
/// The 25th percentile of |N(0, 1)|: Φ⁻¹(0.625).
const ABS_NORMAL_P25: f64 = 0.318_639_363_964_375_4;
/// Highest cut-off, as a fraction of the sample rate.
pub const MAX_CUTOFF_FRACTION: f64 = 0.4;
/// Q of the two biquads of the 4th-order Butterworth: 1/(2·sin(π/8)), 1/(2·sin(3π/8)).
const BUTTERWORTH4_Q: [f64; 2] = [1.306_562_964_876_376_5, 0.541_196_100_146_197];

/// The uncertainty the learning must converge under, and the margin.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LearningParams {
    /// Smallest plant/model gain ratio γ_min, > 0.
    pub gain_min: f32,
    /// Largest plant/model gain ratio γ_max, ≥ γ_min.
    pub gain_max: f32,
    /// Relative error of the model's mode frequency t: the plant's mode is within (1 ± t)·f_mode,
    /// 0 ≤ t < 0.9 (ignored without a mode).
    pub mode_frequency_tolerance: f32,
    /// m in |Q·(1 − L·G)| ≤ 1 − m, 0 < m < 1.
    pub margin: f32,
    /// Without a mode in the effects: the plant may have one at or above this fraction of the
    /// sample rate, f_u = fraction/T (module doc), 0 < fraction; 0.5 or more trusts the model's
    /// claim of no dynamics up to the Nyquist frequency.
    pub unmodelled_mode_fraction: f32,
    /// ρ of the learning at a periodic trial's harmonics above Q's cut-off from the stage's
    /// response measured on the trial (module doc), 0 ≤ ρ ≤ 1; 0 leaves them to Q. The default
    /// 0.5 takes the XY stage's 100 Hz triangle below 0.1 % of the stroke, where Q alone stops
    /// above it; it runs only on trials that average several passes ([`Trial::noise`]).
    pub harmonic_gain: f32,
    /// κ of the harmonic step's mixing above Q's band (module doc, "Mixing above the band"):
    /// the step is scaled so that what the model predicts it mixes into the harmonics above the
    /// band, through the stage file's dynamics, stays within κ of the trial's error RMS;
    /// 0 ≤ κ; 0 leaves the step unscaled.
    pub collateral_share: f32,
}

impl Default for LearningParams {
    /// γ in [0.6, 1.7] (a stage file whose gain is ×1.5 or ×0.6 off stays inside), mode ±20 %,
    /// margin 0.1, learning above the cut-off at ρ = 0.5; without a mode, one may lie at or above 1/20 of the sample rate (500 Hz at
    /// 10 kHz: a piezo stage's first flexure or load mode lies between a few hundred hertz and
    /// tens of kilohertz).
    fn default() -> Self {
        Self {
            gain_min: 0.6,
            gain_max: 1.7,
            mode_frequency_tolerance: 0.2,
            margin: 0.1,
            unmodelled_mode_fraction: 0.05,
            harmonic_gain: 0.5,
            collateral_share: 0.12,
        }
    }
}

/// One biquad, denominator `1 + a1·z⁻¹ + a2·z⁻²`, transposed direct form II (f64).
#[derive(Debug, Clone, Copy, PartialEq)]
struct Biquad {
    b: [f64; 3],
    a: [f64; 2],
}

impl Biquad {
    /// RBJ low-pass at `w0 = 2π·f_c·T` with quality `q` (the bilinear transform of
    /// 1/(s² + s/q + 1) prewarped at w0).
    fn lowpass(w0: f64, q: f64) -> Self {
        let (sin, cos) = (libm::sin(w0), libm::cos(w0));
        let alpha = sin / (2.0 * q);
        let a0 = 1.0 + alpha;
        let b1 = (1.0 - cos) / a0;
        Self {
            b: [0.5 * b1, b1, 0.5 * b1],
            a: [-2.0 * cos / a0, (1.0 - alpha) / a0],
        }
    }

    /// One sample: returns y, updates the state `s`.
    #[inline]
    fn tick(&self, s: &mut [f64; 2], x: f64) -> f64 {
        let y = self.b[0] * x + s[0];
        s[0] = self.b[1] * x - self.a[0] * y + s[1];
        s[1] = self.b[2] * x - self.a[1] * y;
        y
    }

    /// Filters `v` in place in the direction `reverse`; `periodic`: from the periodic steady
    /// state, else from the steady state of the first sample met.
    fn filter(&self, v: &mut [f32], reverse: bool, periodic: bool) {
        let n = v.len();
        let at = |i: usize| if reverse { n - 1 - i } else { i };
        let Some(&first) = v.get(at(0)) else { return };
        let mut s = if periodic {
            // Final state from zero: f; from s0: Aⁿ·s0 + f. Periodic: s0 = (I − Aⁿ)⁻¹·f.
            let mut f = [0.0; 2];
            for i in 0..n {
                self.tick(&mut f, f64::from(v[at(i)]));
            }
            let an = mat_pow([[-self.a[0], 1.0], [-self.a[1], 0.0]], n);
            let m = [[1.0 - an[0][0], -an[0][1]], [-an[1][0], 1.0 - an[1][1]]];
            let det = m[0][0] * m[1][1] - m[0][1] * m[1][0];
            if det.abs() > 1e-300 {
                [
                    (m[1][1] * f[0] - m[0][1] * f[1]) / det,
                    (m[0][0] * f[1] - m[1][0] * f[0]) / det,
                ]
            } else {
                [0.0; 2]
            }
        } else {
            let x = f64::from(first);
            [x * (1.0 - self.b[0]), x * (self.b[2] - self.a[1])]
        };
        for i in 0..n {
            let j = at(i);
            v[j] = self.tick(&mut s, f64::from(v[j])) as f32;
        }
    }
}

/// `m^n` by squaring.
fn mat_pow(mut m: [[f64; 2]; 2], mut n: usize) -> [[f64; 2]; 2] {
    let mul = |a: [[f64; 2]; 2], b: [[f64; 2]; 2]| {
        [
            [
                a[0][0] * b[0][0] + a[0][1] * b[1][0],
                a[0][0] * b[0][1] + a[0][1] * b[1][1],
            ],
            [
                a[1][0] * b[0][0] + a[1][1] * b[1][0],
                a[1][0] * b[0][1] + a[1][1] * b[1][1],
            ],
        ]
    };
    let mut out = [[1.0, 0.0], [0.0, 1.0]];
    while n > 0 {
        if n & 1 == 1 {
            out = mul(out, m);
        }
        m = mul(m, m);
        n >>= 1;
    }
    out
}

/// A complex number (re, im) for the rule's frequency responses.
#[derive(Debug, Clone, Copy)]
struct C(f64, f64);

impl C {
    fn mul(self, o: C) -> C {
        C(self.0 * o.0 - self.1 * o.1, self.0 * o.1 + self.1 * o.0)
    }
    fn div(self, o: C) -> C {
        let d = o.0 * o.0 + o.1 * o.1;
        C(
            (self.0 * o.0 + self.1 * o.1) / d,
            (self.1 * o.0 - self.0 * o.1) / d,
        )
    }
    fn expj(phase: f64) -> C {
        C(libm::cos(phase), libm::sin(phase))
    }
    fn abs(self) -> f64 {
        libm::hypot(self.0, self.1)
    }
}

/// The harmonic step's changes (h, Δ(h)) at sample j of a period of n: Σ 2·Re(Δ(h)·e^(+j2πhj/n)).
fn change_at(changes: &[(usize, C)], j: usize, n: usize) -> f64 {
    changes
        .iter()
        .map(|&(h, d)| {
            let (c, s) = harmonics::twiddle(h, j, n);
            2.0 * (d.0 * c + d.1 * s)
        })
        .sum()
}

/// The validated learning settings of one axis: the model it inverts, the delay and mode of its
/// effects, the limits, and the filter its rule chose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Learning {
    model: StaticModel,
    settings: CompensatorSettings,
    /// ⌊D⌋ and D − ⌊D⌋.
    delay_whole: usize,
    delay_fraction: f64,
    /// (f_mode \[Hz\], ζ, ρ) of the model's mode (ρ the share of ζ on the relative motion).
    mode: Option<(f64, f64, f64)>,
    /// The rate-dependent hysteresis of the effects: (1 − bᵢ, g_wᵢ) per element and k_r \[m/V\].
    relaxation: ([(f64, f64); RELAXATION_LAGS], f64),
    params: LearningParams,
    learning_gain: f64,
    cutoff_hz: f64,
    /// b = ⟨|Q(f)|²⟩ over (0, 1/(2T)): the share of a white noise's variance Q passes.
    noise_band_share: f64,
    sections: [Biquad; 2],
}

/// What a step measured and did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepSummary {
    /// RMS of r − y over the trial just measured \[m\].
    pub rms_error_m: f64,
    /// Largest |r − y| over the trial \[m\].
    pub max_abs_error_m: f64,
    /// Samples of the new command moved by the window or the slew limit.
    pub limited: usize,
    /// Whether the base was held at the window and filtered with the learned part (module doc).
    pub base_filtered: bool,
    /// σ̂: the sensor noise estimated from the trial's error \[m\] (module doc).
    pub noise_rms_m: f64,
    /// s: the share of L·e learned in this step, in \[0, 1\] (module doc).
    pub learned_share: f64,
    /// Harmonics above Q's cut-off learned from the stage's response measured on the trial
    /// (module doc; periodic trials only).
    pub harmonics_learned: usize,
    /// α: the factor the step at those harmonics was scaled by for its mixing above Q's band
    /// (module doc, "Mixing above the band"), in (0, 1]; 1 unscaled.
    pub harmonic_scale: f64,
}

/// The noise of a trial that averages several passes of a periodic trajectory, from the spread
/// between its passes ([`pass_noise_rms`]): of one sample of the averaged record.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrialNoise {
    /// σ_y of the averaged measured record \[m\].
    pub measured_m: f64,
    /// σ_u of the averaged command \[V\].
    pub command_v: f64,
}

/// Share of a record's nonzero sample-to-sample differences that must be whole multiples of the
/// smallest for [`quantum`] to read it as a quantised record.
pub const QUANTISED_SHARE: f64 = 0.9;

/// Fewest small sample-to-sample differences [`quantum`] judges a record by.
pub const QUANTUM_MIN_STEPS: usize = 10;

/// σ of one sample of the average of `record`'s passes: `record` holds m ≥ 2 whole passes of
/// `period` samples; per sample j the passes' unbiased variance v_j = Σ_p (x_pj − x̄_j)²/(m − 1),
/// and `σ² = ⟨v_j⟩_j / m` (the noise of a mean of m draws), at least q/√12 for a quantised
/// record of step q ([`quantum`]): passes of a quantised sensor that agree to the bit read no
/// spread, while their average still carries the quantisation error. Needs no assumption about the
/// noise's spectrum within a pass, only that it is independent between passes; what the passes
/// share (the trajectory, its rings) does not count. `None` for fewer than two passes, a length
/// that is not a whole number of them, or no finite sample; non-finite samples are left out.
pub fn pass_noise_rms(record: &[f32], period: usize) -> Option<f64> {
    if period == 0 || !record.len().is_multiple_of(period) || record.len() / period < 2 {
        return None;
    }
    let passes = record.len() / period;
    let (mut sum, mut samples) = (0.0f64, 0usize);
    for j in 0..period {
        let values = || {
            (0..passes)
                .map(move |p| record[p * period + j])
                .filter(|v| v.is_finite())
                .map(f64::from)
        };
        let count = values().count();
        if count < 2 {
            continue;
        }
        let mean = values().sum::<f64>() / count as f64;
        let variance = values().map(|v| (v - mean) * (v - mean)).sum::<f64>() / (count - 1) as f64;
        sum += variance / count as f64;
        samples += 1;
    }
    let spread = (samples > 0).then(|| libm::sqrt(sum / samples as f64))?;
    // Repeated readings of a quantised sensor agree to the bit, and their spread reads no
    // noise where the average still carries the quantisation error: not below q/√12.
    Some(match quantum(record) {
        Some(q) => spread.max(q / libm::sqrt(12.0)),
        None => spread,
    })
}

/// The step q of a quantised record: the mean of the nonzero differences between consecutive
/// finite samples within 1.3× the smallest, accepted when at least [`QUANTUM_MIN_STEPS`]
/// nonzero differences lie within 20 q and at least [`QUANTISED_SHARE`] of those are whole
/// multiples of it (within 1 %); `None` for a record that is not quantised (or shows too few
/// steps).
pub fn quantum(record: &[f32]) -> Option<f64> {
    let steps = || {
        record.windows(2).filter_map(|w| {
            let d = libm::fabs(f64::from(w[1]) - f64::from(w[0]));
            (d.is_finite() && d > 0.0).then_some(d)
        })
    };
    let smallest = steps().fold(f64::INFINITY, f64::min);
    if !smallest.is_finite() {
        return None;
    }
    // The mean of the one-step differences: each reading carries its own rounding (a record in
    // f32 metres), which the smallest alone would carry into every multiple.
    let (sum, count) = steps()
        .filter(|&d| d <= 1.3 * smallest)
        .fold((0.0, 0usize), |(s, c), d| (s + d, c + 1));
    let q = sum / count as f64;
    // Steps of up to 20 q, so that q's own rounding does not add up.
    let (mut whole, mut all) = (0usize, 0usize);
    for d in steps().filter(|&d| d <= 20.0 * q) {
        let k = d / q;
        all += 1;
        if libm::fabs(k - libm::round(k)) <= 0.01 {
            whole += 1;
        }
    }
    (all >= QUANTUM_MIN_STEPS && whole as f64 >= QUANTISED_SHARE * all as f64).then_some(q)
}

/// One trial, per axis: all slices of the same length.
#[derive(Debug, Clone, Copy)]
pub struct Trial<'a> {
    /// r: the reference at the output samples \[m\].
    pub reference_m: &'a [f32],
    /// u_k: the command of the trial (the voltage applied) \[V\].
    pub command_v: &'a [f32],
    /// y_k: the measured output \[m\].
    pub measured_m: &'a [f32],
    /// u_0: the compensator's command for r \[V\].
    pub base_v: &'a [f32],
    /// Whether the trial is one period of a trajectory played in a loop (else one run from rest
    /// at `output_min_v`).
    pub periodic: bool,
    /// The averaged record's noise from the spread between its passes, when the trial averages
    /// several (else estimated from the error's fourth differences; module doc).
    pub noise: Option<TrialNoise>,
    /// The trial before on the same trajectory and the same base (periodic trials): the harmonic
    /// step reads the stage's response from the change between the two where the last step
    /// moved a harmonic (module `harmonics`, "Two trials"). `None`: from this trial alone.
    pub previous: Option<PreviousTrial<'a>>,
    /// The table the trial played, where a servo added its correction on top (`command_v` is
    /// then the voltage applied): above Q's cut-off the harmonic step learns the table from its
    /// own response G·S (module `harmonics`, "Under a servo"). `None`: the command is the table.
    pub table_v: Option<&'a [f32]>,
}

/// The trial before ([`Trial::previous`]): slices of the same length as the trial's.
#[derive(Debug, Clone, Copy)]
pub struct PreviousTrial<'a> {
    /// u_{k−1}: its command \[V\].
    pub command_v: &'a [f32],
    /// y_{k−1}: its measured output \[m\].
    pub measured_m: &'a [f32],
    /// Its table, where a servo added its correction on top ([`Trial::table_v`]).
    pub table_v: Option<&'a [f32]>,
}

/// The lowest harmonic h of a period of n samples of `sample_period_s` above `cutoff_hz`:
/// h = ⌊f_c·n·T⌋ + 1.
fn first_harmonic_above(cutoff_hz: f64, n: usize, sample_period_s: f64) -> usize {
    libm::floor(cutoff_hz * n as f64 * sample_period_s) as usize + 1
}

impl Learning {
    /// Learning for the axis whose compensator is `compensator` (a position model) and whose
    /// effects are `effects` (delay and mode used; the rest is left to the learning), with the
    /// uncertainty and margin of `params`. Chooses the cut-off by the rule of the module doc.
    pub fn new(
        compensator: &Compensator,
        effects: &Effects,
        params: LearningParams,
    ) -> Result<Self, ParamError> {
        if !compensator.is_position() {
            return Err(ParamError::OutOfRange {
                field: "model",
                value: 0.0,
                requirement: "a static (position) model",
            });
        }
        let (lo, hi) = (
            finite("gain_min", params.gain_min)?,
            finite("gain_max", params.gain_max)?,
        );
        let margin = finite("margin", params.margin)?;
        if !(margin > 0.0 && margin < 1.0) {
            return Err(ParamError::OutOfRange {
                field: "margin",
                value: margin,
                requirement: "in (0, 1)",
            });
        }
        // Both finite (checked above), so plain comparisons cover every case.
        if lo <= 0.0 {
            return Err(ParamError::OutOfRange {
                field: "gain_min",
                value: lo,
                requirement: "> 0",
            });
        }
        let spread = (f64::from(hi) - f64::from(lo)) / (f64::from(hi) + f64::from(lo));
        if hi < lo || spread >= 1.0 - f64::from(margin) {
            return Err(ParamError::OutOfRange {
                field: "gain_max",
                value: hi,
                requirement:
                    ">= gain_min and (gain_max - gain_min)/(gain_max + gain_min) < 1 - margin",
            });
        }
        let tolerance = finite("mode_frequency_tolerance", params.mode_frequency_tolerance)?;
        if !(0.0..0.9).contains(&tolerance) {
            return Err(ParamError::OutOfRange {
                field: "mode_frequency_tolerance",
                value: tolerance,
                requirement: "in [0, 0.9)",
            });
        }
        let unmodelled = finite("unmodelled_mode_fraction", params.unmodelled_mode_fraction)?;
        if unmodelled <= 0.0 {
            return Err(ParamError::OutOfRange {
                field: "unmodelled_mode_fraction",
                value: unmodelled,
                requirement: "> 0",
            });
        }
        let harmonic_gain = finite("harmonic_gain", params.harmonic_gain)?;
        if !(0.0..=1.0).contains(&harmonic_gain) {
            return Err(ParamError::OutOfRange {
                field: "harmonic_gain",
                value: harmonic_gain,
                requirement: "in [0, 1]",
            });
        }
        let collateral_share = finite("collateral_share", params.collateral_share)?;
        if collateral_share < 0.0 {
            return Err(ParamError::OutOfRange {
                field: "collateral_share",
                value: collateral_share,
                requirement: "at least 0",
            });
        }
        let settings = compensator.settings();
        let d = f64::from(effects.delay_samples());
        let p = effects.params();
        let mut learning = Self {
            model: *compensator.model(),
            settings,
            delay_whole: effects.reference_index_offset(),
            delay_fraction: d - libm::floor(d),
            mode: effects.has_mode().then(|| {
                (
                    f64::from(p.mode_frequency_hz),
                    f64::from(p.mode_damping),
                    f64::from(p.mode_relative_damping),
                )
            }),
            relaxation: {
                let (elements, linear) = effects.relaxation_elements();
                (
                    elements.map(|(r, g)| (f64::from(r), f64::from(g))),
                    f64::from(linear),
                )
            },
            params,
            learning_gain: 2.0 / (f64::from(lo) + f64::from(hi)),
            cutoff_hz: 0.0,
            noise_band_share: 1.0,
            sections: [Biquad::lowpass(0.1, 1.0); 2],
        };
        let t = f64::from(settings.sample_period_s);
        let mut cutoff = MAX_CUTOFF_FRACTION / t;
        let bound = 1.0 - f64::from(margin);
        for i in 0..RULE_FREQUENCIES {
            let f = (i as f64 + 0.5) / RULE_FREQUENCIES as f64 * 0.5 / t;
            let w = learning.worst_factor(f);
            if w > bound {
                let tan_c = libm::tan(PI * f * t) / libm::pow(w / bound - 1.0, 0.125);
                // A hair below the boundary, so that rounding cannot put it above.
                cutoff = cutoff.min(0.999 * libm::atan(tan_c) / (PI * t));
            }
        }
        learning.cutoff_hz = cutoff;
        let w0 = 2.0 * PI * cutoff * t;
        learning.sections = BUTTERWORTH4_Q.map(|q| Biquad::lowpass(w0, q));
        learning.noise_band_share = (0..RULE_FREQUENCIES)
            .map(|i| {
                let q = learning.filter_gain((i as f64 + 0.5) / RULE_FREQUENCIES as f64 * 0.5 / t);
                q * q
            })
            .sum::<f64>()
            / RULE_FREQUENCIES as f64;
        Ok(learning)
    }

    /// The cut-off f_c of Q chosen by the rule \[Hz\].
    pub fn cutoff_hz(&self) -> f64 {
        self.cutoff_hz
    }

    /// λ = 2/(γ_min + γ_max).
    pub fn learning_gain(&self) -> f64 {
        self.learning_gain
    }

    /// The parameters as given.
    pub fn params(&self) -> &LearningParams {
        &self.params
    }

    /// |Q(f)| = 1/(1 + (tan(πfT)/tan(πf_cT))⁸) (zero phase).
    pub fn filter_gain(&self, f_hz: f64) -> f64 {
        let t = f64::from(self.settings.sample_period_s);
        let x = libm::tan(PI * f_hz * t) / libm::tan(PI * self.cutoff_hz * t);
        1.0 / (1.0 + libm::pow(x * x, 4.0))
    }

    /// W(f): the largest |1 − L·G| over the gain and mode sets at `f_hz` (module doc).
    pub fn worst_factor(&self, f_hz: f64) -> f64 {
        let t = f64::from(self.settings.sample_period_s);
        let w = 2.0 * PI * f_hz;
        let d = self.delay_whole as f64 + self.delay_fraction;
        // L's shift: e^(jω⌊D⌋T)·((1 − φ) + φ·e^(jωT)); the delay of G: e^(−jωDT).
        let phi = self.delay_fraction;
        let step = C::expj(w * t);
        let shift =
            C::expj(w * t * self.delay_whole as f64).mul(C(1.0 - phi + phi * step.0, phi * step.1));
        let delay = C::expj(-w * d * t);
        let base = shift.mul(delay);
        let gains = [self.params.gain_min, self.params.gain_max].map(f64::from);
        let lambda = self.learning_gain;
        let factor = |ratio: C| {
            gains
                .iter()
                .map(|g| {
                    let lg = ratio.mul(base);
                    C(1.0 - lambda * g * lg.0, -lambda * g * lg.1).abs()
                })
                .fold(0.0, f64::max)
        };
        let mode = |f_mode: f64, zeta: f64, rho: f64| {
            let wt = 2.0 * PI * f_mode;
            C(wt * wt, 2.0 * rho * zeta * wt * w).div(C(wt * wt - w * w, 2.0 * zeta * wt * w))
        };
        let Some((fm, zeta, rho)) = self.mode else {
            // No mode in the model: none in the plant, or one at or above f_u.
            let fraction = f64::from(self.params.unmodelled_mode_fraction);
            if fraction >= 0.5 {
                return factor(C(1.0, 0.0));
            }
            let f_u = fraction / t;
            let span = 2.0 / (t * f_u);
            let at = |f_mode: f64| factor(mode(f_mode, UNMODELLED_MODE_DAMPING, 0.0));
            return (0..RULE_MODE_SAMPLES)
                .map(|i| f_u * libm::pow(span, i as f64 / (RULE_MODE_SAMPLES - 1) as f64))
                .map(at)
                .fold(factor(C(1.0, 0.0)).max(at(f_hz.max(f_u))), f64::max);
        };
        let wm = 2.0 * PI * fm;
        // L's mode inverse: 1 + j·2(1 − ρ)ζ·sin(ωT)/(ω_m·T) − 4·sin²(ωT/2)/(ω_m·T)².
        let half = libm::sin(0.5 * w * t);
        let inverse = C(
            1.0 - 4.0 * half * half / (wm * t * wm * t),
            2.0 * (1.0 - rho) * zeta * libm::sin(w * t) / (wm * t),
        );
        let tol = f64::from(self.params.mode_frequency_tolerance);
        let mode_at = |mu: f64| factor(mode(mu * fm, zeta, rho).mul(inverse));
        let on_peak = (f_hz / fm).clamp(1.0 - tol, 1.0 + tol);
        (0..RULE_MODE_SAMPLES)
            .map(|i| 1.0 - tol + 2.0 * tol * i as f64 / (RULE_MODE_SAMPLES - 1) as f64)
            .map(mode_at)
            .fold(mode_at(on_peak), f64::max)
    }

    /// This learning with ρ of the learning above Q's cut-off `harmonic_gain` (0 ≤ ρ ≤ 1,
    /// [`LearningParams::harmonic_gain`]; the rest, Q and its cut-off included, unchanged):
    /// what [`back_off::BackOff::harmonic_scale`] scales. Refuses another ρ.
    pub fn with_harmonic_gain(&self, harmonic_gain: f32) -> Result<Self, ParamError> {
        if !(0.0..=1.0).contains(&harmonic_gain) {
            return Err(ParamError::OutOfRange {
                field: "harmonic_gain",
                value: harmonic_gain,
                requirement: "in [0, 1]",
            });
        }
        let mut scaled = *self;
        scaled.params.harmonic_gain = harmonic_gain;
        Ok(scaled)
    }

    /// This learning for a stage whose gain is `gain_ratio` (γ̂ > 0, finite) times the model's:
    /// L's gain becomes λ/γ̂ (Q and its cut-off stay: the rule's set of gains then stands for the
    /// estimate's error, not the model's). Refuses a γ̂ outside \[gain_min, gain_max\].
    pub fn with_model_gain(&self, gain_ratio: f64) -> Result<Self, ParamError> {
        let (lo, hi) = (
            f64::from(self.params.gain_min),
            f64::from(self.params.gain_max),
        );
        if !(gain_ratio >= lo && gain_ratio <= hi) {
            return Err(ParamError::OutOfRange {
                field: "gain_ratio",
                value: gain_ratio as f32,
                requirement: "in [gain_min, gain_max]",
            });
        }
        let mut scaled = *self;
        scaled.learning_gain = self.learning_gain / gain_ratio;
        Ok(scaled)
    }

    /// (γ̂, ĉ \[m\]): the plant/model gain ratio and offset the trial shows, `y ≈ γ̂·ŷ + ĉ`
    /// (module doc), or `None` when the model does
    /// not explain the trial (R² below [`GAIN_FIT_MIN_R2`], a constant prediction, a slice
    /// shorter than 2 or of another length, or a non-finite result). Non-finite samples are left
    /// out of the fit.
    pub fn gain_ratio(&self, trial: &Trial<'_>) -> Option<(f64, f64)> {
        let n = trial.command_v.len();
        if n < 2 || trial.measured_m.len() != n {
            return None;
        }
        let mut state = if trial.periodic {
            self.periodic_state(&|j| trial.command_v[j], n)
        } else {
            ModelState::at_rest(self.settings.limits.output_min_v)
        };
        let (mut count, mut sp, mut sy, mut spp, mut syy, mut spy) =
            (0.0f64, 0.0, 0.0, 0.0, 0.0, 0.0);
        for (&u, &y) in trial.command_v.iter().zip(trial.measured_m) {
            let predicted = f64::from(self.model.step(&mut state, u));
            let y = f64::from(y);
            if predicted.is_finite() && y.is_finite() {
                count += 1.0;
                sp += predicted;
                sy += y;
                spp += predicted * predicted;
                syy += y * y;
                spy += predicted * y;
            }
        }
        if count < 2.0 {
            return None;
        }
        let var_p = spp - sp * sp / count;
        let var_y = syy - sy * sy / count;
        let cov = spy - sp * sy / count;
        if !(var_p > 0.0 && var_y > 0.0) {
            return None;
        }
        let gamma = cov / var_p;
        let offset = (sy - gamma * sp) / count;
        let r2 = cov * cov / (var_p * var_y);
        (gamma.is_finite() && gamma > 0.0 && offset.is_finite() && r2 >= GAIN_FIT_MIN_R2)
            .then_some((gamma, offset))
    }

    /// |Q(f)|·W(f): the worst contraction of the error at `f_hz` per trial.
    pub fn convergence_factor(&self, f_hz: f64) -> f64 {
        self.filter_gain(f_hz) * self.worst_factor(f_hz)
    }

    /// The next command into `next_v` (the length of the trial's slices). Refuses slices of
    /// different lengths (naming the first that differs from `command_v`) or shorter than 2.
    pub fn step(&self, trial: &Trial<'_>, next_v: &mut [f32]) -> Result<StepSummary, ParamError> {
        self.step_remembering(trial, &mut [], next_v)
    }

    /// [`Learning::step`] with the stage's responses at the harmonics remembered from earlier
    /// steps on the same trajectory: `remembered[h]` = Ĝ(h) \[m/V\] as (re, im), (0, 0) where
    /// none, read where this trial's estimate is refused and written where one is accepted
    /// (module `harmonics`, "Remembered responses"; without a servo only). A slice shorter than
    /// n/2 + 1 remembers only the harmonics it holds.
    pub fn step_remembering(
        &self,
        trial: &Trial<'_>,
        remembered: &mut [[f32; 2]],
        next_v: &mut [f32],
    ) -> Result<StepSummary, ParamError> {
        let n = trial.command_v.len();
        for (field, len) in [
            ("reference_m", trial.reference_m.len()),
            ("measured_m", trial.measured_m.len()),
            ("base_v", trial.base_v.len()),
            ("next_v", next_v.len()),
            (
                "previous.command_v",
                trial.previous.map_or(n, |p| p.command_v.len()),
            ),
            (
                "previous.measured_m",
                trial.previous.map_or(n, |p| p.measured_m.len()),
            ),
            ("table_v", trial.table_v.map_or(n, <[f32]>::len)),
            (
                "previous.table_v",
                trial
                    .previous
                    .and_then(|p| p.table_v)
                    .map_or(n, <[f32]>::len),
            ),
        ] {
            if len != n {
                return Err(ParamError::OutOfRange {
                    field,
                    value: len as f32,
                    requirement: "the length of command_v",
                });
            }
        }
        if n < 2 {
            return Err(ParamError::OutOfRange {
                field: "command_v",
                value: n as f32,
                requirement: "at least 2 samples",
            });
        }
        let error = |j: usize| {
            let e = trial.reference_m[j] - trial.measured_m[j];
            if e.is_finite() {
                f64::from(e)
            } else {
                0.0
            }
        };
        let (mut sq, mut max) = (0.0f64, 0.0f64);
        for j in 0..n {
            let e = error(j);
            sq += e * e;
            max = max.max(e.abs());
        }
        let base = |j: usize| {
            let b = trial.base_v[j];
            if b.is_finite() {
                b
            } else {
                self.settings.limits.output_min_v
            }
        };
        let command = |j: usize| {
            let u = trial.command_v[j];
            if u.is_finite() {
                u
            } else {
                base(j)
            }
        };
        let held = (0..n)
            .filter(|&j| {
                let b = base(j);
                b <= self.settings.limits.output_min_v || b >= self.settings.limits.output_max_v
            })
            .count();
        let filter_base = held as f64 >= LIMITED_BASE_SHARE * n as f64;
        let zero = |_: usize| 0.0f32;
        let kept: &dyn Fn(usize) -> f32 = if filter_base { &zero } else { &base };
        let (noise_rms_m, command_noise_v) = match trial.noise {
            Some(noise) => (noise.measured_m, noise.command_v),
            None => (
                self.fourth_difference_noise(trial.periodic, &error, next_v),
                self.fourth_difference_noise(trial.periodic, &|j| f64::from(command(j)), next_v),
            ),
        };
        let (learned_share, in_band_ms) =
            self.learned_share(trial.periodic, noise_rms_m, &error, next_v);
        if trial.periodic {
            // L·e alone, plus under a servo its correction U − T, then each harmonic's own
            // share of both (module doc, "Sensor noise" and "Under a servo"); from the table.
            let table = |j: usize| match trial.table_v {
                Some(t) if t[j].is_finite() => t[j],
                _ => command(j),
            };
            self.learned_update(true, self.learning_gain, &error, &command, &command, next_v);
            if trial.table_v.is_some() {
                for (j, v) in next_v.iter_mut().enumerate() {
                    *v += command(j) - table(j);
                }
            }
            self.share_per_harmonic(noise_rms_m, learned_share, &error, next_v);
            for (j, v) in next_v.iter_mut().enumerate() {
                *v += table(j) - kept(j);
            }
        } else {
            self.learned_update(
                false,
                learned_share * self.learning_gain,
                &error,
                &command,
                kept,
                next_v,
            );
        }
        for section in &self.sections {
            section.filter(next_v, false, trial.periodic);
        }
        for section in &self.sections {
            section.filter(next_v, true, trial.periodic);
        }
        for (j, v) in next_v.iter_mut().enumerate() {
            *v += kept(j);
        }
        // While the error Q passes dominates, what lies above the cut-off is that error's
        // transient (module doc, "Above Q's cut-off").
        let settled = in_band_ms <= IN_BAND_SETTLED_SHARE * (sq / n as f64);
        let (harmonics_learned, harmonic_scale) =
            if trial.periodic && trial.noise.is_some() && settled {
                let error_rms_m = libm::sqrt(sq / n as f64);
                self.learn_harmonics(
                    trial,
                    remembered,
                    noise_rms_m,
                    command_noise_v,
                    error_rms_m,
                    &command,
                    next_v,
                )
            } else {
                (0, 1.0)
            };
        let limited = self.limit(next_v, trial.periodic);
        Ok(StepSummary {
            rms_error_m: libm::sqrt(sq / n as f64),
            max_abs_error_m: max,
            limited,
            base_filtered: filter_base,
            noise_rms_m,
            learned_share,
            harmonics_learned,
            harmonic_scale,
        })
    }

    /// The harmonic step of the module doc on `next_v` (Q's result); returns the harmonics
    /// learned and the factor α their step was scaled by.
    #[allow(clippy::too_many_arguments)]
    fn learn_harmonics(
        &self,
        trial: &Trial<'_>,
        remembered: &mut [[f32; 2]],
        noise_measured_m: f64,
        noise_command_v: f64,
        error_rms_m: f64,
        command: &dyn Fn(usize) -> f32,
        next_v: &mut [f32],
    ) -> (usize, f64) {
        let finite_or_zero = |v: f32| if v.is_finite() { f64::from(v) } else { 0.0 };
        let reference = |j: usize| finite_or_zero(trial.reference_m[j]);
        // A non-finite reading counts as no error (as in the step).
        let measured = |j: usize| {
            let y = trial.measured_m[j];
            if y.is_finite() {
                f64::from(y)
            } else {
                reference(j)
            }
        };
        let n = next_v.len();
        // The model's own output along u_k, from its periodic state.
        let start = self.periodic_state(command, n);
        let slope = self.mean_slope(command, n, start);
        let model = |f: f64, i: usize| self.model_response(f, slope, i);
        let window =
            f64::from(self.settings.limits.output_max_v - self.settings.limits.output_min_v);
        let mut state = start;
        let mut predicted = |j: usize| {
            if j == 0 {
                state = start;
            }
            f64::from(self.model.step(&mut state, command(j)))
        };
        // The trial before, read the same way (a non-finite sample as this trial's).
        let previous_command = |j: usize| match trial.previous {
            Some(p) if p.command_v[j].is_finite() => p.command_v[j],
            _ => command(j),
        };
        let previous_measured = |j: usize| match trial.previous {
            Some(p) if p.measured_m[j].is_finite() => f64::from(p.measured_m[j]),
            _ => measured(j),
        };
        let previous_start = if trial.previous.is_some() {
            self.periodic_state(&previous_command, n)
        } else {
            ModelState::at_rest(previous_command(0))
        };
        let mut previous_state = previous_start;
        let mut previous_predicted = |j: usize| {
            if j == 0 {
                previous_state = previous_start;
            }
            f64::from(self.model.step(&mut previous_state, previous_command(j)))
        };
        let previous_command_v = |j: usize| f64::from(previous_command(j));
        // A table's non-finite entry as the command's.
        let table = |j: usize| match trial.table_v {
            Some(t) if t[j].is_finite() => f64::from(t[j]),
            _ => f64::from(command(j)),
        };
        let previous_table = |j: usize| match trial.previous.and_then(|p| p.table_v) {
            Some(t) if t[j].is_finite() => f64::from(t[j]),
            _ => previous_command_v(j),
        };
        let mut changes = [(0usize, C(0.0, 0.0)); MAX_HARMONICS];
        // |Ĝ/ḡ| measured at each harmonic the step learned, from the first above the cut-off.
        let mut gains = [0.0f64; MAX_HARMONICS];
        let (learned, changed) = harmonics::learn_harmonics(
            &mut harmonics::HarmonicInputs {
                previous: trial.previous.map(|p| harmonics::PreviousInputs {
                    command: &previous_command_v,
                    measured: &previous_measured,
                    predicted: &mut previous_predicted,
                    table: p.table_v.map(|_| &previous_table as &dyn Fn(usize) -> f64),
                }),
                table: trial.table_v.map(|_| &table as &dyn Fn(usize) -> f64),
                predicted: &mut predicted,
                slope,
                reference: &reference,
                measured: &measured,
                command: &|j| f64::from(command(j)),
                sample_period_s: f64::from(self.settings.sample_period_s),
                cutoff_hz: self.cutoff_hz,
                noise_measured_m,
                noise_command_v,
                model: &model,
                model_count: HARMONIC_MODEL_SAMPLES + 1,
                gain: f64::from(self.params.harmonic_gain),
                cap_v: HARMONIC_STEP_CAP * window,
                remembered,
            },
            next_v,
            &mut changes,
            &mut gains,
        );
        let scale = self.limit_collateral(
            command,
            start,
            slope,
            error_rms_m,
            &mut changes[..changed],
            &gains,
            next_v,
        );
        self.cancel_mixing(
            command,
            start,
            slope,
            &changes[..changed],
            HARMONIC_STEP_CAP * window,
            next_v,
        );
        (learned, scale)
    }

    /// Scales the harmonic step's `changes` (and `next_v` with them) by one factor α ≤ 1 so that
    /// what the hysteresis model mixes from them into the harmonics above Q's band, through the
    /// stage's dynamics, stays within κ ([`LearningParams::collateral_share`]) of the trial's
    /// error RMS (module doc, "Mixing above the band"): with M = Ŵ(u + Δ) − Ŵ(u) − ḡ·Δ,
    /// `c² = Σ_h 2·|G(f_h)/ḡ|²·|M(h)|²` over the harmonics the step examines, |G/ḡ| the larger
    /// of the stage file's own response and the one measured where the step learned
    /// (`measured_gains`, from the first harmonic above the cut-off), and
    /// `α = min(1, κ·e_rms/c)`. Returns α.
    #[allow(clippy::too_many_arguments)]
    fn limit_collateral(
        &self,
        command: &dyn Fn(usize) -> f32,
        start: ModelState,
        slope: f64,
        error_rms_m: f64,
        changes: &mut [(usize, C)],
        measured_gains: &[f64],
        next_v: &mut [f32],
    ) -> f64 {
        let n = next_v.len();
        let share = f64::from(self.params.collateral_share);
        if changes.is_empty() || n < 4 || error_rms_m.is_nan() || error_rms_m <= 0.0 || share <= 0.0
        {
            return 1.0;
        }
        let t = f64::from(self.settings.sample_period_s);
        let first = self.first_above_cutoff(n);
        let last = ((n - 1) / 2).min(first + MAX_HARMONICS - 1);
        if first > last {
            return 1.0;
        }
        let mut mixed = [C(0.0, 0.0); MAX_HARMONICS];
        let count = last + 1 - first;
        if !self.mixing(
            command,
            start,
            slope,
            changes,
            n,
            first,
            &mut mixed[..count],
        ) {
            return 1.0;
        }
        let mut collateral_ms = 0.0;
        for (k, m) in mixed[..count].iter().enumerate() {
            let f = (first + k) as f64 / (n as f64 * t);
            let measured = measured_gains.get(k).copied().unwrap_or(0.0);
            let gain = (self.model_response(f, slope, 0).abs() / libm::fabs(slope)).max(measured);
            let size = gain * m.abs() / n as f64;
            collateral_ms += 2.0 * size * size;
        }
        let collateral = libm::sqrt(collateral_ms);
        if collateral.is_nan() || collateral <= share * error_rms_m {
            return 1.0;
        }
        let alpha = share * error_rms_m / collateral;
        for (j, v) in next_v.iter_mut().enumerate() {
            *v -= ((1.0 - alpha) * change_at(changes, j, n)) as f32;
        }
        for (_, d) in changes.iter_mut() {
            *d = C(d.0 * alpha, d.1 * alpha);
        }
        alpha
    }

    /// The lowest harmonic of a period of n samples above Q's cut-off: the first the harmonic
    /// step examines, and the end of the band the in-band learning keeps.
    fn first_above_cutoff(&self, n: usize) -> usize {
        first_harmonic_above(self.cutoff_hz, n, f64::from(self.settings.sample_period_s))
    }

    /// M = Ŵ(u + Δ) − Ŵ(u) − ḡ·Δ along one period (each from its periodic state; Δ(j) the
    /// harmonic step's `changes` in time, `start` the model's periodic state along u, `slope` ḡ),
    /// as the unnormalised DFT sums `out[k] = Σ_j M(j)·e^(−j2π(first + k)j/n)`. False where M is
    /// not finite (`out` then undefined).
    #[allow(clippy::too_many_arguments)]
    fn mixing(
        &self,
        command: &dyn Fn(usize) -> f32,
        start: ModelState,
        slope: f64,
        changes: &[(usize, C)],
        n: usize,
        first: usize,
        out: &mut [C],
    ) -> bool {
        let changed = |j: usize| (f64::from(command(j)) + change_at(changes, j, n)) as f32;
        let (mut now, mut then) = (start, self.periodic_state(&changed, n));
        for j in 0..n {
            let (u, v) = (command(j), changed(j));
            let w = f64::from(self.model.step(&mut now, u));
            let x = f64::from(self.model.step(&mut then, v));
            let m = x - w - slope * (f64::from(v) - f64::from(u));
            if !m.is_finite() {
                return false;
            }
            for (k, acc) in out.iter_mut().enumerate() {
                let (c, s) = harmonics::twiddle(first + k, j, n);
                acc.0 += m * c;
                acc.1 += m * s;
            }
        }
        true
    }

    /// Cancels in Q's band what the hysteresis model mixes there from the harmonic step's
    /// `changes` (module doc, "Mixing into the band"): with Δ(j) the changes in time,
    /// M = Ŵ(u + Δ) − Ŵ(u) − ḡ·Δ along one period of each (from its periodic state), and each
    /// harmonic h below the step's first, `next(h) −= λ·M(h)/G_model(f_h)` (at most `cap_v`).
    /// `start` is the model's periodic state along u ([`Self::periodic_state`]) and `slope` ḡ.
    fn cancel_mixing(
        &self,
        command: &dyn Fn(usize) -> f32,
        start: ModelState,
        slope: f64,
        changes: &[(usize, C)],
        cap_v: f64,
        next_v: &mut [f32],
    ) {
        let n = next_v.len();
        if changes.is_empty() || n < 4 {
            return;
        }
        let t = f64::from(self.settings.sample_period_s);
        let band = self
            .first_above_cutoff(n)
            .min((n - 1) / 2 + 1)
            .min(SHARED_HARMONICS);
        let mut mixed = [C(0.0, 0.0); SHARED_HARMONICS];
        if !self.mixing(command, start, slope, changes, n, 0, &mut mixed[..band]) {
            return;
        }
        let mut corrections = [C(0.0, 0.0); SHARED_HARMONICS];
        for (h, (m, out)) in mixed[..band].iter().zip(&mut corrections).enumerate() {
            let g = self.model_response(h as f64 / (n as f64 * t), slope, 0);
            let mut c = C(m.0 / n as f64, m.1 / n as f64).div(g);
            c = C(-self.learning_gain * c.0, -self.learning_gain * c.1);
            let size = c.abs();
            if !size.is_finite() {
                continue;
            }
            if size > cap_v {
                c = C(c.0 * cap_v / size, c.1 * cap_v / size);
            }
            *out = c;
        }
        for (j, v) in next_v.iter_mut().enumerate() {
            let mut x = 0.0;
            for (h, c) in corrections[..band].iter().enumerate() {
                let (cs, sn) = harmonics::twiddle(h, j, n);
                // The component at h and its conjugate at n − h (h = 0: once).
                let k = if h == 0 { 1.0 } else { 2.0 };
                x += k * (c.0 * cs + c.1 * sn);
            }
            *v += x as f32;
        }
    }

    /// The model's periodic state for a command repeated with period `n`: from rest at its first
    /// sample, after one whole period (the state each pass of the periodic trial starts from).
    fn periodic_state(&self, command: &dyn Fn(usize) -> f32, n: usize) -> ModelState {
        let mut state = ModelState::at_rest(command(0));
        for j in 0..n {
            self.model.step(&mut state, command(j));
        }
        state
    }

    /// ḡ: the model's mean slope dy/du along one period of the command \[m/V\], from its
    /// periodic state `start` ([`Self::periodic_state`]).
    fn mean_slope(&self, command: &dyn Fn(usize) -> f32, n: usize, start: ModelState) -> f64 {
        let mut state = start;
        let (mut sum, mut count, mut direction) = (0.0f64, 0usize, 1.0f32);
        for j in 0..n {
            let from = state;
            self.model.step(&mut state, command(j));
            let du = state.input_v - from.input_v;
            if du != 0.0 {
                direction = if du > 0.0 { 1.0 } else { -1.0 };
            }
            let g = f64::from(self.model.step_slope(&from, &state, direction));
            if g.is_finite() {
                sum += g;
                count += 1;
            }
        }
        if count > 0 {
            sum / count as f64
        } else {
            0.0
        }
    }

    /// G_model(f) = ḡ·M_μ(f)·e^(−j2πfDT) of the set the harmonic step accepts \[m/V\]: `i` = 0
    /// the stage file's own mode (or none), 1 ..= [`HARMONIC_MODEL_SAMPLES`] the mode at μ
    /// across (1 ± t) (without a mode in the file: geometrically across the rule's span from
    /// f_u to 2/T).
    fn model_response(&self, f_hz: f64, slope: f64, i: usize) -> C {
        let t = f64::from(self.settings.sample_period_s);
        let w = 2.0 * PI * f_hz;
        let d = self.delay_whole as f64 + self.delay_fraction;
        let delay = C::expj(-w * d * t);
        let resonance = |fm: f64, zeta: f64, rho: f64| {
            let wm = 2.0 * PI * fm;
            C(wm * wm, 2.0 * rho * zeta * wm * w).div(C(wm * wm - w * w, 2.0 * zeta * wm * w))
        };
        let position = i.saturating_sub(1) as f64 / (HARMONIC_MODEL_SAMPLES - 1) as f64;
        let mode = match (self.mode, i) {
            (Some((fm, zeta, rho)), 0) => resonance(fm, zeta, rho),
            (Some((fm, zeta, rho)), _) => {
                let tol = f64::from(self.params.mode_frequency_tolerance);
                resonance(fm * (1.0 - tol + 2.0 * tol * position), zeta, rho)
            }
            (None, 0) => C(1.0, 0.0),
            (None, _) => {
                let f_u = f64::from(self.params.unmodelled_mode_fraction) / t;
                let f_mode = f_u * libm::pow(2.0 / (t * f_u), position);
                resonance(f_mode, UNMODELLED_MODE_DAMPING, 0.0)
            }
        };
        let g = mode.mul(delay);
        C(slope * g.0, slope * g.1)
    }

    /// σ̂ of a white noise in `x` from its fourth differences (module doc, "Sensor noise");
    /// `scratch` is overwritten. 0 for fewer than 8 differences.
    fn fourth_difference_noise(
        &self,
        periodic: bool,
        x: &dyn Fn(usize) -> f64,
        scratch: &mut [f32],
    ) -> f64 {
        let n = scratch.len();
        let count = if periodic { n } else { n.saturating_sub(4) };
        if count < 8 {
            return 0.0;
        }
        for (j, d) in scratch.iter_mut().take(count).enumerate() {
            let e = |k: usize| x((j + k) % n);
            *d = libm::fabs(e(0) - 4.0 * e(1) + 6.0 * e(2) - 4.0 * e(3) + e(4)) as f32;
        }
        let rank = count / 4;
        let (_, p25, _) = scratch[..count].select_nth_unstable_by(rank, f32::total_cmp);
        f64::from(*p25) / (ABS_NORMAL_P25 * libm::sqrt(FOURTH_DIFFERENCE_VARIANCE))
    }

    /// (s, ⟨(Q·e)²⟩): the share of L·e to learn for the noise σ̂ = `sigma` (module doc, "Sensor
    /// noise") and the mean square of the error Q passes \[m²\]; `scratch` is overwritten.
    fn learned_share(
        &self,
        periodic: bool,
        sigma: f64,
        error: &dyn Fn(usize) -> f64,
        scratch: &mut [f32],
    ) -> (f64, f64) {
        let n = scratch.len();
        for (j, v) in scratch.iter_mut().enumerate() {
            *v = error(j) as f32;
        }
        for section in &self.sections {
            section.filter(scratch, false, periodic);
        }
        for section in &self.sections {
            section.filter(scratch, true, periodic);
        }
        let in_band = scratch
            .iter()
            .map(|&v| f64::from(v) * f64::from(v))
            .sum::<f64>()
            / n as f64;
        let noise = sigma * sigma * self.noise_band_share;
        let share = if in_band > 0.0 {
            (1.0 - noise / in_band).clamp(0.0, 1.0)
        } else {
            0.0
        };
        (share, in_band)
    }

    /// Scales the periodic record `learned` (λ·Δu) harmonic by harmonic: its component at
    /// harmonic h ≤ H_s by `s_h = max(0, 1 − (σ²/n)/|E(h)|²)` (E the error's DFT coefficient,
    /// σ²/n a white noise's power per coefficient), the rest by the whole band's `share`
    /// (module doc, "Sensor noise").
    fn share_per_harmonic(
        &self,
        sigma: f64,
        share: f64,
        error: &dyn Fn(usize) -> f64,
        learned: &mut [f32],
    ) {
        let n = learned.len();
        let t = f64::from(self.settings.sample_period_s);
        // Where Q passes more than 1/257 of the error: up to twice the cut-off.
        let band = libm::floor(2.0 * self.cutoff_hz * n as f64 * t) as usize;
        let last = band.min((n - 1) / 2).min(SHARED_HARMONICS - 1);
        let bin_noise = sigma * sigma / n as f64;
        let scale = 1.0 / n as f64;
        let mut components = [C(0.0, 0.0); SHARED_HARMONICS];
        let mut shares = [0.0f64; SHARED_HARMONICS];
        for h in 0..=last {
            let (mut e, mut d) = (C(0.0, 0.0), C(0.0, 0.0));
            for (j, &v) in learned.iter().enumerate() {
                let (c, s) = harmonics::twiddle(h, j, n);
                let x = error(j);
                e.0 += x * c;
                e.1 += x * s;
                d.0 += f64::from(v) * c;
                d.1 += f64::from(v) * s;
            }
            let power = (e.0 * e.0 + e.1 * e.1) * scale * scale;
            shares[h] = if power > 0.0 {
                (1.0 - bin_noise / power).max(0.0)
            } else {
                0.0
            };
            components[h] = C(d.0 * scale, d.1 * scale);
        }
        for (j, v) in learned.iter_mut().enumerate() {
            let mut x = share * f64::from(*v);
            for h in 0..=last {
                let (c, s) = harmonics::twiddle(h, j, n);
                // The component at h and its conjugate at n − h (h = 0: once).
                let k = if h == 0 { 1.0 } else { 2.0 };
                let d = components[h];
                x += k * (shares[h] - share) * (d.0 * c + d.1 * s);
            }
            *v = x as f32;
        }
    }

    /// `out[j] = u_k[j] − u_0[j] + gain·Δu[j]` (module doc; gain = s·λ).
    fn learned_update(
        &self,
        periodic: bool,
        gain: f64,
        error: &dyn Fn(usize) -> f64,
        command: &dyn Fn(usize) -> f32,
        base: &dyn Fn(usize) -> f32,
        out: &mut [f32],
    ) {
        let n = out.len();
        let index = |i: isize| -> usize {
            if periodic {
                i.rem_euclid(n as isize) as usize
            } else {
                i.clamp(0, n as isize - 1) as usize
            }
        };
        let shifted = |i: isize| {
            let k = i + self.delay_whole as isize;
            let (a, b) = (error(index(k)), error(index(k + 1)));
            a + self.delay_fraction * (b - a)
        };
        let t = f64::from(self.settings.sample_period_s);
        let (velocity, curvature) = self.mode.map_or((0.0, 0.0), |(f, zeta, rho)| {
            let wt = 2.0 * PI * f * t;
            ((1.0 - rho) * zeta / wt, 1.0 / (wt * wt))
        });
        // The model along u_k: a periodic trial starts from the state one period of u_k leaves.
        let mut start = ModelState::at_rest(if periodic {
            command(0)
        } else {
            self.settings.limits.output_min_v
        });
        if periodic {
            for j in 0..n {
                self.model.step(&mut start, command(j));
            }
        }
        let lag = self.model.has_input_lag().then(|| {
            (
                f64::from(self.model.input_lag_fraction()),
                f64::from(self.model.input_lag_hold_share()),
            )
        });
        let (elements, relaxation_linear) = self.relaxation;
        let relaxes = elements.iter().any(|&(_, g)| g != 0.0);
        // The linearised model's memory of the learned correction Δu (module doc, "Rate-dependent
        // hysteresis"): the lagged input's Δv, the last Δu, and the relaxation elements' Δvᵢ.
        let mut dv = 0.0f64;
        let mut du_last = 0.0f64;
        let mut relaxed = [0.0f64; RELAXATION_LAGS];
        // A periodic trial's memory starts in its periodic state: one pass to reach it.
        let passes = if periodic && (lag.is_some() || relaxes) {
            2
        } else {
            1
        };
        for pass in 0..passes {
            let write = pass + 1 == passes;
            let mut state = start;
            let mut direction = 1.0f32;
            for (j, o) in out.iter_mut().enumerate() {
                let from = state;
                let u = command(j);
                self.model.step(&mut state, u);
                let du = state.input_v - from.input_v;
                if du != 0.0 {
                    direction = if du > 0.0 { 1.0 } else { -1.0 };
                }
                let slope = f64::from(self.model.step_slope(&from, &state, direction));
                let i = j as isize;
                let (zm, z0, zp) = (shifted(i - 1), shifted(i), shifted(i + 1));
                let s = z0 + velocity * (zp - zm) + curvature * (zp - 2.0 * z0 + zm);
                // Δy = slope·Δu + k2·(dh/dv)·Δv_pre + Σ g_wᵢ·Δvᵢ, solved for Δu.
                let (dv_pre, lag_coefficient) = match lag {
                    Some((c, b)) => (
                        dv + c * (du_last - dv) - b * du_last,
                        f64::from(self.model.map().k2_m_per_h)
                            * f64::from(self.model.lagged_input_slope(&from, &state, direction)),
                    ),
                    None => (0.0, 0.0),
                };
                let relaxation: f64 = elements
                    .iter()
                    .zip(&relaxed)
                    .map(|(&(_, g), v)| g * v)
                    .sum();
                let mut correction = if slope.is_finite() && slope.abs() > 0.0 {
                    (s - lag_coefficient * dv_pre - relaxation) / slope
                } else {
                    0.0
                };
                if !correction.is_finite() {
                    // A model the linearisation cannot follow here: nothing learned, memory reset.
                    correction = 0.0;
                    dv = 0.0;
                    relaxed = [0.0; RELAXATION_LAGS];
                }
                if let Some((_, b)) = lag {
                    dv = dv_pre + b * correction;
                }
                if relaxes {
                    // Δp = Δw − k_r·Δu, Δw = Δy − Σ g_wᵢ·Δvᵢ = s − relaxation.
                    let dp = s - relaxation - relaxation_linear * correction;
                    for (v, &(rate, _)) in relaxed.iter_mut().zip(&elements) {
                        *v += rate * (dp - *v);
                    }
                }
                du_last = correction;
                if write {
                    let learned = gain * correction;
                    *o = (f64::from(u) - f64::from(base(j)) + learned) as f32;
                }
            }
        }
    }

    /// Clamps `u` to the window and the slew limit (module doc); returns the samples moved.
    fn limit(&self, u: &mut [f32], periodic: bool) -> usize {
        let CompensatorSettings {
            limits:
                Limits {
                    output_min_v: lo,
                    output_max_v: hi,
                    slew_limit_v_per_s,
                    ..
                },
            sample_period_s,
        } = self.settings;
        let step = slew_limit_v_per_s * sample_period_s;
        let mut moved = 0;
        let mut set = |v: &mut f32, x: f32| {
            if *v != x {
                *v = x;
                moved += 1;
            }
        };
        let Some((first, rest)) = u.split_first_mut() else {
            return 0;
        };
        let from_rest = if periodic { *first } else { lo };
        let x = clamp(clamp(*first, from_rest - step, from_rest + step), lo, hi);
        set(first, x);
        let mut previous = *first;
        for v in rest.iter_mut() {
            let x = clamp(clamp(*v, previous - step, previous + step), lo, hi);
            set(v, x);
            previous = *v;
        }
        if periodic {
            // Backward from the first sample around the wrap: u[j] ∈ u[j+1] ± step, u[n] = u[0].
            let anchor = u[0];
            let mut next = anchor;
            for v in u[1..].iter_mut().rev() {
                let x = clamp(*v, next - step, next + step);
                set(v, x);
                next = *v;
            }
        }
        moved
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 4th-order Butterworth pair at `cutoff_hz` for 10 kHz, as `Learning::new` builds it.
    fn sections(cutoff_hz: f64) -> [Biquad; 2] {
        BUTTERWORTH4_Q.map(|q| Biquad::lowpass(2.0 * PI * cutoff_hz * 1e-4, q))
    }

    /// The XY stage's x stack (y = 3.57e-7·(u − h) m) at 10 kHz in a 0–120 V window with the
    /// slew limit `slew_limit_v_per_s`, its operator driven by a lag of `lag_s` (0: none), the
    /// effects `params`: the model, the effects and the learning with the default parameters.
    fn x_stage(
        slew_limit_v_per_s: f32,
        lag_s: f32,
        params: crate::effects::EffectParams,
    ) -> (StaticModel, Effects, Learning) {
        let map = crate::static_model::StaticMap {
            k1_m_per_v: 3.57e-7,
            k2_m_per_h: -3.57e-7,
            offset_m: 0.0,
        };
        let bw = crate::fixtures::x_stack(1.0, crate::STATE_LIMIT);
        let model = StaticModel::new(bw, map)
            .unwrap()
            .with_input_lag(lag_s, 1e-4)
            .unwrap();
        let settings = CompensatorSettings {
            limits: crate::Limits::new(0.0, 120.0, slew_limit_v_per_s),
            sample_period_s: 1e-4,
        };
        let range = crate::effects::OperatingRange {
            input_v: (0.0, 120.0),
            output_m: (0.0, 50e-6),
        };
        let effects = Effects::new(params, 1e-4, range).unwrap();
        let compensator = Compensator::new(model, settings).unwrap();
        let learning = Learning::new(&compensator, &effects, LearningParams::default()).unwrap();
        (model, effects, learning)
    }

    #[test]
    fn circular_forward_backward_is_zero_phase_with_the_stated_gain() {
        // One period of a sinusoid, filtered circularly: every sample is |Q(f)| times the input
        // (no phase, no start-up transient), |Q| = 1/(1 + (tan(πfT)/tan(πf_cT))⁸).
        let (fc, n) = (1000.0, 200);
        for cycles in [1usize, 10, 20, 30, 50] {
            let f = cycles as f64 * 1e4 / n as f64;
            let x: [f32; 200] =
                core::array::from_fn(|j| libm::sin(2.0 * PI * f * j as f64 * 1e-4 + 0.3) as f32);
            let mut y = x;
            for s in &sections(fc) {
                s.filter(&mut y, false, true);
            }
            for s in &sections(fc) {
                s.filter(&mut y, true, true);
            }
            let r = libm::tan(PI * f * 1e-4) / libm::tan(PI * fc * 1e-4);
            let gain = 1.0 / (1.0 + libm::pow(r, 8.0));
            for j in 0..n {
                let want = gain * f64::from(x[j]);
                assert!(
                    (f64::from(y[j]) - want).abs() < 2e-5,
                    "{f} Hz, sample {j}: {} vs {want}",
                    y[j]
                );
            }
        }
    }

    #[test]
    fn a_record_from_rest_keeps_its_level_at_both_ends() {
        // Not periodic: each pass starts in the steady state of its first sample, so a constant
        // record (a voltage far from 0) passes unchanged, ends included.
        let mut y = [60.0f32; 300];
        for s in &sections(500.0) {
            s.filter(&mut y, false, false);
            s.filter(&mut y, true, false);
        }
        assert!(y.iter().all(|&v| (v - 60.0).abs() < 1e-4), "{:?}", &y[..4]);
    }

    #[test]
    fn a_periodic_table_respects_window_and_slew_across_the_wrap() {
        let (_, _, learning) = x_stage(2e4, 0.0, Default::default());
        // A rising ramp from −20 V to 150 V: out of the window at both ends, steps of 0.85 V
        // within it, and a 170 V fall across the wrap.
        let mut u: [f32; 200] = core::array::from_fn(|j| -20.0 + 0.85 * j as f32);
        let moved = learning.limit(&mut u, true);
        assert!(moved > 0);
        let step = 2e4 * 1e-4 + 1e-4;
        for j in 0..200 {
            assert!((0.0..=120.0).contains(&u[j]), "{j}: {}", u[j]);
            let previous = u[(j + 199) % 200];
            assert!(
                (u[j] - previous).abs() <= step,
                "{j}: {previous} -> {}",
                u[j]
            );
        }
        // From rest: the first sample is reachable from output_min_v.
        let mut u = [50.0f32; 10];
        learning.limit(&mut u, false);
        assert_eq!(u[0], 2.0);
    }

    #[test]
    fn a_base_the_window_held_is_filtered_and_one_inside_it_is_kept() {
        let (_, _, learning) = x_stage(5e5, 0.0, Default::default());
        let next = |base: &[f32; 100]| {
            // No error: the next command is the base plus Q of nothing learned, or Q of the base.
            let r = [1e-5f32; 100];
            let trial = Trial {
                reference_m: &r,
                command_v: base,
                measured_m: &r,
                base_v: base,
                periodic: true,
                noise: None,
                previous: None,
                table_v: None,
            };
            let mut out = [0.0f32; 100];
            let summary = learning.step(&trial, &mut out).unwrap();
            (out, summary.base_filtered)
        };
        // A 100 Hz sine clipped at 120 V for a third of its period: its corners lie above Q's
        // cut-off, and they are the window's.
        let clipped: [f32; 100] = core::array::from_fn(|j| {
            (80.0 + 60.0 * libm::sin(2.0 * PI * j as f64 / 100.0)).min(120.0) as f32
        });
        let (out, filtered) = next(&clipped);
        assert!(filtered);
        let moved = (0..100)
            .map(|j| (out[j] - clipped[j]).abs())
            .fold(0.0, f32::max);
        assert!(moved > 0.01, "the corners were kept: {moved} V");
        // Filtered with Q, not replaced: the level and the fundamental stay.
        assert!(
            (0..100).all(|j| (out[j] - clipped[j]).abs() < 5.0),
            "{out:?}"
        );
        // The same sine inside the window is the base, kept exactly.
        let inside: [f32; 100] =
            core::array::from_fn(|j| (60.0 + 40.0 * libm::sin(2.0 * PI * j as f64 / 100.0)) as f32);
        let (out, filtered) = next(&inside);
        assert!(!filtered);
        assert!(
            (0..100).all(|j| (out[j] - inside[j]).abs() < 1e-4),
            "{out:?}"
        );
    }

    /// A stage whose hysteresis is rate-dependent, played by the core's own forward chain: the
    /// relaxation of the whole w (g_w = 2, τ_w = 5 ms: at low rates the output moves 3× what the
    /// model's w moves, at high rates 1×) or the operator's input lag (τ_v = 2 ms). The learning
    /// inverts the linearised dynamics, not only the one-sample slope. With the one-sample slope
    /// the relaxation's trials grow (1.8 → 20 µm over eight trials: L is up to 3× too large at
    /// low rates) and the lag's fall by 0.29 per trial instead of 1 − λ ≈ 0.13.
    /// The share learned: a trial whose error is the sensor's white noise learns (almost)
    /// nothing and estimates the noise; one whose error is a smooth deviation far above it learns
    /// all of it.
    #[test]
    fn a_trial_at_the_noise_learns_nothing_and_one_above_it_everything() {
        let (_, _, learning) = x_stage(1e5, 0.0, Default::default());
        const N: usize = 1000;
        let sigma = 5e-9f64;
        // A reproducible Gaussian noise (Box–Muller over splitmix64).
        let mut seed = 12_345u64;
        let mut uniform = || {
            seed = seed.wrapping_add(0x9e37_79b9_7f4a_7c15);
            let mut z = seed;
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            z ^= z >> 31;
            ((z >> 11) as f64 + 0.5) / (1u64 << 53) as f64
        };
        let noise: [f64; N] = core::array::from_fn(|_| {
            let (a, b) = (uniform(), uniform());
            libm::sqrt(-2.0 * libm::log(a)) * libm::cos(2.0 * PI * b) * sigma
        });
        let command = [60.0f32; N];
        let mut next = [0.0f32; N];
        for (deviation_m, share) in [(0.0, (0.0, 0.1)), (2e-7, (0.95, 1.0))] {
            let measured: [f32; N] = core::array::from_fn(|j| {
                let smooth = deviation_m * libm::sin(2.0 * PI * j as f64 / N as f64);
                (3e-6 + smooth + noise[j]) as f32
            });
            let reference = [3e-6f32; N];
            let summary = learning
                .step(
                    &Trial {
                        reference_m: &reference,
                        command_v: &command,
                        measured_m: &measured,
                        base_v: &command,
                        periodic: true,
                        noise: None,
                        previous: None,
                        table_v: None,
                    },
                    &mut next,
                )
                .unwrap();
            assert!(
                (summary.noise_rms_m / sigma - 1.0).abs() < 0.15,
                "noise {:.3e} m",
                summary.noise_rms_m
            );
            assert!(
                (share.0..=share.1).contains(&summary.learned_share),
                "deviation {deviation_m}: share {}",
                summary.learned_share
            );
        }
    }

    /// Under a servo, a trial already at the reference (no error left to learn, each harmonic's
    /// share 0) keeps its table: the servo's correction U − T in the voltage applied is handed
    /// over with the share learned, not whole (from U the table took a 0.5 V correction at
    /// 300 Hz, where the servo's |S| can exceed 1, into the next trial).
    #[test]
    fn under_a_servo_a_trial_at_the_reference_keeps_its_table() {
        let (_, _, learning) = x_stage(1e5, 0.0, Default::default());
        const N: usize = 1000;
        let table: [f32; N] = core::array::from_fn(|j| {
            (60.0 + 30.0 * libm::sin(2.0 * PI * j as f64 / N as f64)) as f32
        });
        let applied: [f32; N] = core::array::from_fn(|j| {
            table[j] + (0.5 * libm::sin(2.0 * PI * 3.0 * j as f64 / N as f64)) as f32
        });
        let reference = [3e-6f32; N];
        let step = |table_v: Option<&[f32]>| {
            let mut next = [0.0f32; N];
            learning
                .step(
                    &Trial {
                        reference_m: &reference,
                        command_v: &applied,
                        measured_m: &reference,
                        base_v: &table,
                        periodic: true,
                        noise: Some(TrialNoise {
                            measured_m: 1e-9,
                            command_v: 1e-3,
                        }),
                        previous: None,
                        table_v,
                    },
                    &mut next,
                )
                .unwrap();
            (0..N)
                .map(|j| (next[j] - table[j]).abs())
                .fold(0.0f32, f32::max)
        };
        assert!(step(Some(&table)) < 1e-3, "{}", step(Some(&table)));
        // Without the table the correction is taken whole (Q passes 300 Hz).
        assert!(step(None) > 0.4, "{}", step(None));
    }

    /// A reproducible standard normal sequence (Box–Muller over splitmix64).
    fn gaussian(seed: u64) -> impl FnMut() -> f64 {
        let mut state = seed;
        move || {
            let mut uniform = || {
                state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
                let mut z = state;
                z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
                z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
                z ^= z >> 31;
                ((z >> 11) as f64 + 0.5) / (1u64 << 53) as f64
            };
            let (a, b) = (uniform(), uniform());
            libm::sqrt(-2.0 * libm::log(a)) * libm::cos(2.0 * PI * b)
        }
    }

    /// A periodic trial whose error is a 200 nm deviation at its second harmonic plus a 5 nm
    /// white noise: the noise the step learns (the step's result with the noise minus without)
    /// is what the harmonics at the noise let through, about 0.4 of it in RMS; with one share
    /// for the whole band (s ≈ 1 here) the step learned all of the noise Q passes.
    #[test]
    fn a_periodic_trial_learns_each_harmonic_by_its_own_share_of_the_noise() {
        let (_, _, learning) = x_stage(1e5, 0.0, Default::default());
        const N: usize = 1000;
        let sigma = 5e-9f64;
        let mut normal = gaussian(2024);
        let noise: [f64; N] = core::array::from_fn(|_| sigma * normal());
        let command = [60.0f32; N];
        let reference = [3e-6f32; N];
        let learn = |with_noise: bool| {
            let measured: [f32; N] = core::array::from_fn(|j| {
                let smooth = 2e-7 * libm::sin(2.0 * PI * 2.0 * j as f64 / N as f64);
                let n = if with_noise { noise[j] } else { 0.0 };
                (3e-6 + smooth + n) as f32
            });
            let mut next = [0.0f32; N];
            let summary = learning
                .step(
                    &Trial {
                        reference_m: &reference,
                        command_v: &command,
                        measured_m: &measured,
                        base_v: &command,
                        periodic: true,
                        noise: Some(TrialNoise {
                            measured_m: sigma,
                            command_v: 1e-6,
                        }),
                        previous: None,
                        table_v: None,
                    },
                    &mut next,
                )
                .unwrap();
            assert!(summary.learned_share > 0.99, "{}", summary.learned_share);
            next
        };
        let (clean, noisy) = (learn(false), learn(true));
        let rms = |x: &dyn Fn(usize) -> f64| {
            libm::sqrt((0..N).map(|j| x(j) * x(j)).sum::<f64>() / N as f64)
        };
        let learned_noise = rms(&|j| f64::from(noisy[j]) - f64::from(clean[j]));
        // All of the noise Q passes, through L: λ/g · σ·√b (a constant command: one slope g).
        let mut state = ModelState::at_rest(60.0);
        let from = state;
        learning.model.step(&mut state, 60.0);
        let slope = f64::from(learning.model.step_slope(&from, &state, 1.0));
        let all = learning.learning_gain / slope * sigma * libm::sqrt(learning.noise_band_share);
        assert!(
            learned_noise < 0.7 * all && learned_noise > 0.2 * all,
            "learned noise {learned_noise:.3e} V, all of it {all:.3e} V"
        );
    }

    /// One periodic step from the command as its own base, with a nearly noiseless trial
    /// (10 pm, 1 µV) that averages passes.
    fn quiet_periodic_step(
        learning: &Learning,
        reference: &[f32],
        command: &[f32],
        measured: &[f32],
        next: &mut [f32],
    ) -> StepSummary {
        learning
            .step(
                &Trial {
                    reference_m: reference,
                    command_v: command,
                    measured_m: measured,
                    base_v: command,
                    periodic: true,
                    noise: Some(TrialNoise {
                        measured_m: 1e-11,
                        command_v: 1e-6,
                    }),
                    previous: None,
                    table_v: None,
                },
                next,
            )
            .unwrap()
    }

    /// Learning above the cut-off waits for the error inside Q's band to settle: a periodic
    /// trial whose 40 nm error at harmonic 20 (2 kHz, above the cut-off) comes with a 1 µm error
    /// at its fundamental learns no harmonic; without the latter it learns harmonic 20.
    #[test]
    fn harmonics_above_the_cut_off_wait_for_the_error_inside_q_s_band() {
        let (model, _, learning) = x_stage(1e5, 0.0, Default::default());
        let learning = learning.with_harmonic_gain(0.5).unwrap();
        const N: usize = 100;
        let cutoff = learning.cutoff_hz();
        assert!(cutoff > 200.0 && cutoff < 1500.0, "{cutoff}");
        let wave = |h: f64, j: usize| libm::sin(2.0 * PI * h * j as f64 / N as f64);
        let command: [f32; N] =
            core::array::from_fn(|j| (60.0 + 40.0 * wave(1.0, j) + 0.3 * wave(20.0, j)) as f32);
        // The stage is the model: its output along the command, in its periodic state.
        let mut state = ModelState::at_rest(command[0]);
        for &u in &command {
            model.step(&mut state, u);
        }
        let measured: [f32; N] = core::array::from_fn(|j| model.step(&mut state, command[j]));
        let learned = |in_band_m: f64| {
            let reference: [f32; N] = core::array::from_fn(|j| {
                (f64::from(measured[j]) + 4e-8 * wave(20.0, j) + in_band_m * wave(1.0, j)) as f32
            });
            let mut next = [0.0f32; N];
            quiet_periodic_step(&learning, &reference, &command, &measured, &mut next)
                .harmonics_learned
        };
        assert_eq!(learned(1e-6), 0);
        assert!(learned(0.0) >= 1);
    }

    /// A harmonic learned at 4 kHz moves the stack's hysteresis along the whole loop (its
    /// reversals add to the path the Bouc-Wen state follows), which shows in Q's band; the step
    /// cancels what the model predicts there, so the next trial's in-band error is a small share
    /// of what the harmonic's change alone leaves (the stage here is the model itself).
    #[test]
    fn a_learned_harmonic_s_mixing_into_the_band_is_cancelled() {
        let (model, _, learning) = x_stage(1e5, 0.0, Default::default());
        let learning = learning.with_harmonic_gain(1.0).unwrap();
        const N: usize = 100;
        const H: usize = 40;
        let band = learning.first_above_cutoff(N);
        assert!(band < H, "{band}");
        let wave = |h: usize, j: usize| libm::sin(2.0 * PI * (h * j) as f64 / N as f64);
        let command: [f32; N] =
            core::array::from_fn(|j| (60.0 + 40.0 * wave(1, j) + 0.3 * wave(H, j)) as f32);
        let periodic_output = |u: &[f32; N]| periodic_output(&model, u);
        let measured = periodic_output(&command).map(|y| y as f32);
        let reference: [f32; N] =
            core::array::from_fn(|j| (f64::from(measured[j]) + 2e-7 * wave(H, j)) as f32);
        let mut next = [0.0f32; N];
        let summary = quiet_periodic_step(&learning, &reference, &command, &measured, &mut next);
        assert!(summary.harmonics_learned >= 1);
        // The command with the harmonic's change alone: the next table's component at H.
        let component = |x: &dyn Fn(usize) -> f64, h: usize| component(x, h, N);
        let change = {
            let (a, b) = (
                component(&|j| f64::from(next[j]), H),
                component(&|j| f64::from(command[j]), H),
            );
            C(a.0 - b.0, a.1 - b.1)
        };
        assert!(change.abs() > 0.1, "{}", change.abs());
        let alone: [f32; N] = core::array::from_fn(|j| {
            let (c, s) = harmonics::twiddle(H, j, N);
            (f64::from(command[j]) + 2.0 * (change.0 * c + change.1 * s)) as f32
        });
        let in_band_error = |u: &[f32; N]| {
            let y = periodic_output(u);
            let e = |j: usize| f64::from(reference[j]) - y[j];
            libm::sqrt(
                (0..band)
                    .map(|h| component(&e, h).abs().powi(2))
                    .sum::<f64>(),
            )
        };
        let (without, with) = (in_band_error(&alone), in_band_error(&next));
        assert!(without > 1e-9, "the change mixes {without} m into the band");
        assert!(with < 0.35 * without, "{with} m left of {without} m");
    }

    /// The model's output along `u` repeated, from its periodic state (one period from rest).
    fn periodic_output<const N: usize>(model: &StaticModel, u: &[f32; N]) -> [f64; N] {
        let mut state = ModelState::at_rest(u[0]);
        for &v in u {
            model.step(&mut state, v);
        }
        core::array::from_fn(|j| f64::from(model.step(&mut state, u[j])))
    }

    /// X(h) = (1/n)·Σ_j x(j)·e^(−j2πhj/n) over a period of n samples.
    fn component(x: &dyn Fn(usize) -> f64, h: usize, n: usize) -> C {
        let mut acc = C(0.0, 0.0);
        for j in 0..n {
            let (c, s) = harmonics::twiddle(h, j, n);
            acc = C(acc.0 + x(j) * c, acc.1 + x(j) * s);
        }
        C(acc.0 / n as f64, acc.1 / n as f64)
    }

    /// The x stage's compensator (window 0–120 V, slew 1e5 V/s, 10 kHz) and effects, for a
    /// learning built with other parameters.
    fn x_compensator() -> (Compensator, Effects) {
        let (model, effects, _) = x_stage(1e5, 0.0, Default::default());
        let settings = CompensatorSettings {
            limits: crate::Limits::new(0.0, 120.0, 1e5),
            sample_period_s: 1e-4,
        };
        (Compensator::new(model, settings).unwrap(), effects)
    }

    /// A negative or non-finite κ is refused when the learning is built, naming the field.
    #[test]
    fn a_collateral_share_below_zero_is_refused() {
        let (compensator, effects) = x_compensator();
        for share in [-0.1, f32::NAN, f32::INFINITY] {
            let params = LearningParams {
                collateral_share: share,
                ..LearningParams::default()
            };
            let field = match Learning::new(&compensator, &effects, params) {
                Err(ParamError::NonFinite { field } | ParamError::OutOfRange { field, .. }) => {
                    field
                }
                other => panic!("{share}: {other:?}"),
            };
            assert_eq!(field, "collateral_share", "{share}");
        }
        let off = LearningParams {
            collateral_share: 0.0,
            ..LearningParams::default()
        };
        assert!(Learning::new(&compensator, &effects, off).is_ok());
    }

    /// The harmonic step's mixing above the band, as the guard predicts it for the change the
    /// step made (`Learning::limit_collateral`'s c), stays within κ of the trial's error RMS; with
    /// κ = 0 (the step unscaled) the same trial's change mixes more than that.
    #[test]
    fn a_learned_harmonic_s_mixing_above_the_band_is_bounded() {
        let (compensator, effects) = x_compensator();
        let model = *compensator.model();
        let with_share = |share: f32| {
            Learning::new(
                &compensator,
                &effects,
                LearningParams {
                    collateral_share: share,
                    harmonic_gain: 1.0,
                    ..LearningParams::default()
                },
            )
            .unwrap()
        };
        const N: usize = 100;
        let wave = |h: usize, j: usize| libm::sin(2.0 * PI * (h * j) as f64 / N as f64);
        // A triangle's turning points, where a ripple adds reversals.
        let triangle = |j: usize| {
            let p = (j as f64 / N as f64 + 0.25).rem_euclid(1.0);
            if p < 0.5 {
                4.0 * p - 1.0
            } else {
                3.0 - 4.0 * p
            }
        };
        let command: [f32; N] = core::array::from_fn(|j| (60.0 + 50.0 * triangle(j)) as f32);
        let periodic_output = |u: &[f32; N]| periodic_output(&model, u);
        let measured = periodic_output(&command).map(|y| y as f32);
        // An error at the harmonics above the band, as a corner's ring leaves it.
        let error = |j: usize| (30..45).map(|h| 1.5e-7 * wave(h, j)).sum::<f64>();
        let reference: [f32; N] =
            core::array::from_fn(|j| (f64::from(measured[j]) + error(j)) as f32);
        let error_rms = libm::sqrt((0..N).map(|j| error(j).powi(2)).sum::<f64>() / N as f64);
        let collateral = |learning: &Learning| {
            let mut next = [0.0f32; N];
            let summary = quiet_periodic_step(learning, &reference, &command, &measured, &mut next);
            assert!(
                summary.harmonics_learned >= 10,
                "{}",
                summary.harmonics_learned
            );
            let t = 1e-4;
            let first = learning.first_above_cutoff(N);
            // The step's change above the band, alone.
            let component = |x: &dyn Fn(usize) -> f64, h: usize| component(x, h, N);
            let diff = |j: usize| f64::from(next[j]) - f64::from(command[j]);
            let changes: [C; N] = core::array::from_fn(|h| {
                if (first..N / 2).contains(&h) {
                    component(&diff, h)
                } else {
                    C(0.0, 0.0)
                }
            });
            let delta = |j: usize| {
                (first..N / 2)
                    .map(|h| {
                        let (c, s) = harmonics::twiddle(h, j, N);
                        2.0 * (changes[h].0 * c + changes[h].1 * s)
                    })
                    .sum::<f64>()
            };
            let changed: [f32; N] =
                core::array::from_fn(|j| (f64::from(command[j]) + delta(j)) as f32);
            let start = learning.periodic_state(&|j| command[j], N);
            let slope = learning.mean_slope(&|j| command[j], N, start);
            let (w, x) = (periodic_output(&command), periodic_output(&changed));
            let mixed = |j: usize| x[j] - w[j] - slope * delta(j);
            let c2: f64 = (first..N / 2)
                .map(|h| {
                    let g = learning.model_response(h as f64 / (N as f64 * t), slope, 0);
                    let size = g.abs() / slope.abs() * component(&mixed, h).abs();
                    2.0 * size * size
                })
                .sum();
            (
                libm::sqrt(c2),
                changes[first..N / 2].iter().map(|c| c.abs()).sum::<f64>(),
            )
        };
        let (bounded, moved) = collateral(&with_share(0.12));
        let (unscaled, moved_unscaled) = collateral(&with_share(0.0));
        assert!(
            moved > 0.0 && moved < moved_unscaled,
            "{moved} V of {moved_unscaled} V"
        );
        assert!(
            bounded <= 0.12 * error_rms * 1.05,
            "{bounded} m against {error_rms} m"
        );
        assert!(
            unscaled > 0.12 * error_rms,
            "{unscaled} m against {error_rms} m"
        );
    }

    /// Four passes of a 20 Hz sine read by a sensor of 3.1 nm steps without noise agree to the
    /// bit: their spread is zero, and the noise is the quantisation's q/√12; the same sine
    /// unquantised keeps its spread (zero), and a quantised record with noise keeps its spread
    /// where that is larger.
    #[test]
    fn a_quantised_record_s_noise_is_at_least_its_quantisation() {
        const N: usize = 1000;
        let q = 3.1e-9;
        let sine = |j: usize| 20e-6 + 10e-6 * libm::sin(2.0 * PI * (j % N) as f64 / N as f64);
        let quantised: [f32; 4 * N] =
            core::array::from_fn(|j| (libm::round(sine(j) / q) * q) as f32);
        let step = quantum(&quantised).unwrap();
        assert!((step / q - 1.0).abs() < 0.01, "{step}");
        let sigma = pass_noise_rms(&quantised, N).unwrap();
        assert!(
            (sigma / (q / libm::sqrt(12.0)) - 1.0).abs() < 0.01,
            "{sigma}"
        );
        let smooth: [f32; 4 * N] = core::array::from_fn(|j| sine(j) as f32);
        assert_eq!(quantum(&smooth), None);
        assert_eq!(pass_noise_rms(&smooth, N), Some(0.0));
        let mut draw = gaussian(7);
        let noisy: [f32; 4 * N] =
            core::array::from_fn(|j| (libm::round((sine(j) + 20e-9 * draw()) / q) * q) as f32);
        let sigma = pass_noise_rms(&noisy, N).unwrap();
        assert!((sigma / 10e-9 - 1.0).abs() < 0.1, "{sigma}");
    }

    /// Four passes of a record whose every pass rings at 2.2 kHz (50 nm, as a lightly damped
    /// mode at a triangle's corners) under a 5 nm white noise: the spread between the passes gives
    /// the averaged record's noise, 5/√4 = 2.5 nm, the ring left out; the fourth differences of
    /// the averaged record read the ring as noise (≈ 20× too high).
    #[test]
    fn the_noise_of_averaged_passes_comes_from_their_spread_not_their_ring() {
        const N: usize = 1000;
        const PASSES: usize = 4;
        let sigma = 5e-9f64;
        let mut seed = 99u64;
        let mut uniform = || {
            seed = seed.wrapping_add(0x9e37_79b9_7f4a_7c15);
            let mut z = seed;
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            z ^= z >> 31;
            ((z >> 11) as f64 + 0.5) / (1u64 << 53) as f64
        };
        let mut record = [0.0f32; N * PASSES];
        for (i, v) in record.iter_mut().enumerate() {
            let j = i % N;
            let ring = 5e-8 * libm::sin(2.0 * PI * 220.0 * j as f64 / N as f64);
            let (a, b) = (uniform(), uniform());
            let noise = libm::sqrt(-2.0 * libm::log(a)) * libm::cos(2.0 * PI * b) * sigma;
            *v = (1e-5 + ring + noise) as f32;
        }
        let from_passes = pass_noise_rms(&record, N).unwrap();
        assert!(
            (from_passes / (sigma / 2.0) - 1.0).abs() < 0.1,
            "{from_passes:.3e}"
        );
        let (_, _, learning) = x_stage(1e5, 0.0, Default::default());
        let averaged: [f32; N] = core::array::from_fn(|j| {
            (0..PASSES).map(|p| record[p * N + j]).sum::<f32>() / PASSES as f32
        });
        let mut scratch = [0.0f32; N];
        let fourth = learning.fourth_difference_noise(
            true,
            &|j| f64::from(averaged[j]) - 1e-5,
            &mut scratch,
        );
        assert!(
            fourth > 5.0 * from_passes,
            "{fourth:.3e} vs {from_passes:.3e}"
        );
        // Fewer than two passes, or not whole ones: no estimate.
        assert!(pass_noise_rms(&record[..N], N).is_none());
        assert!(pass_noise_rms(&record[..N * 2 + 1], N).is_none());
    }

    /// The gain a trial shows: a stage whose output is 1.5 × the model's plus 2 µm gives (1.5,
    /// 2 µm); L's gain follows it, and a ratio outside the rule's gain set is refused.
    #[test]
    fn the_trial_shows_the_model_gain_and_l_follows_it() {
        let (model, _, learning) = x_stage(1e5, 0.0, Default::default());
        const N: usize = 500;
        let command: [f32; N] = core::array::from_fn(|j| {
            60.0 + 50.0 * libm::sinf(2.0 * core::f32::consts::PI * j as f32 / N as f32)
        });
        let mut state = ModelState::at_rest(command[0]);
        for &u in &command {
            model.step(&mut state, u);
        }
        let measured: [f32; N] =
            core::array::from_fn(|j| 1.5 * model.step(&mut state, command[j]) + 2e-6);
        let trial = Trial {
            reference_m: &measured,
            command_v: &command,
            measured_m: &measured,
            base_v: &command,
            periodic: true,
            noise: None,
            previous: None,
            table_v: None,
        };
        let (gain, offset) = learning.gain_ratio(&trial).unwrap();
        assert!((gain - 1.5).abs() < 1e-4, "{gain}");
        assert!((offset - 2e-6).abs() < 1e-9, "{offset}");
        let scaled = learning.with_model_gain(gain).unwrap();
        assert!((scaled.learning_gain() * gain - learning.learning_gain()).abs() < 1e-12);
        assert!(learning.with_model_gain(2.0).is_err());
        // A measured output the model does not explain gives no ratio.
        let unrelated: [f32; N] = core::array::from_fn(|j| if j % 2 == 0 { 1e-6 } else { 0.0 });
        let noise = Trial {
            measured_m: &unrelated,
            ..trial
        };
        assert!(learning.gain_ratio(&noise).is_none());
    }

    #[test]
    fn rate_dependent_models_are_inverted_by_the_learning() {
        use crate::effects::{EffectParams, EffectsState};
        let relaxing = EffectParams {
            relaxation_gain: [2.0, 0.0],
            relaxation_time_constant_s: [5e-3, 0.0],
            ..EffectParams::default()
        };
        // (lag, effects, largest error ratio from one trial to the next over the first five,
        // largest final / first error)
        let cases = [
            (0.0, relaxing, 1.0, 0.05),
            (2e-3, EffectParams::default(), 0.2, 1e-3),
        ];
        for (lag_s, params, ratio, final_share) in cases {
            let (model, effects, learning) = x_stage(1e5, lag_s, params);
            const N: usize = 500; // one 20 Hz period at 10 kHz
            let sine = |phase: f64, j: usize| {
                (60.0 + 40.0 * libm::sin(2.0 * PI * j as f64 / N as f64 + phase)) as f32
            };
            // The stage's output over the third period of `u` played in a loop from rest.
            let play = |u: &[f32; N]| -> [f32; N] {
                let mut state = ModelState::at_rest(u[0]);
                let mut chain = EffectsState::new();
                let mut y = [0.0f32; N];
                for k in 0..3 * N {
                    model.step(&mut state, u[k % N]);
                    let w = model.map().output(state.input_v, state.hysteresis.h);
                    let z = effects.forward_z(&mut chain, u[k % N], w);
                    if k >= 2 * N {
                        y[k - 2 * N] = z;
                    }
                }
                y
            };
            let reference = play(&core::array::from_fn(|j| sine(0.05, j)));
            let base: [f32; N] = core::array::from_fn(|j| sine(0.0, j));
            let mut command = base;
            let mut errors = [0.0f64; 9];
            for error in errors.iter_mut() {
                let measured = play(&command);
                let trial = Trial {
                    reference_m: &reference,
                    command_v: &command,
                    measured_m: &measured,
                    base_v: &base,
                    periodic: true,
                    noise: None,
                    previous: None,
                    table_v: None,
                };
                let mut next = [0.0f32; N];
                *error = learning.step(&trial, &mut next).unwrap().rms_error_m;
                command = next;
            }
            for k in 1..errors.len() {
                let bound = if k <= 5 { ratio } else { 1.05 };
                assert!(errors[k] <= bound * errors[k - 1], "trial {k}: {errors:?}");
            }
            assert!(errors[8] <= final_share * errors[0], "{errors:?}");
        }
    }
}
