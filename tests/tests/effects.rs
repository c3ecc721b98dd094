//! The effects around the hysteresis model (core/src/effects.rs): each effect alone against an
//! independent f64 reference written here, the forward chain against the inverse chain with the
//! core compensator (controller and plant side by side, open loop), the build-time
//! validation, and finiteness of the per-sample functions.

use piezo_core::effects::{
    compensate_axis, couple, decouple, simulate_axis, EffectParams, Effects, EffectsState,
    OperatingRange, LOG_CREEP_ELEMENTS,
};
use piezo_core::{
    BoucWen, BoucWenParams, Compensator, CompensatorSettings, CompensatorState, Limits, ModelState,
    ParamError, StaticMap, StaticModel,
};
use proptest::prelude::*;
use std::f64::consts::PI;

const PERIOD: f32 = 1e-4;
const STROKE: f64 = 38e-6;
/// The xy-stage's window 0–120 V and its hysteresis model's output over it, with margin.
const W_RANGE: OperatingRange = OperatingRange {
    input_v: (0.0, 120.0),
    output_m: (-5e-6, 45e-6),
};

fn effects(params: EffectParams) -> Effects {
    Effects::new(params, PERIOD, W_RANGE).unwrap()
}

/// Runs the forward chain with w given directly (u only drives the creep); returns z[j].
fn forward(effects: &Effects, u: &[f64], w: &[f64]) -> Vec<f64> {
    let mut state = EffectsState::new();
    u.iter()
        .zip(w)
        .map(|(&u, &w)| f64::from(effects.forward_z(&mut state, u as f32, w as f32)))
        .collect()
}

fn max_abs_diff(a: &[f64], b: &[f64]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max)
}

// ---------------------------------------------------------------- creep

/// Independent reference: the exact solution of τ·ẋ = −x + (u − u_ref) for a command held from
/// t_m to t_m+1, as a superposition of step responses (x(t_j) = Σ_m Δu_m·(1 − e^(−(t_j − t_m)/τ))).
fn creep_reference(gains: &[f64], taus: &[f64], u: &[f64], period: f64) -> Vec<f64> {
    let steps: Vec<(usize, f64)> = (1..u.len())
        .map(|m| (m, u[m] - u[m - 1]))
        .filter(|&(_, du)| du != 0.0)
        .collect();
    (0..u.len())
        .map(|j| {
            let mut c = 0.0;
            for (&g, &tau) in gains.iter().zip(taus) {
                let x: f64 = steps
                    .iter()
                    .filter(|&&(m, _)| m < j)
                    .map(|&(m, du)| du * (1.0 - (-((j - m) as f64) * period / tau).exp()))
                    .sum();
                c += g * x;
            }
            c
        })
        .collect()
}

#[test]
fn creep_bank_matches_the_exact_first_order_solution() {
    let gains = [4e-9f32, -1.5e-9, 2e-9];
    let taus = [2e-3f32, 0.05, 0.4];
    let e = effects(EffectParams {
        creep_gain_m_per_v: gains,
        creep_time_constant_s: taus,
        ..EffectParams::default()
    });
    let g64: Vec<f64> = gains.iter().map(|&g| f64::from(g)).collect();
    let t64: Vec<f64> = taus.iter().map(|&t| f64::from(t)).collect();
    let n = 5000;
    let period = f64::from(PERIOD);
    // A step 10 V → 70 V at sample 200, and a 7 Hz sine around 50 V.
    let step: Vec<f64> = (0..n).map(|j| if j < 200 { 10.0 } else { 70.0 }).collect();
    let sine: Vec<f64> = (0..n)
        .map(|j| 50.0 + 30.0 * (2.0 * PI * 7.0 * j as f64 * period).sin())
        .collect();
    for (name, u) in [("step", step), ("sine", sine)] {
        let zeros = vec![0.0; n];
        let core = forward(&e, &u, &zeros);
        let reference = creep_reference(&g64, &t64, &u, period);
        let scale = reference.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let err = max_abs_diff(&core, &reference);
        println!(
            "creep {name}: max |c| {scale:.3e} m, max error {err:.3e} m ({:.2e})",
            err / scale
        );
        assert!(scale > 1e-7, "{name}: creep too small to test");
        assert!(err < 1e-5 * scale, "{name}: error {err:e} of {scale:e}");
    }
    // The step response in closed form, one element: c[j] = g·Δu·(1 − e^(−(j − 200)·T/τ)).
    let single = effects(EffectParams {
        creep_gain_m_per_v: [5e-9, 0.0, 0.0],
        creep_time_constant_s: [0.01, 0.0, 0.0],
        ..EffectParams::default()
    });
    let u: Vec<f64> = (0..1000)
        .map(|j| if j < 200 { 0.0 } else { 100.0 })
        .collect();
    let core = forward(&single, &u, &vec![0.0; 1000]);
    for (j, &c) in core.iter().enumerate() {
        let expected = if j <= 200 {
            0.0
        } else {
            5e-9 * 100.0 * (1.0 - (-((j - 200) as f64) * period / 0.01).exp())
        };
        assert!(
            (c - expected).abs() < 1e-6 * 5e-7,
            "j={j}: {c} vs {expected}"
        );
    }
}

// ---------------------------------------------------------------- logarithmic creep

