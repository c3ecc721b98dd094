//! Two-axis compliant stage of seed 002 (MODELS.md §3): two PI P-887 stacks with Bouc-Wen hysteresis
//! (n = 1) driving a monolithic Al 7075-T6 flexure mechanism, after the paper's Lagrange model (eq. 1–4).
//!
//! **Mechanics, per axis** (the paper's eq. 2–4 read for one axis; the x and y chains use the same form
//! with their own masses). Generalised coordinates q = [x1, φ1, x2, x3]: lever pivot translation x1 and
//! rotation φ1 (two levers of mass m1, length L1, input arm b1), the link bodies x2 (two of mass m2) and
//! the platform x3 (mass m3, the measured output):
//!
//! T = m1·ẋ1² + m1·ẋ1·φ̇1·L1 + (m1·L1²/4 + I1)·φ̇1² + m2·ẋ2² + m3·ẋ3²/2,  I1 = m1·L1²/12,
//! Π = kx·x1² + 3kφ·φ1² + kx·(x2 − x3)² + kx·(x1 − x2 + L1·φ1)² + ks·(x1 + b1·φ1 − η)² + kg·x3²,
//! Φ = τd·(Π with η̇, q̇ in place of η, q) (stiffness-proportional damping),
//!
//! and Lagrange's equation (1) gives M·q̈ + C·q̇ + K·q = f·η + τd·f·η̇. Departures from the printed (garbled)
//! eq. 3–4, stated as readings: the stack acts through its own stiffness ks (the paper writes kx), the
//! platform has parallelogram guide stiffness kg (the paper's stiffness-reducing chains 7 and 8, without
//! which x3 has no restoring force), the x and y chains do not share coordinates (the paper: "mutually
//! independent"; coupling is a separate effect), and damping is stiffness-proportional.
//!
//! **Stack** (P-887.91, 10×10×36 mm, +38 µm free stroke at 120 V): free elongation η = d·(u − h) with
//! ḣ = α·u̇ − β·|u̇|·h − γ·u̇·|h| (seed 002 eq. 5, n = 1, h in volts); d is set so that the first loading
//! 0 → 120 V gives exactly 38 µm free stroke.
//!
//! **Chosen values** (Al 7075-T6: E = 71.7 GPa, ρ = 2810 kg/m³): lever m1 = 4 g (≈ 30×10×5 mm), link m2 = 8 g,
//! platform m3 = 50 g for x (platform 5, ≈ 40×40×11 mm) and 120 g for y (platform 6 carries the x stack,
//! its chain and platform 5); L1 = 18.37 mm, b1 = 10 mm (lever ratio 1.84, giving a static gain of 1.684 and
//! so ≈ 64 µm at 120 V); kx = 5e7 N/m (axial stiffness of a 0.5 mm notch hinge, 10 mm wide); kφ = 5 N·m/rad
//! (Paros–Weisbord, t = 0.5 mm, R = 1 mm, b = 10 mm: ≈ 4.5); ks = 1e8 N/m (100 N/µm, stack stiffness of
//! the datasheet's order); kg = 1e6 N/m (four leaf springs); τd = 3.5e-6 s (ζ ≈ 3.5 % x, 2.4 % y on the
//! first mode). First modes ≈ 3.2 kHz (x) and 2.2 kHz (y); highest ≈ 45 kHz.
//!
//! **Hysteresis fitted** (static, to the five figures of MODELS.md §3): x: α = 0.18522, β = 0.029586,
//! γ = −0.020710; y: α = 0.16792, β = 0.025721, γ = −0.018005 (β + γ = 0.3·β > 0: bounded class).
//! 0 → 120 → 0 V in 10 V steps: largest opening 8.20 µm (x) / 7.36 µm (y), at 40 V; 12 V loop
//! 0.332 / 0.271 µm; maximum 64.0 µm. At 80 V the opening is 7.37 / 6.59 µm (90 % of the largest).
//!
//! **Why the largest opening is not at 80 V (the paper's value) with this map.** With n = 1 and an
//! output affine in (u, h), as here (η = d·(u − h)), the opening of a 0 → U → 0 loop is
//! d·(h_asc(u) − h_desc(u)). While h_desc > 0 its slope is α + (β − γ)·h > α − (β + γ)·h_asc, so
//! the opening grows as u falls; after h_desc crosses zero at u0 both branches obey
//! dh/du = α − (β + γ)·|h| with h_asc(u) = H(u), h_desc(u) = −H(u0 − u), so the opening is extremal
//! where h_desc = −h_asc, at exactly **u* = u0/2 < U/2 = 60 V** (and at 0 V if h_desc never
//! crosses zero). That holds for every α, β, γ, so no refit reaches 80 V; here u0 = 89.2 V (x)
//! and 86.0 V (y), u* = 44.6 / 43.0 V (40 V on the 10 V grid). The paper's text also says "at 80 V" for the 0–12 V loop, which cannot be
//! (2/3 of the span in both cases, or a copy slip), so the location is the weakest of the figures.
//!
//! **A physical way to 80 V, kept as a variant** ([`XyStage::paper_opening_at_80v`]): the stacks'
//! piezo coefficient rises with field (soft PZT: the large-signal d33 exceeds the small-signal one),
//! d(u) = d0·(1 + a·u), which weights the hysteretic part by (1 + a·u). With a = 0.002 /V (d +24 %
//! over 0–120 V) and the n = 1 stacks refitted (x: α = 0.15362, β = 0.057946, γ = −0.055356; y:
//! α = 0.15733, β = 0.035710, γ = −0.033560), all five figures are met and the largest opening is
//! at 80 V (`host-sim/reference/tests/plants.rs`). It is not the default: piezo-core's static map
//! y = k1·u + k2·h has no (1 + a·u)·h term, so the demo's compensator built from the plant's stack
//! parameters, and the firmware's parameter file copied from them, would no longer match the plant.

