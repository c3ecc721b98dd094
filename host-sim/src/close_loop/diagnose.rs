//! Diagnosis of a residual: one candidate regressor family per physical effect, ranked by the share of
//! the residual variance each explains when fitted (an error-reduction-ratio style term selection), a
//! whiteness test of what is left, and an estimate of the sensor noise.
//!
//! For the current model prediction ŷ, its hysteresis state h and the residual r = y − ŷ on the scored
//! samples, every candidate is fitted by linear least squares together with the nuisance basis
//! N = (1, u, h) (so that a candidate is not credited with what a refit of the linear map would take):
//!
//! share = 1 − SSE(r | N ∪ X) / SSE(r | N),
//!
//! with X, per effect (Ts the sample period, grids over the nonlinear parameter, best grid point kept):
//! - creep: x_τ\[k\] = a·x_τ\[k−1\] + (1 − a)·(u\[k−1\] − u\[0\]), a = e^(−Ts/τ), τ on a log grid from 4·Ts to
//!   a quarter of the record (one or two elements, greedy) — the core's creep bank driven by the input;
//!   and the logarithmic creep, the sum of twelve such elements half a decade apart from √10·Ts;
//! - drift, a function of time alone: t (linear) and 1 − e^(−t/τ) (settling, τ on a log grid from
//!   2.4 input periods to 2.5 records);
//! - delay: the prediction replaced by ŷ(t − D) (what adding the delay does; no free coefficient), D on
//!   a grid of 0.25–64 samples;
//! - asymmetry: (u[k−1] − u_mid)², u_mid the middle of the input range over the scored samples
//!   (u[−1] := u_mid; the core's even-order term on the previous command);
//! - dynamics: the prediction replaced by M_{f,ζ}\[ŷ\], M the unit-DC-gain second-order mode (no free
//!   coefficient), f on a log grid from 11× the dominant input frequency to 0.4/Ts,
//!   ζ ∈ {0.05, 0.1, 0.2, 0.4, 0.7, 1, 1.5, 2.5}, in both its forms: force-driven,
//!   z̈ + 2ζω·ż + ω²·(z − ŷ) = 0, and driven through the stack's spring and damper,
//!   z̈ + 2ζω·(ż − dŷ/dt) + ω²·(z − ŷ) = 0, i.e. z = ŷ + M\[−(d²ŷ/dt²)/ω²\] (the second
//!   derivative by central differences). Well below the mode the second form has no phase lag and
//!   moves the output by −(d²ŷ/dt²)/ω² alone, a gain that grows with the input's frequency: the
//!   force-driven form's lag 2ζ·f/f_mode would hide it;
//! - coupling: the other axis's prediction (two-axis records only).
//!
//! The screening only ranks and initialises candidates (its ΔBIC = N·ln(SSE₁/SSE₀) + p·ln N is
//! reported): whether an effect is added is decided on data the fit did not see (`select`).
//! The Ljung–Box statistic Q = N(N+2)·Σ_{l=1..20} ρ_l²/(N−l) (χ²₂₀ 95 % point 31.41) is reported too.
//!
//! Sensor noise: σ = 1.4826·median|Δ²r − median Δ²r| / √6 over the residual's second differences
//! (white noise of σ gives Var Δ²r = 6σ²; a smooth model error adds little, and the median ignores the
//! few samples around input steps).

// Small dense linear algebra reads best with index loops.
#![allow(clippy::needless_range_loop)]

/// The effects `close-loop` can add (names as in the report; serialised as [`EffectKind::name`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(into = "&'static str")]
pub enum EffectKind {
    /// Creep: first-order elements driven by the input (Kelvin–Voigt or logarithmic).
    Creep,
    /// Drift: a slow function of time that does not depend on u (linear or settling).
    Drift,
    /// Input (or sensor) delay.
    Delay,
    /// Even-order output term.
    Asymmetry,
    /// Second-order mode between hysteresis and output.
    Dynamics,
    /// Cross-axis coupling.
    Coupling,
    /// Rate-dependent hysteresis: the hysteresis output relaxes through a first-order lag.
    RateDependent,
}

impl EffectKind {
    /// All, in report order.
    pub const ALL: [EffectKind; 7] = [
        Self::Creep,
        Self::Drift,
        Self::Delay,
        Self::Asymmetry,
        Self::Dynamics,
        Self::Coupling,
        Self::RateDependent,
    ];

    /// Name in reports.
    pub fn name(self) -> &'static str {
        match self {
            Self::Creep => "creep",
            Self::Drift => "drift",
            Self::Delay => "delay",
            Self::Asymmetry => "asymmetry",
            Self::Dynamics => "dynamics",
            Self::Coupling => "coupling",
            Self::RateDependent => "rate-dependent hysteresis",
        }
    }
}

impl From<EffectKind> for &'static str {
    fn from(effect: EffectKind) -> Self {
        effect.name()
    }
}