/// Independent reference of the logarithmic creep: superposition of the step responses of its
/// elements, Σ_m Δu_m·(g_log/2)·Σ_l (1 − e^(−(t_j − t_m)/τ_l)), τ_l = t0·10^((l+1)/2), in f64.
fn log_creep_reference(gain: f64, t0: f64, u: &[f64], period: f64) -> Vec<f64> {
    let taus: Vec<f64> = (0..LOG_CREEP_ELEMENTS)
        .map(|l| t0 * 10f64.powf(0.5 * (l + 1) as f64))
        .collect();
    let steps: Vec<(usize, f64)> = (1..u.len())
        .map(|m| (m, u[m] - u[m - 1]))
        .filter(|&(_, du)| du != 0.0)
        .collect();
    (0..u.len())
        .map(|j| {
            steps
                .iter()
                .filter(|&&(m, _)| m < j)
                .map(|&(m, du)| {
                    let t = (j - m) as f64 * period;
                    du * 0.5 * gain * taus.iter().map(|tau| 1.0 - (-t / tau).exp()).sum::<f64>()
                })
                .sum()
        })
        .collect()
}

#[test]
fn log_creep_matches_its_f64_reference_and_grows_per_decade() {
    let (gain, t0) = (2e-9f32, 1e-3f32);
    let e = effects(EffectParams {
        log_creep_gain_m_per_v: gain,
        log_creep_time_s: t0,
        ..EffectParams::default()
    });
    assert!(!e.is_identity());
    let period = f64::from(PERIOD);
    let n = 4000;
    let step: Vec<f64> = (0..n).map(|j| if j < 100 { 10.0 } else { 70.0 }).collect();
    let sine: Vec<f64> = (0..n)
        .map(|j| 50.0 + 30.0 * (2.0 * PI * 5.0 * j as f64 * period).sin())
        .collect();
    for (name, u) in [("step", &step), ("sine", &sine)] {
        let core = forward(&e, u, &vec![0.0; n]);
        let reference = log_creep_reference(f64::from(gain), f64::from(t0), u, period);
        let scale = reference.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let err = max_abs_diff(&core, &reference);
        println!("log creep {name}: max |c| {scale:.3e} m, max error {err:.3e} m");
        assert!(scale > 1e-8, "{name}: creep too small to test");
        assert!(err < 1e-5 * scale, "{name}: error {err:e} of {scale:e}");
    }
    // After the step of 60 V: g·Δu·log10(1 + t/t0) within ±0.11·g·Δu (t ≤ 10^5.5·t0).
    let period_long = 1e-3f32;
    let long = Effects::new(
        EffectParams {
            log_creep_gain_m_per_v: gain,
            log_creep_time_s: 1e-2,
            ..EffectParams::default()
        },
        period_long,
        W_RANGE,
    )
    .unwrap();
    let n = 200_000;
    let u: Vec<f64> = (0..n).map(|j| if j < 1 { 10.0 } else { 70.0 }).collect();
    let core = forward(&long, &u, &vec![0.0; n]);
    let scale = f64::from(gain) * 60.0;
    for j in [3usize, 10, 100, 1000, 10_000, 100_000, 199_999] {
        let t = (j - 1) as f64 * f64::from(period_long);
        let expected = scale * (1.0 + t / 1e-2).log10();
        assert!(
            (core[j] - expected).abs() < 0.11 * scale,
            "t={t}: {} vs {expected}",
            core[j]
        );
    }
}

// ---------------------------------------------------------------- settling drift

#[test]
fn settling_drift_matches_its_formula_at_the_output_and_for_the_command() {
    let (rate, amplitude, tau) = (-2e-8f64, 3e-7f64, 0.05f64);
    let e = effects(EffectParams {
        drift_rate_m_per_s: rate as f32,
        drift_settling_m: amplitude as f32,
        drift_settling_time_constant_s: tau as f32,
        delay_s: 2.5 * PERIOD,
        ..EffectParams::default()
    });
    assert!(!e.is_identity());
    let period = f64::from(PERIOD);
    let d = |t: f64| rate * t + amplitude * (1.0 - (-t / tau).exp());
    let mut state = EffectsState::new();
    for k in 0..5000usize {
        e.forward_z(&mut state, 0.0, 0.0);
        let expected = d(k as f64 * period);
        let got = f64::from(e.drift_m(&state));
        assert!(
            (got - expected).abs() < 1e-6 * amplitude,
            "k={k}: {got} vs {expected}"
        );
        // The inverse subtracts the drift at the output time of command j: (j + D)·T.
        let for_command = f64::from(e.drift_for_command_m(k));
        let expected = d((k as f64 + 2.5) * period);
        assert!(
            (for_command - expected).abs() < 1e-6 * amplitude,
            "j={k}: {for_command}"
        );
    }
    // Independent of u: the same drift for any command.
    let mut other = EffectsState::new();
    for k in 0..100 {
        e.forward_z(&mut other, 50.0 * (k % 7) as f32, 1e-6);
    }
    let mut plain = EffectsState::new();
    for _ in 0..100 {
        e.forward_z(&mut plain, 0.0, 1e-6);
    }
    assert_eq!(e.drift_m(&other), e.drift_m(&plain));
}