use super::{drive, HeldLinear, InputAt, Plant, PlantError};
use crate::bouc_wen::BoucWen;

/// One axis: lever-amplified flexure chain driven by one stack.
#[derive(Debug, Clone, PartialEq)]
pub struct XyAxis {
    /// m1 (each of two levers), kg.
    pub lever_mass_kg: f64,
    /// m2 (each of two links), kg.
    pub link_mass_kg: f64,
    /// m3, kg.
    pub platform_mass_kg: f64,
    /// L1, m.
    pub lever_output_arm_m: f64,
    /// b1, m.
    pub lever_input_arm_m: f64,
    /// kx, N/m.
    pub hinge_stiffness_n_per_m: f64,
    /// kφ, N·m/rad.
    pub hinge_rotational_stiffness_nm_per_rad: f64,
    /// ks, N/m.
    pub stack_stiffness_n_per_m: f64,
    /// kg, N/m.
    pub guide_stiffness_n_per_m: f64,
    /// τd, s.
    pub damping_time_constant_s: f64,
    /// Free stroke at the rated voltage, m.
    pub free_stroke_m: f64,
    /// Rated voltage, V.
    pub rated_voltage_v: f64,
    /// a, 1/V: field dependence of the stack's piezo coefficient, d(u) = d0·(1 + a·u) (0: constant).
    pub stack_gain_slope_per_v: f64,
    /// Bouc-Wen, n = 1, h in V.
    pub hysteresis: BoucWen,
}

/// Derived matrices of one axis.
#[derive(Debug, Clone, PartialEq)]
struct AxisModel {
    minv: [[f64; 4]; 4],
    k: [[f64; 4]; 4],
    f: [f64; 4],
    tau: f64,
    d_m_per_v: f64,
    gain_slope_per_v: f64,
    static_gain: f64,
    bw: BoucWen,
}

#[allow(clippy::needless_range_loop)] // index form mirrors the matrix algebra
fn solve4(a: [[f64; 4]; 4], b: [f64; 4]) -> [f64; 4] {
    let mut m = [[0.0; 5]; 4];
    for i in 0..4 {
        m[i][..4].copy_from_slice(&a[i]);
        m[i][4] = b[i];
    }
    for i in 0..4 {
        let p = (i..4)
            .max_by(|&r, &s| m[r][i].abs().total_cmp(&m[s][i].abs()))
            .unwrap_or(i);
        m.swap(i, p);
        for r in 0..4 {
            if r != i {
                let f = m[r][i] / m[i][i];
                for c in i..5 {
                    m[r][c] -= f * m[i][c];
                }
            }
        }
    }
    std::array::from_fn(|i| m[i][4] / m[i][i])
}

