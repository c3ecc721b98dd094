//! A bipolar piezo stack whose *whole* strain relaxes: its loops widen as the drive frequency
//! rises, with one structural mode near 740 Hz and a stiffening strain the Bouc-Wen model does
//! not have — the stand-in for a measured actuator whose static fit leaves 1–2 % of its span.
//!
//! **Drive** (the amplifier's output resistance R charging the stack capacitance C): the voltage
//! on the stack's electrodes lags the command u, τₐ·v̇ₐ = u − vₐ with τₐ = R·C.
//!
//! **Dielectric loss** (a discrete Debye spectrum, ε(ω) = ε∞ + Σ Δεᵢ/(1 + jωτᵢ)): the
//! polarisation follows vₐ partly at once and partly through K first-order relaxations,
//!
//! τᵢ·ṗᵢ = vₐ − pᵢ (i = 1..K),  P = w₀·vₐ + Σ wᵢ·pᵢ  (w₀ = 1 − Σ wᵢ > 0, at rest P = u).
//!
//! Both the linear strain and the domain switching follow the polarisation P (strain ∝ P for the
//! converse effect), so the hysteresis (Bouc-Wen, n = 1, h in volts) is driven by P,
//! ḣ = α·Ṗ − β·|Ṗ|·h − γ·Ṗ·|h|, and the *whole* elongation lags u. Unlike
//! [`super::BipolarStack`], whose hysteretic part alone relaxes and whose loops narrow, the phase of
//! the whole strain grows with frequency and the loop opens: the opening at u = 0 grows from 20
//! to 100 Hz (`tests/plants.rs`).
//!
//! **Stiffening** (rate-independent, odd: the extrinsic, domain-wall share of the piezo
//! coefficient grows with the field, the anhysteretic part of the Rayleigh law d = d₀ + α·|E|):
//! with x = P − h, the free elongation is η = d·(x + c·x³/X²), X = 90 V, monotone in x for every
//! c ≥ 0. The core's static map k1·u + k2·h + y0 and its even-order output term cannot follow x³,
//! so a static fit leaves a shape error (about 0.6 % of the span on 20 and 40 Hz records).
//!
//! **A second switching population** ([`RelaxingStack::shaped`], `relaxing-stack-shaped`): domains
//! that switch at low fields and saturate within a few volts of a reversal, a second Bouc-Wen
//! element h₂ driven by the same P, ḣ₂ = α₂·Ṗ − β₂·|Ṗ|·h₂ − γ₂·Ṗ·|h₂| (α₂ = 0.3,
//! β₂ = γ₂ = 0.1, |h₂| ≤ α₂/(β₂ + γ₂) = 1.5 V), and x = P − h − h₂. Each reversal curve then
//! bends at two scales (within ≈ 5 V and ≈ 40 V of the reversal), which one Bouc-Wen element
//! (one exponent n) cannot follow at every loop size of a rising-amplitude sweep: a
//! rate-independent shape error, in the fit and in every prediction alike. close-loop's base fit
//! of 20 and 40 Hz records leaves 0.8 % of the span (0.6 % without h₂; a measured actuator's
//! static fit, 2 %; a larger or slower-saturating h₂ is absorbed by the fitted exponent and
//! leaves less). dh₂/dP ≤ α₂ = 0.3, so dx/dP ≥ 1 − 0.36 − 0.3 > 0: the elongation stays
//! monotone in the voltage.
//!
//! **Mode** (force-driven): the measured tip displacement z obeys
//! z̈ + 2ζω·ż + ω²·(z − η) = 0, f = ω/2π = 740 Hz, ζ = 0.03.
//!
//! **Values.** τₐ = 80 µs (≈ 40 Ω on a 2 µF stack); relaxations 0.5 and 2 ms, weights 0.06 each
//! (w₀ = 0.88); c = 0.25; hysteresis α = 0.3, β = 0.015, γ = 0.01 (the bounded class,
//! |h| ≤ α/(β + γ) = 12 V; dh/dP ≤ α + (β − γ)·12 V = 0.36 < 1, so the elongation is monotone in
//! the voltage on every branch, as a stack's is); d chosen so that the first static sweep −90 → +90 V
//! spans 35 µm; valid for |u| ≤ 100 V.
//!
//! State: `[z, ż, h, vₐ, p₁, …, p_K]`, then h₂ for the shaped stack. A voltage step moves no state at once (vₐ is continuous),
//! so [`Plant::input_jump`] does nothing and the plant is integrated by the adaptive
//! Dormand–Prince pair over holds too.