/// Initial values of an effect's parameters, from its screening fit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum EffectInit {
    /// Creep elements (gain m/V, time constant s); a gain of 0 is an unused element.
    Creep {
        /// Gains \[m/V\].
        gains_m_per_v: [f64; 2],
        /// Time constants \[s\].
        time_constants_s: [f64; 2],
    },
    /// Logarithmic creep, t₀ = one sample period.
    LogCreep {
        /// g_log \[m/V per decade\].
        gain_m_per_v: f64,
    },
    /// Drift rate \[m/s\].
    Drift {
        /// Rate.
        rate_m_per_s: f64,
    },
    /// Settling drift A·(1 − e^(−t/τ)).
    Settling {
        /// A \[m\].
        amplitude_m: f64,
        /// τ \[s\].
        time_constant_s: f64,
    },
    /// Delay \[s\].
    Delay {
        /// Delay.
        delay_s: f64,
    },
    /// Even term e·(u\[k−1\] − centre)² on the previous command.
    Asymmetry {
        /// e \[m/V²\].
        coefficient_m_per_v2: f64,
        /// Centre u_c \[V\].
        center_v: f64,
    },
    /// Mode.
    Dynamics {
        /// Natural frequency \[Hz\].
        frequency_hz: f64,
        /// Damping ratio.
        damping: f64,
    },
    /// Coupling coefficient.
    Coupling {
        /// Coefficient.
        coefficient: f64,
    },
    /// Rate-dependent hysteresis: the hysteretic part k2·h of w relaxes, g·(first-order lag of
    /// k2·h, τ); screened as the coefficient c of the lag of h (g = c/k2).
    RateDependent {
        /// c \[m per unit h\].
        lag_coefficient_m: f64,
        /// τ \[s\].
        time_constant_s: f64,
    },
}

impl EffectInit {
    /// The effect these values belong to.
    pub fn kind(&self) -> EffectKind {
        match self {
            Self::Creep { .. } | Self::LogCreep { .. } => EffectKind::Creep,
            Self::Drift { .. } | Self::Settling { .. } => EffectKind::Drift,
            Self::Delay { .. } => EffectKind::Delay,
            Self::Asymmetry { .. } => EffectKind::Asymmetry,
            Self::Dynamics { .. } => EffectKind::Dynamics,
            Self::Coupling { .. } => EffectKind::Coupling,
            Self::RateDependent { .. } => EffectKind::RateDependent,
        }
    }

    /// The form in words.
    pub fn form(&self) -> &'static str {
        match self {
            Self::Creep { .. } => "Kelvin-Voigt",
            Self::LogCreep { .. } => "logarithmic",
            Self::Drift { .. } => "linear",
            Self::Settling { .. } => "exponential settling",
            _ => "",
        }
    }
}

/// What the model currently predicts, on the whole record (the scored part starts at `from`).
pub struct Signals<'a> {
    /// Times \[s\].
    pub t_s: &'a [f64],
    /// Input \[V\].
    pub u: &'a [f64],
    /// Measured output \[m\].
    pub y: &'a [f64],
    /// Current prediction \[m\].
    pub y_hat: &'a [f64],
    /// Current hysteresis state.
    pub h: &'a [f64],
    /// The other axis's z (two-axis records).
    pub other_y_hat: Option<&'a [f64]>,
    /// First scored sample.
    pub from: usize,
    /// Sample period \[s\].
    pub sample_period_s: f64,
    /// First sample of each record (`[0]` for one record): a filter of the prediction (the
    /// delay's, the mode's) starts again from rest at each, as the model's simulation does.
    pub segments: &'a [usize],
}

/// `filter` run on each record of `s` on its own (records starting at `segments`), so that no
/// record's state, nor the step between two records' sensor offsets, carries into the next.
pub fn per_record(s: &[f64], segments: &[usize], filter: impl Fn(&[f64]) -> Vec<f64>) -> Vec<f64> {
    let n = s.len();
    let mut out = Vec::with_capacity(n);
    let starts = segments.iter().copied().filter(|&a| a > 0 && a < n);
    let mut a = 0;
    for b in starts.chain(std::iter::once(n)) {
        if b > a {
            out.extend(filter(&s[a..b]));
            a = b;
        }
    }
    out
}

