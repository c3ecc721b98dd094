//! Branch-based `min`, `max` and `clamp`, and the power `x^n` of the per-sample path.
//!
//! On the Cortex-M4F (FPv4, no VMAXNM/VMINNM) `f32::max`/`f32::min` compile to calls of the
//! `fmaxf`/`fminf` library routines, and `f32::clamp` keeps a panic path for `min > max`. These
//! compile to a compare and conditional moves. NaN behaviour is stated per function; callers
//! handle NaN before relying on it.
//!
//! The power is chosen by target: on bare metal (`target_os = "none"`, the Cortex-M4F) the f32-only
//! `2^(n·log2 x)` of [`pow_nonnegative`], because libm's `powf` computes in f64, which that FPU
//! emulates in software; on a host with an f64 unit, a table-driven f64 power that is correctly
//! rounded to f32 and faster there than both (libm's `powf` takes a slow generic path).

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

/// `x^n` for `x ≥ 0` and `n ≥ 1`, in f32 arithmetic only: `2^(n·log2 x)`.
///
/// libm's `powf` is accurate to 0.6 ulp but computes in f64, which the Cortex-M4F's single-precision
/// FPU emulates in software (≈ 2000 instructions per call, measured with `firmware/bench.sh`). Here
/// `x = m·2^e` with `m ∈ [√½, √2)`, `ln m = 2·artanh(t)`, `t = (m − 1)/(m + 1)` by its series to
/// t⁹ (|t| ≤ 0.172: truncation < 2e-9), and `2^y = 2^k·e^(r)`, `r = (y − k)·ln 2 ∈ [−0.35, 0.35]`,
/// by its Taylor polynomial to r⁷ (truncation < 2e-8); `y = n·log2 x` is carried as an exact whole
/// part `n_hi·e` plus a rounded rest, so that large |log2 x| does not cost accuracy. Measured
/// relative error against f64 in `tests/tests/libm_accuracy.rs`.
/// `x ≤ 1e-30` (and NaN) gives 0; results beyond f32 range give +∞ or 0.
#[inline]
pub fn pow_nonnegative(x: f32, n: f32) -> f32 {
    pow_f32_only(x, n)
}

/// The power of the per-sample path, `x^n` for `x ≥ 0`, `n ≥ 1`, selected by target (module doc):
/// [`pow_nonnegative`] on bare metal, `pow_host` (correctly rounded, f64 tables) on a host. Same edges on both: `x ≤ 1e-30` and
/// NaN give 0, +∞ gives +∞. Always inlined (the Bouc-Wen RK4 slope, the compensator's fast path).
#[inline(always)]
pub(crate) fn pow_nonnegative_inline(x: f32, n: f32) -> f32 {
    #[cfg(target_os = "none")]
    {
        pow_f32_only(x, n)
    }
    #[cfg(not(target_os = "none"))]
    {
        pow_host(x, n)
    }
}

/// The f32-only power behind [`pow_nonnegative`], always inlined.
#[inline(always)]
fn pow_f32_only(x: f32, n: f32) -> f32 {
    if x.is_nan() || x <= 1e-30 {
        return 0.0;
    }
    if x == f32::INFINITY {
        return f32::INFINITY;
    }
    let bits = x.to_bits();
    let mut exponent = ((bits >> 23) & 0xff) as i32 - 127;
    let mut mantissa = f32::from_bits((bits & 0x007f_ffff) | 0x3f80_0000);
    if mantissa > core::f32::consts::SQRT_2 {
        mantissa *= 0.5;
        exponent += 1;
    }
    let t = (mantissa - 1.0) / (mantissa + 1.0);
    let t2 = t * t;
    let ln_mantissa =
        2.0 * t * (1.0 + t2 * (1.0 / 3.0 + t2 * (0.2 + t2 * (1.0 / 7.0 + t2 * (1.0 / 9.0)))));
    // y = n·(e + log2 m), kept as whole + fraction: n = n_hi + n_lo with n_hi on 12 significant
    // bits, so n_hi·e (|e| ≤ 127) is exact and only the small rest is rounded.
    let n_hi = f32::from_bits(n.to_bits() & 0xffff_f000);
    let n_lo = n - n_hi;
    let e = exponent as f32;
    let whole = n_hi * e;
    let rest = n_lo * e + n * (ln_mantissa * core::f32::consts::LOG2_E);
    let y = whole + rest;
    if y >= 128.0 {
        return f32::INFINITY;
    }
    if y < -126.0 {
        return 0.0;
    }
    let k = if y >= 0.0 {
        (y + 0.5) as i32
    } else {
        (y - 0.5) as i32
    };
    let r = ((whole - k as f32) + rest) * core::f32::consts::LN_2;
    let e_r = 1.0
        + r * (1.0
            + r * (0.5
                + r * (1.0 / 6.0
                    + r * (1.0 / 24.0
                        + r * (1.0 / 120.0 + r * (1.0 / 720.0 + r * (1.0 / 5040.0)))))));
    e_r * f32::from_bits(((k + 127) as u32) << 23)
}