#[test]
fn new_effects_are_refused_without_their_time_constant() {
    for (params, field) in [
        (
            EffectParams {
                drift_settling_m: 1e-7,
                ..EffectParams::default()
            },
            "drift_settling_time_constant_s",
        ),
        (
            EffectParams {
                log_creep_gain_m_per_v: 1e-9,
                log_creep_time_s: -1.0,
                ..EffectParams::default()
            },
            "log_creep_time_s",
        ),
    ] {
        let got = Effects::new(params, PERIOD, W_RANGE);
        assert!(
            matches!(got, Err(ParamError::OutOfRange { field: f, .. }) if f == field),
            "{field}: {got:?}"
        );
    }
    let got = Effects::new(
        EffectParams {
            drift_settling_m: f32::NAN,
            ..EffectParams::default()
        },
        PERIOD,
        W_RANGE,
    );
    assert!(matches!(
        got,
        Err(ParamError::NonFinite {
            field: "drift_settling_m"
        })
    ));
    // Their time constants are ignored (but must be finite) while the effect is absent.
    assert!(Effects::new(
        EffectParams {
            drift_settling_time_constant_s: -3.0,
            log_creep_time_s: 0.0,
            ..EffectParams::default()
        },
        PERIOD,
        W_RANGE
    )
    .unwrap()
    .is_identity());
}

// ---------------------------------------------------------------- even term

#[test]
fn even_term_matches_its_formula_on_the_previous_command_and_inverts() {
    let (e_coef, center) = (3e-10f64, 55.0f64);
    let e = effects(EffectParams {
        even_coefficient_m_per_v2: e_coef as f32,
        even_center_v: center as f32,
        ..EffectParams::default()
    });
    // A varying command (a chirp over 0–120 V plus a deterministic jitter) and an unrelated w.
    let n = 2000;
    let u: Vec<f64> = (0..n)
        .map(|j| {
            let t = j as f64 / n as f64;
            let jitter = ((j * 7919 % 101) as f64 / 101.0 - 0.5) * 4.0;
            (60.0 + 55.0 * (2.0 * PI * (3.0 * t + 8.0 * t * t)).sin() + jitter).clamp(0.0, 120.0)
        })
        .collect();
    let w: Vec<f64> = (0..n)
        .map(|j| 20e-6 + 15e-6 * (0.011 * j as f64).cos())
        .collect();
    let core = forward(&e, &u, &w);
    // f64 reference: s[j] = w[j] + e·(u[j−1] − u_c)², u[−1] = u_c.
    let reference: Vec<f64> = (0..n)
        .map(|j| {
            let previous = if j == 0 {
                center
            } else {
                f64::from(u[j - 1] as f32)
            };
            f64::from(w[j] as f32) + e_coef * (previous - center) * (previous - center)
        })
        .collect();
    let err = max_abs_diff(&core, &reference);
    let bend = reference
        .iter()
        .zip(&w)
        .map(|(s, w)| (s - w).abs())
        .fold(0.0, f64::max);
    println!("even term: max |term| {bend:.3e} m, max error {err:.3e} m");
    assert!(bend > 5e-7, "even term too small to test: {bend:e}");
    assert!(err < 1e-11, "even term error {err:e}");
    assert_eq!(
        core[0],
        f64::from(w[0] as f32),
        "the term is 0 at the first sample"
    );
    // The inverse without a mode: w* = s* − e·(u[j−1] − u_c)², exact, with the controller's state
    // advanced by the same commands.
    let mut state = EffectsState::new();
    for j in 0..n {
        let term = f64::from(e.even_term_m(&state));
        let expected_term = reference[j] - f64::from(w[j] as f32);
        assert!(
            (term - expected_term).abs() < 1e-12,
            "j={j}: {term} vs {expected_term}"
        );
        let s = reference[j] as f32;
        let back = f64::from(e.inverse_target_w(&state, s, s, s));
        assert!(
            (back - f64::from(w[j] as f32)).abs() < 1e-11,
            "j={j}: {back} vs {}",
            w[j]
        );
        e.commit_command(&mut state, u[j] as f32, w[j] as f32);
    }
}

// ---------------------------------------------------------------- mode

/// Independent reference: z̈ + 2ζω·ż + ω²·z = ω²·s by RK4 in f64, `sub` steps per half sample, with
/// s[j] held on [t_j − T/2, t_j + T/2), at rest at s[0] at t = −T/2; z sampled at t_j.
fn mode_reference(f: f64, zeta: f64, s: &[f64], period: f64, sub: usize) -> Vec<f64> {
    let w = 2.0 * PI * f;
    let rhs = |z: f64, v: f64, s: f64| (v, w * w * (s - z) - 2.0 * zeta * w * v);
    let h = 0.5 * period / sub as f64;
    let mut z = s[0];
    let mut v = 0.0;
    let advance = |z: &mut f64, v: &mut f64, s: f64| {
        for _ in 0..sub {
            let k1 = rhs(*z, *v, s);
            let k2 = rhs(*z + 0.5 * h * k1.0, *v + 0.5 * h * k1.1, s);
            let k3 = rhs(*z + 0.5 * h * k2.0, *v + 0.5 * h * k2.1, s);
            let k4 = rhs(*z + h * k3.0, *v + h * k3.1, s);
            *z += h / 6.0 * (k1.0 + 2.0 * k2.0 + 2.0 * k3.0 + k4.0);
            *v += h / 6.0 * (k1.1 + 2.0 * k2.1 + 2.0 * k3.1 + k4.1);
        }
    };
    s.iter()
        .map(|&sj| {
            advance(&mut z, &mut v, sj);
            let out = z;
            advance(&mut z, &mut v, sj);
            out
        })
        .collect()
}