/// One screened candidate.
#[derive(Debug, Clone)]
pub struct Candidate {
    /// Effect.
    pub effect: EffectKind,
    /// Share of the residual variance explained.
    pub share: f64,
    /// ΔBIC of adding it.
    pub delta_bic: f64,
    /// Initial parameters.
    pub init: EffectInit,
    /// What was tested, in words.
    pub test: &'static str,
    /// The screening's figures (name, value), for the report.
    pub figures: Vec<(&'static str, f64)>,
}

/// Least squares of `r` on the columns `basis` (all of length N): returns (SSE, coefficients).
pub fn least_squares(basis: &[&[f64]], r: &[f64]) -> (f64, Vec<f64>) {
    let p = basis.len();
    // Scale columns for conditioning.
    let scale: Vec<f64> = basis
        .iter()
        .map(|c| {
            let s = (c.iter().map(|v| v * v).sum::<f64>() / c.len().max(1) as f64).sqrt();
            if s > 0.0 && s.is_finite() {
                s
            } else {
                1.0
            }
        })
        .collect();
    let mut a = vec![vec![0.0; p + 1]; p];
    for k in 0..r.len() {
        for i in 0..p {
            let xi = basis[i][k] / scale[i];
            for j in i..p {
                a[i][j] += xi * basis[j][k] / scale[j];
            }
            a[i][p] += xi * r[k];
        }
    }
    for i in 0..p {
        for j in 0..i {
            a[i][j] = a[j][i];
        }
        // Tiny ridge against exactly collinear columns.
        a[i][i] += 1e-12 * (a[i][i] + 1e-300);
    }
    let coef = crate::optimise::linear::solve(&mut a, p)
        .unwrap_or_else(|| vec![0.0; p])
        .iter()
        .zip(&scale)
        .map(|(c, s)| c / s)
        .collect::<Vec<f64>>();
    let mut sse = 0.0;
    for k in 0..r.len() {
        let fit: f64 = (0..p).map(|i| coef[i] * basis[i][k]).sum();
        sse += (r[k] - fit).powi(2);
    }
    (sse, coef)
}

/// First-order low-pass of the input as the core's creep element computes it.
pub fn creep_element(u: &[f64], tau_s: f64, ts: f64) -> Vec<f64> {
    let a = (-ts / tau_s).exp();
    let u0 = u.first().copied().unwrap_or(0.0);
    let mut x = 0.0;
    let mut out = Vec::with_capacity(u.len());
    let mut prev = u0;
    for &v in u {
        x = a * x + (1.0 - a) * (prev - u0);
        out.push(x);
        prev = v;
    }
    out
}

/// `s` delayed by `d` samples (linear interpolation; before the start the first sample).
pub fn delayed(s: &[f64], d: f64) -> Vec<f64> {
    let whole = d.floor() as usize;
    let frac = d - d.floor();
    (0..s.len())
        .map(|k| {
            let at = |i: isize| s[i.max(0) as usize];
            let i = k as isize - whole as isize;
            (1.0 - frac) * at(i) + frac * at(i - 1)
        })
        .collect()
}

/// The unit-DC-gain mode z̈ + 2ζω ż + ω² z = ω² s, exact for piecewise-constant s (f64 reference of the
/// core's discretisation): with s\[k\] held over the period, z\[k\] is the state at its middle (the core's
/// choice, which adds no half-sample delay); from rest at s\[0\].
pub fn mode_filter(s: &[f64], frequency_hz: f64, damping: f64, ts: f64) -> Vec<f64> {
    let w = 2.0 * std::f64::consts::PI * frequency_hz;
    // With s held, e = z − s obeys ė = ż, v̇ = −ω²·e − 2ζω·v: (e, v) ← Φ_half·(e, v) per half period.
    let phi = mode_transition(w, damping, 0.5 * ts);
    let s0 = s.first().copied().unwrap_or(0.0);
    let (mut z, mut v) = (s0, 0.0);
    let half = |z: f64, v: f64, hold: f64| {
        let e = z - hold;
        (
            phi[0][0] * e + phi[0][1] * v + hold,
            phi[1][0] * e + phi[1][1] * v,
        )
    };
    s.iter()
        .map(|&hold| {
            let (zm, vm) = half(z, v, hold);
            (z, v) = half(zm, vm, hold);
            zm
        })
        .collect()
}

/// d²s/dt² by central differences (s\[k+1\] − 2·s\[k\] + s\[k−1\])/Ts², the end samples taking
/// their neighbour's.
pub fn second_derivative(s: &[f64], ts: f64) -> Vec<f64> {
    let n = s.len();
    if n < 3 {
        return vec![0.0; n];
    }
    let inner = |k: usize| (s[k + 1] - 2.0 * s[k] + s[k - 1]) / (ts * ts);
    (0..n).map(|k| inner(k.clamp(1, n - 2))).collect()
}

/// Φ = e^(A·Ts) of A = [[0, 1], [−ω², −2ζω]].
pub fn mode_transition(w: f64, zeta: f64, ts: f64) -> [[f64; 2]; 2] {
    // e^(At) = e^(−σt)·[(c + σ·S)·I + S·(A + σI)], σ = ζω, c = cos(ω_d t), S = sin(ω_d t)/ω_d
    // (cosh/sinh when overdamped, c = 1 and S = t when critically damped).
    let sigma = zeta * w;
    let disc = zeta * zeta - 1.0;
    let (c, s_over) = if disc < -1e-12 {
        let wd = w * (-disc).sqrt();
        ((wd * ts).cos(), (wd * ts).sin() / wd)
    } else if disc > 1e-12 {
        let wd = w * disc.sqrt();
        ((wd * ts).cosh(), (wd * ts).sinh() / wd)
    } else {
        (1.0, ts)
    };
    let e = (-sigma * ts).exp();
    [
        [e * (c + sigma * s_over), e * s_over],
        [-e * w * w * s_over, e * (c - sigma * s_over)],
    ]
}

/// Dominant input frequency \[Hz\] from the mean crossings of u over the scored part.
pub fn dominant_frequency_hz(u: &[f64], ts: f64) -> f64 {
    let n = u.len();
    if n < 4 {
        return 1.0 / (ts * n.max(1) as f64);
    }
    let mean = u.iter().sum::<f64>() / n as f64;
    let crossings = u
        .windows(2)
        .filter(|w| (w[0] - mean).signum() != (w[1] - mean).signum() && w[0] != mean)
        .count();
    (crossings.max(1) as f64 / 2.0) / (ts * n as f64)
}

/// Ljung–Box Q over lags 1..=`lags`.
pub fn ljung_box(r: &[f64], lags: usize) -> f64 {
    let n = r.len();
    if n <= lags + 1 {
        return 0.0;
    }
    let mean = r.iter().sum::<f64>() / n as f64;
    let c0: f64 = r.iter().map(|v| (v - mean).powi(2)).sum();
    if c0 <= 0.0 {
        return 0.0;
    }
    let mut q = 0.0;
    for l in 1..=lags {
        let cl: f64 = (l..n).map(|k| (r[k] - mean) * (r[k - l] - mean)).sum();
        let rho = cl / c0;
        q += rho * rho / (n - l) as f64;
    }
    q * n as f64 * (n as f64 + 2.0)
}

/// χ²₂₀ 95 % point.
pub const LJUNG_BOX_LIMIT_20: f64 = 31.41;

/// Sensor noise estimate σ from the residual's second differences (module doc): robust to a smooth
/// model error and to the few samples around input steps.
pub fn noise_estimate(r: &[f64]) -> f64 {
    if r.len() < 4 {
        return 0.0;
    }
    let mut d: Vec<f64> = r.windows(3).map(|w| w[2] - 2.0 * w[1] + w[0]).collect();
    let med = median(&mut d);
    let mut dev: Vec<f64> = d.iter().map(|v| (v - med).abs()).collect();
    1.4826 * median(&mut dev) / 6f64.sqrt()
}

fn median(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    let mid = v.len() / 2;
    let (_, m, _) = v.select_nth_unstable_by(mid, |a, b| a.total_cmp(b));
    *m
}

/// The residual's whiteness and noise figures.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ResidualFigures {
    /// RMS \[m\].
    pub rms: f64,
    /// Sensor noise estimate σ \[m\] ([`noise_estimate`]).
    pub noise: f64,
    /// Ljung–Box Q over 20 lags.
    pub ljung_box_q20: f64,
}