impl XyAxis {
    fn model(&self) -> AxisModel {
        let (m1, m2, m3) = (self.lever_mass_kg, self.link_mass_kg, self.platform_mass_kg);
        let (l1, b1) = (self.lever_output_arm_m, self.lever_input_arm_m);
        let i1 = m1 * l1 * l1 / 12.0;
        let m = [
            [2.0 * m1, m1 * l1, 0.0, 0.0],
            [m1 * l1, m1 * l1 * l1 / 2.0 + 2.0 * i1, 0.0, 0.0],
            [0.0, 0.0, 2.0 * m2, 0.0],
            [0.0, 0.0, 0.0, m3],
        ];
        let mut k = [[0.0; 4]; 4];
        let mut add = |v: [f64; 4], s: f64| {
            for i in 0..4 {
                for j in 0..4 {
                    k[i][j] += 2.0 * s * v[i] * v[j];
                }
            }
        };
        let kx = self.hinge_stiffness_n_per_m;
        let ks = self.stack_stiffness_n_per_m;
        add([1.0, 0.0, 0.0, 0.0], kx);
        add(
            [0.0, 1.0, 0.0, 0.0],
            3.0 * self.hinge_rotational_stiffness_nm_per_rad,
        );
        add([0.0, 0.0, 1.0, -1.0], kx);
        add([1.0, l1, -1.0, 0.0], kx);
        add([1.0, b1, 0.0, 0.0], ks);
        add([0.0, 0.0, 0.0, 1.0], self.guide_stiffness_n_per_m);
        let f = [2.0 * ks, 2.0 * ks * b1, 0.0, 0.0];
        let cols: [[f64; 4]; 4] = std::array::from_fn(|j| {
            let mut e = [0.0; 4];
            e[j] = 1.0;
            solve4(m, e)
        });
        let minv = std::array::from_fn(|i| std::array::from_fn(|j| cols[j][i]));
        let static_gain = solve4(k, f)[3];
        let h_rated = self.hysteresis.jump(0.0, 0.0, self.rated_voltage_v);
        let a = self.stack_gain_slope_per_v;
        let d_m_per_v = self.free_stroke_m
            / ((1.0 + a * self.rated_voltage_v) * (self.rated_voltage_v - h_rated));
        AxisModel {
            minv,
            k,
            f,
            tau: self.damping_time_constant_s,
            d_m_per_v,
            gain_slope_per_v: a,
            static_gain,
            bw: self.hysteresis,
        }
    }
}

impl AxisModel {
    /// x = [q(4), q̇(4), h]; `hysteresis_rate` is the rate of the Bouc-Wen operator's input
    /// (u̇, or v̇ of the stack's dielectric lag).
    #[allow(clippy::needless_range_loop)] // index form mirrors M·q̈ = f − K·q
    #[allow(clippy::too_many_arguments)]
    fn rhs(
        &self,
        u: f64,
        du: f64,
        hysteresis_rate: f64,
        rate_scale_v_per_s: f64,
        e: f64,
        x: &[f64],
        dx: &mut [f64],
    ) {
        let (ud, dud) = drive(u, du, e);
        // α·(1 + |v̇|/ṙ₀)·v̇: the rate-dependent Bouc-Wen's extra switching at speed.
        let dh = self
            .bw
            .rate_with_speed_gain(x[8], hysteresis_rate, rate_scale_v_per_s);
        let a = self.gain_slope_per_v;
        let eta = self.d_m_per_v * (1.0 + a * ud) * (ud - x[8]);
        let deta = self.d_m_per_v * (a * dud * (ud - x[8]) + (1.0 + a * ud) * (dud - dh));
        let mut force = [0.0; 4];
        for i in 0..4 {
            let mut s = self.f[i] * (eta + self.tau * deta);
            for j in 0..4 {
                s -= self.k[i][j] * (x[j] + self.tau * x[4 + j]);
            }
            force[i] = s;
        }
        for i in 0..4 {
            dx[i] = x[4 + i];
            dx[4 + i] = (0..4).map(|j| self.minv[i][j] * force[j]).sum();
        }
        dx[8] = dh;
    }
}

