//! Effects added around the hysteresis model: creep (a Kelvin–Voigt bank and a logarithmic creep),
//! an even-order term of the previous command, a second-order mode, an input delay, drift (linear
//! and exponential settling) and cross-axis coupling — each with its inverse or its place in the
//! inverse chain.
//!
//! # The forward chain (per axis, command sample j, sample period T)
//! ```text
//! u[j]                      command [V]
//! w[j] = H(u[j])            the hysteresis model's output [m] (StaticModel, computed by the caller)
//! c[j] = Σᵢ gᵢ·xᵢ[j]        creep bank, at most MAX_CREEP_ELEMENTS elements:
//!        xᵢ[j] = aᵢ·xᵢ[j−1] + (1 − aᵢ)·(u[j−1] − u_ref),  aᵢ = exp(−T/τᵢ),  xᵢ[0] = 0
//!      + g_log·½·Σₗ xₗ[j]   logarithmic creep: the same elements with τₗ = t₀·10^((l+1)/2),
//!                           l = 0 … LOG_CREEP_ELEMENTS − 1 (half a decade apart, 6 decades)
//! c_w[j] = Σᵢ g_wᵢ·vᵢ[j]    rate-dependent hysteresis (relaxation of w − k_r·u), at most
//!        vᵢ[j] = bᵢ·vᵢ[j−1] + (1 − bᵢ)·(p[j−1] − p_ref),  bᵢ = exp(−T/τ_wᵢ),  vᵢ[0] = 0
//!        p[j] = w[j] − k_r·u[j]  MAX_RELAXATION_ELEMENTS elements, p_ref the first p; with a
//!                           spread W > 0 the first element is N lags τ_w₀·10^(W·(k/(N−1) − ½))
//!                           of gain g_w₀/N (k = 0 … N − 1, N = RELAXATION_SPREAD_POINTS)
//! s[j] = w[j] + e·(u[j−1] − u_c)² + c[j] + c_w[j],   u[−1] := u_c       even-order term
//! z[j] = M(s)[j]            second-order mode  z̈ + 2ζω·ż + ω²·z = ω²·s + 2ρζω·ṡ,  ω = 2π·f_mode
//! y[k] = z(k − D) + d(k·T) + κ·z_other(k − D)                           output sample k
//! d(t) = r_d·t + A_d·(1 − exp(−t/τ_d))                                  drift
//! ```
//!
//! Signs and units: gᵢ \[m/V\] (positive: the output keeps moving in the direction of a command
//! change), τᵢ \[s\]; e \[m/V²\], u_c \[V\] (e > 0 adds upwards on both sides of u_c); f_mode \[Hz\],
//! ζ \[1\] (unit DC gain: a constant s gives z = s), ρ ∈ \[0, 1\] the share of the damping that acts on the
//! relative motion z − s (0: all of it on z, a force-driven mode; 1: all of it on z − s, a mode
//! driven through a stack's own spring and damper); D = delay_s/T \[samples\] (the output lags);
//! drift r_d \[m/s\] from t = 0 at the first output sample; A_d \[m\] (positive: the output settles
//! upwards), τ_d \[s\]; g_log \[m/V per decade of time\] (positive: the output keeps moving in the
//! direction of a command change), t₀ \[s\]; κ \[1\] the part of the *other* axis's z that appears on
//! this axis; g_wᵢ \[1\] ≥ 0 (the low-frequency output is (1 + Σ g_wᵢ)·w, the high-frequency one w:
//! the loop's gain falls and its phase lags as the rate rises), τ_wᵢ \[s\]. All zero is the
//! identity: y\[k\] = w\[k\]. k_r \[m/V\]: the linear strain that does not relax (0: all of w
//! relaxes; the map's k1: only its hysteretic part k2·h + y0, the domain switching, relaxes while
//! the lattice strain k1·u follows the voltage at once).
//!
//! | effect | fields | equation | inverse |
//! |---|---|---|---|
//! | creep (Kelvin–Voigt) | `creep_gain_m_per_v`, `creep_time_constant_s` | Σᵢ gᵢ·xᵢ | exact, in [`Effects::creep_m`] |
//! | creep (logarithmic) | `log_creep_gain_m_per_v`, `log_creep_time_s` | g_log·½·Σₗ xₗ ≈ g_log·Δu·log₁₀(1 + t/t₀) after a step | exact, in [`Effects::creep_m`] |
//! | hysteresis input lag | `hysteresis_lag_s` | the Bouc-Wen operator driven by v, τ_v·v̇ = u − v | exact, the compensator's Newton solve ([`crate::static_model`]) |
//! | hysteresis rate gain | `hysteresis_rate_gain_s_per_v` | the operator's A·(1 + c·\|v̇\|) | exact, the compensator's Newton solve ([`crate::static_model`]) |
//! | rate-dependent hysteresis | `relaxation_gain`, `relaxation_time_constant_s`, `relaxation_spread_decades` | Σᵢ g_wᵢ·vᵢ, vᵢ a first-order lag of w (or a box of N lags) | exact, in [`Effects::relaxation_m`] |
//! | even term | `even_coefficient_m_per_v2`, `even_center_v` | e·(u\[j−1\] − u_c)² | exact, [`Effects::even_term_m`] |
//! | mode | `mode_frequency_hz`, `mode_damping`, `mode_relative_damping` | z̈ + 2ζω·(ż − ρ·ṡ) + ω²·(z − s) = 0 | central differences |
//! | delay | `delay_s` | z(k − D) | reference taken ahead |
//! | drift (linear) | `drift_rate_m_per_s` | r_d·t | subtracted, [`Effects::drift_for_command_m`] |
//! | drift (settling) | `drift_settling_m`, `drift_settling_time_constant_s` | A_d·(1 − e^(−t/τ_d)) | subtracted, [`Effects::drift_for_command_m`] |
//! | coupling | `coupling` | κ·z_other(k − D) | exact 2×2, [`decouple`] |
//!
//! * **Creep** is the exact solution of `τᵢ·ẋᵢ = −xᵢ + (u − u_ref)` for a command held from
//!   t_{j−1} to t_j; u_ref is the first command (the state starts relaxed there). c\[j\] depends
//!   only on u up to j−1. The state is updated in the delta form `xᵢ += (1 − aᵢ)·(Δu − xᵢ)` with
//!   `1 − aᵢ = −expm1(−T/τᵢ)` from f64, exact in f32 also for τᵢ ≫ T.
//! * **Logarithmic creep**: the creep of a piezo stack after a step Δu grows as
//!   g_log·Δu·log₁₀(t/t₀) over decades. It is run as a fixed bank of LOG_CREEP_ELEMENTS elements
//!   of the creep's form (same input u\[j−1\] − u_ref, same update), τₗ = t₀·10^((l+1)/2), each of
//!   weight g_log/2: after a step its response is g_log·Δu·log₁₀(1 + t/t₀) within ±0.11·g_log·Δu for
//!   t ≤ 10^5.5·t₀, and it levels off at 6·g_log·Δu beyond 10^6·t₀. Superposed over every
//!   command change; it depends only on u up to j−1, so it enters the inverse with the creep.
//! * **Rate-dependent hysteresis** (a Hammerstein model: the rate-independent hysteresis w
//!   followed by linear dynamics, here the relaxation `G(s) = 1 + Σᵢ g_wᵢ/(1 + s·τ_wᵢ)` of a
//!   stack's dielectric and domain-wall response; the Hammerstein form of Wang, Zhang, Mao &
//!   Zhou, "A Hammerstein-based model for rate-dependent hysteresis in piezoelectric actuator",
//!   CCDC 2012, doi:10.1109/CCDC.2012.6244223: a Bouc-Wen model followed by a linear model).
//!   Each element is the exact solution of `τ_wᵢ·v̇ᵢ = −vᵢ + (p − p_ref)`, p = w − k_r·u, for p
//!   held from t_{j−1} to t_j, updated in the delta form of the creep. c_w\[j\] depends only on
//!   w and u up to j−1, so its inverse is explicit: `w* = s* − c[j] − c_w[j] − even`, and the compensator's
//!   per-sample map is unchanged. The inverse recursion (v driven by the w the inverse chose) is
//!   stable iff `Σᵢ g_wᵢ·tanh(T/(2τ_wᵢ)) < 1` (its one real root below every bᵢ stays above −1);
//!   [`Effects::new`] asks ≤ [`MAX_RELAXATION_LOOP_GAIN`] = 0.5 and g_wᵢ ≥ 0 (a spread element
//!   counts each of its N lags with g_w₀/N).
//! * **Spread relaxation**: a dielectric's relaxation times are spread, not one; with W > 0
//!   (`relaxation_spread_decades`, ≤ [`MAX_RELAXATION_SPREAD_DECADES`]) the first element is the
//!   box distribution of relaxation times, ln τ uniform over W decades centred on τ_w₀ (Nowick &
//!   Berry, *Anelastic Relaxation in Crystalline Solids*, Academic Press 1972, ch. 4, the box
//!   distribution), run as N = [`RELAXATION_SPREAD_POINTS`] lags at
//!   τ_w₀·10^(W·(k/(N − 1) − ½)) of gain g_w₀/N:
//!   `G(s) = 1 + (g_w₀/N)·Σₖ 1/(1 + s·τ_w₀ₖ) + g_w₁/(1 + s·τ_w₁)`. Its loop opening grows over
//!   W decades of rate instead of one, and W = 0 is the single lag. The N lags are the same
//!   delta-form update, so forward and inverse stay exact and explicit; the second element keeps
//!   one lag (the state holds N + 1 lags, which every copy of an axis's chain carries).
//! * **Even term** `e·(u[j−1] − u_c)²` on the *previous* command u\[j−1\] (the last command the
//!   state has seen, the same one the creep uses; u\[−1\] := u_c, so the term is 0 at the first
//!   sample). Electrostriction is an even function of the drive voltage; evaluated at the previous
//!   command it is known before u\[j\] is chosen, so its inverse is exact and explicit, like the
//!   creep's, and the per-sample map u\[j\] → y\[j\] that the compensator inverts is unchanged (no
//!   monotonicity condition: e and u_c only need to be finite). The cost of the one-sample lag
//!   against an even term on u\[j\] is `e·((u[j] − u_c)² − (u[j−1] − u_c)²) ≈ 2e·(u − u_c)·Δu`
//!   per sample \[m\] (Δu = u\[j\] − u\[j−1\]): negligible at loop rates (e.g. e = 1e-10 m/V²,
//!   u − u_c = 60 V, Δu = 0.05 V gives 6e-10 m).
//! * **Mode**, state `[z − s, ż/ω]`, discretised exactly (matrix exponential, f64, scaling and
//!   squaring, kept as `Φ − I` so that the static gain stays exact in f32) for an input that is
//!   piecewise constant, **held over the interval centred on its sample instant**:
//!   s(t) = s\[j\] for t ∈ \[t_j − T/2, t_j + T/2). Each sample is two half steps: the first gives
//!   z\[j\] = z(t_j), the second carries the state to t_j + T/2. The centred hold adds no half-sample
//!   lag (a converter's zero-order-hold lag of T/2 belongs to the delay D), so the sampled mode
//!   differs from the continuous one by O((ωT)²) only. Stable for every T (|λ| = e^(−ζωT/2) per
//!   half step). Requires 0 < f_mode < 0.45/T and ζ > 0; absent when f_mode = 0 (then z = s).
//!   **With relative damping** (ρ > 0) the mode passes 2ρζω·ṡ, so its input must be continuous
//!   (a staircase would kick the mode at every step): between t_{j−1} and t_j, s follows the
//!   parabola through s\[j−1\] and s\[j\] with the curvature of the last three samples,
//!   s(t_{j−1} + τ) = s\[j−1\] + Δ₁·τ/T + ½·Δ₂·τ·(τ − T)/T², Δ₁ = s\[j\] − s\[j−1\],
//!   Δ₂ = s\[j\] − 2s\[j−1\] + s\[j−2\] (s\[−1\] := s\[0\]): a smooth drive between samples, whose
//!   curvature a straight ramp would miss (it lowers a mode's response by ≈ (ω_in·T)²/12 of the
//!   drive, as large as the mode's own (ω_in/ω)² when ωT ≈ 2). With x = \[z − s, ż/ω\],
//!   ẋ = ω·A·x + b·ṡ, A = \[\[0, 1\], \[−1, −2ζ\]\], b = \[−1, 2ρζ\], one sample is exactly
//!   `x[j] = Φ·x[j−1] + g₁·Δ₁ + g₂·Δ₂`, Φ = exp(ωT·A) (kept as Φ − I),
//!   g₁ = A⁻¹·(Φ − I)·b/(ωT), g₂ = A⁻¹·(g₁ − b)/(ωT) − g₁/2 (≈ −ωT·A·b/12 for ωT ≪ 1), and
//!   z\[j\] = s\[j\] + x₀\[j\]. Its transfer function
//!   (1 + 2ρζ·s/ω)/(1 + 2ζ·s/ω + s²/ω²) has the phase −2(1 − ρ)ζ·f/f_mode well below the mode
//!   (zero at ρ = 1: a stack's internal, stiffness-proportional damping delays nothing) while the
//!   ring after a disturbance decays at ζ.
//! * **Delay**: D may be fractional (0 ≤ D ≤ MAX_DELAY_SAMPLES; within 1e-4 of a whole number it is
//!   taken as that number). `z(k − D)` interpolates linearly between the two z samples around it;
//!   z before the first sample is z\[0\] (the read is clamped to the first sample, so the first
//!   sample only writes one value). The z samples are kept in a fixed ring of 128 values (the
//!   power of two above MAX_DELAY_SAMPLES + 2, indices masked) inside [`EffectsState`].
//! * **Drift** adds `d(t_k) = r_d·t_k + A_d·(1 − e^(−t_k/τ_d))`, t_k = k·T, k counted from the first
//!   sample: a slow function of time that does not depend on u (linear drift and exponential
//!   settling, e.g. thermal; a constant offset is the static map's `offset_m`). Computed as
//!   `−A_d·expm1(−t/τ_d)`.
//! * **Coupling** (two axes, each axis's κ in its own parameters): with both axes' delayed z,
//!   `y_x = zx_d + drift_x + κ_x·zy_d`, `y_y = zy_d + drift_y + κ_y·zx_d` ([`couple`]); the other
//!   axis's z is delayed by *this* axis's D: `effects_x.delayed_z(&state_y)`. |κ| < 0.5.
//!
//! # The inverse chain (controller side, never fails)
//! For the reference y* at output samples, the command u\[j\] is chosen to reach, at output time
//! j + D:
//! 1. **delay**: take y*(j + D), interpolated linearly from the integer reference samples
//!    ([`Effects::interpolate_reference`], [`Effects::reference_index_offset`]); the controller
//!    needs the reference [`Effects::lead_samples`] samples ahead of the current command;
//! 2. **drift**: subtract `d((j + D)·T)` ([`Effects::drift_for_command_m`]); steps 1 and 2 for one
//!    axis: [`Effects::desired_z_m`];
//! 3. **coupling**: for two axes, `(zx*, zy*) = decouple(κ_x, κ_y, ·, ·)` (exact 2×2 inverse);
//! 4. **mode**: the continuous-time inverse with central differences over T,
//!    `s* = z*[j] + (2(1 − ρ)ζ/ω)·(z*[j+1] − z*[j−1])/(2T) + (z*[j+1] − 2z*[j] + z*[j−1])/(ωT)²`;
//!    truncation error `((1 − ρ)ζ/(3ω))·T²·z⃛ + T²·z⁗/(12ω²)`, second order in T, plus the O((ωT)²)
//!    difference between the sampled and the continuous mode; with relative damping the exact
//!    inverse (1 + 2ζ·s/ω + s²/ω²)/(1 + 2ρζ·s/ω) is taken to second order in s/ω (the term left
//!    out is −(2ρζ/ω)·z⃛*/ω², 2ρζ·f/f_mode of the curvature term); s* = z*\[j\] without a mode;
//!    from 22.2 kHz (W/T ≥ 2) the two differences are taken over 2h + 1 samples centred on j
//!    ([`MODE_CURVATURE_SPAN_S`], [`Effects::inverse_target_w_window`]): the curvature is the mean
//!    of the 2h + 1 second differences, so a kink of the reference asks for its impulse Δṙ/ω²
//!    over ≈ 90 µs at any loop rate instead of in one tick (where the slew limit would cut it
//!    short); the reference is read h more samples ahead, so the mean adds no delay;
//! 5. **creep, rate-dependent hysteresis and even term**:
//!    `w* = s* − c[j] − c_w[j] − e·(u[j−1] − u_c)²`, exact and explicit (the terms depend only on
//!    commands and w before sample j: [`Effects::creep_m`], [`Effects::relaxation_m`],
//!    [`Effects::even_term_m`]);
//! 6. the inverse compensator gives u\[j\] for w*, and [`Effects::commit_command`] advances the
//!    effects state with the u\[j\] actually commanded and the w\[j\] it reaches.
//!
//! [`compensate_axis`] and [`simulate_axis`] run the two chains over a whole single-axis record.
//!
//! # Plausibility (checked when built, against the axis's [`OperatingRange`])
//! Each effect's size is bounded by a dimensionless measure against the hysteresis model over the
//! output window `[u_min, u_max]`: its stroke S = w_max − w_min \[m\] and linear gain
//! g_lin = S/(u_max − u_min) \[m/V\]. A set beyond a bound is refused
//! ([`ParamError::Implausible`], naming the field and the measure):
//!
//! | effect | measure | bound | why |
//! |---|---|---|---|
//! | creep | (Σᵢ\|gᵢ\| + (LOG_CREEP_ELEMENTS/2)·\|g_log\|) / g_lin: the settled creep over the elastic gain | [`MAX_CREEP_RATIO`] = 2 | stack creep is a few % per decade, tens of % in all |
//! | even term | \|e\|·max over the window of (u − u_c)² / S | [`MAX_EVEN_RATIO`] = 2 | electrostriction is a part of the stroke, not a multiple |
//! | linear drift | \|r_d\|·1 h / S: strokes per hour | [`MAX_DRIFT_STROKES_PER_HOUR`] = 3 600 | beyond one stroke per second the inverse leaves the window within a second: a command, not a drift |
//! | settling drift | \|A_d\| / S | [`MAX_SETTLING_RATIO`] = 1 | a settling beyond the stroke pins the output at the window's edge |
//!
//! The bounds are several times what `host-sim close-loop` lets a fit reach (creep ≤ 0.5 g_lin
//! plus 0.1 g_lin per decade, even term ≤ S/4 over the half span, settling ≤ S/2).
//!
//! # Safety of the per-sample path
//! Never panics, no allocation. For finite inputs every result is finite: internal signals are
//! held within ±1e30 m (far beyond any stage). A non-finite command or w holds the previous one in
//! [`Effects::forward_z`]; a non-finite reference sample makes [`Effects::inverse_target_w`] return
//! NaN, which the compensator answers by holding the last voltage.