impl ResidualFigures {
    /// The figures of residual `r`.
    pub fn of(r: &[f64]) -> Self {
        Self {
            rms: (r.iter().map(|v| v * v).sum::<f64>() / r.len().max(1) as f64).sqrt(),
            noise: noise_estimate(r),
            ljung_box_q20: ljung_box(r, 20),
        }
    }

    /// The figures for the report, with the whiteness limit and verdict.
    pub fn report(&self) -> ResidualReport {
        ResidualReport {
            rms: self.rms,
            noise_estimate: self.noise,
            ljung_box_q20: self.ljung_box_q20,
            ljung_box_limit: LJUNG_BOX_LIMIT_20,
            white: self.ljung_box_q20 < LJUNG_BOX_LIMIT_20,
        }
    }
}

/// A residual's figures in a report ([`ResidualFigures::report`]).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct ResidualReport {
    /// RMS \[m\].
    pub rms: f64,
    /// Sensor noise estimate σ \[m\].
    pub noise_estimate: f64,
    /// Ljung–Box Q over 20 lags.
    pub ljung_box_q20: f64,
    /// The 95 % limit of Q over 20 lags ([`LJUNG_BOX_LIMIT_20`]).
    pub ljung_box_limit: f64,
    /// Whether Q is below the limit.
    pub white: bool,
}

fn log_grid(lo: f64, hi: f64, n: usize) -> Vec<f64> {
    if !(hi > lo) || n < 2 {
        return vec![lo];
    }
    (0..n)
        .map(|i| lo * (hi / lo).powf(i as f64 / (n - 1) as f64))
        .collect()
}

/// Screens every effect in `candidates` on the current prediction; results sorted best first.
pub fn screen(sig: &Signals, candidates: &[EffectKind]) -> Vec<Candidate> {
    use rayon::prelude::*;
    let screening = Screening::new(sig);
    let mut out: Vec<Candidate> = candidates
        .par_iter()
        .filter_map(|&effect| screening.effect(effect))
        .flatten()
        .collect();
    out.sort_by(|a, b| b.share.total_cmp(&a.share));
    out
}

/// What every candidate's screening shares (module doc): the residual on the scored samples, the
/// nuisance basis N = (1, u, h) and SSE(r | N).
struct Screening<'s, 'a> {
    /// The model's current prediction.
    sig: &'s Signals<'a>,
    /// r = y − ŷ over the scored samples.
    r: Vec<f64>,
    /// The constant column of N.
    ones: Vec<f64>,
    /// SSE(r | N).
    sse0: f64,
    /// Length of the whole record \[s\].
    record_s: f64,
    /// Dominant input frequency over the scored samples \[Hz\].
    f_dom: f64,
}

impl<'s, 'a> Screening<'s, 'a> {
    fn new(sig: &'s Signals<'a>) -> Self {
        let from = sig.from;
        let n_all = sig.u.len();
        let ts = sig.sample_period_s;
        let r: Vec<f64> = (from..n_all).map(|k| sig.y[k] - sig.y_hat[k]).collect();
        let ones = vec![1.0; r.len()];
        let (sse0, _) = least_squares(&[&ones, &sig.u[from..], &sig.h[from..]], &r);
        Self {
            sig,
            r,
            ones,
            sse0,
            record_s: ts * n_all as f64,
            f_dom: dominant_frequency_hz(&sig.u[from..], ts),
        }
    }

    /// N = (1, u, h) over the scored samples.
    fn nuisance(&self) -> [&[f64]; 3] {
        let from = self.sig.from;
        [&self.ones, &self.sig.u[from..], &self.sig.h[from..]]
    }

    /// The scored samples' indices in the whole record.
    fn scored(&self) -> std::ops::Range<usize> {
        self.sig.from..self.sig.u.len()
    }

    /// SSE(r | N ∪ `cols`) and the coefficients of `cols`.
    fn score(&self, cols: &[&[f64]]) -> (f64, Vec<f64>) {
        let mut basis: Vec<&[f64]> = self.nuisance().to_vec();
        basis.extend_from_slice(cols);
        let (sse, coef) = least_squares(&basis, &self.r);
        (sse, coef[3..].to_vec())
    }

    /// ΔBIC of a candidate with `p` parameters that leaves `sse1`.
    fn bic(&self, sse1: f64, p: usize) -> f64 {
        let n = self.r.len();
        n as f64 * (sse1.max(1e-300) / self.sse0.max(1e-300)).ln() + p as f64 * (n as f64).ln()
    }