use super::{drive, InputAt, Plant, PlantError};
use crate::bouc_wen::BoucWen;

/// Largest relaxation terms.
pub const MAX_RELAXATIONS: usize = 4;

/// Reference voltage X of the stiffening term, V.
const STIFFENING_REF_V: f64 = 90.0;

/// The relaxing stack. Build with [`RelaxingStack::new`] (checked) or [`Default`].
#[derive(Debug, Clone, PartialEq)]
pub struct RelaxingStack {
    drive_time_constant_s: f64,
    relaxation_times_s: Vec<f64>,
    relaxation_weights: Vec<f64>,
    stiffening: f64,
    mode_frequency_hz: f64,
    mode_damping: f64,
    hysteresis: BoucWen,
    /// The second switching population h₂ (the shaped stack), or none.
    second_hysteresis: Option<BoucWen>,
    d_m_per_v: f64,
    /// Electrostrictive coefficient e, 1/V (effect).
    pub electrostriction_per_v: f64,
}

/// The shaped stack's second Bouc-Wen element (module doc).
const SECOND_HYSTERESIS: BoucWen = BoucWen {
    a: 0.3,
    beta: 0.1,
    gamma: 0.1,
    n: 1.0,
};

impl RelaxingStack {
    /// The default stack on a mount ten times stiffer (`relaxing-stack-stiff`): its mode at
    /// 7.4 kHz, so that up to 100 Hz its resonance raises the gain by at most 0.02 % (the 740 Hz
    /// mode's: 1.9 %): the rate dependence that 20 and 40 Hz sines fix, without a mode they barely
    /// excite.
    pub fn stiff() -> Self {
        let mut p = Self::default();
        p.mode_frequency_hz *= 10.0;
        p
    }

    /// The default stack with a second switching population h₂ (module doc;
    /// `relaxing-stack-shaped`): a rate-independent shape error no core form has, span 35 µm.
    pub fn shaped() -> Self {
        let mut p = Self {
            second_hysteresis: Some(SECOND_HYSTERESIS),
            ..Self::default()
        };
        p.d_m_per_v = p.gain_for_span(35e-6);
        p
    }

    /// d (m/V) for which the first static sweep −90 → +90 V spans `span_m`.
    fn gain_for_span(&self, span_m: f64) -> f64 {
        let h_low = self.hysteresis.jump(0.0, 0.0, -90.0);
        let h_high = self.hysteresis.jump(h_low, -90.0, 90.0);
        let (g_low, g_high) = self.second_hysteresis.map_or((0.0, 0.0), |b| {
            let low = b.jump(0.0, 0.0, -90.0);
            (low, b.jump(low, -90.0, 90.0))
        });
        let c = self.stiffening;
        let shape = |x: f64| x + c * x * x * x / (STIFFENING_REF_V * STIFFENING_REF_V);
        span_m / (shape(90.0 - h_high - g_high) - shape(-90.0 - h_low - g_low))
    }
}

impl Default for RelaxingStack {
    fn default() -> Self {
        // Valid by construction (the `default_is_valid` test).
        Self::new(
            80e-6,
            &[0.5e-3, 2e-3],
            &[0.06, 0.06],
            0.25,
            740.0,
            0.03,
            35e-6,
        )
        .unwrap_or_else(|_| unreachable!("the default parameters are valid"))
    }
}

fn bad(name: &'static str, value: f64) -> PlantError {
    PlantError::BadParameter { name, value }
}