/// The XY stage. States: x axis [q(4), q̇(4), h] then y axis likewise (18), then, with the
/// dielectric lag, the lagged stack voltages v_x, v_y (20).
///
/// **Dielectric lag** (effect `dielectric-lag`, [`XyStage::dielectric_lag_s`] = τ_v > 0): the
/// stacks' domain switching follows the voltage through the stack's dielectric relaxation, so the
/// Bouc-Wen operator is driven by a first-order lag of the stack voltage,
/// τ_v·v̇ = u − v, ḣ = α·v̇ − β·|v̇|·h − γ·v̇·|h|, while the linear piezo strain d·u follows u at
/// once: η = d·(u − h(v)). The loop opens wider and tilts as the rate rises (rate-dependent
/// hysteresis); at rest v = u. The core's models carry no such lag.
///
/// **Rate-dependent Bouc-Wen** (effect `rate-bouc-wen`, [`XyStage::hysteresis_rate_scale_v_per_s`]
/// = ṙ₀ > 0): the operator's gain grows with the input's speed, ḣ = α·(1 + |u̇|/ṙ₀)·u̇ −
/// β·|u̇|·h − γ·u̇·|h| (the rate-dependent Bouc-Wen models whose parameters are functions of the
/// input rate, here the simplest, α linear in |u̇|): the faster the drive, the more the domains
/// switch per volt and the wider and taller the hysteretic part of the loop; at slow rates the
/// standard operator. With the dielectric lag, u̇ is v̇. A voltage step moves h as the standard
/// operator does (a step has no finite speed). ṙ₀ = 1e5 V/s raises α up to 1.38 times on a
/// 100 Hz, 0–120 V sine; a much smaller ṙ₀ makes the stack move backwards at speed (not a
/// stack). The core's models carry no such form.
#[derive(Debug, Clone, PartialEq)]
pub struct XyStage {
    x_axis: XyAxis,
    y_axis: XyAxis,
    models: [AxisModel; 2],
    /// Output coupling (effect): measured x += κ_xy·y_platform, measured y += κ_yx·x_platform.
    pub coupling: [f64; 2],
    /// Electrostrictive coefficient e, 1/V (effect).
    pub electrostriction_per_v: f64,
    /// τ_v of the stacks' dielectric lag, s (effect; 0: none).
    pub dielectric_lag_s: f64,
    /// ṙ₀ of the rate-dependent Bouc-Wen, V/s (effect; 0: none).
    pub hysteresis_rate_scale_v_per_s: f64,
}

impl Default for XyStage {
    fn default() -> Self {
        let base = XyAxis {
            lever_mass_kg: 4e-3,
            link_mass_kg: 8e-3,
            platform_mass_kg: 0.05,
            lever_output_arm_m: 18.37e-3,
            lever_input_arm_m: 10e-3,
            hinge_stiffness_n_per_m: 5e7,
            hinge_rotational_stiffness_nm_per_rad: 5.0,
            stack_stiffness_n_per_m: 1e8,
            guide_stiffness_n_per_m: 1e6,
            damping_time_constant_s: 3.5e-6,
            free_stroke_m: 38e-6,
            rated_voltage_v: 120.0,
            stack_gain_slope_per_v: 0.0,
            hysteresis: BoucWen {
                a: 0.18522,
                beta: 0.029586,
                gamma: -0.020710,
                n: 1.0,
            },
        };
        let y = XyAxis {
            platform_mass_kg: 0.12,
            hysteresis: BoucWen {
                a: 0.16792,
                beta: 0.025721,
                gamma: -0.018005,
                n: 1.0,
            },
            ..base.clone()
        };
        // Valid by construction (checked by the `default_parameters_are_valid` test).
        let models = [base.model(), y.model()];
        Self {
            x_axis: base,
            y_axis: y,
            models,
            coupling: [0.0; 2],
            electrostriction_per_v: 0.0,
            dielectric_lag_s: 0.0,
            hysteresis_rate_scale_v_per_s: 0.0,
        }
    }
}