    /// The share of the residual variance a candidate that leaves `sse1` explains.
    fn share(&self, sse1: f64) -> f64 {
        if self.sse0 > 0.0 {
            (1.0 - sse1 / self.sse0).max(0.0)
        } else {
            0.0
        }
    }

    /// The candidates of one effect (`None` when it has none).
    fn effect(&self, effect: EffectKind) -> Option<Vec<Candidate>> {
        match effect {
            EffectKind::Creep => Some(vec![self.kelvin_voigt_creep()?, self.log_creep()]),
            EffectKind::Drift => Some(vec![self.linear_drift(), self.settling_drift()?]),
            EffectKind::Delay => Some(vec![self.delay()?]),
            EffectKind::Asymmetry => Some(vec![self.asymmetry()]),
            EffectKind::Dynamics => Some(vec![self.dynamics()?]),
            EffectKind::Coupling => Some(vec![self.coupling()?]),
            EffectKind::RateDependent => Some(vec![self.rate_dependent()?]),
        }
    }

    /// Kelvin–Voigt creep: one element on the time-constant grid, a second (greedy) if it explains
    /// ≥ 1 % more of the residual.
    fn kelvin_voigt_creep(&self) -> Option<Candidate> {
        let (sig, from, ts) = (self.sig, self.sig.from, self.sig.sample_period_s);
        let taus = log_grid(4.0 * ts, self.record_s / 4.0, 16);
        let cols: Vec<Vec<f64>> = taus
            .iter()
            .map(|&tau| creep_element(sig.u, tau, ts)[from..].to_vec())
            .collect();
        let singles: Vec<(f64, f64, usize)> = cols
            .iter()
            .enumerate()
            .map(|(i, c)| {
                let (sse, coef) = self.score(&[c]);
                (sse, coef[0], i)
            })
            .collect();
        let best = singles.iter().copied().min_by(|a, b| a.0.total_cmp(&b.0))?;
        // A second element, greedy, only if it explains ≥ 1 % more of the residual.
        let pair = (0..cols.len())
            .filter(|&j| j != best.2)
            .map(|j| {
                let (sse, coef) = self.score(&[&cols[best.2], &cols[j]]);
                (sse, coef, j)
            })
            .min_by(|a, b| a.0.total_cmp(&b.0));
        let (sse, gains_m_per_v, time_constants_s, p) = match pair {
            Some((sse2, coef, j)) if self.share(sse2) - self.share(best.0) >= 0.01 => {
                (sse2, [coef[0], coef[1]], [taus[best.2], taus[j]], 4)
            }
            _ => (
                best.0,
                [best.1, 0.0],
                [taus[best.2], taus[best.2] * 10.0],
                2,
            ),
        };
        Some(Candidate {
            effect: EffectKind::Creep,
            share: self.share(sse),
            delta_bic: self.bic(sse, p),
            init: EffectInit::Creep {
                gains_m_per_v,
                time_constants_s,
            },
            test: "residual against first-order low-pass histories of u (time-constant grid)",
            figures: vec![
                ("gain_m_per_v[0]", gains_m_per_v[0]),
                ("time_constant_s[0]", time_constants_s[0]),
                ("gain_m_per_v[1]", gains_m_per_v[1]),
                ("time_constant_s[1]", time_constants_s[1]),
            ],
        })
    }

    /// The logarithmic creep: twelve elements half a decade apart, t0 = Ts.
    fn log_creep(&self) -> Candidate {
        let (sig, from, ts) = (self.sig, self.sig.from, self.sig.sample_period_s);
        let mut col = vec![0.0; self.r.len()];
        for l in 0..12 {
            let tau = ts * 10f64.powf(0.5 * (l + 1) as f64);
            for (c, x) in col.iter_mut().zip(&creep_element(sig.u, tau, ts)[from..]) {
                *c += 0.5 * x;
            }
        }
        let (sse, coef) = self.score(&[&col]);
        Candidate {
            effect: EffectKind::Creep,
            share: self.share(sse),
            delta_bic: self.bic(sse, 1),
            init: EffectInit::LogCreep {
                gain_m_per_v: coef[0],
            },
            test: "residual against the logarithmic creep of u (g_log·log10(1 + t/Ts) per step)",
            figures: vec![("gain_m_per_v_per_decade", coef[0])],
        }
    }

    /// Time since the record's start over the scored samples \[s\].
    fn time(&self) -> Vec<f64> {
        let t_s = self.sig.t_s;
        t_s[self.sig.from..].iter().map(|t| t - t_s[0]).collect()
    }

    /// Linear drift: the residual against time.
    fn linear_drift(&self) -> Candidate {
        let (sse, coef) = self.score(&[&self.time()]);
        Candidate {
            effect: EffectKind::Drift,
            share: self.share(sse),
            delta_bic: self.bic(sse, 1),
            init: EffectInit::Drift {
                rate_m_per_s: coef[0],
            },
            test: "residual against time (linear drift)",
            figures: vec![("rate_m_per_s", coef[0])],
        }
    }

    /// Settling drift: the residual against 1 − e^(−t/τ) on the time-constant grid.
    fn settling_drift(&self) -> Option<Candidate> {
        let ts = self.sig.sample_period_s;
        let t = self.time();
        let lo = (2.0 / self.f_dom).max(20.0 * ts);
        let taus = log_grid(1.2 * lo, (2.5 * self.record_s).max(3.0 * lo), 16);
        let settling = taus
            .iter()
            .map(|&tau| {
                let col: Vec<f64> = t.iter().map(|t| -(-t / tau).exp_m1()).collect();
                let (sse, coef) = self.score(&[&col]);
                (sse, coef[0], tau)
            })
            .min_by(|a, b| a.0.total_cmp(&b.0))?;
        Some(Candidate {
            effect: EffectKind::Drift,
            share: self.share(settling.0),
            delta_bic: self.bic(settling.0, 2),
            init: EffectInit::Settling {
                amplitude_m: settling.1,
                time_constant_s: settling.2,
            },
            test: "residual against 1 - exp(-t/tau) (settling drift, tau grid)",
            figures: vec![("amplitude_m", settling.1), ("time_constant_s", settling.2)],
        })
    }