/// 1/c for the 16 mantissa intervals of [1, 2), c = 1 + (j + ½)/16.
const INV_CENTRE: [f64; 16] = [
    0.9696969696969697,
    0.9142857142857143,
    0.8648648648648649,
    0.8205128205128205,
    0.7804878048780488,
    0.7441860465116279,
    0.7111111111111111,
    0.6808510638297872,
    0.6530612244897959,
    0.6274509803921569,
    0.6037735849056604,
    0.5818181818181818,
    0.5614035087719298,
    0.5423728813559322,
    0.5245901639344263,
    0.5079365079365079,
];
/// log2 c for the same centres.
const LOG2_CENTRE: [f64; 16] = [
    0.044394119358453436,
    0.12928301694496647,
    0.20945336562894978,
    0.28540221886224837,
    0.3575520046180837,
    0.42626475470209796,
    0.4918530963296747,
    0.5545888516776374,
    0.6147098441152082,
    0.6724253419714956,
    0.7279204545631992,
    0.7813597135246596,
    0.8328900141647416,
    0.8826430493618412,
    0.9307373375628862,
    0.9772799234999164,
];
/// 2^(j/16).
const EXP2_SIXTEENTHS: [f64; 16] = [
    1.0,
    1.0442737824274138,
    1.0905077326652577,
    1.1387886347566916,
    1.189207115002721,
    1.241857812073484,
    1.2968395546510096,
    1.3542555469368927,
    core::f64::consts::SQRT_2,
    1.4768261459394993,
    1.5422108254079407,
    1.6104903319492543,
    1.681792830507429,
    1.7562521603732995,
    1.8340080864093424,
    1.9152065613971474,
];

/// The host power behind [`pow_nonnegative_inline`] (module doc): `x = m·2^e`, `m` split into 16
/// intervals with centres `c`, `ln m = ln c + ln(1 + r)`, `r = m/c − 1` (|r| ≤ 1/31, series to r⁶), and
/// `2^y = 2^(k/16)·e^f`, `|f| ≤ ln 2/32` (series to f⁵), in f64: the f32 result is correctly rounded
/// (≤ 0.5 ulp, measured in the tests below); same edges as [`pow_nonnegative`].
#[cfg(not(target_os = "none"))]
#[inline(always)]
fn pow_host(x: f32, n: f32) -> f32 {
    if x.is_nan() || x <= 1e-30 {
        return 0.0;
    }
    if x == f32::INFINITY {
        return f32::INFINITY;
    }
    let bits = x.to_bits();
    let exponent = ((bits >> 23) & 0xff) as i32 - 127;
    let index = ((bits >> 19) & 0xf) as usize;
    let mantissa = f64::from(f32::from_bits((bits & 0x007f_ffff) | 0x3f80_0000));
    let r = mantissa * INV_CENTRE[index] - 1.0;
    let r2 = r * r;
    // ln(1 + r) = r − r²/2 + r³/3 − r⁴/4 + r⁵/5 − r⁶/6 (Estrin), |r| ≤ 1/31.
    let ln1p =
        r * (1.0 - 0.5 * r) + r2 * r * ((1.0 / 3.0 - 0.25 * r) + r2 * (0.2 - r * (1.0 / 6.0)));
    let y = f64::from(n)
        * (f64::from(exponent) + LOG2_CENTRE[index] + ln1p * core::f64::consts::LOG2_E);
    if y >= 128.0 {
        return f32::INFINITY;
    }
    if y < -150.0 {
        return 0.0;
    }
    let scaled = y * 16.0;
    let k = if scaled >= 0.0 {
        (scaled + 0.5) as i64
    } else {
        (scaled - 0.5) as i64
    };
    let f = (y - k as f64 * (1.0 / 16.0)) * core::f64::consts::LN_2;
    let f2 = f * f;
    // e^f to f⁵ (Estrin), |f| ≤ ln 2/32.
    let e_f = (1.0 + f) + f2 * ((0.5 + f * (1.0 / 6.0)) + f2 * (1.0 / 24.0 + f * (1.0 / 120.0)));
    let whole = k >> 4;
    let scale = f64::from_bits(((whole + 1023) as u64) << 52);
    (e_f * EXP2_SIXTEENTHS[(k & 15) as usize] * scale) as f32
}