use crate::compensator::{Compensator, CompensatorState};
use crate::error::{finite, positive, ParamError};
use crate::math::clamp;
use crate::static_model::{check_input_lag, check_rate_gain, ModelState, StaticModel};

/// Largest number of creep elements.
pub const MAX_CREEP_ELEMENTS: usize = 3;
/// Number of elements of the logarithmic creep's fixed bank (half a decade apart: 6 decades).
pub const LOG_CREEP_ELEMENTS: usize = 12;
/// Largest input delay, in sample periods.
pub const MAX_DELAY_SAMPLES: usize = 64;
/// Largest accepted mode frequency, as a fraction of the sample rate.
pub const MAX_MODE_FREQUENCY_RATIO: f32 = 0.45;
/// W: the span over which the mode's inverse averages the reference's curvature \[s\]: N·T, the
/// odd number N = 2h + 1 of samples nearest W/T (h = round((W/T − 1)/2), at least 0, at most
/// [`MAX_CURVATURE_HALF_WIDTH`]). At 10 and 20 kHz N = 1 (the three-point difference); at
/// 50 kHz N = 5. It makes the drive at a reference's kink (a triangle's corner: a step of ṙ)
/// rate-independent: a pulse of height Δṙ/(ω²·N·T) over N·T ≈ W instead of Δṙ/(ω²·T) in one tick,
/// whose height grows with the rate until the slew limit cuts it short.
pub const MODE_CURVATURE_SPAN_S: f64 = 90e-6;
/// Largest h of [`MODE_CURVATURE_SPAN_S`]: the inverse reads the reference h + 1 samples ahead.
pub const MAX_CURVATURE_HALF_WIDTH: usize = 8;
/// Bound on |coupling| (the 2×2 coupling matrix keeps det > 0.75).
pub const MAX_COUPLING: f32 = 0.5;
/// Largest number of elements of the rate-dependent hysteresis (relaxation of w).
pub const MAX_RELAXATION_ELEMENTS: usize = 2;
/// N: the lags the first relaxation element runs as when its time constants are spread
/// (`relaxation_spread_decades` > 0): τ_w₀·10^(W·(k/(N − 1) − ½)), k = 0 … N − 1, each of gain g_w₀/N.
pub const RELAXATION_SPREAD_POINTS: usize = 5;
/// Largest spread W of the relaxation times \[decades\].
pub const MAX_RELAXATION_SPREAD_DECADES: f32 = 4.0;
/// The most lags the relaxation runs: the first element's N when spread, and the second's one.
pub const RELAXATION_LAGS: usize = RELAXATION_SPREAD_POINTS + MAX_RELAXATION_ELEMENTS - 1;

/// τₖ/τ_w₀ = 10^(W·(k/(N − 1) − ½)) of lag k of a relaxation element spread over
/// `spread_decades` W (N = [`RELAXATION_SPREAD_POINTS`]; 1 for W = 0).
pub fn relaxation_spread_factor(spread_decades: f64, k: usize) -> f64 {
    let share = k as f64 / (RELAXATION_SPREAD_POINTS - 1) as f64 - 0.5;
    libm::pow(10.0, spread_decades * share)
}
/// Bound on Σᵢ g_wᵢ·tanh(T/(2τ_wᵢ)): the inverse recursion of the relaxation is stable below 1;
/// at 0.5 its slowest-alternating root stays above −1/3 (well damped).
pub const MAX_RELAXATION_LOOP_GAIN: f64 = 0.5;

/// Largest settled creep (Kelvin–Voigt gains plus the logarithmic bank's full 6 decades) relative
/// to the model's linear gain over the window.
pub const MAX_CREEP_RATIO: f32 = 2.0;
/// Largest output change of the even term over the window relative to the stroke.
pub const MAX_EVEN_RATIO: f32 = 2.0;
/// Largest linear drift over an hour, in strokes.
pub const MAX_DRIFT_STROKES_PER_HOUR: f32 = 3600.0;
/// Largest settling drift amplitude relative to the stroke.
pub const MAX_SETTLING_RATIO: f32 = 1.0;

/// What the effects of one axis are judged against: the output window and the hysteresis model's
/// output over it (both sorted).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OperatingRange {
    /// The output window (the input of the model) `(u_min, u_max)` \[V\].
    pub input_v: (f32, f32),
    /// The hysteresis model's output range over it `(w_min, w_max)` \[m\].
    pub output_m: (f32, f32),
}

impl OperatingRange {
    /// The first loading from rest at `u_min` to `u_max`: output `[y_rest, y_rest + g·(u_max −
    /// u_min)]`, sorted, with `g` the first-loading secant gain
    /// (`StaticModel::first_loading`) \[m/V\].
    pub fn first_loading(rest_m: f32, gain_m_per_v: f32, input_v: (f32, f32)) -> Self {
        let top = rest_m + gain_m_per_v * (input_v.1 - input_v.0);
        Self {
            input_v,
            output_m: (rest_m.min(top), rest_m.max(top)),
        }
    }

    /// Checks both spans (finite, max ≥ min); returns (input span \[V\], stroke \[m\]).
    fn spans(&self) -> Result<(f32, f32), ParamError> {
        let mut spans = [0.0f32; 2];
        for (i, (field, (lo, hi))) in [
            ("input_range_v", self.input_v),
            ("w_range_m", self.output_m),
        ]
        .into_iter()
        .enumerate()
        {
            finite(field, lo)?;
            finite(field, hi)?;
            if hi < lo {
                return Err(ParamError::OutOfRange {
                    field,
                    value: hi,
                    requirement: "max >= min",
                });
            }
            spans[i] = hi - lo;
        }
        Ok((spans[0], spans[1]))
    }
}