    /// Rate-dependent hysteresis: the residual against first-order lags of the hysteresis state h
    /// (the hysteretic part k2·h of w relaxes, the nuisance basis spans h itself), τ on a grid from
    /// one sample period to a tenth of the record or 50 ms.
    fn rate_dependent(&self) -> Option<Candidate> {
        let (sig, from, ts) = (self.sig, self.sig.from, self.sig.sample_period_s);
        let taus = log_grid(ts, (self.record_s / 10.0).clamp(4.0 * ts, 0.05), 16);
        let best = taus
            .iter()
            .map(|&tau| {
                let col = creep_element(sig.h, tau, ts)[from..].to_vec();
                let (sse, coef) = self.score(&[&col]);
                (sse, coef[0], tau)
            })
            .min_by(|a, b| a.0.total_cmp(&b.0))?;
        Some(Candidate {
            effect: EffectKind::RateDependent,
            share: self.share(best.0),
            delta_bic: self.bic(best.0, 2),
            init: EffectInit::RateDependent {
                lag_coefficient_m: best.1,
                time_constant_s: best.2,
            },
            test: "residual against first-order lags of the hysteresis state (time-constant grid)",
            figures: vec![("lag_coefficient_m", best.1), ("time_constant_s", best.2)],
        })
    }

    /// Delay: the prediction delayed by D against the measurement, D on the grid.
    fn delay(&self) -> Option<Candidate> {
        let (sig, ts) = (self.sig, self.sig.sample_period_s);
        let grid = [
            0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0, 12.0, 16.0, 20.0,
            24.0, 32.0, 40.0, 48.0, 56.0, 64.0,
        ];
        // The prediction delayed by D replaces ŷ (coefficient 1: what adding the delay does),
        // with the linear map refitted through the nuisance basis.
        let rows: Vec<(f64, f64)> = grid
            .iter()
            .map(|&d| {
                let yd = per_record(sig.y_hat, sig.segments, |s| delayed(s, d));
                let shifted: Vec<f64> = self.scored().map(|k| sig.y[k] - yd[k]).collect();
                (d, least_squares(&self.nuisance(), &shifted).0)
            })
            .collect();
        let best = rows.iter().copied().min_by(|a, b| a.1.total_cmp(&b.1))?;
        // Rate correlation: the first-order signature of a delay, r ≈ −D·dŷ/dt.
        let rate: Vec<f64> = self
            .scored()
            .map(|k| (sig.y_hat[k] - sig.y_hat[k.saturating_sub(1)]) / ts)
            .collect();
        let corr = correlation(&self.r, &rate);
        let d_s = best.0 * ts;
        Some(Candidate {
            effect: EffectKind::Delay,
            share: self.share(best.1),
            delta_bic: self.bic(best.1, 1),
            init: EffectInit::Delay { delay_s: d_s },
            test: "the prediction delayed by D against the measurement (D grid); correlation of the residual with the predicted rate",
            figures: vec![("delay_s", d_s), ("correlation_with_rate", corr)],
        })
    }