/// `1.5·2⁵²`: adding it to an f64 of magnitude below 2⁵¹ rounds that to a whole number held in the
/// low bits of the sum.
#[cfg(not(target_os = "none"))]
const ROUND_SHIFT: f64 = 6_755_399_441_055_744.0;

/// `x^n` in f64 for the host's f64 RK4 of the Bouc-Wen step (`crate::bouc_wen`; `x ≥ 0`,
/// `1 ≤ n ≤ 16`): the tables and polynomials of `pow_host` without its rounding to f32, so
/// `y = n·log2 x` with `log2 x = e + log2 c + ln(1 + r)·log2 e` (series to r⁶, |r| ≤ 1/31) and
/// `x^n = 2^(k/16)·e^f`, `k = round(16·y)` (by the `ROUND_SHIFT` addition, no float-to-integer
/// conversion on the way), `|f| ≤ ln 2/32` (series to f⁵), `2^(k/16)` as the table entry with `k/16`'s
/// whole part added to its exponent bits. Relative error ≤ 1e-11·n (measured in the tests below),
/// far below f32 rounding. `x ≤ 1e-30` and NaN give 0 (as [`pow_nonnegative`]); `y ≥ 1000` gives +∞
/// (so does `x = +∞`), `y < −1000` gives 0.
#[cfg(not(target_os = "none"))]
#[inline(always)]
pub(crate) fn pow_host_f64(x: f64, n: f64) -> f64 {
    if x.is_nan() || x <= 1e-30 {
        return 0.0;
    }
    let bits = x.to_bits();
    let exponent = (bits >> 52) as i64 - 1023;
    let index = ((bits >> 48) & 0xf) as usize;
    let mantissa = f64::from_bits((bits & 0x000f_ffff_ffff_ffff) | 0x3ff0_0000_0000_0000);
    let r = mantissa * INV_CENTRE[index] - 1.0;
    let r2 = r * r;
    // ln(1 + r) = r − r²/2 + r³/3 − r⁴/4 + r⁵/5 − r⁶/6 (Estrin), |r| ≤ 1/31.
    let ln1p =
        r * (1.0 - 0.5 * r) + r2 * r * ((1.0 / 3.0 - 0.25 * r) + r2 * (0.2 - r * (1.0 / 6.0)));
    // 16·y, with 16·n formed off the dependency chain.
    let y16 =
        (16.0 * n) * ((exponent as f64 + LOG2_CENTRE[index]) + ln1p * core::f64::consts::LOG2_E);
    if y16 >= 16.0 * 1000.0 {
        return f64::INFINITY;
    }
    if y16 < -16.0 * 1000.0 {
        return 0.0;
    }
    let shifted = y16 + ROUND_SHIFT;
    // |16·y| ≤ 16 000: the difference of the bit patterns is round(16·y) exactly.
    let k = (shifted.to_bits() as i64).wrapping_sub(ROUND_SHIFT.to_bits() as i64);
    let f = (y16 - (shifted - ROUND_SHIFT)) * (core::f64::consts::LN_2 / 16.0);
    let f2 = f * f;
    // e^f to f⁵ (Estrin), |f| ≤ ln 2/32.
    let e_f = (1.0 + f) + f2 * ((0.5 + f * (1.0 / 6.0)) + f2 * (1.0 / 24.0 + f * (1.0 / 120.0)));
    // 2^(k/16) = 2^(k >> 4)·2^((k & 15)/16): the whole part goes into the exponent field (|k >> 4| ≤
    // 1000 here, so the sum stays a normal number).
    let scale = (EXP2_SIXTEENTHS[(k & 15) as usize].to_bits() as i64).wrapping_add((k >> 4) << 52);
    e_f * f64::from_bits(scale as u64)
}