/// Refuses `value` of `field` when `ratio` (its measure) exceeds `limit` (NaN: 0/0, accepted).
fn plausible(
    field: &'static str,
    value: f32,
    measure: &'static str,
    ratio: f32,
    limit: f32,
) -> Result<(), ParamError> {
    if ratio > limit {
        Err(ParamError::Implausible {
            field,
            value,
            measure,
            ratio,
            limit,
        })
    } else {
        Ok(())
    }
}

/// Length of the ring of past z samples: the delay reads z\[k − n\] and z\[k − n − 1\], n ≤ 64;
/// a power of two at least MAX_DELAY_SAMPLES + 2, so that an index wraps with a mask.
const RING_LEN: usize = (MAX_DELAY_SAMPLES + 2).next_power_of_two();
/// `index & RING_MASK` = `index % RING_LEN`.
const RING_MASK: usize = RING_LEN - 1;
/// Internal signals are held within ±this \[m\] (or V) so that finite inputs give finite results.
const SIGNAL_LIMIT: f32 = 1.0e30;

const RELAXATION_GAIN_FIELDS: [&str; MAX_RELAXATION_ELEMENTS] =
    ["relaxation_gain[0]", "relaxation_gain[1]"];
const RELAXATION_TIME_FIELDS: [&str; MAX_RELAXATION_ELEMENTS] = [
    "relaxation_time_constant_s[0]",
    "relaxation_time_constant_s[1]",
];
const CREEP_GAIN_FIELDS: [&str; MAX_CREEP_ELEMENTS] = [
    "creep_gain_m_per_v[0]",
    "creep_gain_m_per_v[1]",
    "creep_gain_m_per_v[2]",
];
const CREEP_TIME_FIELDS: [&str; MAX_CREEP_ELEMENTS] = [
    "creep_time_constant_s[0]",
    "creep_time_constant_s[1]",
    "creep_time_constant_s[2]",
];

/// The effect parameters of one axis. All zero (the default) is no effect.
///
/// With the `serde` feature, every field is optional when read (absent: 0), unknown fields are
/// refused, and the creep arrays may be shorter than [`MAX_CREEP_ELEMENTS`] (missing elements 0).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(feature = "serde", serde(default, deny_unknown_fields))]
pub struct EffectParams {
    /// Creep gains gᵢ \[m/V\]; an element with gain 0 is absent.
    #[cfg_attr(feature = "serde", serde(deserialize_with = "up_to_creep_elements"))]
    pub creep_gain_m_per_v: [f32; MAX_CREEP_ELEMENTS],
    /// Creep time constants τᵢ \[s\], > 0 for every present element (ignored, but finite, otherwise).
    #[cfg_attr(feature = "serde", serde(deserialize_with = "up_to_creep_elements"))]
    pub creep_time_constant_s: [f32; MAX_CREEP_ELEMENTS],
    /// e in the even term e·(u\[j−1\] − u_c)² \[m/V²\] (any finite value).
    pub even_coefficient_m_per_v2: f32,
    /// u_c in the even term e·(u\[j−1\] − u_c)² \[V\] (any finite value).
    pub even_center_v: f32,
    /// f_mode \[Hz\]: 0 for no mode, else 0 < f_mode < 0.45 / sample period.
    pub mode_frequency_hz: f32,
    /// ζ \[1\]: damping ratio of the mode, > 0 when the mode is present.
    pub mode_damping: f32,
    /// ρ \[1\] in \[0, 1\]: the share of the mode's damping that acts on the relative motion z − s
    /// (module doc): 0 a force-driven mode (centred hold), 1 a mode driven through the stack's own
    /// spring and damper (first-order hold); ignored, but in \[0, 1\], without a mode.
    pub mode_relative_damping: f32,
    /// Input delay \[s\], 0 ≤ delay ≤ 64 sample periods.
    pub delay_s: f32,
    /// Linear drift of the output \[m/s\], from t = 0 at the first sample.
    pub drift_rate_m_per_s: f32,
    /// κ \[1\]: the part of the other axis's z added to this axis's output, |κ| < 0.5.
    pub coupling: f32,
    /// A_d in the settling drift A_d·(1 − exp(−t/τ_d)) \[m\], from t = 0 at the first sample
    /// (positive: the output settles upwards; any finite value, 0: none).
    pub drift_settling_m: f32,
    /// τ_d of the settling drift \[s\], > 0 when `drift_settling_m` ≠ 0 (ignored, but finite,
    /// otherwise).
    pub drift_settling_time_constant_s: f32,
    /// g_log \[m/V per decade of time\]: after a command step Δu the logarithmic creep adds about
    /// g_log·Δu·log₁₀(1 + t/t₀) (positive: in the direction of the step; any finite value, 0: none).
    pub log_creep_gain_m_per_v: f32,
    /// t₀ of the logarithmic creep \[s\], > 0 when `log_creep_gain_m_per_v` ≠ 0: the shortest of
    /// its time constants is √10·t₀ (ignored, but finite, otherwise).
    pub log_creep_time_s: f32,
    /// g_wᵢ \[1\] of the rate-dependent hysteresis: the part of the hysteresis output w that
    /// follows it with the lag τ_wᵢ (≥ 0; 0: the element is absent).
    #[cfg_attr(
        feature = "serde",
        serde(deserialize_with = "up_to_relaxation_elements")
    )]
    pub relaxation_gain: [f32; MAX_RELAXATION_ELEMENTS],
    /// τ_wᵢ \[s\] of the rate-dependent hysteresis, > 0 for every present element (ignored, but
    /// finite, otherwise).
    #[cfg_attr(
        feature = "serde",
        serde(deserialize_with = "up_to_relaxation_elements")
    )]
    pub relaxation_time_constant_s: [f32; MAX_RELAXATION_ELEMENTS],
    /// W \[decades\] in \[0, 4\]: the first relaxation element's time constants spread
    /// log-uniformly over W decades centred (geometrically) on τ_w₀, the box distribution of
    /// relaxation times; run as [`RELAXATION_SPREAD_POINTS`] lags τ_w₀·10^(W·(k/(N − 1) − ½)) of
    /// gain g_w₀/N each (0: one time constant; the second element always has one).
    pub relaxation_spread_decades: f32,
    /// k_r \[m/V\]: the relaxation is driven by w − k_r·u (0: all of w relaxes; the map's k1: only
    /// the hysteretic part; any finite value).
    pub relaxation_linear_m_per_v: f32,
    /// τ_v \[s\] of the hysteresis's input lag: the Bouc-Wen operator is driven by a first-order
    /// lag of the command ([`crate::static_model`], [`Effects::hysteresis_model`]); 0: none, else
    /// between one sample period and 1 s.
    pub hysteresis_lag_s: f32,
    /// c \[s/V\] of the hysteresis's rate-dependent gain: the Bouc-Wen operator's A grows to
    /// A·(1 + c·|v̇|) with the speed of its input ([`crate::static_model`],
    /// [`Effects::hysteresis_model`]); 0: none, else at most
    /// [`crate::static_model::MAX_RATE_GAIN_S_PER_V`].
    pub hysteresis_rate_gain_s_per_v: f32,
}

impl EffectParams {
    /// The hysteresis model these effects run around: `model` (standard or asymmetric, built
    /// without a lag: the quasi-static model whose first loading sets the operating range) with
    /// its operator driven by the input lag `hysteresis_lag_s` when there is one
    /// ([`StaticModel::with_input_lag`] at the sample period `sample_period_s` \[s\]; refused on
    /// the asymmetric model). Every builder of an axis (stage file, firmware, close-loop) takes
    /// the model the compensator inverts from here.
    pub fn hysteresis_model(
        &self,
        model: StaticModel,
        sample_period_s: f32,
    ) -> Result<StaticModel, ParamError> {
        model
            .with_input_lag(self.hysteresis_lag_s, sample_period_s)?
            .with_rate_gain(self.hysteresis_rate_gain_s_per_v, sample_period_s)
    }
}

/// Reads a sequence of at most [`MAX_CREEP_ELEMENTS`] numbers (missing elements 0).
#[cfg(feature = "serde")]
fn up_to_creep_elements<'de, D>(deserializer: D) -> Result<[f32; MAX_CREEP_ELEMENTS], D::Error>
where
    D: serde::Deserializer<'de>,
{
    deserializer.deserialize_seq(UpTo::<MAX_CREEP_ELEMENTS>)
}

/// Reads a sequence of at most [`MAX_RELAXATION_ELEMENTS`] numbers (missing elements 0).
#[cfg(feature = "serde")]
fn up_to_relaxation_elements<'de, D>(
    deserializer: D,
) -> Result<[f32; MAX_RELAXATION_ELEMENTS], D::Error>
where
    D: serde::Deserializer<'de>,
{
    deserializer.deserialize_seq(UpTo::<MAX_RELAXATION_ELEMENTS>)
}

/// A sequence of at most N numbers, missing elements 0.
#[cfg(feature = "serde")]
struct UpTo<const N: usize>;

#[cfg(feature = "serde")]
impl<'de, const N: usize> serde::de::Visitor<'de> for UpTo<N> {
    type Value = [f32; N];
    fn expecting(&self, f: &mut core::fmt::Formatter) -> core::fmt::Result {
        write!(f, "an array of at most {N} numbers")
    }
    fn visit_seq<A: serde::de::SeqAccess<'de>>(self, mut seq: A) -> Result<Self::Value, A::Error> {
        let mut out = [0.0f32; N];
        let mut len = 0;
        while let Some(v) = seq.next_element::<f32>()? {
            if len == N {
                return Err(serde::de::Error::invalid_length(len + 1, &self));
            }
            out[len] = v;
            len += 1;
        }
        Ok(out)
    }
}

/// The bounds of the module doc's plausibility table, for finite `params`.
fn check_plausible(
    params: &EffectParams,
    range: OperatingRange,
    span_v: f32,
    stroke_m: f32,
) -> Result<(), ParamError> {
    let gain = stroke_m / span_v;
    let log_total = 0.5 * LOG_CREEP_ELEMENTS as f32 * libm::fabsf(params.log_creep_gain_m_per_v);
    let creep = params
        .creep_gain_m_per_v
        .iter()
        .fold(log_total, |sum, g| sum + libm::fabsf(*g));
    let worst = if log_total > 0.0 {
        ("log_creep_gain_m_per_v", params.log_creep_gain_m_per_v)
    } else {
        let i = (0..MAX_CREEP_ELEMENTS)
            .max_by(|&a, &b| {
                libm::fabsf(params.creep_gain_m_per_v[a])
                    .total_cmp(&libm::fabsf(params.creep_gain_m_per_v[b]))
            })
            .unwrap_or(0);
        (CREEP_GAIN_FIELDS[i], params.creep_gain_m_per_v[i])
    };
    if creep > 0.0 {
        plausible(
            worst.0,
            worst.1,
            "the settled creep over the linear gain, (Σ|g_i| + 6·|g_log|) / g_lin,",
            creep / gain,
            MAX_CREEP_RATIO,
        )?;
    }
    let e = params.even_coefficient_m_per_v2;
    if e != 0.0 {
        let c = params.even_center_v;
        let (u0, u1) = range.input_v;
        let reach = libm::fabsf(u0 - c).max(libm::fabsf(u1 - c));
        plausible(
            "even_coefficient_m_per_v2",
            e,
            "the even term's largest output over the window relative to the stroke, \
             |e|·max (u − u_c)² / S,",
            libm::fabsf(e) * reach * reach / stroke_m,
            MAX_EVEN_RATIO,
        )?;
    }
    let r = params.drift_rate_m_per_s;
    if r != 0.0 {
        plausible(
            "drift_rate_m_per_s",
            r,
            "the drift over an hour in strokes, |r_d|·3600 s / S,",
            libm::fabsf(r) * 3600.0 / stroke_m,
            MAX_DRIFT_STROKES_PER_HOUR,
        )?;
    }
    let a = params.drift_settling_m;
    if a != 0.0 {
        plausible(
            "drift_settling_m",
            a,
            "the settling drift relative to the stroke, |A_d| / S,",
            libm::fabsf(a) / stroke_m,
            MAX_SETTLING_RATIO,
        )?;
    }
    Ok(())
}