impl XyStage {
    /// Validates both axes (positive masses, stiffnesses, arms, stroke and rated voltage; n = 1; bounded class).
    pub fn new(x_axis: XyAxis, y_axis: XyAxis) -> Result<Self, PlantError> {
        for a in [&x_axis, &y_axis] {
            let checks = [
                ("lever_mass_kg", a.lever_mass_kg),
                ("link_mass_kg", a.link_mass_kg),
                ("platform_mass_kg", a.platform_mass_kg),
                ("lever_output_arm_m", a.lever_output_arm_m),
                ("lever_input_arm_m", a.lever_input_arm_m),
                ("hinge_stiffness_n_per_m", a.hinge_stiffness_n_per_m),
                (
                    "hinge_rotational_stiffness_nm_per_rad",
                    a.hinge_rotational_stiffness_nm_per_rad,
                ),
                ("stack_stiffness_n_per_m", a.stack_stiffness_n_per_m),
                ("guide_stiffness_n_per_m", a.guide_stiffness_n_per_m),
                ("free_stroke_m", a.free_stroke_m),
                ("rated_voltage_v", a.rated_voltage_v),
            ];
            for (name, value) in checks {
                if !(value > 0.0 && value.is_finite()) {
                    return Err(PlantError::BadParameter { name, value });
                }
            }
            if !(a.damping_time_constant_s >= 0.0) {
                return Err(PlantError::BadParameter {
                    name: "damping_time_constant_s",
                    value: a.damping_time_constant_s,
                });
            }
            // d(u) must stay positive over the stacks' −30..130 V.
            if !(a.stack_gain_slope_per_v >= 0.0 && a.stack_gain_slope_per_v < 1.0 / 30.0) {
                return Err(PlantError::BadParameter {
                    name: "stack_gain_slope_per_v",
                    value: a.stack_gain_slope_per_v,
                });
            }
            if a.hysteresis.n != 1.0 || !a.hysteresis.is_bounded_class() {
                return Err(PlantError::BadParameter {
                    name: "hysteresis (n = 1, bounded class)",
                    value: a.hysteresis.n,
                });
            }
        }
        let models = [x_axis.model(), y_axis.model()];
        Ok(Self {
            x_axis,
            y_axis,
            models,
            coupling: [0.0; 2],
            electrostriction_per_v: 0.0,
            dielectric_lag_s: 0.0,
            hysteresis_rate_scale_v_per_s: 0.0,
        })
    }

    /// The variant whose largest 0–120 V loop opening is at 80 V, as the paper reports: stack
    /// gain rising with field, a = 0.002 /V, and n = 1 stacks refitted to the five figures (see the
    /// module doc for why the default cannot put it there and why this is not the default).
    pub fn paper_opening_at_80v() -> Self {
        let base = Self::default();
        let (x, y) = base.axes();
        let with = |axis: &XyAxis, a: f64, beta: f64, gamma: f64| XyAxis {
            stack_gain_slope_per_v: 0.002,
            hysteresis: BoucWen {
                a,
                beta,
                gamma,
                n: 1.0,
            },
            ..axis.clone()
        };
        let x = with(x, 0.15362, 0.057946, -0.055356);
        let y = with(y, 0.15733, 0.035710, -0.033560);
        let models = [x.model(), y.model()];
        Self {
            x_axis: x,
            y_axis: y,
            models,
            coupling: [0.0; 2],
            electrostriction_per_v: 0.0,
            dielectric_lag_s: 0.0,
            hysteresis_rate_scale_v_per_s: 0.0,
        }
    }

    /// Axis parameters (x, y).
    pub fn axes(&self) -> (&XyAxis, &XyAxis) {
        (&self.x_axis, &self.y_axis)
    }

    /// Static platform displacement per unit free stack elongation (x, y).
    pub fn static_gain(&self) -> [f64; 2] {
        [self.models[0].static_gain, self.models[1].static_gain]
    }

    /// Stack gain d (d0 at 0 V when `stack_gain_slope_per_v` ≠ 0), m/V (x, y).
    pub fn stack_gain_m_per_v(&self) -> [f64; 2] {
        [self.models[0].d_m_per_v, self.models[1].d_m_per_v]
    }
}