impl RelaxingStack {
    /// Checks and builds: a positive drive time constant τₐ (s); 0 to 4 (`MAX_RELAXATIONS`)
    /// positive relaxation times with positive weights summing to less than 1 (the rest follows at
    /// once); a stiffening c in [0, 1]; a
    /// positive mode frequency and damping ratio in (0, 1); a positive span (m) of the first static
    /// −90 → +90 V sweep.
    pub fn new(
        drive_time_constant_s: f64,
        times_s: &[f64],
        weights: &[f64],
        stiffening: f64,
        mode_frequency_hz: f64,
        mode_damping: f64,
        span_m: f64,
    ) -> Result<Self, PlantError> {
        if !(drive_time_constant_s > 0.0 && drive_time_constant_s.is_finite()) {
            return Err(bad("drive_time_constant_s", drive_time_constant_s));
        }
        if times_s.len() > MAX_RELAXATIONS || times_s.len() != weights.len() {
            return Err(bad(
                "relaxation terms (0..=4 times with one weight each)",
                times_s.len() as f64,
            ));
        }
        if let Some(&t) = times_s.iter().find(|&&t| !(t > 0.0 && t.is_finite())) {
            return Err(bad("relaxation_time_s", t));
        }
        if let Some(&w) = weights.iter().find(|&&w| !(w > 0.0 && w.is_finite())) {
            return Err(bad("relaxation_weight", w));
        }
        let sum: f64 = weights.iter().sum();
        if !(sum < 1.0) {
            return Err(bad("sum of relaxation weights (must be below 1)", sum));
        }
        if !(0.0..=1.0).contains(&stiffening) {
            return Err(bad("stiffening", stiffening));
        }
        if !(mode_frequency_hz > 0.0 && mode_frequency_hz.is_finite()) {
            return Err(bad("mode_frequency_hz", mode_frequency_hz));
        }
        if !(mode_damping > 0.0 && mode_damping < 1.0) {
            return Err(bad("mode_damping", mode_damping));
        }
        if !(span_m > 0.0 && span_m.is_finite()) {
            return Err(bad("span_m", span_m));
        }
        let hysteresis = BoucWen {
            a: 0.3,
            beta: 0.015,
            gamma: 0.01,
            n: 1.0,
        };
        let mut stack = Self {
            drive_time_constant_s,
            relaxation_times_s: times_s.to_vec(),
            relaxation_weights: weights.to_vec(),
            stiffening,
            mode_frequency_hz,
            mode_damping,
            hysteresis,
            second_hysteresis: None,
            d_m_per_v: 0.0,
            electrostriction_per_v: 0.0,
        };
        stack.d_m_per_v = stack.gain_for_span(span_m);
        Ok(stack)
    }

    /// d, m/V.
    pub fn stack_gain_m_per_v(&self) -> f64 {
        self.d_m_per_v
    }

    /// Drive time constant τₐ (s), relaxation times (s) and weights.
    pub fn relaxations(&self) -> (f64, &[f64], &[f64]) {
        (
            self.drive_time_constant_s,
            &self.relaxation_times_s,
            &self.relaxation_weights,
        )
    }

    /// Mode frequency (Hz) and damping ratio.
    pub fn mode(&self) -> (f64, f64) {
        (self.mode_frequency_hz, self.mode_damping)
    }

    /// The share w₀ of the polarisation that follows the stack voltage at once.
    fn instant_weight(&self) -> f64 {
        1.0 - self.relaxation_weights.iter().sum::<f64>()
    }

    /// Polarisation P (V) and its rate Ṗ (V/s) from the state and the command u.
    fn polarisation(&self, x: &[f64], u: f64) -> (f64, f64) {
        let va = x[3];
        let dva = (u - va) / self.drive_time_constant_s;
        let w0 = self.instant_weight();
        let (mut p, mut dp) = (w0 * va, w0 * dva);
        for (i, (&tau, &w)) in self
            .relaxation_times_s
            .iter()
            .zip(&self.relaxation_weights)
            .enumerate()
        {
            p += w * x[4 + i];
            dp += w * (va - x[4 + i]) / tau;
        }
        (p, dp)
    }

    /// Index of h₂ in the state (the shaped stack).
    fn second_index(&self) -> usize {
        4 + self.relaxation_times_s.len()
    }