/// The precomputed mode: Φ − I of one half step (centred hold) or of one step (first-order hold,
/// with relative damping), and the inverse's difference coefficients.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Mode {
    /// exp(ω·T/2·\[\[0, 1\], \[−1, −2ζ\]\]) − I, row-major, acting on \[z − s, ż/ω\]; with
    /// relative damping exp(ω·T·\[\[0, 1\], \[−1, −2ζ\]\]) − I instead.
    half_step_minus_identity: [[f32; 2]; 2],
    /// With relative damping: \[g₁, g₂\], the state's response to the input's change
    /// Δ₁ = s\[j\] − s\[j−1\] and curvature Δ₂ = s\[j\] − 2s\[j−1\] + s\[j−2\] over the sample
    /// (module doc); None: centred hold.
    ramp_gain: Option<[[f32; 2]; 2]>,
    /// (1 − ρ)ζ/(ω·T): multiplies z*\[j+1\] − z*\[j−1\] (= (2(1 − ρ)ζ/ω)·ż* by central
    /// differences).
    velocity_coefficient: f32,
    /// 1/(ω·T)²: multiplies z*\[j+1\] − 2z*\[j\] + z*\[j−1\] (= z̈*/ω²).
    curvature_coefficient: f32,
    /// (1 − ρ)ζ/(ω·T·(h + 1)): multiplies z*\[j+h+1\] − z*\[j−h−1\] (= (2(1 − ρ)ζ/ω)·ż* by
    /// central differences over 2(h + 1) samples).
    window_velocity_coefficient: f32,
    /// 1/((ω·T)²·(2h + 1)): multiplies the sum of the 2h + 1 second differences centred on j,
    /// (z*\[j+h+1\] − z*\[j+h\]) − (z*\[j−h\] − z*\[j−h−1\]) (= z̈*/ω² averaged over N·T).
    window_curvature_coefficient: f32,
    /// h: the curvature's half width in samples ([`MODE_CURVATURE_SPAN_S`]).
    curvature_half_width: usize,
}

impl Mode {
    /// One half step from (z, v = ż/ω) with the input s held.
    #[inline(always)]
    fn half_step(&self, z: f32, v: f32, s: f32) -> (f32, f32) {
        let d = &self.half_step_minus_identity;
        let e = z - s;
        (z + d[0][0] * e + d[0][1] * v, v + d[1][0] * e + d[1][1] * v)
    }

    /// One whole step of the smooth hold from z\[j−1\], v = ż/ω at t_{j−1}, the inputs
    /// s\[j−2\] (`s_before`) and s\[j−1\] (`s_prev`) to t_j with the input s\[j\]; `g` is
    /// [`Mode::ramp_gain`].
    #[inline(always)]
    fn ramp_step(
        &self,
        g: &[[f32; 2]; 2],
        (z, v): (f32, f32),
        s_before: f32,
        s_prev: f32,
        s: f32,
    ) -> (f32, f32) {
        let d = &self.half_step_minus_identity;
        let e = z - s_prev;
        let d1 = s - s_prev;
        let d2 = d1 - (s_prev - s_before);
        let e_next = e + d[0][0] * e + d[0][1] * v + g[0][0] * d1 + g[1][0] * d2;
        let v_next = v + d[1][0] * e + d[1][1] * v + g[0][1] * d1 + g[1][1] * d2;
        (s + e_next, v_next)
    }
}

/// Validated effect settings of one axis at one sample period. State lives in [`EffectsState`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Effects {
    params: EffectParams,
    sample_period_s: f32,
    /// 1 − aᵢ = 1 − exp(−T/τᵢ) (0 for an absent element).
    creep_rate: [f32; MAX_CREEP_ELEMENTS],
    /// gᵢ \[m/V\] (0 for an absent element).
    creep_gain: [f32; MAX_CREEP_ELEMENTS],
    mode: Option<Mode>,
    /// D = delay_s / T \[samples\].
    delay_samples: f32,
    /// ⌊D⌋.
    delay_whole: usize,
    /// D − ⌊D⌋ ∈ \[0, 1).
    delay_fraction: f32,
    /// 1 − exp(−T/τₗ) of the logarithmic creep's elements (0 without it).
    log_creep_rate: [f32; LOG_CREEP_ELEMENTS],
    /// g_log/2: the weight of each logarithmic creep element \[m/V\].
    log_creep_weight: f32,
    /// 1/τ_d \[1/s\] (0 without a settling drift).
    drift_settling_rate_per_s: f32,
    /// The rate-dependent hysteresis's elements (all gains 0 without it).
    relaxation: Relaxation,
}

/// The validated elements of the rate-dependent hysteresis (relaxation of w).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
struct Relaxation {
    /// 1 − b = 1 − exp(−T/τ) of each lag (0 for an absent one): the first element's
    /// `first_lags` lags, then the second element's one.
    rate: [f32; RELAXATION_LAGS],
    /// The gain of each of the first element's lags, g_w₀/`first_lags`, and the second's, g_w₁ \[1\].
    gain: [f32; MAX_RELAXATION_ELEMENTS],
    /// The first element's lags: N with a spread, 1 without.
    first_lags: usize,
    /// The lags in use: `first_lags` + 1, 0 without the relaxation.
    lags: usize,
    /// k_r \[m/V\].
    linear: f32,
}

impl Relaxation {
    /// Validates the gains and time constants at the sample period `t` \[s\] (module doc).
    fn new(params: &EffectParams, t: f32) -> Result<Self, ParamError> {
        let mut out = Self {
            linear: finite(
                "relaxation_linear_m_per_v",
                params.relaxation_linear_m_per_v,
            )?,
            ..Self::default()
        };
        let spread = finite(
            "relaxation_spread_decades",
            params.relaxation_spread_decades,
        )?;
        if !(0.0..=MAX_RELAXATION_SPREAD_DECADES).contains(&spread) {
            return Err(ParamError::OutOfRange {
                field: "relaxation_spread_decades",
                value: spread,
                requirement: "in [0, 4] decades",
            });
        }
        let points = if spread > 0.0 {
            RELAXATION_SPREAD_POINTS
        } else {
            1
        };
        out.first_lags = points;
        let mut loop_gain = 0.0f64;
        for i in 0..MAX_RELAXATION_ELEMENTS {
            let g = finite(RELAXATION_GAIN_FIELDS[i], params.relaxation_gain[i])?;
            let tau = finite(
                RELAXATION_TIME_FIELDS[i],
                params.relaxation_time_constant_s[i],
            )?;
            if g < 0.0 {
                return Err(ParamError::OutOfRange {
                    field: RELAXATION_GAIN_FIELDS[i],
                    value: g,
                    requirement: ">= 0",
                });
            }
            if g != 0.0 {
                positive(RELAXATION_TIME_FIELDS[i], tau)?;
                // The first element's N lags (one without a spread), then the second's one.
                let (n, first) = if i == 0 { (points, 0) } else { (1, points) };
                let gain = f64::from(g) / n as f64;
                out.gain[i] = gain as f32;
                let spread_here = if n > 1 { f64::from(spread) } else { 0.0 };
                for k in 0..n {
                    let x =
                        f64::from(t) / (f64::from(tau) * relaxation_spread_factor(spread_here, k));
                    if let Some(rate) = out.rate.get_mut(first + k) {
                        *rate = -libm::expm1(-x) as f32;
                    }
                    loop_gain += gain * libm::tanh(0.5 * x);
                }
                out.lags = points + 1;
            }
        }
        if loop_gain > MAX_RELAXATION_LOOP_GAIN || !loop_gain.is_finite() {
            return Err(ParamError::OutOfRange {
                field: "relaxation_gain",
                value: loop_gain as f32,
                requirement: "sum of g_i * tanh(T / (2 tau_i)) <= 0.5 (a stable inverse)",
            });
        }
        Ok(out)
    }

    fn is_absent(&self) -> bool {
        self.lags == 0
    }
}

/// The state of the effects of one axis (creep, mode, delay line, sample counter).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EffectsState {
    /// xᵢ for the next sample \[V\].
    creep_v: [f32; MAX_CREEP_ELEMENTS],
    /// xₗ of the logarithmic creep for the next sample \[V\].
    log_creep_v: [f32; LOG_CREEP_ELEMENTS],
    /// u_ref: the first command \[V\].
    input_reference_v: f32,
    /// The last command u\[j−1\] \[V\] (held for a non-finite one; meaningless before the first).
    previous_input_v: f32,
    /// The last w \[m\] (held for a non-finite one).
    previous_w_m: f32,
    /// Whether a first sample has been processed.
    started: bool,
    /// Whether the state was built at rest at a known input ([`EffectsState::at_rest`]).
    rested: bool,
    /// Mode output z at t_j + T/2 \[m\].
    mode_z_m: f32,
    /// Mode scaled velocity ż/ω at t_j + T/2 \[m\] (at t_j with relative damping).
    mode_scaled_velocity_m: f32,
    /// The mode's input s\[j\] of the last sample \[m\] (with relative damping).
    mode_input_m: f32,
    /// The mode's input s\[j − 1\] of the sample before \[m\] (with relative damping).
    mode_input_before_m: f32,
    /// The last RING_LEN z samples; `ring[head]` is the newest, `ring[0]` the first (z\[0\])
    /// until the ring wraps.
    ring: [f32; RING_LEN],
    /// Index of the newest z (< RING_LEN).
    head: usize,
    /// Number of samples processed (saturating).
    samples: u32,
    /// The relaxation's lags vᵢ for the next sample \[m\].
    relaxation_m: [f32; RELAXATION_LAGS],
    /// p_ref: the first p = w − k_r·u \[m\].
    w_reference_m: f32,
}

impl Default for EffectsState {
    fn default() -> Self {
        Self::new()
    }
}

impl EffectsState {
    /// Before the first sample: creep relaxed, mode at rest (at the first s), empty delay line.
    pub const fn new() -> Self {
        Self {
            creep_v: [0.0; MAX_CREEP_ELEMENTS],
            log_creep_v: [0.0; LOG_CREEP_ELEMENTS],
            input_reference_v: 0.0,
            previous_input_v: 0.0,
            previous_w_m: 0.0,
            started: false,
            rested: false,
            mode_z_m: 0.0,
            mode_scaled_velocity_m: 0.0,
            mode_input_m: 0.0,
            mode_input_before_m: 0.0,
            ring: [0.0; RING_LEN],
            head: 0,
            samples: 0,
            relaxation_m: [0.0; RELAXATION_LAGS],
            w_reference_m: 0.0,
        }
    }

    /// At rest at the input `input_v` \[V\]: the stage has been held at `input_v` long enough for
    /// the creep to relax there (u_ref = `input_v`, not the first command) and the even term of the
    /// first sample is `e·(input_v − u_c)²`. The mode starts at rest at the first s and the delay
    /// line holds the first z, as for [`EffectsState::new`]. This is the start every tool uses for
    /// a record or a run that begins at u0: the model state `ModelState::at_rest(u0)` and this
    /// state at u0.
    pub const fn at_rest(input_v: f32) -> Self {
        let mut state = Self::new();
        state.input_reference_v = input_v;
        state.previous_input_v = input_v;
        state.rested = true;
        state
    }

    /// Number of samples processed so far; the current output sample is k = this − 1.
    pub fn samples(&self) -> u32 {
        self.samples
    }

    /// The newest z \[m\] (z\[k\]; 0 before the first sample).
    pub fn latest_z_m(&self) -> f32 {
        self.z_back(0)
    }

    /// z\[k − back\] (back < RING_LEN), z\[0\] before the first sample: `back` is clamped to
    /// k = samples − 1, the samples written so far (0 before any: `ring[0]` = 0).
    #[inline(always)]
    fn z_back(&self, back: usize) -> f32 {
        let written = self.samples.saturating_sub(1) as usize;
        let back = if back < written { back } else { written };
        self.ring[self.head.wrapping_sub(back) & RING_MASK]
    }
}

/// Holds a value within ±[`SIGNAL_LIMIT`] (NaN gives the lower limit).
#[inline(always)]
fn bounded(x: f32) -> f32 {
    clamp(x, -SIGNAL_LIMIT, SIGNAL_LIMIT)
}

impl Effects {
    /// [`EffectParams::hysteresis_model`] at these effects' sample period.
    pub fn hysteresis_model(&self, model: StaticModel) -> Result<StaticModel, ParamError> {
        self.params.hysteresis_model(model, self.sample_period_s)
    }