impl Plant for XyStage {
    fn name(&self) -> &'static str {
        "xy-stage"
    }
    fn input_names(&self) -> &'static [&'static str] {
        &["ux_V", "uy_V"]
    }
    fn output_names(&self) -> &'static [&'static str] {
        &["x_m", "y_m"]
    }
    fn state_dim(&self) -> usize {
        if self.dielectric_lag_s > 0.0 {
            20
        } else {
            18
        }
    }
    fn initial_state(&self, x: &mut [f64]) {
        x.fill(0.0);
    }
    fn rhs(&self, t: f64, x: &[f64], input: &dyn InputAt, dx: &mut [f64]) {
        for axis in 0..2 {
            let (u, du) = input.input(axis, t);
            // The operator's input rate: u̇, or v̇ = (u − v)/τ_v behind the dielectric lag.
            let hysteresis_rate = if self.dielectric_lag_s > 0.0 {
                let dv = (u - x[18 + axis]) / self.dielectric_lag_s;
                dx[18 + axis] = dv;
                dv
            } else {
                du
            };
            let r = axis * 9..axis * 9 + 9;
            self.models[axis].rhs(
                u,
                du,
                hysteresis_rate,
                self.hysteresis_rate_scale_v_per_s,
                self.electrostriction_per_v,
                &x[r.clone()],
                &mut dx[r],
            );
        }
    }
    fn input_jump(&self, x: &mut [f64], channel: usize, u_from: f64, u_to: f64) {
        if self.dielectric_lag_s > 0.0 {
            // v is continuous: a voltage step moves h only as v follows it.
            return;
        }
        let i = channel.min(1) * 9 + 8;
        x[i] = self.models[channel.min(1)].bw.jump(x[i], u_from, u_to);
    }
    fn output(&self, x: &[f64], _u: &[f64], y: &mut [f64]) {
        y[0] = x[3] + self.coupling[0] * x[12];
        y[1] = x[12] + self.coupling[1] * x[3];
    }
    fn free_displacement(&self, x: &[f64], u: &[f64], out: &mut [f64]) {
        for axis in 0..2 {
            let m = &self.models[axis];
            let (ud, _) = drive(u[axis], 0.0, self.electrostriction_per_v);
            out[axis] = m.static_gain
                * m.d_m_per_v
                * (1.0 + m.gain_slope_per_v * ud)
                * (ud - x[axis * 9 + 8]);
        }
    }
    fn default_sample_rate_hz(&self) -> f64 {
        10_000.0
    }
    fn check_input_span(&self, u_min_v: f64, u_max_v: f64) -> Result<(), PlantError> {
        // P-887 stacks: −30 V .. 130 V is the manufacturer's allowed range.
        if u_min_v < -30.0 || u_max_v > 130.0 {
            return Err(PlantError::InputOutOfRange {
                plant: "xy-stage",
                span_v: u_max_v - u_min_v,
                max_span_v: 160.0,
                reason: "P-887 stacks accept -30 V .. 130 V",
            });
        }
        Ok(())
    }
    /// Per axis, with u held: η is constant (it depends on u and the frozen h only), so
    /// q̇ = v, v̇ = M⁻¹·(f·η − K·q − τd·K·v), ḣ = 0; the free displacement G·d·(1 + a·u)·(u − h) is
    /// constant (F = 0). This holds for the field-dependent variant and with electrostriction too.
    fn held_input_linear(&self) -> Option<HeldLinear> {
        if self.dielectric_lag_s > 0.0 {
            // h moves while v follows a held u: not linear between holds.
            return None;
        }
        let n = self.state_dim();
        let mut a = vec![0.0; n * n];
        for (axis, m) in self.models.iter().enumerate() {
            let o = axis * 9;
            for i in 0..4 {
                a[(o + i) * n + o + 4 + i] = 1.0;
                for j in 0..4 {
                    // ∂v̇_i/∂q_j = −(M⁻¹·K)_ij, ∂v̇_i/∂v_j = −τd·(M⁻¹·K)_ij.
                    let mk: f64 = (0..4).map(|l| m.minv[i][l] * m.k[l][j]).sum();
                    a[(o + 4 + i) * n + o + j] = -mk;
                    a[(o + 4 + i) * n + o + 4 + j] = -m.tau * mk;
                }
            }
        }
        Some(HeldLinear {
            a,
            free_displacement: vec![0.0; 2 * n],
        })
    }
    fn set_electrostriction(&mut self, per_v: f64) {
        self.electrostriction_per_v = per_v;
    }
}