    /// Free elongation η = d·(x + c·x³/X²), x = P' − h − h₂ (P' the polarisation through the
    /// electrostrictive drive; h₂ = 0 without the second population).
    fn eta(&self, p: f64, x_state: &[f64]) -> f64 {
        let (pd, _) = drive(p, 0.0, self.electrostriction_per_v);
        let h2 = if self.second_hysteresis.is_some() {
            x_state[self.second_index()]
        } else {
            0.0
        };
        let x = pd - x_state[2] - h2;
        self.d_m_per_v * (x + self.stiffening * x * x * x / (STIFFENING_REF_V * STIFFENING_REF_V))
    }
}

impl Plant for RelaxingStack {
    fn name(&self) -> &'static str {
        "relaxing-stack"
    }
    fn input_names(&self) -> &'static [&'static str] {
        &["u_V"]
    }
    fn output_names(&self) -> &'static [&'static str] {
        &["y_m"]
    }
    fn state_dim(&self) -> usize {
        4 + self.relaxation_times_s.len() + usize::from(self.second_hysteresis.is_some())
    }
    fn initial_state(&self, x: &mut [f64]) {
        x.fill(0.0);
    }
    fn rhs(&self, t: f64, x: &[f64], input: &dyn InputAt, dx: &mut [f64]) {
        let (u, _) = input.input(0, t);
        let (p, dp) = self.polarisation(x, u);
        dx[3] = (u - x[3]) / self.drive_time_constant_s;
        for (i, &tau) in self.relaxation_times_s.iter().enumerate() {
            dx[4 + i] = (x[3] - x[4 + i]) / tau;
        }
        let w = 2.0 * std::f64::consts::PI * self.mode_frequency_hz;
        let eta = self.eta(p, x);
        dx[0] = x[1];
        dx[1] = -2.0 * self.mode_damping * w * x[1] - w * w * (x[0] - eta);
        dx[2] = self.hysteresis.rate(x[2], dp);
        if let Some(second) = &self.second_hysteresis {
            let i = self.second_index();
            dx[i] = second.rate(x[i], dp);
        }
    }
    fn input_jump(&self, _x: &mut [f64], _channel: usize, _u_from: f64, _u_to: f64) {
        // vₐ is continuous: a voltage step moves h only as the stack charges.
    }
    fn output(&self, x: &[f64], _u: &[f64], y: &mut [f64]) {
        y[0] = x[0];
    }
    fn free_displacement(&self, x: &[f64], u: &[f64], out: &mut [f64]) {
        let (p, _) = self.polarisation(x, u[0]);
        out[0] = self.eta(p, x);
    }
    fn default_sample_rate_hz(&self) -> f64 {
        10_000.0
    }
    fn check_input_span(&self, u_min_v: f64, u_max_v: f64) -> Result<(), PlantError> {
        super::check_bipolar_span(
            "relaxing-stack",
            "the relaxing stack accepts -100 V .. 100 V",
            u_min_v,
            u_max_v,
        )
    }
    fn set_electrostriction(&mut self, per_v: f64) {
        self.electrostriction_per_v = per_v;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_is_valid_and_bad_parameters_are_refused() {
        let p = RelaxingStack::default();
        assert_eq!(p.state_dim(), 6);
        let ok = |tau_a: f64, w: &[f64], c: f64, z: f64| {
            RelaxingStack::new(tau_a, &[1e-3, 2e-3][..w.len()], w, c, 740.0, z, 35e-6).is_ok()
        };
        assert!(ok(1e-4, &[0.1], 0.1, 0.03));
        assert!(ok(1e-4, &[], 0.0, 0.03));
        assert!(!ok(0.0, &[0.1], 0.1, 0.03));
        assert!(!ok(1e-4, &[0.6, 0.4], 0.1, 0.03));
        assert!(!ok(1e-4, &[-0.1], 0.1, 0.03));
        assert!(!ok(1e-4, &[0.1], 1.01, 0.03));
        let shaped = RelaxingStack::shaped();
        assert_eq!(shaped.state_dim(), 7);
        assert!(shaped.second_hysteresis.is_some());
        assert!(!ok(1e-4, &[0.1], -0.1, 0.03));
        assert!(!ok(1e-4, &[0.1], f64::NAN, 0.03));
        assert!(!ok(1e-4, &[0.1], 0.1, 1.0));
        assert!(RelaxingStack::new(1e-4, &[1e-3], &[0.1, 0.1], 0.1, 740.0, 0.03, 35e-6).is_err());
    }
}