    /// Validates `params` for the sample period `sample_period_s` \[s\] and their plausibility
    /// over `range` (the output window and the model's output over it; see the module doc).
    pub fn new(
        params: EffectParams,
        sample_period_s: f32,
        range: OperatingRange,
    ) -> Result<Self, ParamError> {
        let t = positive("sample_period_s", sample_period_s)?;
        let (span_v, stroke_m) = range.spans()?;
        check_input_lag(finite("hysteresis_lag_s", params.hysteresis_lag_s)?, t)?;
        check_rate_gain(finite(
            "hysteresis_rate_gain_s_per_v",
            params.hysteresis_rate_gain_s_per_v,
        )?)?;

        let mut creep_rate = [0.0f32; MAX_CREEP_ELEMENTS];
        let mut creep_gain = [0.0f32; MAX_CREEP_ELEMENTS];
        for i in 0..MAX_CREEP_ELEMENTS {
            let g = finite(CREEP_GAIN_FIELDS[i], params.creep_gain_m_per_v[i])?;
            let tau = finite(CREEP_TIME_FIELDS[i], params.creep_time_constant_s[i])?;
            if g != 0.0 {
                positive(CREEP_TIME_FIELDS[i], tau)?;
                creep_rate[i] = -libm::expm1(-f64::from(t) / f64::from(tau)) as f32;
                creep_gain[i] = g;
            }
        }

        finite(
            "even_coefficient_m_per_v2",
            params.even_coefficient_m_per_v2,
        )?;
        finite("even_center_v", params.even_center_v)?;

        let f = finite("mode_frequency_hz", params.mode_frequency_hz)?;
        let zeta = finite("mode_damping", params.mode_damping)?;
        let rho = finite("mode_relative_damping", params.mode_relative_damping)?;
        if !(0.0..=1.0).contains(&rho) {
            return Err(ParamError::OutOfRange {
                field: "mode_relative_damping",
                value: rho,
                requirement: "in [0, 1]",
            });
        }
        let mode = if f == 0.0 {
            None
        } else {
            if !(f > 0.0 && f64::from(f) * f64::from(t) < f64::from(MAX_MODE_FREQUENCY_RATIO)) {
                return Err(ParamError::OutOfRange {
                    field: "mode_frequency_hz",
                    value: f,
                    requirement: "0 (no mode) or in (0, 0.45 / sample_period_s)",
                });
            }
            if zeta <= 0.0 {
                return Err(ParamError::OutOfRange {
                    field: "mode_damping",
                    value: zeta,
                    requirement: "> 0",
                });
            }
            Some(discretise_mode(f, zeta, rho, t)?)
        };

        let delay = finite("delay_s", params.delay_s)?;
        let mut d = f64::from(delay) / f64::from(t);
        let nearest = libm::round(d);
        if libm::fabs(d - nearest) < 1e-4 {
            d = nearest;
        }
        if !(d >= 0.0 && d <= MAX_DELAY_SAMPLES as f64) {
            return Err(ParamError::OutOfRange {
                field: "delay_s",
                value: delay,
                requirement: "in [0, 64 sample periods] (MAX_DELAY_SAMPLES)",
            });
        }
        let delay_whole = libm::floor(d) as usize;
        let delay_fraction = (d - delay_whole as f64) as f32;

        finite("drift_rate_m_per_s", params.drift_rate_m_per_s)?;
        let settling = finite("drift_settling_m", params.drift_settling_m)?;
        let settling_tau = finite(
            "drift_settling_time_constant_s",
            params.drift_settling_time_constant_s,
        )?;
        let mut drift_settling_rate_per_s = 0.0;
        if settling != 0.0 {
            positive("drift_settling_time_constant_s", settling_tau)?;
            drift_settling_rate_per_s = (1.0 / f64::from(settling_tau)) as f32;
        }
        let log_gain = finite("log_creep_gain_m_per_v", params.log_creep_gain_m_per_v)?;
        let log_t0 = finite("log_creep_time_s", params.log_creep_time_s)?;
        let mut log_creep_rate = [0.0f32; LOG_CREEP_ELEMENTS];
        if log_gain != 0.0 {
            positive("log_creep_time_s", log_t0)?;
            for (l, rate) in log_creep_rate.iter_mut().enumerate() {
                let tau = f64::from(log_t0) * libm::pow(10.0, 0.5 * (l + 1) as f64);
                *rate = -libm::expm1(-f64::from(t) / tau) as f32;
            }
        }
        let relaxation = Relaxation::new(&params, t)?;
        check_plausible(&params, range, span_v, stroke_m)?;
        let coupling = finite("coupling", params.coupling)?;
        if libm::fabsf(coupling) >= MAX_COUPLING {
            return Err(ParamError::OutOfRange {
                field: "coupling",
                value: coupling,
                requirement: "|coupling| < 0.5",
            });
        }

        Ok(Self {
            params,
            sample_period_s: t,
            creep_rate,
            creep_gain,
            mode,
            delay_samples: d as f32,
            delay_whole,
            delay_fraction,
            log_creep_rate,
            log_creep_weight: 0.5 * log_gain,
            drift_settling_rate_per_s,
            relaxation,
        })
    }

    /// The parameters as given.
    pub fn params(&self) -> &EffectParams {
        &self.params
    }

    /// The sample period \[s\].
    pub fn sample_period_s(&self) -> f32 {
        self.sample_period_s
    }

    /// Whether the chain is the identity (no creep of either kind, no even term, no mode, no delay,
    /// no drift of either kind, no coupling): then y\[k\] = w\[k\].
    pub fn is_identity(&self) -> bool {
        let p = &self.params;
        self.creep_gain.iter().all(|&g| g == 0.0)
            && p.even_coefficient_m_per_v2 == 0.0
            && self.mode.is_none()
            && self.delay_samples == 0.0
            && p.drift_rate_m_per_s == 0.0
            && p.coupling == 0.0
            && p.drift_settling_m == 0.0
            && self.log_creep_weight == 0.0
            && self.relaxation.is_absent()
    }

    /// The rate-dependent hysteresis's lags as (1 − bᵢ, gain) with k_r \[m/V\] (gains 0
    /// without it; a spread element's N lags each with its share g_w/N): c_w = Σ gainᵢ·vᵢ,
    /// vᵢ\[j\] = vᵢ\[j−1\] + (1 − bᵢ)·(p\[j−1\] − p_ref − vᵢ\[j−1\]), p = w − k_r·u.
    pub(crate) fn relaxation_elements(&self) -> ([(f32, f32); RELAXATION_LAGS], f32) {
        let r = &self.relaxation;
        let gain = |i: usize| match i.cmp(&r.first_lags) {
            core::cmp::Ordering::Less => r.gain[0],
            core::cmp::Ordering::Equal => r.gain[1],
            core::cmp::Ordering::Greater => 0.0,
        };
        (core::array::from_fn(|i| (r.rate[i], gain(i))), r.linear)
    }

    /// Whether the second-order mode is present.
    pub fn has_mode(&self) -> bool {
        self.mode.is_some()
    }

    /// D = delay_s / T \[samples\].
    pub fn delay_samples(&self) -> f32 {
        self.delay_samples
    }

    /// ⌊D⌋: z*\[j\] is the reference interpolated between output samples j + ⌊D⌋ and j + ⌊D⌋ + 1.
    pub fn reference_index_offset(&self) -> usize {
        self.delay_whole
    }

    /// D − ⌊D⌋ ∈ \[0, 1): the weight of the later of the two reference samples.
    pub fn delay_fraction(&self) -> f32 {
        self.delay_fraction
    }

    /// How many output samples ahead of the current command the inverse needs the reference:
    /// ⌈D⌉, plus h + 1 for the mode's central differences ([`Effects::curvature_half_width`];
    /// nothing extra without a mode).
    pub fn lead_samples(&self) -> usize {
        let ceil = self.delay_whole + usize::from(self.delay_fraction > 0.0);
        ceil + self.mode.map_or(0, |m| m.curvature_half_width + 1)
    }

    /// h: the mode's inverse averages the curvature over 2h + 1 samples centred on the command
    /// ([`MODE_CURVATURE_SPAN_S`]; 0 without a mode).
    pub fn curvature_half_width(&self) -> usize {
        self.mode.map_or(0, |m| m.curvature_half_width)
    }

    /// The reference at the fractional output time j + D, from the samples at j + ⌊D⌋
    /// (`at_offset_m`) and j + ⌊D⌋ + 1 (`after_offset_m`) \[m\].
    #[inline]
    pub fn interpolate_reference(&self, at_offset_m: f32, after_offset_m: f32) -> f32 {
        if self.delay_fraction == 0.0 {
            at_offset_m
        } else {
            at_offset_m + self.delay_fraction * (after_offset_m - at_offset_m)
        }
    }

    /// The drift d(t) = r_d·t + A_d·(1 − e^(−t/τ_d)) \[m\] at t = (j + D)·T, the output time of
    /// command j.
    #[inline]
    pub fn drift_for_command_m(&self, command_index: usize) -> f32 {
        let t = (command_index as f32 + self.delay_samples) * self.sample_period_s;
        self.drift_at(t)
    }

    /// d(t) = r_d·t + A_d·(1 − e^(−t/τ_d)) \[m\], t ≥ 0 \[s\] from the first sample.
    #[inline]
    fn drift_at(&self, t_s: f32) -> f32 {
        let linear = self.params.drift_rate_m_per_s * t_s;
        let settling = if self.drift_settling_rate_per_s == 0.0 {
            0.0
        } else {
            -self.params.drift_settling_m * libm::expm1f(-t_s * self.drift_settling_rate_per_s)
        };
        bounded(bounded(linear) + bounded(settling))
    }

    /// Single-axis steps 1 and 2 of the inverse: z*\[j\] = y*(j + D) − r_d·(j + D)·T \[m\], from the
    /// reference at the output samples (`reference_m[k]` = y*\[k\]; indices past the end hold the
    /// last sample). NaN for an empty reference.
    pub fn desired_z_m(&self, reference_m: &[f32], command_index: usize) -> f32 {
        let Some(last) = reference_m.len().checked_sub(1) else {
            return f32::NAN;
        };
        let i0 = command_index.saturating_add(self.delay_whole);
        let at = reference_m[i0.min(last)];
        let after = reference_m[i0.saturating_add(1).min(last)];
        self.interpolate_reference(at, after) - self.drift_for_command_m(command_index)
    }

    /// The even term e·(u\[j−1\] − u_c)² \[m\] of the next sample to process, u\[j−1\] the last
    /// command the state has seen (0 before the first sample: u\[−1\] := u_c). Held within ±1e30.
    #[inline]
    pub fn even_term_m(&self, state: &EffectsState) -> f32 {
        let e = self.params.even_coefficient_m_per_v2;
        if e == 0.0 || !(state.started || state.rested) {
            return 0.0;
        }
        let d = state.previous_input_v - self.params.even_center_v;
        bounded(e * d * d)
    }

    /// The creep c\[j\] = Σ gᵢ·xᵢ\[j\] + g_log·½·Σₗ xₗ\[j\] \[m\] of the next sample to process (the
    /// Kelvin–Voigt bank and the logarithmic creep).
    #[inline]
    pub fn creep_m(&self, state: &EffectsState) -> f32 {
        let mut c = 0.0;
        for (g, x) in self.creep_gain.iter().zip(state.creep_v.iter()) {
            c += g * x;
        }
        if self.log_creep_weight != 0.0 {
            let mut sum = 0.0;
            for x in state.log_creep_v.iter() {
                sum += x;
            }
            c += self.log_creep_weight * bounded(sum);
        }
        bounded(c)
    }

    /// The rate-dependent hysteresis c_w\[j\] = Σ g_wᵢ·vᵢ\[j\] \[m\] of the next sample to process
    /// (vᵢ a first-order lag of p − p_ref, p = w − k_r·u; 0 without it and before the first
    /// sample).
    #[inline]
    pub fn relaxation_m(&self, state: &EffectsState) -> f32 {
        let r = &self.relaxation;
        if r.lags == 0 {
            return 0.0;
        }
        let mut first = 0.0;
        for v in state.relaxation_m.iter().take(r.first_lags) {
            first += v;
        }
        let second = state.relaxation_m.get(r.first_lags).copied().unwrap_or(0.0);
        bounded(r.gain[0] * first + r.gain[1] * second)
    }

