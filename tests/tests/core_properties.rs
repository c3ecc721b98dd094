//! Property tests of the core (proptest): boundedness inside the bounded class, rate independence,
//! forward(inverse(y_d)) = y_d, and an inverse that never returns NaN, never leaves its window and
//! never exceeds its slew limit, for any f32 reference including NaN and ±∞.

use piezo_core::{
    Asymmetry, BoucWen, BoucWenParams, Compensator, CompensatorSettings, CompensatorState, Limits,
    ModelState, StaticMap, StaticModel,
};
use proptest::prelude::*;

/// Bounded-class parameter sets (β ≥ 0, β + γ·sgn A > 0; classes I and II), any sign of A, n in
/// {1, 2} (the exact paths) or anywhere in [1, 4] (the RK4 path).
fn bounded_params() -> impl Strategy<Value = BoucWenParams> {
    (
        0.05f32..2.0,
        prop::bool::ANY,
        0.1f32..5.0,
        -0.95f32..3.0,
        prop_oneof![Just(1.0f32), Just(2.0f32), 1.0f32..4.0],
    )
        .prop_map(|(a_abs, negative, beta, gamma_fraction, n)| {
            // γ' = γ·sgn A ∈ (−0.95β, 3β): class I (|γ'| ≤ β) and class II (γ' > β). β ≥ 0.1 keeps the
            // unloading slope at saturation, A'·2β/(β + γ') ≥ A'/2, away from zero: at β = 0 the
            // saturated state is an equilibrium of both directions and amplifies rounding (×e^(γΔu)).
            let gamma_normalised = gamma_fraction * beta;
            let a = if negative { -a_abs } else { a_abs };
            BoucWenParams {
                a,
                beta,
                gamma: gamma_normalised * a.signum(),
                n,
            }
        })
        .prop_filter("bounded class", |p| p.beta + p.gamma * p.a.signum() > 1e-3)
}

/// Moves of the input: large and small, both directions.
fn moves() -> impl Strategy<Value = Vec<f32>> {
    prop::collection::vec(
        prop_oneof![-50.0f32..50.0, -1.0f32..1.0, -0.01f32..0.01],
        1..60,
    )
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(400))]

    /// Starting from rest, the unclamped increments never leave |h| ≤ (A'/(β + γ'))^(1/n), computed
    /// here independently in f64.
    #[test]
    fn state_stays_bounded_inside_the_bounded_class(p in bounded_params(), moves in moves()) {
        let bw = BoucWen::new(p).unwrap();
        let bound = (f64::from(p.a.abs()) / (f64::from(p.beta) + f64::from(p.gamma * p.a.signum())))
            .powf(1.0 / f64::from(p.n));
        let mut h = 0.0f32;
        for du in moves {
            h = bw.advance_unclamped(h, du);
            prop_assert!(h.is_finite());
            prop_assert!(f64::from(h.abs()) <= bound * (1.0 + 1e-4) + 1e-30,
                "|h| = {} > bound {} (params {:?})", h.abs(), bound, p);
        }
    }

    /// The same input path sampled at two rates (each coarse segment cut into `split` pieces) gives
    /// the same h at the common instants.
    #[test]
    fn state_is_rate_independent(
        p in bounded_params(),
        vertices in prop::collection::vec(-30.0f32..30.0, 2..25),
        split in 2usize..12,
    ) {
        let bw = BoucWen::new(p).unwrap();
        let scale = bw.state_bound();
        let mut coarse = piezo_core::HysteresisState::at_rest(vertices[0]);
        let mut fine = coarse;
        for w in vertices.windows(2) {
            let hc = bw.step(&mut coarse, w[1]);
            let mut hf = fine.h;
            for j in 1..=split {
                // Land exactly on the vertex: w0 + (w1 − w0)·1 can round away from w1 in f32, and
                // then the two runs would not follow the same path.
                let u = if j == split {
                    w[1]
                } else {
                    w[0] + (w[1] - w[0]) * j as f32 / split as f32
                };
                hf = bw.step(&mut fine, u);
            }
            prop_assert!((hc - hf).abs() <= 2e-5 * scale,
                "coarse {hc} vs fine {hf} (bound {scale}, params {p:?})");
        }
    }
}