#[test]
fn mode_matches_an_f64_integration_and_has_unit_dc_gain_and_resonance_peak() {
    let period = f64::from(PERIOD);
    for (f_mode, zeta) in [(200.0f32, 0.05f32), (1500.0, 0.3), (4400.0, 1.5)] {
        let e = effects(EffectParams {
            mode_frequency_hz: f_mode,
            mode_damping: zeta,
            ..EffectParams::default()
        });
        let n = 4000;
        let step: Vec<f64> = (0..n).map(|j| if j < 50 { 2e-6 } else { 30e-6 }).collect();
        let sine: Vec<f64> = (0..n)
            .map(|j| 20e-6 + 10e-6 * (2.0 * PI * 0.8 * f64::from(f_mode) * j as f64 * period).sin())
            .collect();
        for (name, s) in [("step", step), ("sine", sine)] {
            let core = forward(&e, &vec![0.0; n], &s);
            let reference = mode_reference(f64::from(f_mode), f64::from(zeta), &s, period, 40);
            let err = max_abs_diff(&core, &reference);
            println!("mode {f_mode} Hz ζ={zeta} {name}: max error {err:.3e} m");
            assert!(err < 2e-11 / f64::from(zeta).min(1.0), "{name}: {err:e}");
        }
        // DC gain 1: held s gives z = s.
        let held = forward(&e, &vec![0.0; n], &vec![25e-6; n]);
        assert!(held.iter().all(|&z| (z - 25e-6).abs() < 1e-11));
    }
    // Resonance: at f = f_mode the steady amplitude is 1/(2ζ) (sampled: × sinc(π·f·T) ≈ 0.9993).
    let zeta = 0.05f64;
    let e = effects(EffectParams {
        mode_frequency_hz: 200.0,
        mode_damping: zeta as f32,
        ..EffectParams::default()
    });
    let n = 10_000;
    let amplitude = 1e-7;
    let s: Vec<f64> = (0..n)
        .map(|j| amplitude * (2.0 * PI * 200.0 * j as f64 * period).sin())
        .collect();
    let core = forward(&e, &vec![0.0; n], &s);
    let peak = core[n - 500..].iter().fold(0.0f64, |m, z| m.max(z.abs())) / amplitude;
    println!("mode resonance gain {peak:.4} (1/(2ζ) = {})", 0.5 / zeta);
    assert!((peak * 2.0 * zeta - 1.0).abs() < 0.01, "peak gain {peak}");
}

// ---------------------------------------------------------------- delay and drift

#[test]
fn delay_matches_the_interpolated_signal_and_drift_is_linear() {
    let n = 600;
    let w: Vec<f64> = (0..n)
        .map(|k| {
            let t = k as f64;
            1e-5 * (0.05 * t).sin() + 3e-6 * ((k * 7919 % 101) as f64 / 101.0)
        })
        .collect();
    let w32: Vec<f64> = w.iter().map(|&v| f64::from(v as f32)).collect();
    for delay_samples in [0.0f64, 3.0, 2.37, 0.5, 63.25, 64.0] {
        let drift = 2.5e-6;
        let e = effects(EffectParams {
            delay_s: (delay_samples * f64::from(PERIOD)) as f32,
            drift_rate_m_per_s: drift as f32,
            ..EffectParams::default()
        });
        assert!((f64::from(e.delay_samples()) - delay_samples).abs() < 1e-4);
        // The delay the core took (delay_s is rounded to f32).
        let delay_samples = f64::from(e.delay_samples());
        let mut state = EffectsState::new();
        for (k, &wk) in w.iter().enumerate() {
            e.forward_z(&mut state, 0.0, wk as f32);
            // f64 reference: w at k − D, linear interpolation, w[0] before the start.
            let x = k as f64 - delay_samples;
            let expected = if x <= 0.0 {
                w32[0]
            } else {
                let i = x.floor() as usize;
                let f = x - i as f64;
                if f == 0.0 {
                    w32[i]
                } else {
                    w32[i] + f * (w32[i + 1] - w32[i])
                }
            };
            let got = f64::from(e.delayed_z(&state));
            assert!(
                (got - expected).abs() < 1e-11,
                "D={delay_samples} k={k}: {got} vs {expected}"
            );
            let expected_drift = drift * k as f64 * f64::from(PERIOD);
            let got_drift = f64::from(e.drift_m(&state));
            assert!((got_drift - expected_drift).abs() < 1e-6 * expected_drift.max(1e-9));
            let out = f64::from(e.output_m(&state));
            assert!((out - expected - expected_drift).abs() < 1e-11);
        }
        assert_eq!(
            e.lead_samples(),
            delay_samples.ceil() as usize,
            "D={delay_samples}"
        );
    }
}

// ---------------------------------------------------------------- coupling