    /// Asymmetry: the residual against the even function (u\[k−1\] − u_mid)².
    fn asymmetry(&self) -> Candidate {
        let sig = self.sig;
        let (u_lo, u_hi) = sig.u[sig.from..]
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &v| {
                (lo.min(v), hi.max(v))
            });
        let mid = 0.5 * (u_lo + u_hi);
        // u[k−1], with u[−1] := u_mid (the core's term is 0 at the first sample).
        let col: Vec<f64> = self
            .scored()
            .map(|k| k.checked_sub(1).map_or(0.0, |p| (sig.u[p] - mid).powi(2)))
            .collect();
        let (sse, coef) = self.score(&[&col]);
        // sign(u̇)·u: how much of the residual is an odd-in-rate, input-proportional term.
        let su: Vec<f64> = self
            .scored()
            .map(|k| (sig.u[k] - sig.u[k.saturating_sub(1)]).signum() * sig.u[k])
            .collect();
        let (sse_su, _) = self.score(&[&su]);
        Candidate {
            effect: EffectKind::Asymmetry,
            share: self.share(sse),
            delta_bic: self.bic(sse, 1),
            init: EffectInit::Asymmetry {
                coefficient_m_per_v2: coef[0],
                center_v: mid,
            },
            test:
                "residual against the even function (u[k-1] - u_mid)^2; and against sign(du/dt)*u",
            figures: vec![
                ("coefficient_m_per_v2", coef[0]),
                ("center_v", mid),
                ("share_sign_rate_times_u", self.share(sse_su)),
            ],
        }
    }

    /// Dynamics: the prediction through a second-order mode against the measurement, on the
    /// frequency × damping grid.
    fn dynamics(&self) -> Option<Candidate> {
        let (sig, ts, f_dom) = (self.sig, self.sig.sample_period_s, self.f_dom);
        // Inside the plausible range of the mode (full::EffectBounds).
        let f_hi = 0.8 * 0.5 / ts;
        let f_lo = 1.1 * (10.0 * f_dom).min(0.1 / ts);
        let freqs = log_grid(f_lo, f_hi, 20);
        let zetas = [0.05, 0.1, 0.2, 0.4, 0.7, 1.0, 1.5, 2.5];
        let grid: Vec<(f64, f64)> = freqs
            .iter()
            .flat_map(|&f| zetas.iter().map(move |&z| (f, z)))
            .collect();
        // The prediction through the mode replaces ŷ (what adding the mode does), with the
        // linear map refitted through the nuisance basis.
        let curvature = per_record(sig.y_hat, sig.segments, |s| second_derivative(s, ts));
        let rows: Vec<(f64, f64, f64, f64)> = grid
            .iter()
            .flat_map(|&(f, z)| {
                let w = 2.0 * std::f64::consts::PI * f;
                let mode = |s: &[f64]| mode_filter(s, f, z, ts);
                let force = per_record(sig.y_hat, sig.segments, mode);
                let through_stack: Vec<f64> = curvature.iter().map(|a| -a / (w * w)).collect();
                let through_stack = per_record(&through_stack, sig.segments, mode);
                let sse_of = |m: &dyn Fn(usize) -> f64| {
                    let moved: Vec<f64> = self.scored().map(|k| sig.y[k] - m(k)).collect();
                    least_squares(&self.nuisance(), &moved).0
                };
                [
                    (f, z, 0.0, sse_of(&|k| force[k])),
                    (f, z, 1.0, sse_of(&|k| sig.y_hat[k] + through_stack[k])),
                ]
            })
            .collect();
        let best = rows.iter().copied().min_by(|a, b| a.3.total_cmp(&b.3))?;
        Some(Candidate {
            effect: EffectKind::Dynamics,
            share: self.share(best.3),
            delta_bic: self.bic(best.3, 2),
            init: EffectInit::Dynamics {
                frequency_hz: best.0,
                damping: best.1,
            },
            test:
                "the prediction through a second-order mode, force-driven and driven through the \
                   stack, against the measurement (frequency x damping grid)",
            figures: vec![
                ("dominant_input_frequency_hz", f_dom),
                ("frequency_hz", best.0),
                ("damping", best.1),
                ("relative_damping", best.2),
            ],
        })
    }

    /// Coupling: the residual against the other axis's prediction (two-axis records).
    fn coupling(&self) -> Option<Candidate> {
        let other = self.sig.other_y_hat?;
        let col = &other[self.sig.from..];
        let (sse, coef) = self.score(&[col]);
        Some(Candidate {
            effect: EffectKind::Coupling,
            share: self.share(sse),
            delta_bic: self.bic(sse, 1),
            init: EffectInit::Coupling {
                coefficient: coef[0],
            },
            test: "residual against the other axis's z",
            figures: vec![
                ("coefficient", coef[0]),
                ("correlation", correlation(&self.r, col)),
            ],
        })
    }
}

/// Pearson correlation.
pub fn correlation(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len().min(b.len()) as f64;
    if n < 2.0 {
        return 0.0;
    }
    let ma = a.iter().sum::<f64>() / n;
    let mb = b.iter().sum::<f64>() / n;
    let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
    for (x, y) in a.iter().zip(b) {
        sab += (x - ma) * (y - mb);
        saa += (x - ma).powi(2);
        sbb += (y - mb).powi(2);
    }
    if saa > 0.0 && sbb > 0.0 {
        sab / (saa * sbb).sqrt()
    } else {
        0.0
    }
}