/// `x^p` in f64 for `x ≥ 0`, `p ≥ 0` (the oscillator's `|z|^(ν−1)`), with the tables of
/// `pow_host`: `ln(1 + r)` to r¹⁰ and `e^f` to f⁸; relative error ≤ 1e-12 for p ≤ 15 (the rounding
/// of `p·log2 x`, measured in the tests below; a few ulp for p ≈ 1), ample for the oscillator's f64
/// RK4 state; 0 for x = 0 < p, 1 for p = 0. Several times faster than libm's `pow` on a host.
/// Subnormal or non-finite `x` go to libm.
pub(crate) fn pow_f64(x: f64, p: f64) -> f64 {
    if p == 0.0 {
        return 1.0;
    }
    if x == 0.0 {
        return 0.0;
    }
    if !(f64::MIN_POSITIVE..f64::INFINITY).contains(&x) {
        return libm::pow(x, p);
    }
    let bits = x.to_bits();
    let exponent = ((bits >> 52) & 0x7ff) as i64 - 1023;
    let index = ((bits >> 48) & 0xf) as usize;
    let mantissa = f64::from_bits((bits & 0x000f_ffff_ffff_ffff) | 0x3ff0_0000_0000_0000);
    let r = mantissa * INV_CENTRE[index] - 1.0;
    let ln1p = r
        * (1.0
            - r * (0.5
                - r * (1.0 / 3.0
                    - r * (0.25
                        - r * (0.2
                            - r * (1.0 / 6.0
                                - r * (1.0 / 7.0 - r * (0.125 - r * (1.0 / 9.0 - r * 0.1)))))))));
    let y = p * (exponent as f64 + LOG2_CENTRE[index] + ln1p * core::f64::consts::LOG2_E);
    if y >= 1024.0 {
        return f64::INFINITY;
    }
    if y < -1000.0 {
        return libm::pow(x, p);
    }
    let scaled = y * 16.0;
    let k = if scaled >= 0.0 {
        (scaled + 0.5) as i64
    } else {
        (scaled - 0.5) as i64
    };
    let f = (y - k as f64 * (1.0 / 16.0)) * core::f64::consts::LN_2;
    let e_f = 1.0
        + f * (1.0
            + f * (0.5
                + f * (1.0 / 6.0
                    + f * (1.0 / 24.0
                        + f * (1.0 / 120.0
                            + f * (1.0 / 720.0 + f * (1.0 / 5040.0 + f * (1.0 / 40320.0))))))));
    let scale = f64::from_bits((((k >> 4) + 1023) as u64) << 52);
    e_f * EXP2_SIXTEENTHS[(k & 15) as usize] * scale
}

/// exp(X) − I of an N×N matrix in f64: scaling until ‖X·2⁻ˢ‖₁ ≤ 1/4, an 18-term Taylor series of
/// exp − I, then s squarings in the form (I + E)² − I = 2E + E², which keeps the small entries of
/// exp(X) − I exact when X is small (no cancellation against I). `None` for a non-finite X or result.
/// Used at build time only (discretisations), never per sample.
pub(crate) fn expm_minus_identity<const N: usize>(x: &[[f64; N]; N]) -> Option<[[f64; N]; N]> {
    let norm = (0..N)
        .map(|c| (0..N).map(|r| libm::fabs(x[r][c])).sum::<f64>())
        .fold(0.0f64, libm::fmax);
    if !norm.is_finite() {
        return None;
    }
    let mut squarings = 0u32;
    let mut scale = 1.0f64;
    while norm * scale > 0.25 {
        scale *= 0.5;
        squarings += 1;
        if squarings > 200 {
            return None;
        }
    }
    let mut a = [[0.0f64; N]; N];
    for (row_a, row_x) in a.iter_mut().zip(x) {
        for (v, &xv) in row_a.iter_mut().zip(row_x) {
            *v = xv * scale;
        }
    }
    let mut term = a;
    let mut e = a;
    for j in 2..=18u32 {
        term = mat_mul(&term, &a);
        for (row_e, row_t) in e.iter_mut().zip(term.iter_mut()) {
            for (ev, tv) in row_e.iter_mut().zip(row_t.iter_mut()) {
                *tv /= f64::from(j);
                *ev += *tv;
            }
        }
    }
    for _ in 0..squarings {
        let sq = mat_mul(&e, &e);
        for (row_e, row_s) in e.iter_mut().zip(&sq) {
            for (ev, &sv) in row_e.iter_mut().zip(row_s) {
                *ev = 2.0 * *ev + sv;
            }
        }
    }
    e.iter().flatten().all(|v| v.is_finite()).then_some(e)
}

