//! Measures the accuracy of the libm f32 functions the core's per-sample path uses (powf, expm1f,
//! log1pf, tanhf, tanf, atanhf, atanf, sqrtf) against f64 over the argument ranges the core feeds
//! them, and fails if any exceeds 4 ulp (micromath, measured here earlier, reached 30 % on powf).
//! `-- --nocapture` prints the table quoted in the README.

fn ulps(got: f32, exact: f64) -> f64 {
    if exact == 0.0 {
        return f64::from(got.abs()) / f64::from(f32::MIN_POSITIVE);
    }
    let spacing = f64::from((exact as f32).abs()) * f64::from(f32::EPSILON);
    (f64::from(got) - exact).abs() / spacing.max(f64::MIN_POSITIVE)
}

fn sweep(
    name: &str,
    lo: f32,
    hi: f32,
    f32_fn: impl Fn(f32) -> f32,
    f64_fn: impl Fn(f64) -> f64,
) -> f64 {
    let n = 200_000;
    let mut worst = 0.0f64;
    for i in 0..=n {
        let x = lo + (hi - lo) * i as f32 / n as f32;
        let exact = f64_fn(f64::from(x));
        if !exact.is_finite() {
            continue;
        }
        worst = worst.max(ulps(f32_fn(x), exact));
    }
    println!("libm {name:<8} on [{lo}, {hi}]: max error {worst:.2} ulp");
    worst
}

#[test]
fn libm_functions_used_by_the_core_are_accurate() {
    let mut worst = 0.0f64;
    for n in [1.419f32, 1.5, 2.5, 3.05869] {
        worst = worst.max(sweep(
            &format!("powf^{n}"),
            1e-4,
            300.0,
            |x| libm::powf(x, n),
            |x| x.powf(f64::from(n)),
        ));
    }
    worst = worst.max(sweep("expm1f", -20.0, 20.0, libm::expm1f, f64::exp_m1));
    worst = worst.max(sweep("log1pf", -0.99, 20.0, libm::log1pf, f64::ln_1p));
    worst = worst.max(sweep("tanhf", 0.01, 20.0, libm::tanhf, f64::tanh));
    worst = worst.max(sweep("tanf", 0.01, 1.5, libm::tanf, f64::tan));
    worst = worst.max(sweep("atanhf", 0.01, 0.999, libm::atanhf, f64::atanh));
    worst = worst.max(sweep("atanf", 0.01, 20.0, libm::atanf, f64::atan));
    worst = worst.max(sweep("sqrtf", 0.0, 1e4, libm::sqrtf, f64::sqrt));
    assert!(worst <= 4.0, "a libm function is off by {worst} ulp");
}

/// The core's own f32 power (`piezo_core::math::pow_nonnegative`), used on the per-sample path in
/// place of libm's f64-based `powf`: relative error against f64.
#[test]
fn f32_power_of_the_core_is_accurate() {
    let samples = 400_000;
    for n in [1.419f32, 1.5, 2.5, 3.05869, 4.0] {
        let mut worst = 0.0f64;
        for i in 0..=samples {
            // Log-spaced over [1e-4, 1e4].
            let x = 10f32.powf(-4.0 + 8.0 * i as f32 / samples as f32);
            let exact = f64::from(x).powf(f64::from(n));
            let got = f64::from(piezo_core::math::pow_nonnegative(x, n));
            worst = worst.max(((got - exact) / exact).abs());
        }
        println!("core pow_nonnegative x^{n} on [1e-4, 1e4]: max relative error {worst:.2e}");
        assert!(
            worst <= 1.5e-7 * f64::from(n),
            "x^{n}: relative error {worst:e}"
        );
    }
}