/// One-sided amplitude spectrum (Hann window, direct DFT on ≤ 4096 log-spaced bins): (Hz, m).
pub fn spectrum(r: &[f64], ts: f64) -> Vec<(f64, f64)> {
    let n = r.len();
    if n < 8 {
        return Vec::new();
    }
    let mean = r.iter().sum::<f64>() / n as f64;
    let w: Vec<f64> = (0..n)
        .map(|k| {
            let hann = 0.5 - 0.5 * (2.0 * std::f64::consts::PI * k as f64 / (n - 1) as f64).cos();
            (r[k] - mean) * hann
        })
        .collect();
    let df = 1.0 / (n as f64 * ts);
    let f_max = 0.5 / ts;
    let bins = log_grid(df, f_max, 400);
    bins.iter()
        .map(|&f| {
            let (mut re, mut im) = (0.0, 0.0);
            let dphi = 2.0 * std::f64::consts::PI * f * ts;
            let (s, c) = dphi.sin_cos();
            let (mut cr, mut ci) = (1.0, 0.0);
            for &v in &w {
                re += v * cr;
                im -= v * ci;
                let nr = cr * c - ci * s;
                ci = cr * s + ci * c;
                cr = nr;
            }
            (f, 4.0 * (re * re + im * im).sqrt() / n as f64)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    /// A residual's figures serialise with the keys of the report, the whiteness verdict against
    /// the limit; an effect serialises as its name.
    #[test]
    fn residual_figures_and_effects_serialise_as_in_the_report() {
        let figures = ResidualFigures {
            rms: 2e-7,
            noise: 2e-9,
            ljung_box_q20: 12.5,
        };
        let json = crate::to_json(&figures.report()).unwrap();
        assert_eq!(
            json,
            serde_json::json!({
                "rms": 2e-7,
                "noise_estimate": 2e-9,
                "ljung_box_q20": 12.5,
                "ljung_box_limit": LJUNG_BOX_LIMIT_20,
                "white": true,
            })
        );
        let coloured = ResidualFigures {
            ljung_box_q20: 1e4,
            ..figures
        };
        assert_eq!(crate::to_json(&coloured.report()).unwrap()["white"], false);
        for effect in EffectKind::ALL {
            assert_eq!(crate::to_json(&effect).unwrap(), effect.name());
        }
    }

    #[test]
    fn mode_filter_has_unit_dc_gain_and_rings_at_its_frequency() {
        let ts = 1e-4;
        let s = vec![1.0; 20000];
        let mut step = vec![0.0; 20000];
        step[1..].copy_from_slice(&s[1..]);
        let z = mode_filter(&step, 100.0, 0.05, ts);
        assert!((z[19999] - 1.0).abs() < 1e-3, "{}", z[19999]);
        // First peak at t = π/ω_d ≈ 5 ms with overshoot e^(−ζπ/√(1−ζ²)) ≈ 0.855.
        let (k, peak) =
            z.iter()
                .enumerate()
                .take(100)
                .fold((0, 0.0), |a, (k, &v)| if v > a.1 { (k, v) } else { a });
        let _ = k;
        let (kp, vp) = z
            .iter()
            .enumerate()
            .skip(10)
            .take(100)
            .fold((0, f64::MIN), |a, (k, &v)| if v > a.1 { (k, v) } else { a });
        assert!((kp as f64 - 50.5).abs() <= 2.0, "peak at {kp}");
        assert!((vp - 1.855).abs() < 0.01, "{vp} {peak}");
    }

    /// The screening's stack-driven mode, ŷ + M[−(d²ŷ/dt²)/ω²], is the steady state of
    /// z̈ + 2ζω·(ż − ṡ) + ω²·(z − s) = 0: H(jΩ) = (ω² + 2jζωΩ)/(ω² − Ω² + 2jζωΩ), a gain above 1
    /// and (nearly) no phase lag well below the mode.
    #[test]
    fn the_stack_driven_mode_is_the_relative_damping_law() {
        let (ts, f_in, f_mode, zeta) = (1e-5, 100.0, 1000.0, 0.1);
        let (w_in, w) = (2.0 * PI * f_in, 2.0 * PI * f_mode);
        let t: Vec<f64> = (0..40_000).map(|k| k as f64 * ts).collect();
        let s: Vec<f64> = t.iter().map(|t| (w_in * t).sin()).collect();
        let push: Vec<f64> = second_derivative(&s, ts)
            .iter()
            .map(|a| -a / (w * w))
            .collect();
        let m = mode_filter(&push, f_mode, zeta, ts);
        // H = (a + jb)/(c + jb), a = ω², c = ω² − Ω², b = 2ζωΩ.
        let (a, c, b) = (w * w, w * w - w_in * w_in, 2.0 * zeta * w * w_in);
        let (den, re_num, im_num) = (c * c + b * b, a * c + b * b, b * c - a * b);
        let (re, im) = (re_num / den, im_num / den);
        let worst = (30_000..40_000)
            .map(|k| {
                let expected = re * (w_in * t[k]).sin() + im * (w_in * t[k]).cos();
                (s[k] + m[k] - expected).abs()
            })
            .fold(0.0, f64::max);
        // The gain 1.0101 shows; the half-sample delay of the held drive is what is left.
        assert!(re > 1.01 && im.abs() < 2e-3, "{re} {im}");
        assert!(worst < 2e-4, "{worst}");
    }

    /// Two records whose sensor offsets differ: the mode run over the records together rings
    /// at the step between them, run per record it starts from rest at each.
    #[test]
    fn a_filter_of_the_prediction_starts_again_at_each_record() {
        let s: Vec<f64> = (0..200).map(|k| if k < 100 { 1.0 } else { 3.0 }).collect();
        let mode = |s: &[f64]| mode_filter(s, 1000.0, 0.05, 1e-4);
        let together = mode(&s);
        let per = per_record(&s, &[0, 100], mode);
        assert_eq!(per.len(), s.len());
        assert!(per.iter().zip(&s).all(|(a, b)| (a - b).abs() < 1e-12));
        assert!((together[101] - 3.0).abs() > 0.1, "{}", together[101]);
        assert_eq!(per_record(&s, &[0], mode), together);
    }

    #[test]
    fn ljung_box_separates_white_from_correlated() {
        let mut x = 1u64;
        let mut next = || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            (x >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        };
        let white: Vec<f64> = (0..5000).map(|_| next()).collect();
        // Gaussian (Box-Muller) for the noise estimate, which assumes it.
        let gauss: Vec<f64> = (0..20000)
            .map(|_| {
                let (a, b) = (next() + 0.5, next() + 0.5);
                (-2.0 * a.max(1e-300).ln()).sqrt() * (2.0 * std::f64::consts::PI * b).cos()
            })
            .collect();
        assert!(ljung_box(&white, 20) < LJUNG_BOX_LIMIT_20 * 1.5);
        let mut ar = vec![0.0; 5000];
        for k in 1..5000 {
            ar[k] = 0.8 * ar[k - 1] + white[k];
        }
        assert!(ljung_box(&ar, 20) > 10.0 * LJUNG_BOX_LIMIT_20);
        let est = noise_estimate(&gauss);
        assert!((est - 1.0).abs() < 0.05, "{est}");
        // A smooth model error on top hardly moves it.
        let with_error: Vec<f64> = gauss
            .iter()
            .enumerate()
            .map(|(k, v)| v + 5.0 * (k as f64 * 0.01).sin())
            .collect();
        let est = noise_estimate(&with_error);
        assert!((est - 1.0).abs() < 0.05, "{est}");
    }
}