#[test]
fn coupling_and_decoupling_are_inverse() {
    let mut seed = 12345u64;
    let mut next = || {
        seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((seed >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
    };
    for _ in 0..10_000 {
        let (cxy, cyx) = (0.49 * next(), 0.49 * next());
        let (zx, zy) = (40e-6 * next(), 40e-6 * next());
        let (yx, yy) = couple(cxy as f32, cyx as f32, zx as f32, zy as f32);
        let (ex, ey) = (
            f64::from(zx as f32) + f64::from(cxy as f32) * f64::from(zy as f32),
            f64::from(zy as f32) + f64::from(cyx as f32) * f64::from(zx as f32),
        );
        assert!((f64::from(yx) - ex).abs() < 1e-11 && (f64::from(yy) - ey).abs() < 1e-11);
        let (bx, by) = decouple(cxy as f32, cyx as f32, yx, yy);
        assert!(
            (f64::from(bx) - zx).abs() < 3e-11 && (f64::from(by) - zy).abs() < 3e-11,
            "({zx}, {zy}) → ({bx}, {by})"
        );
    }
}

// ---------------------------------------------------------------- forward ∘ inverse

fn xy_model(a: f32, beta: f32, gamma: f32, k1: f32) -> StaticModel {
    let bw = BoucWen::with_input_range(
        BoucWenParams {
            a,
            beta,
            gamma,
            n: 1.0,
        },
        0.0,
        120.0,
        1e3,
    )
    .unwrap();
    StaticModel::new(
        bw,
        StaticMap {
            k1_m_per_v: k1,
            k2_m_per_h: -k1,
            offset_m: 0.0,
        },
    )
    .unwrap()
}

fn x_model() -> StaticModel {
    xy_model(0.18522, 0.029586, -0.020710, 3.573_939e-7)
}

fn y_model() -> StaticModel {
    xy_model(0.16792, 0.025721, -0.018005, 3.5560867e-7)
}

fn compensator(model: StaticModel) -> Compensator {
    Compensator::new(
        model,
        CompensatorSettings {
            limits: Limits::new(0.0, 120.0, 1e5),
            sample_period_s: PERIOD,
        },
    )
    .unwrap()
}

/// A cosine between 15 % and 85 % of the stroke, faded in from 0 over the first 0.25 s (quintic
/// smoothstep), so that it starts at rest.
fn reference(frequency_hz: f64, phase: f64, n: usize) -> Vec<f32> {
    (0..n)
        .map(|k| {
            let t = k as f64 * f64::from(PERIOD);
            let x = (t / 0.25).min(1.0);
            let fade = x * x * x * (10.0 - 15.0 * x + 6.0 * x * x);
            (fade * STROKE * (0.5 - 0.35 * (2.0 * PI * frequency_hz * t + phase).cos())) as f32
        })
        .collect()
}

/// RMS of y − r after the first 0.5 s, relative to the stroke.
fn relative_rms(y: &[f32], r: &[f32]) -> f64 {
    let skip = 5000;
    piezo_core::metrics::rms(&y[skip..], &r[skip..]).unwrap() / STROKE
}

fn all_effects_but_mode() -> EffectParams {
    EffectParams {
        creep_gain_m_per_v: [3e-9, 2e-9, 0.0],
        creep_time_constant_s: [0.02, 0.5, 0.0],
        even_coefficient_m_per_v2: 2e-10,
        even_center_v: 50.0,
        delay_s: 2.5e-4,
        // Negative: over the 2 s the bottom of the cycle stays clear of 0 V.
        drift_rate_m_per_s: -1e-6,
        ..EffectParams::default()
    }
}

/// Single axis: controller (compensate_axis) and plant (simulate_axis) with the same parameters;
/// returns the relative tracking RMS, and the one of the plain compensator (no effect inverse).
fn single_axis_tracking(params: EffectParams, frequency_hz: f64) -> (f64, f64) {
    let n = 20_000;
    let r = reference(frequency_hz, 0.0, n);
    let e = effects(params);
    let plain = effects(EffectParams::default());
    let comp = compensator(x_model());
    let run = |controller: &Effects| {
        let mut u = vec![0.0f32; n];
        compensate_axis(
            &comp,
            CompensatorState::at_rest(0.0),
            controller,
            &r,
            &mut u,
        );
        let mut y = vec![0.0f32; n];
        simulate_axis(&x_model(), ModelState::at_rest(0.0), &e, &u, &mut y);
        relative_rms(&y, &r)
    };
    (run(&e), run(&plain))
}

#[test]
fn single_axis_inverse_chain_tracks_without_mode() {
    let (compensated, uncompensated) = single_axis_tracking(all_effects_but_mode(), 2.0);
    println!(
        "single axis, creep + even + delay 2.5 samples + drift, 2 Hz: RMS error {compensated:.2e} \
         of stroke (plain compensator: {uncompensated:.2e})"
    );
    assert!(compensated < 1e-5, "{compensated:e}");
    assert!(
        uncompensated > 1e-2,
        "effects too weak to test: {uncompensated:e}"
    );
}

#[test]
fn single_axis_inverse_chain_tracks_with_mode() {
    for frequency_hz in [2.0, 20.0] {
        let params = EffectParams {
            mode_frequency_hz: 200.0,
            mode_damping: 0.05,
            ..all_effects_but_mode()
        };
        let (compensated, uncompensated) = single_axis_tracking(params, frequency_hz);
        // The mode alone, to show what its inverse removes.
        let mode_only = EffectParams {
            mode_frequency_hz: 200.0,
            mode_damping: 0.05,
            ..EffectParams::default()
        };
        let (mode_compensated, mode_uncompensated) = single_axis_tracking(mode_only, frequency_hz);
        println!(
            "single axis, all effects with a 200 Hz ζ=0.05 mode, {frequency_hz} Hz: RMS error \
             {compensated:.2e} of stroke (plain: {uncompensated:.2e}); mode alone \
             {mode_compensated:.2e} (plain: {mode_uncompensated:.2e})"
        );
        // At 20 Hz the fractional delay's two linear interpolations (reference shift, plant)
        // dominate: f·(1 − f)·r̈·T² ≈ 1e-5 of the stroke for f = 0.5.
        assert!(compensated < 5e-5, "{compensated:e}");
        assert!(mode_compensated < 1e-5, "{mode_compensated:e}");
    }
}

#[test]
fn two_axis_inverse_chain_tracks_with_all_effects() {
    let n = 20_000;
    let rx = reference(2.0, 0.0, n);
    let ry = reference(3.0, 1.0, n);
    let px = EffectParams {
        mode_frequency_hz: 350.0,
        mode_damping: 0.08,
        coupling: 0.05,
        ..all_effects_but_mode()
    };
    let py = EffectParams {
        creep_gain_m_per_v: [2e-9, 0.0, 1e-9],
        creep_time_constant_s: [0.01, 0.0, 1.0],
        even_coefficient_m_per_v2: -1.5e-10,
        even_center_v: 40.0,
        mode_frequency_hz: 250.0,
        mode_damping: 0.06,
        // y's mode damped relative to its drive (a stack-driven mode).
        mode_relative_damping: 1.0,
        delay_s: 1.25e-4,
        drift_rate_m_per_s: -0.5e-6,
        coupling: -0.03,
        drift_settling_m: 2e-7,
        drift_settling_time_constant_s: 0.3,
        log_creep_gain_m_per_v: 1e-10,
        log_creep_time_s: 1e-3,
        relaxation_gain: [0.3, 0.05],
        relaxation_time_constant_s: [2e-3, 2e-2],
        // Its elements' time constants spread over a decade and a half each.
        relaxation_spread_decades: 1.5,
        relaxation_linear_m_per_v: 2e-7,
        // y's operator behind a 0.5 ms input lag (rate-dependent hysteresis), its gain rising
        // with the lagged input's speed (5 % higher at 100 kV/s, the slew limit: a stronger
        // gain would make the stack's map non-monotone at that speed, and the compensator
        // refuses it there).
        hysteresis_lag_s: 5e-4,
        hysteresis_rate_gain_s_per_v: 5e-7,
    };
    let (ex, ey) = (effects(px), effects(py));
    let (mx, my) = (
        ex.hysteresis_model(x_model()).unwrap(),
        ey.hysteresis_model(y_model()).unwrap(),
    );
    let (cx, cy) = (compensator(mx), compensator(my));
    let (kx, ky) = (px.coupling, py.coupling);
    let run = |invert: bool| {
        let (mut csx, mut csy) = (
            CompensatorState::at_rest(0.0),
            CompensatorState::at_rest(0.0),
        );
        let (mut esx, mut esy) = (EffectsState::new(), EffectsState::new());
        let (mut psx, mut psy) = (ModelState::at_rest(0.0), ModelState::at_rest(0.0));
        let (mut plant_x, mut plant_y) = (EffectsState::new(), EffectsState::new());
        let (mut yx, mut yy) = (vec![0.0f32; n], vec![0.0f32; n]);
        for j in 0..n {
            // Controller.
            let (ux, uy) = if invert {
                let z = |i: usize| decouple(kx, ky, ex.desired_z_m(&rx, i), ey.desired_z_m(&ry, i));
                let (prev, now, next) = (z(j.saturating_sub(1)), z(j), z(j + 1));
                let wx = ex.inverse_target_w(&esx, prev.0, now.0, next.0);
                let wy = ey.inverse_target_w(&esy, prev.1, now.1, next.1);
                let ux = cx.compensate(&mut csx, wx).voltage_v;
                let uy = cy.compensate(&mut csy, wy).voltage_v;
                ex.commit_command(&mut esx, ux, cx.model().output(&csx.model));
                ey.commit_command(&mut esy, uy, cy.model().output(&csy.model));
                (ux, uy)
            } else {
                (
                    cx.compensate(&mut csx, rx[j]).voltage_v,
                    cy.compensate(&mut csy, ry[j]).voltage_v,
                )
            };
            // Plant.
            let wx = mx.step(&mut psx, ux);
            let wy = my.step(&mut psy, uy);
            ex.forward_z(&mut plant_x, ux, wx);
            ey.forward_z(&mut plant_y, uy, wy);
            // Each axis adds the other axis's z delayed by its own D (couple() is this for
            // equal delays).
            yx[j] = ex.delayed_z(&plant_x) + ex.drift_m(&plant_x) + kx * ex.delayed_z(&plant_y);
            yy[j] = ey.delayed_z(&plant_y) + ey.drift_m(&plant_y) + ky * ey.delayed_z(&plant_x);
        }
        (relative_rms(&yx, &rx), relative_rms(&yy, &ry))
    };
    let (ex_rms, ey_rms) = run(true);
    let (px_rms, py_rms) = run(false);
    println!(
        "two axes, all effects (modes 350/250 Hz, coupling 0.05/−0.03): RMS error x {ex_rms:.2e}, \
         y {ey_rms:.2e} of stroke (plain compensators: x {px_rms:.2e}, y {py_rms:.2e})"
    );
    assert!(ex_rms < 2e-5 && ey_rms < 2e-5, "{ex_rms:e} {ey_rms:e}");
    assert!(px_rms > 1e-2 && py_rms > 1e-2);
}

// ---------------------------------------------------------------- validation

#[test]
fn bad_parameters_are_refused_naming_the_field() {
    let ok = EffectParams {
        creep_gain_m_per_v: [1e-9, 0.0, 0.0],
        creep_time_constant_s: [0.1, 0.0, 0.0],
        mode_frequency_hz: 300.0,
        mode_damping: 0.1,
        ..EffectParams::default()
    };
    assert!(Effects::new(ok, PERIOD, W_RANGE).is_ok());
    let out_of_range = |p: EffectParams, field: &str| {
        let got = Effects::new(p, PERIOD, W_RANGE);
        assert!(
            matches!(got, Err(ParamError::OutOfRange { field: f, .. }) if f == field),
            "{field}: {got:?}"
        );
    };
    let non_finite = |p: EffectParams, field: &str| {
        let got = Effects::new(p, PERIOD, W_RANGE);
        assert!(
            matches!(got, Err(ParamError::NonFinite { field: f }) if f == field),
            "{field}: {got:?}"
        );
    };
    out_of_range(
        EffectParams {
            creep_time_constant_s: [-0.1, 0.0, 0.0],
            ..ok
        },
        "creep_time_constant_s[0]",
    );
    out_of_range(
        EffectParams {
            creep_gain_m_per_v: [1e-9, 0.0, 2e-9],
            ..ok
        },
        "creep_time_constant_s[2]",
    );
    non_finite(
        EffectParams {
            creep_gain_m_per_v: [1e-9, f32::NAN, 0.0],
            ..ok
        },
        "creep_gain_m_per_v[1]",
    );
    non_finite(
        EffectParams {
            creep_time_constant_s: [f32::NAN, 0.0, 0.0],
            ..ok
        },
        "creep_time_constant_s[0]",
    );
    for c in [0.5, -0.5, 0.7] {
        out_of_range(EffectParams { coupling: c, ..ok }, "coupling");
    }
    non_finite(
        EffectParams {
            coupling: f32::INFINITY,
            ..ok
        },
        "coupling",
    );
    // The even term needs no monotonicity condition: any sign and centre, up to its
    // plausibility bound (at most MAX_EVEN_RATIO strokes over the window).
    for (coefficient, center) in [(-1e-6f32, 0.0f32), (1e-6, 200.0)] {
        assert!(matches!(
            Effects::new(
                EffectParams {
                    even_coefficient_m_per_v2: coefficient,
                    even_center_v: center,
                    ..ok
                },
                PERIOD,
                W_RANGE
            ),
            Err(ParamError::Implausible {
                field: "even_coefficient_m_per_v2",
                ..
            })
        ));
    }
    for (coefficient, center) in [(-1e-9f32, 0.0f32), (1e-9, 200.0), (-3e-9, -50.0)] {
        assert!(Effects::new(
            EffectParams {
                even_coefficient_m_per_v2: coefficient,
                even_center_v: center,
                ..ok
            },
            PERIOD,
            W_RANGE
        )
        .is_ok());
    }
    for bad in [f32::NAN, f32::INFINITY] {
        non_finite(
            EffectParams {
                even_coefficient_m_per_v2: bad,
                ..ok
            },
            "even_coefficient_m_per_v2",
        );
        non_finite(
            EffectParams {
                even_center_v: bad,
                ..ok
            },
            "even_center_v",
        );
    }
    for f in [4500.0, 5000.0, -1.0] {
        out_of_range(
            EffectParams {
                mode_frequency_hz: f,
                ..ok
            },
            "mode_frequency_hz",
        );
    }
    assert!(Effects::new(
        EffectParams {
            mode_frequency_hz: 4490.0,
            ..ok
        },
        PERIOD,
        W_RANGE
    )
    .is_ok());
    for zeta in [0.0, -0.1] {
        out_of_range(
            EffectParams {
                mode_damping: zeta,
                ..ok
            },
            "mode_damping",
        );
    }
    non_finite(
        EffectParams {
            mode_damping: f32::NAN,
            ..ok
        },
        "mode_damping",
    );
    for d in [64.5e-4, 1.0, -1e-4] {
        out_of_range(EffectParams { delay_s: d, ..ok }, "delay_s");
    }
    assert!(Effects::new(
        EffectParams {
            delay_s: 64e-4,
            ..ok
        },
        PERIOD,
        W_RANGE
    )
    .is_ok());
    non_finite(
        EffectParams {
            drift_rate_m_per_s: f32::NAN,
            ..ok
        },
        "drift_rate_m_per_s",
    );
    assert!(matches!(
        Effects::new(ok, 0.0, W_RANGE),
        Err(ParamError::OutOfRange {
            field: "sample_period_s",
            ..
        })
    ));
    assert!(matches!(
        Effects::new(
            ok,
            PERIOD,
            OperatingRange {
                output_m: (1e-5, 0.0),
                ..W_RANGE
            }
        ),
        Err(ParamError::OutOfRange {
            field: "w_range_m",
            ..
        })
    ));
    // The message names the field.
    let message = Effects::new(
        EffectParams {
            coupling: 0.6,
            ..ok
        },
        PERIOD,
        W_RANGE,
    )
    .unwrap_err()
    .to_string();
    assert!(message.contains("coupling"), "{message}");
}

// ---------------------------------------------------------------- finiteness

fn finite_f32() -> impl Strategy<Value = f32> {
    prop_oneof![
        any::<f32>().prop_filter("finite", |v| v.is_finite()),
        -200.0f32..200.0,
        -1e-4f32..1e-4,
    ]
}

prop_compose! {
    fn valid_params()(
        gains in prop::array::uniform3(prop_oneof![Just(0.0f32), -1e-8f32..1e-8]),
        taus in prop::array::uniform3(1e-5f32..100.0),
        even in prop_oneof![Just(0.0f32), -2e-10f32..2e-10],
        center in -200.0f32..200.0,
        mode in prop_oneof![Just(0.0f32), 0.01f32..4499.0],
        damping in 1e-3f32..20.0,
        delay in 0.0f32..64e-4,
        drift in -3e-5f32..3e-5,
        coupling in -0.49f32..0.49,
        settling in prop_oneof![Just(0.0f32), -30e-6f32..30e-6],
        settling_tau in 1e-6f32..1e4,
        log_gain in prop_oneof![Just(0.0f32), -1e-8f32..1e-8],
        log_t0 in 1e-6f32..100.0,
        relaxation_gains in prop::array::uniform2(prop_oneof![Just(0.0f32), 0.0f32..4.0]),
        relaxation_taus in prop::array::uniform2(1e-3f32..100.0),
        lag in prop_oneof![Just(0.0f32), 1e-4f32..1.0],
        relative in prop_oneof![Just(0.0f32), Just(1.0f32), 0.0f32..=1.0],
        spread in prop_oneof![Just(0.0f32), 0.0f32..=4.0],
        rate_gain in prop_oneof![Just(0.0f32), 0.0f32..=1e-3],
    ) -> EffectParams {
        EffectParams {
            creep_gain_m_per_v: gains,
            creep_time_constant_s: taus,
            even_coefficient_m_per_v2: even,
            even_center_v: center,
            mode_frequency_hz: mode,
            mode_damping: damping,
            mode_relative_damping: relative,
            delay_s: delay,
            drift_rate_m_per_s: drift,
            coupling,
            drift_settling_m: settling,
            drift_settling_time_constant_s: settling_tau,
            log_creep_gain_m_per_v: log_gain,
            log_creep_time_s: log_t0,
            relaxation_gain: relaxation_gains,
            relaxation_time_constant_s: relaxation_taus,
            relaxation_spread_decades: spread,
            relaxation_linear_m_per_v: 0.0,
            hysteresis_lag_s: lag,
            hysteresis_rate_gain_s_per_v: rate_gain,
        }
    }
}

proptest! {
    #[test]
    fn per_sample_functions_are_finite_for_finite_input(
        params in valid_params(),
        inputs in prop::collection::vec((finite_f32(), finite_f32(), finite_f32()), 1..80),
    ) {
        // Every drawn parameter set is valid (inside the plausibility bounds; the even term has no
        // monotonicity condition).
        let e = Effects::new(
            params,
            PERIOD,
            OperatingRange {
                output_m: (0.0, 40e-6),
                ..W_RANGE
            },
        );
        prop_assert!(e.is_ok(), "{params:?}: {e:?}");
        let e = e.unwrap();
        let mut state = EffectsState::new();
        let mut controller = EffectsState::new();
        for (i, &(u, w, z)) in inputs.iter().enumerate() {
            let z_prev = inputs[i.saturating_sub(1)].2;
            let z_next = inputs[(i + 1) % inputs.len()].2;
            let target = e.inverse_target_w(&controller, z_prev, z, z_next);
            prop_assert!(target.is_finite(), "inverse {target} from {z_prev} {z} {z_next}");
            e.commit_command(&mut controller, u, target);
            let out = e.forward_z(&mut state, u, w);
            prop_assert!(out.is_finite());
            prop_assert!(e.delayed_z(&state).is_finite());
            prop_assert!(e.drift_m(&state).is_finite());
            prop_assert!(e.output_m(&state).is_finite());
            prop_assert!(e.creep_m(&state).is_finite());
            prop_assert!(e.even_term_m(&state).is_finite());
            prop_assert!(e.even_term_m(&controller).is_finite());
            let (a, b) = couple(params.coupling, -params.coupling, u, w);
            let (c, d) = decouple(params.coupling, 0.3, z, u);
            prop_assert!(a.is_finite() && b.is_finite() && c.is_finite() && d.is_finite());
        }
    }
}

#[test]
fn non_finite_inputs_hold_or_signal() {
    let e = effects(EffectParams {
        mode_frequency_hz: 300.0,
        mode_damping: 0.1,
        creep_gain_m_per_v: [1e-9, 0.0, 0.0],
        creep_time_constant_s: [0.1, 0.0, 0.0],
        ..EffectParams::default()
    });
    let mut state = EffectsState::new();
    e.forward_z(&mut state, 10.0, 5e-6);
    for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
        assert!(e.forward_z(&mut state, bad, bad).is_finite());
        assert!(e.inverse_target_w(&state, 1e-6, bad, 1e-6).is_nan());
    }
    // NaN reaches the compensator, which holds its voltage.
    let comp = compensator(x_model());
    let mut cs = CompensatorState::at_rest(30.0);
    let command = comp.compensate(&mut cs, e.inverse_target_w(&state, 0.0, f32::NAN, 0.0));
    assert_eq!(command.voltage_v, 30.0);
}