/// A·B of two N×N matrices.
fn mat_mul<const N: usize>(a: &[[f64; N]; N], b: &[[f64; N]; N]) -> [[f64; N]; N] {
    let mut m = [[0.0; N]; N];
    for (row_m, row_a) in m.iter_mut().zip(a) {
        for (c, v) in row_m.iter_mut().enumerate() {
            *v = (0..N).map(|k| row_a[k] * b[k][c]).sum();
        }
    }
    m
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

    #[test]
    fn power_edges() {
        assert_eq!(pow_nonnegative(0.0, 1.5), 0.0);
        assert_eq!(pow_nonnegative(f32::NAN, 1.5), 0.0);
        assert_eq!(pow_nonnegative(f32::INFINITY, 1.5), f32::INFINITY);
        assert_eq!(pow_nonnegative(1e30, 3.0), f32::INFINITY);
        assert!((pow_nonnegative(4.0, 1.5) - 8.0).abs() < 1e-5);
        assert!((pow_nonnegative(1.0, 2.7) - 1.0).abs() < 1e-6);
    }

    #[cfg(not(target_os = "none"))]
    #[test]
    fn host_power_is_correctly_rounded() {
        let mut worst = 0.0f64;
        for n in [1.0f32, 1.419, 1.5, 2.5, 3.05869, 4.0, 16.0] {
            for i in 0..=100_000 {
                let x = libm::powf(10.0, -6.0 + 10.0 * i as f32 / 100_000.0);
                let exact = libm::pow(f64::from(x), f64::from(n));
                if !(1e-37..3e38).contains(&exact) {
                    continue;
                }
                let ulp = f64::from(exact as f32) * f64::from(f32::EPSILON);
                worst = worst.max((f64::from(pow_host(x, n)) - exact).abs() / ulp);
            }
        }
        assert!(worst <= 0.5 + 1e-6, "host power off by {worst} ulp");
    }

    #[cfg(not(target_os = "none"))]
    #[test]
    fn host_f64_power_is_accurate_to_1e_11_n() {
        for n in [1.0f64, 1.419, 1.5, 2.5, 3.05869, 4.0, 7.3, 16.0] {
            let mut worst = 0.0f64;
            for i in 0..=200_000 {
                let x = libm::pow(10.0, -6.0 + 10.0 * f64::from(i) / 200_000.0);
                let exact = libm::pow(x, n);
                worst = worst.max(((pow_host_f64(x, n) - exact) / exact).abs());
            }
            assert!(worst <= 1e-11 * n, "n = {n}: off by {worst:e} relative");
        }
        assert_eq!(pow_host_f64(0.0, 1.5), 0.0);
        assert_eq!(pow_host_f64(1e-31, 1.5), 0.0);
        assert_eq!(pow_host_f64(f64::NAN, 1.5), 0.0);
        assert_eq!(pow_host_f64(f64::INFINITY, 1.5), f64::INFINITY);
        assert_eq!(pow_host_f64(1e300, 16.0), f64::INFINITY);
        assert_eq!(pow_host_f64(1e-29, 16.0), 0.0);
        assert!((pow_host_f64(1.0, 3.05869) - 1.0).abs() < 1e-11 * 3.05869);
        assert!((pow_host_f64(4.0, 1.5) - 8.0).abs() < 8.0 * 1e-11 * 1.5);
    }

    #[test]
    fn f64_power_is_accurate_to_1e_12() {
        let mut worst = 0.0f64;
        for p in [1e-6f64, 0.419, 0.5, 1.0, 1.5, 2.05869, 15.0] {
            for i in 0..=100_000 {
                let x = libm::pow(10.0, -8.0 + 14.0 * f64::from(i) / 100_000.0);
                let exact = libm::pow(x, p);
                let got = pow_f64(x, p);
                worst = worst.max(((got - exact) / exact).abs());
            }
        }
        assert!(worst <= 1e-12, "f64 power off by {worst:e} relative");
        assert_eq!(pow_f64(0.0, 0.5), 0.0);
        assert_eq!(pow_f64(0.0, 0.0), 1.0);
        assert_eq!(pow_f64(3.0, 0.0), 1.0);
    }

    #[test]
    fn per_sample_power_has_the_same_edges_and_values() {
        for x in [0.0f32, 1e-31, f32::NAN, f32::INFINITY] {
            let (a, b) = (pow_nonnegative_inline(x, 1.5), pow_nonnegative(x, 1.5));
            assert!(a == b, "x = {x}: {a} vs {b}");
        }
        for (x, n) in [(4.0f32, 1.5f32), (0.3, 3.05869), (1e3, 1.419), (2e-4, 4.0)] {
            let (a, b) = (pow_nonnegative_inline(x, n), pow_nonnegative(x, n));
            assert!(((a - b) / b).abs() < 1e-6, "{x}^{n}: {a} vs {b}");
        }
    }
}