    /// Forward, one command sample: given the command u\[j\] \[V\] and w\[j\] = H(u\[j\]) \[m\] from the
    /// hysteresis model, advances the state and returns z\[j\] \[m\] (before delay, drift and
    /// coupling). A non-finite u or w holds the previous one.
    #[inline]
    pub fn forward_z(&self, state: &mut EffectsState, u_v: f32, w_m: f32) -> f32 {
        let u = if u_v.is_finite() {
            u_v
        } else {
            state.previous_input_v
        };
        let w = if w_m.is_finite() {
            w_m
        } else {
            state.previous_w_m
        };
        if !state.started && !state.rested {
            state.input_reference_v = u;
            state.creep_v = [0.0; MAX_CREEP_ELEMENTS];
            state.log_creep_v = [0.0; LOG_CREEP_ELEMENTS];
        }
        let p = bounded(w - self.relaxation.linear * u);
        if !state.started {
            state.w_reference_m = p;
            state.relaxation_m = [0.0; RELAXATION_LAGS];
        }
        let s =
            bounded(w + self.even_term_m(state) + self.creep_m(state) + self.relaxation_m(state));
        let z = match &self.mode {
            None => s,
            Some(mode) => {
                if !state.started {
                    // At rest at the first s.
                    state.mode_z_m = s;
                    state.mode_scaled_velocity_m = 0.0;
                    state.mode_input_m = s;
                    state.mode_input_before_m = s;
                }
                match &mode.ramp_gain {
                    Some(g) => {
                        let (z, v) = mode.ramp_step(
                            g,
                            (state.mode_z_m, state.mode_scaled_velocity_m),
                            state.mode_input_before_m,
                            state.mode_input_m,
                            s,
                        );
                        state.mode_z_m = bounded(z);
                        state.mode_scaled_velocity_m = bounded(v);
                        state.mode_input_before_m = state.mode_input_m;
                        state.mode_input_m = s;
                        state.mode_z_m
                    }
                    None => {
                        let (z_mid, v_mid) =
                            mode.half_step(state.mode_z_m, state.mode_scaled_velocity_m, s);
                        let (z_mid, v_mid) = (bounded(z_mid), bounded(v_mid));
                        let (z_end, v_end) = mode.half_step(z_mid, v_mid, s);
                        state.mode_z_m = bounded(z_end);
                        state.mode_scaled_velocity_m = bounded(v_end);
                        z_mid
                    }
                }
            }
        };
        if state.started {
            state.head = (state.head + 1) & RING_MASK;
        } else {
            state.head = 0;
        }
        state.ring[state.head] = z;
        state.samples = state.samples.saturating_add(1);
        let du = bounded(u - state.input_reference_v);
        for (x, rate) in state.creep_v.iter_mut().zip(self.creep_rate.iter()) {
            *x += rate * (du - *x);
        }
        if self.log_creep_weight != 0.0 {
            for (x, rate) in state.log_creep_v.iter_mut().zip(self.log_creep_rate.iter()) {
                *x += rate * (du - *x);
            }
        }
        if !self.relaxation.is_absent() {
            let dw = bounded(p - state.w_reference_m);
            for (v, rate) in state
                .relaxation_m
                .iter_mut()
                .zip(self.relaxation.rate.iter())
                .take(self.relaxation.lags)
            {
                *v += rate * (dw - *v);
            }
        }
        state.previous_input_v = u;
        state.previous_w_m = w;
        state.started = true;
        z
    }

    /// z(k − D) \[m\] at the current output sample k (the last one processed), interpolated between
    /// the stored z samples; z\[0\] before the first sample, 0 before any. Called with the *other*
    /// axis's state it gives that axis's z delayed by this axis's D, as the coupling needs.
    #[inline]
    pub fn delayed_z(&self, state: &EffectsState) -> f32 {
        let at = state.z_back(self.delay_whole);
        if self.delay_fraction == 0.0 {
            at
        } else {
            let before = state.z_back(self.delay_whole + 1);
            at + self.delay_fraction * (before - at)
        }
    }

    /// The drift d(t_k) = r_d·t_k + A_d·(1 − e^(−t_k/τ_d)) \[m\] at the current output sample k
    /// (0 before any sample).
    #[inline]
    pub fn drift_m(&self, state: &EffectsState) -> f32 {
        let k = state.samples.saturating_sub(1) as f32;
        self.drift_at(k * self.sample_period_s)
    }

    /// Single-axis output y\[k\] = z(k − D) + d(t_k) \[m\] at the current output sample (no coupling).
    #[inline]
    pub fn output_m(&self, state: &EffectsState) -> f32 {
        self.delayed_z(state) + self.drift_m(state)
    }

    /// Inverse, one command sample: from the desired z at command samples j − 1, j and j + 1 \[m\]
    /// (drift removed, decoupled and shifted by the delay: [`Effects::desired_z_m`], [`decouple`]),
    /// the target w\*\[j\] \[m\] for the hysteresis model's inverse (mode inverse by central
    /// differences, then w\* = s\* − c\[j\] − c_w\[j\] − e·(u\[j−1\] − u_c)²; see the module doc). Call before
    /// [`Effects::commit_command`] for sample j. NaN if a reference sample is not finite (the
    /// compensator then holds its voltage); finite otherwise. The curvature in one tick, whatever
    /// [`Effects::curvature_half_width`]: [`Effects::inverse_target_w_window`] with h = 0 (the
    /// loop's chain takes the window).
    #[inline]
    pub fn inverse_target_w(
        &self,
        state: &EffectsState,
        z_prev_m: f32,
        z_now_m: f32,
        z_next_m: f32,
    ) -> f32 {
        self.target_from(
            state,
            [z_prev_m, z_now_m],
            z_now_m,
            [z_now_m, z_next_m],
            |m| (m.velocity_coefficient, m.curvature_coefficient),
        )
    }

    /// [`Effects::inverse_target_w`] with the mode's curvature averaged over 2h + 1 samples
    /// (h = [`Effects::curvature_half_width`]): from z\* at j − h − 1 and j − h (`before`), j
    /// (`z_now_m`), and j + h and j + h + 1 (`after`) \[m\],
    /// ```text
    /// a = z*[j+h+1] − z*[j+h],  m = z*[j+h] − z*[j−h],  b = z*[j−h] − z*[j−h−1]
    /// s* = z*[j] + (1 − ρ)ζ/(ωT(h+1))·(a + m + b) + (a − b)/((ωT)²·(2h+1))
    /// ```
    /// (the velocity by central differences over 2(h + 1) samples, the curvature the mean of the
    /// 2h + 1 second differences centred on j), then w\* = s\* − c\[j\] − c_w\[j\] −
    /// e·(u\[j−1\] − u_c)². The mean holds a kink's impulse Δṙ/ω² and spreads it over (2h + 1)·T.
    #[inline]
    pub fn inverse_target_w_window(
        &self,
        state: &EffectsState,
        before: [f32; 2],
        z_now_m: f32,
        after: [f32; 2],
    ) -> f32 {
        self.target_from(state, before, z_now_m, after, |m| {
            (
                m.window_velocity_coefficient,
                m.window_curvature_coefficient,
            )
        })
    }

    /// The mode's inverse and the rest of step 5 with the mode's (velocity, curvature)
    /// coefficients from `coefficients`.
    #[inline(always)]
    fn target_from(
        &self,
        state: &EffectsState,
        before: [f32; 2],
        z_now_m: f32,
        after: [f32; 2],
        coefficients: impl Fn(&Mode) -> (f32, f32),
    ) -> f32 {
        let [z_bb, z_b] = before;
        let [z_a, z_aa] = after;
        if !(z_bb.is_finite()
            && z_b.is_finite()
            && z_now_m.is_finite()
            && z_a.is_finite()
            && z_aa.is_finite())
        {
            return f32::NAN;
        }
        let s = match &self.mode {
            None => z_now_m,
            Some(mode) => {
                let ahead = z_aa - z_a;
                let behind = z_b - z_bb;
                let middle = z_a - z_b;
                let (velocity, curvature) = coefficients(mode);
                z_now_m + velocity * (ahead + middle + behind) + curvature * (ahead - behind)
            }
        };
        let w = s - self.creep_m(state) - self.relaxation_m(state) - self.even_term_m(state);
        if w.is_finite() {
            w
        } else {
            z_now_m
        }
    }

    /// After the compensator chose u\[j\] \[V\] for the target, with w\[j\] \[m\] the hysteresis
    /// output it reaches: advances the state exactly as [`Effects::forward_z`] does (it *is*
    /// `forward_z`). Calling `forward_z` on the plant side and `commit_command` on the controller
    /// side with the same u and w keeps the two states — creep, mode, delay line, sample count —
    /// identical, so c\[j\] and the even term in the inverse are the plant's.
    #[inline]
    pub fn commit_command(&self, state: &mut EffectsState, u_v: f32, w_m: f32) {
        let _ = self.forward_z(state, u_v, w_m);
    }
}

/// h = round((W/T − 1)/2) within \[0, [`MAX_CURVATURE_HALF_WIDTH`]\], W = [`MODE_CURVATURE_SPAN_S`]:
/// 2h + 1 samples span the odd multiple of T nearest W.
fn curvature_half_width(sample_period_s: f64) -> usize {
    let h = libm::round((MODE_CURVATURE_SPAN_S / sample_period_s - 1.0) / 2.0);
    if h >= 1.0 {
        (h as usize).min(MAX_CURVATURE_HALF_WIDTH)
    } else {
        0
    }
}

/// Φ − I for the mode (of a half step for the centred hold, of a whole step and the ramp gain g
/// for the first-order hold when ρ > 0) and the inverse's coefficients; f64, 2×2 matrix
/// exponential.
fn discretise_mode(
    frequency_hz: f32,
    damping: f32,
    relative_damping: f32,
    sample_period_s: f32,
) -> Result<Mode, ParamError> {
    let omega = 2.0 * core::f64::consts::PI * f64::from(frequency_hz);
    let zeta = f64::from(damping);
    let rho = f64::from(relative_damping);
    let t = f64::from(sample_period_s);
    let ramp = rho > 0.0;
    let step = if ramp { omega * t } else { 0.5 * omega * t };
    let x = [[0.0, step], [-step, -2.0 * zeta * step]];
    let e = crate::math::expm_minus_identity(&x)
        .ok_or(ParamError::Discretisation { sample_period_s })?;
    let mut half_step_minus_identity = [[0.0f32; 2]; 2];
    for r in 0..2 {
        for c in 0..2 {
            half_step_minus_identity[r][c] = e[r][c] as f32;
        }
    }
    // g₁ = A⁻¹·(Φ − I)·b/(ωT), g₂ = A⁻¹·(g₁ − b)/(ωT) − g₁/2; A⁻¹ = [[−2ζ, −1], [1, 0]],
    // b = [−1, 2ρζ].
    let ramp_gain = ramp.then(|| {
        let a_inv = |x: [f64; 2]| [-2.0 * zeta * x[0] - x[1], x[0]];
        let b = [-1.0, 2.0 * rho * zeta];
        let pb = [
            e[0][0] * b[0] + e[0][1] * b[1],
            e[1][0] * b[0] + e[1][1] * b[1],
        ];
        let g1 = a_inv([pb[0] / step, pb[1] / step]);
        let c = a_inv([(g1[0] - b[0]) / step, (g1[1] - b[1]) / step]);
        let g2 = [c[0] - 0.5 * g1[0], c[1] - 0.5 * g1[1]];
        [[g1[0] as f32, g1[1] as f32], [g2[0] as f32, g2[1] as f32]]
    });
    let h = curvature_half_width(t);
    let (widths, samples) = ((h + 1) as f64, (2 * h + 1) as f64);
    let mode = Mode {
        half_step_minus_identity,
        ramp_gain,
        velocity_coefficient: ((1.0 - rho) * zeta / (omega * t)) as f32,
        curvature_coefficient: (1.0 / ((omega * t) * (omega * t))) as f32,
        window_velocity_coefficient: ((1.0 - rho) * zeta / (omega * t * widths)) as f32,
        window_curvature_coefficient: (1.0 / ((omega * t) * (omega * t) * samples)) as f32,
        curvature_half_width: h,
    };
    let coefficients = [
        mode.velocity_coefficient,
        mode.curvature_coefficient,
        mode.window_velocity_coefficient,
        mode.window_curvature_coefficient,
    ];
    if !half_step_minus_identity
        .iter()
        .flatten()
        .chain(coefficients.iter())
        .chain(ramp_gain.iter().flatten().flatten())
        .all(|v| v.is_finite())
    {
        return Err(ParamError::Discretisation { sample_period_s });
    }
    Ok(mode)
}