/// A stage-like model with a random Bouc-Wen set, scaled so that the hysteretic part is
/// `hysteresis_fraction` of the direct part's slope at most: y = k1·u + k2·h over 0–100 V.
fn invertible_model(
    p: BoucWenParams,
    hysteresis_fraction: f32,
    asymmetry: Asymmetry,
) -> StaticModel {
    let bw = BoucWen::new(p).unwrap();
    // With δ ≠ 0 the state may pass the Bouc-Wen bound (up to ASYMMETRIC_STATE_FACTOR·H).
    let limit = if asymmetry.delta_per_v_s != 0.0 {
        piezo_core::ASYMMETRIC_STATE_FACTOR * bw.state_bound()
    } else {
        bw.state_bound()
    };
    let (lo, hi) = bw.slope_range_within(limit);
    let k1 = 0.4e-6f32;
    // The input shift scales dh/du by (1 − φ/T) ∈ [0, 2].
    let shift_gain = 1.0 + (asymmetry.input_shift_s / 1e-4).abs();
    let k2 = -hysteresis_fraction * k1 / (lo.abs().max(hi.abs()) * shift_gain);
    let map = StaticMap {
        k1_m_per_v: k1,
        k2_m_per_h: k2,
        offset_m: 0.0,
    };
    StaticModel::asymmetric(bw, map, asymmetry, 1e-4).unwrap()
}

fn settings(slew_limit_v_per_s: f32) -> CompensatorSettings {
    CompensatorSettings {
        limits: Limits::new(0.0, 100.0, slew_limit_v_per_s),
        sample_period_s: 1e-4,
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(200))]

    /// For references inside the reachable output range, running the forward model (fresh, on its
    /// own state) on the commanded voltages reproduces the reference to ≤ 1e-4 of the stroke.
    #[test]
    fn forward_of_inverse_reproduces_the_reference(
        p in bounded_params(),
        fraction in 0.02f32..0.6,
        delta in prop_oneof![Just(0.0f32), -0.05f32..0.05],
        shift in prop_oneof![Just(0.0f32), -1e-4f32..1e-4],
        tones in prop::collection::vec((0.2f32..20.0, 0.0f32..6.3), 1..4),
    ) {
        let model = invertible_model(p, fraction, Asymmetry { delta_per_v_s: delta, input_shift_s: shift });
        let compensator = Compensator::new(model, settings(f32::INFINITY)).unwrap();
        let stroke = 0.4e-6f32 * 100.0;
        // Hysteresis moves the output at the window edges by at most fraction·stroke: stay inside.
        let (low, high) = (stroke * (fraction + 0.02), stroke * (1.0 - fraction - 0.02));
        let mut state = CompensatorState::at_rest(0.0);
        let mut forward = ModelState::at_rest(0.0);
        let amplitude = 0.5 * (high - low) / tones.len() as f32;
        for k in 0..2000 {
            let t = k as f32 * 1e-4;
            let mut y_d = 0.5 * (low + high);
            for &(f, phase) in &tones {
                y_d += amplitude * (2.0 * core::f32::consts::PI * f * t + phase).sin();
            }
            let command = compensator.compensate(&mut state, y_d);
            let y = model.step(&mut forward, command.voltage_v);
            prop_assert!((y - y_d).abs() <= 1e-4 * stroke,
                "sample {k}: y = {y}, y_d = {y_d}, status {:?}, params {p:?}", command.status);
        }
    }

    /// Any f32 reference — NaN, ±∞, huge, tiny — gives a finite voltage inside the window that moves
    /// by at most the slew limit per sample.
    #[test]
    fn inverse_output_is_always_safe(
        p in bounded_params(),
        fraction in 0.02f32..0.6,
        references in prop::collection::vec(
            prop_oneof![
                Just(f32::NAN), Just(f32::INFINITY), Just(f32::NEG_INFINITY),
                Just(f32::MAX), Just(f32::MIN), Just(-0.0f32),
                proptest::num::f32::ANY,
                -1e-4f32..1e-4,
            ],
            1..200,
        ),
    ) {
        let model = invertible_model(p, fraction, Asymmetry::default());
        let slew = 2e4f32; // 2 V per 100 µs sample
        let compensator = Compensator::new(model, settings(slew)).unwrap();
        let mut state = CompensatorState::at_rest(50.0);
        let mut last = 50.0f32;
        for y_d in references {
            let command = compensator.compensate(&mut state, y_d);
            let v = command.voltage_v;
            prop_assert!(v.is_finite(), "NaN/inf voltage for reference {y_d}");
            prop_assert!((0.0..=100.0).contains(&v), "voltage {v} outside the window");
            prop_assert!((v - last).abs() <= 2.0 * (1.0 + 1e-5), "slew {} V > 2 V", (v - last).abs());
            prop_assert!(state.model.hysteresis.h.is_finite());
            last = v;
        }
    }
}