/// Two-axis coupling of the delayed z's \[m\]: `(zx + κxy·zy, zy + κyx·zx)` (add each axis's drift
/// separately). Exact for the outputs when both axes have the same delay; otherwise each axis adds
/// the other's z delayed by its own D: `y_x = ex.delayed_z(&sx) + ex.drift_m(&sx) + κxy·ex.delayed_z(&sy)`. κ's are taken within \[−0.5, 0.5\], the validated range (NaN gives −0.5).
/// Results are finite for finite inputs (held within ±f32::MAX).
#[inline]
pub fn couple(c_xy: f32, c_yx: f32, zx: f32, zy: f32) -> (f32, f32) {
    let (a, b) = (clamp_coupling(c_xy), clamp_coupling(c_yx));
    (finite_or_max(zx + a * zy), finite_or_max(zy + b * zx))
}

/// The exact inverse of [`couple`]: `zx = (yx − κxy·yy)/det`, `zy = (yy − κyx·yx)/det`,
/// det = 1 − κxy·κyx > 0.75 (κ's within \[−0.5, 0.5\]; NaN gives −0.5).
/// Results are finite for finite inputs (held within ±f32::MAX).
#[inline]
pub fn decouple(c_xy: f32, c_yx: f32, yx: f32, yy: f32) -> (f32, f32) {
    let (a, b) = (clamp_coupling(c_xy), clamp_coupling(c_yx));
    let inverse_det = 1.0 / (1.0 - a * b);
    (
        finite_or_max((yx - a * yy) * inverse_det),
        finite_or_max((yy - b * yx) * inverse_det),
    )
}

#[inline(always)]
fn clamp_coupling(c: f32) -> f32 {
    clamp(c, -MAX_COUPLING, MAX_COUPLING)
}

#[inline(always)]
fn finite_or_max(x: f32) -> f32 {
    clamp(x, -f32::MAX, f32::MAX)
}

/// Simulates the single-axis chain (hysteresis model, then effects; no coupling) over a record:
/// the model starts from `initial` (`ModelState::at_rest(u0)` for a record that starts at rest at
/// u0), the effects from [`EffectsState::at_rest`] at `initial.input_v`; `y_out_m[k]` = y\[k\] \[m\] for each command `u_v[k]` \[V\] (output sample
/// times = input sample times). The creep sees the input as the model applied it (clamped into its
/// range, a non-finite one held), and so does the even term. Processes `min(u_v.len(), y_out_m.len())` samples.
pub fn simulate_axis(
    model: &StaticModel,
    initial: ModelState,
    effects: &Effects,
    u_v: &[f32],
    y_out_m: &mut [f32],
) {
    let mut model_state = initial;
    let mut state = EffectsState::at_rest(initial.input_v);
    for (&u, y) in u_v.iter().zip(y_out_m.iter_mut()) {
        let w = model.step(&mut model_state, u);
        effects.forward_z(&mut state, model_state.input_v, w);
        *y = effects.output_m(&state);
    }
}

/// Runs the single-axis inverse chain (no coupling) over a reference record `reference_m[k]` = y*\[k\]
/// \[m\] at the output samples: for each command j, z* at j − h − 1, j − h, j, j + h and
/// j + h + 1 by [`Effects::desired_z_m`] (z* before the first sample = z*\[0\];
/// h = [`Effects::curvature_half_width`]), the target by
/// [`Effects::inverse_target_w_window`], the voltage by `compensator` (from `initial`), then
/// [`Effects::commit_command`] with the voltage commanded and the w it reaches. Writes the commands
/// \[V\] to `u_out_v`; processes `min(reference_m.len(), u_out_v.len())` samples.
pub fn compensate_axis(
    compensator: &Compensator,
    initial: CompensatorState,
    effects: &Effects,
    reference_m: &[f32],
    u_out_v: &mut [f32],
) {
    let mut compensator_state = initial;
    let mut state = EffectsState::at_rest(initial.model.input_v);
    let h = effects.curvature_half_width();
    for (j, u) in u_out_v.iter_mut().enumerate().take(reference_m.len()) {
        let z = |i: usize| effects.desired_z_m(reference_m, i);
        let target = effects.inverse_target_w_window(
            &state,
            [z(j.saturating_sub(h + 1)), z(j.saturating_sub(h))],
            z(j),
            [z(j + h), z(j + h + 1)],
        );
        let command = compensator.compensate(&mut compensator_state, target);
        let w = compensator.model().output(&compensator_state.model);
        effects.commit_command(&mut state, command.voltage_v, w);
        *u = command.voltage_v;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The window 0–120 V with a stroke of `stroke_m` \[m\] from 0.
    fn range(stroke_m: f32) -> OperatingRange {
        OperatingRange {
            input_v: (0.0, 120.0),
            output_m: (0.0, stroke_m),
        }
    }

    /// Each bound of the plausibility table refuses a set just beyond it (naming the field) and
    /// accepts one just inside it.
    #[test]
    fn implausible_effects_are_refused_with_their_measure() {
        let stroke = 40e-6f32;
        let gain = stroke / 120.0;
        let build = |p: EffectParams| Effects::new(p, period(), range(stroke));
        let field_of = |p: EffectParams| match build(p) {
            Err(ParamError::Implausible { field, .. }) => field,
            other => panic!("{p:?}: {other:?}"),
        };
        let creep = |g: f32| EffectParams {
            creep_gain_m_per_v: [g, 0.0, 0.0],
            creep_time_constant_s: [0.1, 0.0, 0.0],
            ..EffectParams::default()
        };
        assert_eq!(field_of(creep(1e6)), "creep_gain_m_per_v[0]");
        assert_eq!(
            field_of(creep(-1.01 * MAX_CREEP_RATIO * gain)),
            "creep_gain_m_per_v[0]"
        );
        assert!(build(creep(0.99 * MAX_CREEP_RATIO * gain)).is_ok());
        let log = |g: f32| EffectParams {
            log_creep_gain_m_per_v: g,
            log_creep_time_s: 0.1,
            ..EffectParams::default()
        };
        assert_eq!(
            field_of(log(1.01 * MAX_CREEP_RATIO * gain / 6.0)),
            "log_creep_gain_m_per_v"
        );
        assert!(build(log(0.99 * MAX_CREEP_RATIO * gain / 6.0)).is_ok());
        // The even term's reach counts from its centre to the far end of the window.
        let even = |e: f32, c: f32| EffectParams {
            even_coefficient_m_per_v2: e,
            even_center_v: c,
            ..EffectParams::default()
        };
        assert_eq!(field_of(even(1e30, 60.0)), "even_coefficient_m_per_v2");
        let at_edge = MAX_EVEN_RATIO * stroke / (120.0 * 120.0);
        assert!(build(even(0.99 * at_edge, 0.0)).is_ok());
        assert_eq!(
            field_of(even(0.99 * at_edge, -10.0)),
            "even_coefficient_m_per_v2"
        );
        let drift = |r: f32| EffectParams {
            drift_rate_m_per_s: r,
            ..EffectParams::default()
        };
        let per_hour = MAX_DRIFT_STROKES_PER_HOUR * stroke / 3600.0;
        assert_eq!(field_of(drift(1e30)), "drift_rate_m_per_s");
        assert_eq!(field_of(drift(-1.01 * per_hour)), "drift_rate_m_per_s");
        assert!(build(drift(0.99 * per_hour)).is_ok());
        let settling = |a: f32| EffectParams {
            drift_settling_m: a,
            drift_settling_time_constant_s: 1.0,
            ..EffectParams::default()
        };
        assert_eq!(field_of(settling(1.01 * stroke)), "drift_settling_m");
        assert!(build(settling(0.99 * stroke)).is_ok());
        extern crate std;
        use std::string::ToString;
        let message = build(creep(1e6)).unwrap_err().to_string();
        assert!(
            message.contains("implausible") && message.contains("g_lin"),
            "{message}"
        );
    }

    fn period() -> f32 {
        1e-4
    }

    #[test]
    fn default_is_identity() {
        let effects = Effects::new(EffectParams::default(), period(), range(1e-5)).unwrap();
        assert!(effects.is_identity());
        assert_eq!(effects.lead_samples(), 0);
        let mut state = EffectsState::new();
        for k in 0..100 {
            let w = 1e-7 * k as f32;
            assert_eq!(effects.forward_z(&mut state, 0.3 * k as f32, w), w);
            assert_eq!(effects.output_m(&state), w);
            assert_eq!(effects.inverse_target_w(&state, w, w, w), w);
        }
    }

    #[test]
    fn mode_discretisation_has_unit_static_gain_and_the_right_poles() {
        let effects = Effects::new(
            EffectParams {
                mode_frequency_hz: 500.0,
                mode_damping: 0.05,
                ..EffectParams::default()
            },
            period(),
            range(1e-5),
        )
        .unwrap();
        let mode = effects.mode.unwrap();
        let d = mode.half_step_minus_identity;
        let det = (1.0 + f64::from(d[0][0])) * (1.0 + f64::from(d[1][1]))
            - f64::from(d[0][1]) * f64::from(d[1][0]);
        // det Φ_half = exp(trace·T/2) = exp(−2ζω·T/2).
        let omega = 2.0 * core::f64::consts::PI * 500.0;
        let expected = libm::exp(-0.05 * omega * 1e-4);
        assert!((det - expected).abs() < 1e-6, "{det} vs {expected}");
        let mut state = EffectsState::new();
        let mut z = 0.0;
        for _ in 0..20_000 {
            z = effects.forward_z(&mut state, 1.0, 1e-5);
        }
        assert!((z - 1e-5).abs() < 1e-11, "{z}");
    }

    /// A mode with ω·T ≈ 2 (3.2 kHz at 10 kHz), all its damping relative (ρ = 1), driven by a
    /// smooth 100 Hz sine: the continuous mode z̈ + 2ζω·(ż − ṡ) + ω²·(z − s) = 0, integrated
    /// finely in f64 from the analytic drive.
    fn stack_driven_reference<const N: usize>(f_hz: f64, zeta: f64, drive_hz: f64) -> [f64; N] {
        let (omega, wd, t) = (
            2.0 * core::f64::consts::PI * f_hz,
            2.0 * core::f64::consts::PI * drive_hz,
            1e-4,
        );
        let drive = |t: f64| (1e-5 * libm::sin(wd * t), 1e-5 * wd * libm::cos(wd * t));
        let rhs = |t: f64, x: [f64; 2]| {
            let (s, ds) = drive(t);
            [
                x[1],
                omega * omega * (s - x[0]) + 2.0 * zeta * omega * (ds - x[1]),
            ]
        };
        // At rest at s = 0 with ż = ṡ(0): the steady motion's start, no transient.
        let mut x = [0.0, drive(0.0).1];
        let mut out = [0.0; N];
        let sub = 200;
        let h = t / sub as f64;
        for j in 0..N - 1 {
            for i in 0..sub {
                let t0 = (j * sub + i) as f64 * h;
                let k1 = rhs(t0, x);
                let k2 = rhs(
                    t0 + h / 2.0,
                    [x[0] + h / 2.0 * k1[0], x[1] + h / 2.0 * k1[1]],
                );
                let k3 = rhs(
                    t0 + h / 2.0,
                    [x[0] + h / 2.0 * k2[0], x[1] + h / 2.0 * k2[1]],
                );
                let k4 = rhs(t0 + h, [x[0] + h * k3[0], x[1] + h * k3[1]]);
                for r in 0..2 {
                    x[r] += h / 6.0 * (k1[r] + 2.0 * k2[r] + 2.0 * k3[r] + k4[r]);
                }
            }
            out[j + 1] = x[0];
        }
        out
    }

    #[test]
    fn a_stack_driven_mode_follows_a_smooth_drive_as_the_continuous_mode_does() {
        const N: usize = 400;
        let (f_hz, zeta, drive_hz) = (3200.0, 0.035, 100.0);
        let effects = Effects::new(
            EffectParams {
                mode_frequency_hz: f_hz as f32,
                mode_damping: zeta as f32,
                mode_relative_damping: 1.0,
                ..EffectParams::default()
            },
            period(),
            range(2e-5),
        )
        .unwrap();
        let reference = stack_driven_reference::<N>(f_hz, zeta, drive_hz);
        let mut state = EffectsState::new();
        let wd = 2.0 * core::f64::consts::PI * drive_hz;
        let mut worst = 0.0f64;
        for (j, want) in reference.iter().enumerate() {
            let s = 1e-5 * libm::sin(wd * j as f64 * 1e-4);
            let z = f64::from(effects.forward_z(&mut state, 0.0, s as f32));
            // After the start's ring (the first samples carry no curvature) has decayed.
            if j >= 200 {
                worst = worst.max((z - want).abs());
            }
        }
        // The mode's own response is (f/f_mode)² ≈ 1e-3 of the drive (10 nm here); the smooth
        // hold is within ≈ 1e-10 m of the continuous mode, a straight ramp between samples
        // misses ≈ (ω_in·T)²/12 ≈ 3e-4 of the drive (3.5e-9 m).
        assert!(
            worst < 5e-10,
            "worst {worst:e} m against the continuous mode"
        );
        // The inverse, from the mode's output three samples at a time, returns the drive: no
        // phase term for damping that acts on the relative motion.
        let mut state = EffectsState::new();
        let mut z = [0.0f32; N];
        for (j, z) in z.iter_mut().enumerate() {
            let s = 1e-5 * libm::sin(wd * j as f64 * 1e-4);
            *z = effects.forward_z(&mut state, 0.0, s as f32);
        }
        let mut worst_inverse = 0.0f64;
        for j in 200..N - 1 {
            let s = 1e-5 * libm::sin(wd * j as f64 * 1e-4);
            let target = effects.inverse_target_w(&state, z[j - 1], z[j], z[j + 1]);
            worst_inverse = worst_inverse.max((f64::from(target) - s).abs());
        }
        assert!(
            worst_inverse < 5e-10,
            "worst {worst_inverse:e} m of the inverse"
        );
    }

    #[test]
    fn relative_damping_outside_its_range_is_refused_naming_the_field() {
        for rho in [-0.1, 1.5, f32::NAN, f32::INFINITY] {
            let e = Effects::new(
                EffectParams {
                    mode_frequency_hz: 500.0,
                    mode_damping: 0.05,
                    mode_relative_damping: rho,
                    ..EffectParams::default()
                },
                period(),
                range(1e-5),
            )
            .unwrap_err();
            let field = match e {
                ParamError::OutOfRange { field, .. } | ParamError::NonFinite { field } => field,
                other => panic!("{rho}: {other:?}"),
            };
            assert_eq!(field, "mode_relative_damping", "{rho}: {e:?}");
        }
    }

    #[test]
    fn even_term_uses_the_previous_command_and_inverts() {
        let (e, center) = (2e-10f32, 60.0f32);
        let effects = Effects::new(
            EffectParams {
                even_coefficient_m_per_v2: e,
                even_center_v: center,
                ..EffectParams::default()
            },
            period(),
            range(4e-5),
        )
        .unwrap();
        assert!(!effects.is_identity());
        let mut plant = EffectsState::new();
        let mut controller = EffectsState::new();
        let mut previous: Option<f32> = None;
        for k in 0..=40 {
            let u = (k * 37 % 121) as f32;
            let w = 1e-7 * u;
            let term = previous.map_or(0.0, |p| e * (p - center) * (p - center));
            assert_eq!(effects.even_term_m(&plant), term);
            let target = effects.inverse_target_w(&controller, w + term, w + term, w + term);
            assert!((target - w).abs() < 1e-12, "{k}: {target} vs {w}");
            effects.commit_command(&mut controller, u, w);
            let z = effects.forward_z(&mut plant, u, w);
            assert!((z - (w + term)).abs() < 1e-12, "{k}: {z}");
            previous = Some(u);
        }
    }

    fn relaxation(gains: [f32; 2], taus: [f32; 2]) -> Result<Effects, ParamError> {
        Effects::new(
            EffectParams {
                relaxation_gain: gains,
                relaxation_time_constant_s: taus,
                ..EffectParams::default()
            },
            period(),
            range(1e-4),
        )
    }

    #[test]
    fn relaxation_is_the_exact_lag_of_w_and_its_inverse_is_exact() {
        let (g, tau) = ([0.6f32, 0.2], [1e-3f32, 8e-3]);
        let effects = relaxation(g, tau).unwrap();
        assert!(!effects.is_identity());
        let mut plant = EffectsState::at_rest(0.0);
        let mut controller = EffectsState::at_rest(0.0);
        // f64 reference: v_i[j] = b_i v_i[j-1] + (1 - b_i)(w[j-1] - w[0]).
        let b: [f64; 2] = core::array::from_fn(|i| libm::exp(-1e-4 / f64::from(tau[i])));
        let mut v = [0.0f64; 2];
        let (mut w0, mut previous) = (0.0f64, 0.0f64);
        let mut worst_forward = 0.0f64;
        let mut worst_inverse = 0.0f32;
        for j in 0..3000 {
            let t = j as f64 * 1e-4;
            let w = 2e-5 * (1.0 - libm::cos(2.0 * core::f64::consts::PI * 80.0 * t));
            if j == 0 {
                w0 = w;
            } else {
                for i in 0..2 {
                    v[i] = b[i] * v[i] + (1.0 - b[i]) * (previous - w0);
                }
            }
            let expected = w + f64::from(g[0]) * v[0] + f64::from(g[1]) * v[1];
            let z = effects.forward_z(&mut plant, 0.0, w as f32);
            worst_forward = worst_forward.max(libm::fabs(f64::from(z) - expected));
            // The inverse asked for the plant's z gives back the w that produced it.
            let target = effects.inverse_target_w(&controller, z, z, z);
            worst_inverse = worst_inverse.max((target - w as f32).abs());
            effects.commit_command(&mut controller, 0.0, target);
            previous = w;
        }
        // The lag lowers the output's amplitude at 80 Hz: (1 + Σ g) at DC, |G(jω)| here.
        assert!(worst_forward < 2e-11, "forward {worst_forward}");
        assert!(worst_inverse < 2e-11, "inverse {worst_inverse}");
    }

    #[test]
    fn a_spread_relaxation_is_its_box_of_lags_and_its_inverse_is_exact() {
        // W = 2 decades around τ = 1 ms: 5 lags from 0.1 to 10 ms, g/5 each, and a second
        // element's one lag of 8 ms.
        let (g, tau, g1, tau1) = (0.7f32, 1e-3f32, 0.2f32, 8e-3f32);
        let spread = |decades: f32| {
            Effects::new(
                EffectParams {
                    relaxation_gain: [g, g1],
                    relaxation_time_constant_s: [tau, tau1],
                    relaxation_spread_decades: decades,
                    ..EffectParams::default()
                },
                period(),
                range(1e-4),
            )
        };
        let effects = spread(2.0).unwrap();
        let n = RELAXATION_SPREAD_POINTS;
        let b: [f64; RELAXATION_SPREAD_POINTS] = core::array::from_fn(|k| {
            let tau_k = 1e-3 * libm::pow(10.0, 2.0 * (k as f64 / (n - 1) as f64 - 0.5));
            libm::exp(-1e-4 / tau_k)
        });
        let mut v = [0.0f64; RELAXATION_SPREAD_POINTS];
        let (b1, mut v1) = (libm::exp(-1e-4 / f64::from(tau1)), 0.0f64);
        let mut plant = EffectsState::at_rest(0.0);
        let mut controller = EffectsState::at_rest(0.0);
        let (mut w0, mut previous) = (0.0f64, 0.0f64);
        let (mut worst_forward, mut worst_inverse, mut largest) = (0.0f64, 0.0f32, 0.0f64);
        for j in 0..3000 {
            let t = j as f64 * 1e-4;
            let w = 2e-5 * (1.0 - libm::cos(2.0 * core::f64::consts::PI * 30.0 * t));
            if j == 0 {
                w0 = w;
            } else {
                for k in 0..n {
                    v[k] = b[k] * v[k] + (1.0 - b[k]) * (previous - w0);
                }
                v1 = b1 * v1 + (1.0 - b1) * (previous - w0);
            }
            let relaxed = f64::from(g) / n as f64 * v.iter().sum::<f64>() + f64::from(g1) * v1;
            largest = largest.max(relaxed.abs());
            let z = effects.forward_z(&mut plant, 0.0, w as f32);
            worst_forward = worst_forward.max(libm::fabs(f64::from(z) - (w + relaxed)));
            let target = effects.inverse_target_w(&controller, z, z, z);
            worst_inverse = worst_inverse.max((target - w as f32).abs());
            effects.commit_command(&mut controller, 0.0, target);
            previous = w;
        }
        assert!(largest > 1e-5, "the relaxation is there: {largest}");
        assert!(worst_forward < 2e-11, "forward {worst_forward}");
        assert!(worst_inverse < 2e-11, "inverse {worst_inverse}");
        // The box nests the one lag: as W → 0 its output tends to the one lag's.
        let (one, narrow) = (spread(0.0).unwrap(), spread(1e-5).unwrap());
        let (mut a, mut b) = (EffectsState::at_rest(0.0), EffectsState::at_rest(0.0));
        let mut widest = 0.0f32;
        for j in 0..3000 {
            let w = 2e-5 * (1.0 - libm::cosf(2.0 * core::f32::consts::PI * 30.0 * j as f32 * 1e-4));
            let (za, zb) = (
                one.forward_z(&mut a, 0.0, w),
                narrow.forward_z(&mut b, 0.0, w),
            );
            widest = widest.max((za - zb).abs());
        }
        // f32 rounding of five lags' sum against one lag's, on a relaxation of ~1e-5 m.
        assert!(widest < 1e-10, "W = 1e-5 against W = 0: {widest}");
        // A spread outside [0, 4] decades, or not finite, is refused by name.
        for bad in [-0.1f32, 4.5, f32::NAN, f32::INFINITY] {
            let e = spread(bad).unwrap_err();
            match e {
                ParamError::OutOfRange { field, .. } | ParamError::NonFinite { field } => {
                    assert_eq!(field, "relaxation_spread_decades", "{bad}")
                }
                other => panic!("{bad}: {other:?}"),
            }
        }
    }

    #[test]
    fn relaxation_refuses_bad_sets_and_survives_hostile_inputs() {
        for (gains, taus, field) in [
            ([-0.1f32, 0.0], [1e-3f32, 0.0], "relaxation_gain[0]"),
            ([0.0, f32::NAN], [0.0, 1e-3], "relaxation_gain[1]"),
            ([0.5, 0.0], [0.0, 0.0], "relaxation_time_constant_s[0]"),
            ([0.5, 0.0], [-1e-3, 0.0], "relaxation_time_constant_s[0]"),
            (
                [0.5, 0.0],
                [f32::INFINITY, 0.0],
                "relaxation_time_constant_s[0]",
            ),
            // Σ g·tanh(T/2τ) = 20·tanh(0.05) ≈ 1.0 > 0.5: the inverse would ring.
            ([20.0, 0.0], [1e-3, 0.0], "relaxation_gain"),
            ([f32::MAX, 0.0], [1e-3, 0.0], "relaxation_gain"),
        ] {
            match relaxation(gains, taus) {
                Err(ParamError::OutOfRange { field: f, .. })
                | Err(ParamError::NonFinite { field: f }) => {
                    assert_eq!(f, field, "{gains:?} {taus:?}")
                }
                other => panic!("{gains:?} {taus:?}: {other:?}"),
            }
        }
        // The largest accepted set, driven by hostile w and references: finite, never panics.
        let effects = relaxation([9.0, 0.1], [1e-3, 1e-4]).unwrap();
        let mut plant = EffectsState::new();
        let mut controller = EffectsState::new();
        let hostile = [
            0.0,
            f32::NAN,
            f32::INFINITY,
            -f32::INFINITY,
            f32::MAX,
            -f32::MAX,
            1e-30,
            3e38,
            -2e-5,
        ];
        for k in 0..400 {
            let w = hostile[k % hostile.len()];
            let r = hostile[(k * 7 + 3) % hostile.len()];
            let z = effects.forward_z(&mut plant, 1.0, w);
            assert!(z.is_finite(), "{k}: {z}");
            assert!(effects.output_m(&plant).is_finite());
            let target = effects.inverse_target_w(&controller, r, r, r);
            assert!(target.is_finite() || !r.is_finite(), "{k}: {target}");
            effects.commit_command(&mut controller, 1.0, target);
            assert!(effects.relaxation_m(&controller).is_finite());
        }
    }
}
